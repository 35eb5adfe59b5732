"""The core: the small typed pieces every run is made of, with no I/O beyond saving and loading its own models.

A problem (:mod:`pemviz.core.problems`: simulator + target PEM + safety formula; the built-in scenarios' problems are in
:mod:`pemviz.scenarios.problems`, the exact answers known by enumeration in their scenarios' packages
(e.g. :mod:`pemviz.scenarios.braking.truth`)); the simulator protocols and the rollouts they give
(:mod:`pemviz.core.rollouts`), drawn by the one rollout runner (:mod:`pemviz.core.lockstep`); the detectors that draw a
rollout's perception events (:mod:`pemviz.core.detectors`) and the random streams behind them (:mod:`pemviz.core.rng`);
the proposal networks and their fits (:mod:`pemviz.core.sampling`, seen per bin of the window's column in
:mod:`pemviz.core.proposal_view`); the weights (:mod:`pemviz.core.weights`), the estimate with its interval and verdict
(:mod:`pemviz.core.estimate`) and its diagnostics (:mod:`pemviz.core.diagnostics`); the counterfactuals of a failure
(:mod:`pemviz.core.counterfactuals`); and the checks of what a user plugs in (:mod:`pemviz.core.checks`); its own
models' files are written and read through :mod:`pemviz.core.files`. Nothing is imported here: each module is imported
by its own name (``from pemviz.core.problems import Problem``).
"""

"""The core: the small typed pieces every run is made of, with no I/O beyond saving and loading its own models:
problems (:mod:`pemviz.core.problems`), rollouts and their runner (:mod:`pemviz.core.rollouts`,
:mod:`pemviz.core.lockstep`), detectors and random streams (:mod:`pemviz.core.detectors`, :mod:`pemviz.core.rng`),
proposals and their fits (:mod:`pemviz.core.sampling`), weights, the estimate and its diagnostics
(:mod:`pemviz.core.weights`, :mod:`pemviz.core.estimate`, :mod:`pemviz.core.diagnostics`), counterfactuals and the
checks of what a user plugs in (:mod:`pemviz.core.checks`). Nothing is imported here: each module by its own name."""

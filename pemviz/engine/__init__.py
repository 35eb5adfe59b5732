"""The engine: runs an estimator's stages on a problem and emits events (:mod:`pemviz.engine.experiment`).

With it: the events and what they carry (:mod:`pemviz.engine.events`; the run's plan of stages is the core's,
:mod:`pemviz.core.plan`), what a run costs before it starts and while it runs (:mod:`pemviz.engine.cost`), its
memory and CPUs (:mod:`pemviz.engine.resources`), and where its rollouts are simulated (:mod:`pemviz.engine.executors`).

Nothing is imported here: each name has one import path, its module's (``from pemviz.engine.experiment import
Experiment``). The light modules of this package (``events``, ``cost``, ``resources``) import neither the experiment
nor torch, so ``pemviz --help`` stays fast. To change one of the engine's constants (``STREAM_ABOVE``) set it on
:mod:`pemviz.engine.experiment`, which reads it.
"""

"""The crowd toy (several obstacles, each detected and mislocated), one package: the model, its detector, batched
twin and closed-form answer (:mod:`~pemviz.scenarios.crowd.simulator`, whose names this package re-exports) and its
problem (:mod:`~pemviz.scenarios.crowd.problem`). Importing the package loads the simulator module only."""

from pemviz.scenarios.crowd.simulator import (  # noqa: F401 (re-exported: importable from here as before)
    NOISE_NAMES as NOISE_NAMES,
    OBJECT_NAMES as OBJECT_NAMES,
    OBSERVATION_NAMES as OBSERVATION_NAMES,
    BatchedCrowd as BatchedCrowd,
    CrowdDetector as CrowdDetector,
    CrowdParams as CrowdParams,
    crowd_log_failure_probability as crowd_log_failure_probability,
)

"""The toy braking model of the authors' code, one package: the model, its detector, batched twin and closed-form answer
(:mod:`~pemviz.scenarios.toy.simulator`, whose names this package re-exports) and its problem
(:mod:`~pemviz.scenarios.toy.problem`). Importing the package loads the simulator module only."""

from pemviz.scenarios.toy.simulator import (  # noqa: F401 (re-exported: importable from here as before)
    OBSERVATION_NAMES as OBSERVATION_NAMES,
    BatchedToy as BatchedToy,
    DetectionProbability as DetectionProbability,
    ToyBraking as ToyBraking,
    ToyDetector as ToyDetector,
    ToyParams as ToyParams,
    ToyValue as ToyValue,
    branch_toy as branch_toy,
    simulate_toy as simulate_toy,
    toy_log_failure_probability as toy_log_failure_probability,
)

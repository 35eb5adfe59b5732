"""The toy braking model of the authors' code, one package: the model, detector, batched twin and closed-form answer
(:mod:`~pemviz.scenarios.toy.simulator`) and its problem (:mod:`~pemviz.scenarios.toy.problem`). The user guide
imports :class:`ToyBraking` and :class:`ToyParams` from here."""

from pemviz.scenarios.toy.simulator import ToyBraking, ToyParams

__all__ = ["ToyBraking", "ToyParams"]

"""The toy braking model of the authors' code, one package: the model, its detector, batched twin and closed-form answer
(:mod:`~pemviz.scenarios.toy.simulator`) and its problem (:mod:`~pemviz.scenarios.toy.problem`). Importing the package
loads the simulator module only.

The three names the user guide builds a toy scenario and its zero-variance sampler from are imported from here
(:class:`ToyBraking`, :class:`ToyParams`, :class:`ToyValue`); every other name has one import path, its module's."""

from pemviz.scenarios.toy.simulator import ToyBraking, ToyParams, ToyValue

__all__ = ["ToyBraking", "ToyParams", "ToyValue"]

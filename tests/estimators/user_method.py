"""A user's own method, registered from a module (``PEMVIZ_METHODS=user_method``): plain Monte Carlo whose detector
is mixed 30 % with a fair coin, a defensive mixture (Hesterberg, Technometrics 1995), one importance-weighted batch.
The whole of a method of one's own: a builder and one registration."""

from pemviz.estimators.cross_entropy import DefensiveDetector
from pemviz.estimators.fixed import FixedSampler
from pemviz.methods import Method, register_method


def build(config, problem, check=None):
    """One batch of ``config.n_per_stage`` rollouts drawn by 0.7 p(detect) + 0.3 x 50 %, weighed by p / q."""
    sampler = DefensiveDetector(problem.target, 0.3)
    return FixedSampler(problem, sampler, config.n_per_stage, config.weights_until_failure, config.seed)


METHOD = register_method(Method("defensive-mc", "plain Monte Carlo mixed 30 % with a fair coin", build), replace=True)

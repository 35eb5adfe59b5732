"""A user's own method, registered from a module (``PEMVIZ_METHODS=user_method``): plain Monte Carlo whose detector
is mixed with a fair coin, a defensive mixture (Hesterberg, Technometrics 1995), one importance-weighted batch.
The whole of a method of one's own: its settings, a builder and one registration."""

from dataclasses import dataclass

from pemviz.core.detectors import WindowDetector
from pemviz.estimators.cross_entropy import DefensiveDetector
from pemviz.estimators.fixed import FixedSampler
from pemviz.methods import Method, register_method
from pemviz.settings import MethodSettings, setting


@dataclass(frozen=True)
class CoinSettings(MethodSettings):
    """The coin's share of each detection and where it mixes in: each field is its row of the settings table (its
    flag, range, unit and help), checked when the settings are made."""

    coin_share: float = setting(
        0.3,
        "the coin's share eps",
        "the share of each detection drawn by a fair coin",
        symbol="eps",
        lo=0.0,
        hi=1.0,
        lo_open=True,
        hi_open=True,
        flags=("--coin-share",),
    )
    coin_radius_m: float | None = setting(
        None,
        "the coin's radius",
        "the coin mixes in only where the gap is below this (None: everywhere)",
        unit="m",
        lo=0.0,
        lo_open=True,
        optional=True,
        flags=("--coin-radius",),
    )


def build(config, problem, check=None):
    """One batch of ``config.n_per_stage`` rollouts drawn by (1 - eps) p(detect) + eps x 50 % (within the radius),
    weighed by p / q."""
    own = config.method_settings
    sampler = DefensiveDetector(problem.target, own.coin_share)
    if own.coin_radius_m is not None:
        sampler = WindowDetector(sampler, problem.target, own.coin_radius_m)
    return FixedSampler(problem, sampler, config.n_per_stage, config.weights_until_failure, config.seed)


METHOD = register_method(
    Method("defensive-mc", "plain Monte Carlo mixed with a fair coin", build, settings=CoinSettings), replace=True
)

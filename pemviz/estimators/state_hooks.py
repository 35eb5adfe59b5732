"""The state method's hooks besides its estimator (:attr:`pemviz.methods.Method.validate`), named by the registry as
text and imported when a config of the method is first checked: light to import."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pemviz.estimators.builtin import adaptive_conflict
from pemviz.methods.state import state_settings

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


def state_conflict(config: ExperimentConfig, n_objects: int) -> tuple[str, str] | None:
    """The state method's settings against the others: the cross-entropy sampler's
    (:func:`pemviz.estimators.builtin.adaptive_conflict`, ``n_objects`` the objects the scene perceives a step), and
    the PEM's share with the plain proposal's at most all of a stage.

    Returns:
        (setting, what is allowed) of the first conflict, or None.
    """
    if state_settings(config).state_share + config.adaptive.plain_share > 1.0:
        return "state_share", "state_share + plain_share must be <= 1"
    return adaptive_conflict(config, n_objects)

"""The state method's settings (``method = "state"``: the cross-entropy sampler whose proposal reads the state the stack
acts on), light: it imports :mod:`pemviz.methods.rows` and :mod:`pemviz.methods.adaptive` alone. Its estimator is
:mod:`pemviz.estimators.state` (``StateCrossEntropy``), the proposal's linear model :mod:`pemviz.estimators.state_glm`,
the check of its settings against the others :meth:`StateSettings.conflict`; the registry (:mod:`pemviz.methods`) names
them by text."""

from __future__ import annotations

from dataclasses import dataclass

from pemviz.methods.adaptive import CrossEntropySettings
from pemviz.methods.rows import setting

STATE_MODELS = ("network", "glm", "spline")
"""The state proposal's model of q(detect) (:attr:`StateSettings.state_model`)."""


@dataclass(frozen=True)
class StateSettings(CrossEntropySettings):
    """The cross-entropy sampler of Innes & Ramamoorthy (2022) with the paper's q(detect | salient variables)
    generalised to every perception event of a step as a function of the state the stack acts on
    (:mod:`pemviz.core.features`): the sampler's settings (:class:`~pemviz.methods.adaptive.CrossEntropySettings`,
    rows of the settings table) and these of its own.

    Attributes:
    state_share: the defensive mixture over whole rollouts (Hesterberg 1995; Owen & Zhou 2000): each weight at most
        1 / ``state_share``.
    state_model: ``network`` is :class:`pemviz.core.sampling.FeatureProposal`, ``glm``
        :class:`pemviz.estimators.state_glm.StateGLM` (linear), ``spline`` the same with each column expanded into
        hats at its quantiles (additive); the error shifts, where fitted, are linear either way.
    state_fit_errors: the shifts are :class:`pemviz.core.torch_fits.NoiseShift`. The defaults (``glm``, the PEM's
        errors) are the variant measured closest to the answer on the crossing (the Validation page)."""

    state_share: float = setting(
        0.1,
        "the PEM's share of the state proposal's mixture",
        "the share of the rollouts drawn by the PEM itself in every stage after the failure level and in the final "
        "batch: each weight at most 1 / share",
        kind="real",
        lo=0.0,
        hi=1.0,
        lo_open=True,
        hi_open=True,
        flags=("--state-share",),
    )
    state_model: str = setting(
        "glm",
        "the state proposal's model",
        "q(detect) as a function of the row and its state features",
        kind="choice",
        choices=STATE_MODELS,
        flags=("--state-model",),
        choice_help=(
            ("network", "the paper's network over the row and its features"),
            ("glm", "the PEM's own logit plus a linear function of the row and its features"),
            ("spline", "the PEM's own logit plus an additive function (hats at each feature's quantiles) of them"),
        ),
    )
    state_fit_errors: bool = setting(
        False,
        "the state proposal's error shifts",
        "the state proposal fits the measurement errors' location and log-scale shifts too (off: they are drawn from "
        "the PEM, only the detections proposed)",
        kind="bool",
        flags=("--state-fit-errors",),
    )

    def conflict(self) -> tuple[str, str] | None:
        """As the cross-entropy sampler's (:meth:`CrossEntropySettings.conflict`), the PEM's share with the plain
        proposal's at most all of a stage first."""
        if self.state_share + self.plain_share > 1.0:
            return "state_share", "state_share + plain_share must be <= 1"
        return super().conflict()

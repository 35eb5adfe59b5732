"""The state-dependent proposal's settings (``method = "state"``): :class:`StateSettings`, the
:attr:`pemviz.config.ExperimentConfig.state` of a run; each field's row of :data:`pemviz.settings.SETTINGS` has owner
``state``, and :class:`pemviz.estimators.state.StateCrossEntropy` reads them (with the cross-entropy sampler's own,
:class:`pemviz.methods.adaptive.CrossEntropySettings`, for its stages and fits). Light to import."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StateSettings:
    """The cross-entropy sampler of Innes & Ramamoorthy (2022) with the paper's q(detect | salient variables)
    generalised to every perception event of a step as a function of the state the stack acts on
    (:mod:`pemviz.core.features`).

    Attributes:
    state_share: the PEM's own share of the rollouts of every stage drawn after a stage reached the failure level
        and of the final batch (the adaptive sampler's ``target_share``, for this method): each of those rollouts'
        weights is at most 1 / ``state_share`` (a defensive mixture over whole rollouts: Hesterberg 1995; Owen &
        Zhou 2000), in (0, 1).
    state_model: q(detect)'s model, one of :data:`pemviz.settings.STATE_MODELS`: ``network``, the paper's network
        (:class:`pemviz.core.sampling.FeatureProposal`) over the row and its features; ``glm``, the PEM's own logit
        plus a linear function of them (:class:`pemviz.estimators.state_glm.StateGLM`). The measurement error's
        location and log-scale shifts, where fitted (``state_fit_errors``), are linear in them either way.
    state_fit_errors: the proposal fits the measurement errors' location and log-scale shifts too
        (:class:`pemviz.core.torch_fits.NoiseShift`, linear in the row and its features); False: the errors are drawn
        from the PEM's own error model and only the detections are proposed. The defaults (``glm``, the PEM's errors)
        are the variant measured closest to the answer on the crossing (the Validation page).
    """

    state_share: float = 0.1
    state_model: str = "glm"
    state_fit_errors: bool = False

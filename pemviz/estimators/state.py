"""The state-dependent proposal (``method = "state"``): the cross-entropy sampler of Innes & Ramamoorthy (2022) whose
proposal reads, besides each object's row, the state the stack acts on (:mod:`pemviz.core.features`: the tracker's
state of the object, the ego's), for every perception event of a step; the models are
:class:`pemviz.methods.state.StateSettings`'s.

The rollouts are drawn with the features (:func:`pemviz.core.lockstep.run_batched` asks a detector that
``reads_state`` about the rows with them); each batch the estimator observes gets them back by replay
(:attr:`pemviz.core.problems.Problem.features`), and the target reads the rows' own columns only
(:class:`FirstColumns`), so every log p is the PEM's own."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from pemviz.core.detector_noise import noise_names_of
from pemviz.core.features import with_state
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import FeatureProposal, Proposal
from pemviz.estimators.base import Check
from pemviz.estimators.cross_entropy import CrossEntropy
from pemviz.methods.state import StateSettings

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


class FirstColumns:
    """``detector`` asked about rows that may carry state features after their own ``columns`` columns: it reads the
    first ``columns`` only (None: all), so its answers (detection logits, measurement-error parameters, draws and
    densities) are those at the rows themselves, bit for bit (rows of ``columns`` columns are handed on as they are)."""

    def __init__(self, detector: Any, columns: int | None = None) -> None:
        self.detector, self.columns = detector, columns

    def _rows(self, rows: np.ndarray) -> np.ndarray:
        rows = np.asarray(rows)
        if self.columns is None or rows.shape[1] == self.columns:
            return rows
        return np.ascontiguousarray(rows[:, : self.columns])

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """The detector's logit p(detect | row), float64 [N], at rows [N, >= columns]."""
        return self.detector.detect_logit(self._rows(obs))

    @property
    def noise_names(self) -> tuple[str, ...]:
        return noise_names_of(self.detector)

    @property
    def noise_family(self) -> str:
        return self.detector.noise_family

    @property
    def noise_df(self) -> np.ndarray | None:
        return self.detector.noise_df

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.detector.noise_params(self._rows(rows))

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.detector.noise_from_uniforms(self._rows(rows), u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        return self.detector.noise_log_prob(self._rows(rows), noise)


def no_features_refusal(problem: Problem) -> str:
    """The one line refusing the state method on ``problem``, whose simulator reports no state features."""
    return (
        f"method state: the scene {problem.name!r} reports no state features (its simulator has no state_features(); "
        "docs/your-system.md); use --method adaptive"
    )


def reports_state(problem: Problem) -> bool:
    """Whether ``problem``'s simulator reports state features (its :attr:`Problem.features` replays some)."""
    if problem.features is None:
        return False
    no_rollout = np.zeros((0, 1))  # no rollout of one step
    empty = RolloutBatch(no_rollout[..., None][..., :0], no_rollout[..., None] > 0, no_rollout, no_rollout, ())
    try:
        return problem.features(empty, None) is not None
    except ValueError:  # a simulator of several objects replayed as one: its features exist
        return True


class StateCrossEntropy(CrossEntropy):
    """The cross-entropy sampler with the state-dependent proposal (module docstring); settings: the adaptive sampler's
    and the method's own, :class:`pemviz.methods.state.StateSettings` (their defaults in a config of another method: an
    estimator built on it by hand).

    Raises:
        ValueError: the problem's simulator reports no state features (:func:`no_features_refusal`)."""

    SETTINGS = tuple(StateSettings.__dataclass_fields__)

    def __init__(self, config: ExperimentConfig, problem: Problem, check: Check | None = None) -> None:
        if not reports_state(problem):
            raise ValueError(no_features_refusal(problem))
        self._first = FirstColumns(problem.target)
        super().__init__(config, dataclasses.replace(problem, target=self._first), check)
        self.own = self.ce if isinstance(self.ce, StateSettings) else StateSettings()
        self.ce = dataclasses.replace(self.ce, target_share=float(self.own.state_share))
        self.fits_errors = bool(self.own.state_fit_errors)
        self.replayed = 0
        """Rollouts whose state features were replayed for the fits and weights (rollout-equivalents)."""

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        """:meth:`CrossEntropy.observe` of ``batch`` with its state features (:func:`with_state`, replayed)."""
        return super().observe(self._with_state(batch), failed, robustness)

    def _with_state(self, batch: RolloutBatch) -> RolloutBatch:
        if self._first.columns is None:
            self._first.columns = int(batch.object_rows.shape[-1])
        features = cast(Any, self.problem.features)(batch, None)
        self.replayed += batch.n
        return with_state(batch, features)

    def _new_proposal(self, batch: RolloutBatch) -> Proposal:
        """A :class:`FeatureProposal` (``state_model = "network"``) or a :class:`~pemviz.estimators.state_glm.StateGLM`
        (``"glm"``, linear; ``"spline"``, additive) over every column of the rows with their state features: the first
        (the gap) scaled by the problem's ``h_scale``, the others by their largest magnitude in the pretraining
        rollouts."""
        rows, _ = batch.events()
        scales = [self.problem.h_scale] + [float(np.max(np.abs(rows[:, :, j]))) or 1.0 for j in range(1, rows.shape[2])]
        shape = (tuple(range(rows.shape[2])), tuple(scales), tuple(rows[0, 0]))
        if self.own.state_model in ("glm", "spline"):
            from pemviz.estimators.state_glm import SPLINE_KNOTS, StateGLM

            return StateGLM(*shape, self._first, SPLINE_KNOTS if self.own.state_model == "spline" else 0)
        return FeatureProposal(*shape)

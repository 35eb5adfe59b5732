"""What the panel asks of a scenario's drawing object (:attr:`pemviz.core.problem_view.ProblemView.drawing`): the
hooks of :class:`PanelDrawing`, returning plain data (:mod:`pemviz.scenarios.panel_data`), so the panel names no
scenario: a lane scene (:class:`LanePanel`) or several objects around the ego (:class:`ObjectsPanel`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from pemviz.core.drawing import Drawing
from pemviz.scenarios import registry
from pemviz.scenarios.panel_data import CurveAxis, LaneScene, ObjectsScene, Series, ViewAxis

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch

__all__ = [
    "LaneExplanation",
    "LanePanel",
    "ObjectsPanel",
    "PanelDrawing",
    "lane_panel",
    "objects_panel",
    "panel_scene",
    "scenario_drawing",
]


class LaneExplanation(Protocol):
    """A rollout of a :class:`~pemviz.scenarios.panel_data.LaneScene` explained step by step, e.g.
    :class:`pemviz.scenarios.braking.panel.BrakingExplanation` (e.g. of the braking scenario).

    Attributes:
        time_s: float64 [T] time of each step (seconds).
        p_detect, q_detect: float64 [T] p(detect) under the PEM and q(detect) of the sampler at each step.
        cum_log_weight: float64 [T] the cumulative importance log-weight (nats).
        decisive: int [D] the misses whose flip alone avoids the failure.
        crashed: the rollout failed; replay_matches: the replay reproduces it.
        severity: its outcome (``short``, ``breach_step``).
        controller: the controller's signals, [T] each: ``time_s``, ``accel_mps2``, ``brake_command``,
            ``brake_applied``.
        counterfactual: ``minimal_set`` (int [K]), ``smallest``, ``last_saving_step`` (int or None).
        contact: bool [T], the steps in contact.
        minimal_set_outcome: what detections at the minimal miss set give, in words.
        sentence: what happened, in words."""

    time_s: np.ndarray
    p_detect: np.ndarray
    q_detect: np.ndarray
    cum_log_weight: np.ndarray
    decisive: np.ndarray
    crashed: bool
    replay_matches: bool
    severity: Any
    controller: Any
    counterfactual: Any
    sentence: str

    @property
    def contact(self) -> np.ndarray: ...

    @property
    def minimal_set_outcome(self) -> str: ...

    def summary(self) -> str:
        """One line: the decisive misses or the minimal miss set, or why there are none."""
        ...


@runtime_checkable
class PanelDrawing(Drawing, Protocol):
    """The hooks every drawing the panel draws has (besides :class:`pemviz.core.drawing.Drawing`'s ``dt_s`` and
    ``outcome``)."""

    @property
    def n_steps(self) -> int:
        """T, the steps of a rollout."""
        ...

    def panel_scene(self) -> LaneScene | ObjectsScene:
        """The scene's constants: which kind of scene, its objects' sizes and names, its zones."""
        ...

    def proposal_axis(self) -> ViewAxis:
        """The x axis and bins of the run's proposal view (*Live*)."""
        ...

    def curve_axis(self) -> CurveAxis:
        """The x axis of the proposals' reference-state curves (*Compare*)."""
        ...

    def group_heading(self) -> tuple[str, str]:
        """The rollouts table's group column: (heading, the start of each failure group's label that it says)."""
        ...


@runtime_checkable
class LanePanel(PanelDrawing, Protocol):
    """The hooks of a drawing of the ego and one object ahead of it (:class:`~pemviz.scenarios.panel_data
    .LaneScene`). ``batch, i``: rollout ``i`` of a :class:`pemviz.core.rollouts.RolloutBatch`."""

    def panel_scene(self) -> LaneScene:
        """The lane scene's constants: its cars' sizes, its zones, its labels."""
        ...

    def lane_positions(self, batch: RolloutBatch, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """float64 [T] each (metres): the ego's centre along the road (0 at the start), the object's centre, the
        ruler's length (sensor to the object's rear)."""
        ...

    def lane_explanation(self, batch: RolloutBatch, i: int) -> LaneExplanation:
        """The rollout explained step by step."""
        ...

    def strip_series(self, batch: RolloutBatch, i: int) -> tuple[Series, ...]:
        """The lines of the first strip chart, the ``main`` one first."""
        ...

    def step_caption(self, batch: RolloutBatch, i: int, ex: LaneExplanation, t: int) -> tuple[str, str]:
        """Plain text of the scene's caption at step ``t``: before and after the detector's state."""
        ...


@runtime_checkable
class ObjectsPanel(PanelDrawing, Protocol):
    """The hooks of a drawing of several objects around the ego (:class:`~pemviz.scenarios.panel_data
    .ObjectsScene`)."""

    def panel_scene(self) -> ObjectsScene:
        """The scene's constants: its car sizes, its lanes, its objects' names."""
        ...

    def objects_story(self, batch: RolloutBatch, names: tuple[str, ...]) -> Any | None:
        """What happened in rollout 0 of ``batch`` (``text``, ``severity``, ``acc``, ``in_lane``), or None: the scene
        tells none; e.g. a :class:`pemviz.scenarios.cut_in.story.CutInStory`."""
        ...


def panel_scene(drawing: object) -> LaneScene | ObjectsScene | None:
    """The scene ``drawing`` draws, or None: no drawing, or one without the panel's hooks."""
    scene = getattr(drawing, "panel_scene", None)
    return scene() if callable(scene) else None


def lane_panel(drawing: object) -> LanePanel | None:
    """``drawing`` where it draws a :class:`~pemviz.scenarios.panel_data.LaneScene`, else None."""
    return drawing if isinstance(panel_scene(drawing), LaneScene) else None  # type: ignore[return-value]


def objects_panel(drawing: object) -> ObjectsPanel | None:
    """``drawing`` where it draws an :class:`~pemviz.scenarios.panel_data.ObjectsScene`, else None."""
    return drawing if isinstance(panel_scene(drawing), ObjectsScene) else None  # type: ignore[return-value]


def scenario_drawing(name: str) -> object | None:
    """The drawing object of the registered scenario ``name`` at its default parameters
    (:meth:`pemviz.scenarios.registry.Scenario.drawing_object`), or None: no scenario of that name, or it has no
    drawing (a toy)."""
    try:
        scenario = registry.get(name)
    except KeyError:
        return None
    return scenario.drawing_object()

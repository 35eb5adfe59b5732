"""What the recording and the panel ask of a scenario's drawing object
(:attr:`pemviz.core.problems.Problem.drawing`): the scene-neutral words of a rollout's outcome. Each scenario's
package implements it, with the recording's hooks (:class:`pemviz.sinks.drawing.RecordingDrawing`) and the panel's
(:class:`pemviz.app.drawing.PanelDrawing`); plain protocols, no I/O."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:  # annotations only
    from pemviz.core.rollouts import RolloutBatch


@runtime_checkable
class Severity(Protocol):
    """How bad one rollout's outcome was, in the words every sink shares (what the panel's rollout list reads of a
    drawing's :class:`Outcome`, or of a scene-neutral one).

    Attributes:
        failed: the safety formula is violated (classic robustness below 0).
        short: one line, e.g. ``contact at 3.2 m/s`` or ``safe, min gap 3.41 m``.
        rank: sort key, larger = worse."""

    @property
    def failed(self) -> bool: ...

    @property
    def short(self) -> str: ...

    @property
    def rank(self) -> float: ...


@runtime_checkable
class Outcome(Severity, Protocol):
    """A scenario's words for one rollout's outcome: its :class:`Severity` and whether the objects touched.

    Attributes:
        contact: the objects touched (a collision), not only the margin breached."""

    @property
    def contact(self) -> bool: ...


@runtime_checkable
class Drawing(Protocol):
    """The part of a scenario's drawing object that both the recording and the panel use.

    Attributes:
        dt_s: seconds per step (a rollout's step ``t`` is at ``t * dt_s``)."""

    @property
    def dt_s(self) -> float: ...

    def outcome(self, batch: RolloutBatch, i: int) -> Outcome:
        """The outcome of rollout ``i`` of ``batch`` (observations [N, T, K], object rows where the scene has them).

        Raises:
            ValueError: the batch lacks the columns the scenario reads (not its rollouts)."""
        ...

"""What a sink sees of a problem (:class:`ProblemView`: name, description, signals and units, thresholds, scene
constants, where objects and errors are in the rows) and the scene of a batch's first rollout of several objects
(:func:`object_scene`). Plain data; re-exported by :mod:`pemviz.core.problems`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only, never imported at run time
    from pemviz.core.rollouts import RolloutBatch


@dataclass(frozen=True)
class Thresholds:
    """Levels of the rollouts' first observation (the proposal's input, the window's column) that sinks draw beside
    them.

    Attributes:
        failure: the failure threshold: below it the rollout has failed (e.g. the braking scenario's 2 m crash gap).
        window: the sampler window, where the detector can change the outcome (e.g. the braking scenario's 10 m).
        unit: of both (e.g. ``m``).
        failure_name, window_name: what they are called in legends (e.g. ``crash gap``, ``braking distance``)."""

    failure: float
    window: float
    unit: str
    failure_name: str = "failure below"
    window_name: str = "sampler window"

    def labels(self) -> tuple[str, str]:
        """The failure threshold's and the window's legend, e.g. ``("crash gap 2 m", "braking distance 10 m")``."""
        return (
            f"{self.failure_name} {self.failure:g} {self.unit}".strip(),
            f"{self.window_name} {self.window:g} {self.unit}".strip(),
        )


@dataclass(frozen=True)
class SignalView:
    """One signal of a problem's rollouts: its STL name, the observation column it is read from, its unit."""

    name: str
    column: str
    unit: str


@dataclass(frozen=True)
class ProblemView:
    """What a sink needs to show a problem it knows nothing else about (the run's first event carries it).

    Attributes:
        name: short label.
        description: one line saying what is simulated.
        signals: the safety formula's signals with their observation columns and units.
        thresholds: the failure threshold and the sampler window to draw, or None.
        objects_xy: the object-row columns of each object's position seen from the ego (metres: right, ahead); None:
            none.
        noise_xy: the measurement-error components along those two directions (metres); None: none.
        n_steps: T, the steps of a rollout (None: not known).
        drawing: the scenario's drawing object (:attr:`pemviz.core.problems.Problem.drawing`); None: only the
            signals are drawn.
        look_ahead_s: seconds per rollout the problem's look-ahead adds to a stage, about; 0: none.
        object_labels: what each object m is called (:meth:`object_label`); empty: ``object m``.
        odd_names: the scenario parameters drawn per rollout over an ODD; empty: none.
        committor: whether splitting can rank particles by a learned committor (``--ams-score committor``).
        n_objects: M, the objects the detector sees each step (the engine streams a stage above
            :func:`pemviz.engine.experiment.stream_above` of it)."""

    name: str
    description: str
    signals: tuple[SignalView, ...]
    thresholds: Thresholds | None = None
    objects_xy: tuple[str, str] | None = None
    noise_xy: tuple[int, int] | None = None
    n_steps: int | None = None
    drawing: object | None = None
    look_ahead_s: float = 0.0
    object_labels: tuple[str, ...] = ()
    odd_names: tuple[str, ...] = ()
    committor: bool = False
    n_objects: int = 1

    def object_label(self, m: int) -> str:
        """What object ``m`` (0-based) is called: the problem's label for it, else ``object m``."""
        return object_label(self.object_labels, m)

    @property
    def signal_names(self) -> tuple[str, ...]:
        """The STL signal names, e.g. ``("d", "v", "vl")``."""
        return tuple(s.name for s in self.signals)


def object_label(labels: tuple[str, ...] | None, m: int) -> str:
    """``labels[m]`` where the scene names its objects (:attr:`ProblemView.object_labels`), else ``object m``."""
    return str(labels[m]) if labels and 0 <= m < len(labels) else f"object {m}"


@dataclass(frozen=True)
class ObjectScene:
    """Rollout 0 of a batch of several objects, as a scene seen from the ego (:func:`object_scene`).

    Attributes:
        lateral_m, ahead_m: float64 [T, M] each object's true position (metres: right, ahead).
        detected, seen: bool [T, M] detected; visible to the camera at all.
        measured: float64 [T, M, 2] each detected object's measured position (NaN where not detected), or None.
        tracked: float64 [T, M, 2] each confirmed track's position (NaN where none), or None: no tracker.
        followed: bool [T, M] the object the controller followed at the step."""

    lateral_m: np.ndarray
    ahead_m: np.ndarray
    detected: np.ndarray
    seen: np.ndarray
    measured: np.ndarray | None
    tracked: np.ndarray | None
    followed: np.ndarray


def object_scene(view: ProblemView, batch: RolloutBatch) -> ObjectScene:
    """Where every object of rollout 0 of ``batch`` is, was measured and was tracked, from its object rows and the
    view's ``objects_xy`` / ``noise_xy`` (the one reading of those columns for every sink).

    Raises:
        ValueError: the view names no object positions or the batch has no object rows."""
    if view is None or view.objects_xy is None or batch.objects is None:
        raise ValueError(
            "object_scene: the problem's view names no object positions (objects_xy), or the rollout "
            "has no object rows"
        )
    names = tuple(batch.object_names or ())
    rows = batch.objects[0]  # [T, M, G]
    cx, cz = (names.index(c) for c in view.objects_xy)
    lateral, ahead = rows[:, :, cx].astype(np.float64), rows[:, :, cz].astype(np.float64)
    detected = np.asarray(batch.detected[0], bool)
    seen = rows[:, :, names.index("visible")] > 0.5 if "visible" in names else np.ones_like(detected)
    measured = tracked = None
    if view.noise_xy is not None and batch.noise is not None:
        ix, iz = view.noise_xy
        err = batch.noise[0]
        measured = np.where(detected[..., None], np.stack([lateral + err[..., ix], ahead + err[..., iz]], -1), np.nan)
    if {"tracked", "track_err_x_m", "track_err_y_m"} <= set(names):  # the track's error along and across the road
        has = rows[:, :, names.index("tracked")] > 0.5
        est = np.stack(
            [lateral + rows[:, :, names.index("track_err_y_m")], ahead + rows[:, :, names.index("track_err_x_m")]], -1
        )
        tracked = np.where(has[..., None], est, np.nan)
    followed = rows[:, :, names.index("followed")] > 0.5 if "followed" in names else np.zeros_like(detected)
    return ObjectScene(lateral, ahead, detected, seen, measured, tracked, followed)

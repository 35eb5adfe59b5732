"""What a scenario's panel hooks return (:class:`pemviz.app.drawing.PanelDrawing`): plain data, no viser, no
colours: a :class:`LaneScene` (the ego and one object ahead, zones ahead of the sensor, a ruler, the rollout
explained step by step) or an :class:`ObjectsScene` (several objects on a road of lanes); the panel colours by
:attr:`Zone.role` and :attr:`Series.role`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Zone:
    r"""A zone on the road ahead of the ego's sensor, moving with the ego.

    Attributes:
        name: the scene node's name (letters, digits and ``_``).
        length_m: how far ahead of the sensor it reaches (metres).
        role: ``window`` (where a detection changes what the ego does) or ``margin`` (the failure margin): the panel
            colours it by its role.
        legend: what it means, for the zones' label (may hold ``\n``)."""

    name: str
    length_m: float
    role: str
    legend: str


@dataclass(frozen=True)
class LaneScene:
    """The ego and one object ahead of it in its lane.

    Attributes:
        ego_length_m, object_length_m, width_m: the boxes' lengths and their common width (metres).
        sensor_offset_m: the sensor (camera) ahead of the ego's centre (metres).
        start_distance_m: the ruler's length at the start, sensor to the object's rear (metres).
        object_name: the object's scene node name and label.
        zones: the zones ahead of the sensor, outermost first.
        ruler_label: what the ruler measures, before its value (``<label> 3.20 m``).
        breach_label: the breach gate's label, before its time.
        n_steps: T, the steps of a rollout.
        strip_title: the title of the first strip chart of a rollout (its :class:`Series`)."""

    ego_length_m: float
    object_length_m: float
    width_m: float
    sensor_offset_m: float
    start_distance_m: float
    object_name: str
    zones: tuple[Zone, ...]
    ruler_label: str
    breach_label: str
    n_steps: int
    strip_title: str = "distance and speeds"

    @property
    def object_start_x(self) -> float:
        """The object's centre at the start, the ego's at 0 (metres)."""
        return self.sensor_offset_m + self.start_distance_m + self.object_length_m / 2


@dataclass(frozen=True)
class ObjectsScene:
    """Several objects on a road of lanes, the ego in the middle lane.

    Attributes:
        car_length_m, car_width_m: the boxes drawn for the objects (metres).
        lane_width_m: a lane's width (metres).
        n_lanes: the lanes drawn.
        distance_column: the object rows' column holding each object's distance ahead of the ego's front (metres),
            for the story's charts.
        n_steps: T, the steps of a rollout.
        start_xy_m: each object at the start (step 0), seen from the ego as a rollout's object positions place it
            (:attr:`pemviz.core.problem_view.ProblemView.objects_xy`): (to the right, ahead) in metres, one pair per
            object in object order; the idle scene draws them before any rollout is chosen (empty: the road alone).
        object_labels: what each object is called in the idle scene (empty: ``object m``).

    A scene of no lanes (``n_lanes`` 0) is open ground: the panel draws a plain floor with a 10 m grid, not a road."""

    car_length_m: float
    car_width_m: float
    lane_width_m: float
    n_lanes: int
    distance_column: str
    n_steps: int
    start_xy_m: tuple[tuple[float, float], ...] = ()
    object_labels: tuple[str, ...] = ()


@dataclass(frozen=True)
class Series:
    """One line of a strip chart of a rollout.

    Attributes:
        label: its legend, with its unit.
        values: float64 [T].
        role: ``main`` (the quantity the failure is about: drawn bold, the marker follows it), ``ego`` (the ego's
            speed) or ``object`` (the object's speed): the panel colours it by its role."""

    label: str
    values: np.ndarray
    role: str


@dataclass(frozen=True)
class CurveAxis:
    """The x axis of a proposal's reference-state curve (the problem's ``curve_grid``, metres).

    Attributes:
        series_label: the legend of the x values.
        label: the axis title, with its unit.
        y_label: the y axis' title (``p(detect | d)``)."""

    series_label: str
    label: str
    y_label: str


@dataclass(frozen=True)
class ViewAxis:
    """What the x axis of a run's proposal view is (the panel's *Live* charts of q(detect) over the visited states).

    Attributes:
        label: the axis title, with its unit.
        subject: whose detections the view holds (e.g. ``car 0``), named in the titles of a view of one object
            among several.
        standing_signal: the observation whose bins the chart checks for standing states (the same value as one step
            before), or None: no such check (the view is of one object among several).
        window_name: what the mean q(miss) of the title is taken over (``below``, ``within``).
        edges: float64 [B + 1] the bins' edges (metres).
        series_label: the legend of the x values.
        view_object: None: the batch's own signal (one object a step); else the object whose detections the view
            follows among several.
        distance_column, visible_column: the object rows' columns that place the followed object and say whether
            the sensor can see it (a view of one object among several)."""

    label: str
    subject: str
    standing_signal: str | None
    window_name: str
    edges: np.ndarray
    series_label: str
    view_object: int | None = None
    distance_column: str = ""
    visible_column: str = ""

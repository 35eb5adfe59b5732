"""The cut-in scenario's hooks of the panel (:class:`pemviz.app.drawing.PanelDrawing`), mixed into
:class:`pemviz.scenarios.cut_in.drawing.CutInDrawing`: its scene (every car on a road of three lanes, seen from the
ego), the proposal view of the car that cuts in and the story of a rollout (:mod:`pemviz.scenarios.cut_in.story`).
Plain data, no viser (:mod:`pemviz.scenarios.panel_data`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz.scenarios.panel_data import CurveAxis, ObjectsScene, ViewAxis

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.cut_in.scenario import CutInParams
    from pemviz.scenarios.cut_in.story import CutInStory

CAR_M = (4.5, 1.8)
"""Length and width of a car as the panel draws it (metres)."""
N_LANES = 3
"""The lanes drawn: the ego's and one on each side."""
GAP_BINS_M = np.linspace(0.0, 40.0, 41)
"""Bins of the proposal view: the cut-in car's gap ahead (its rear minus the ego's front bumper, metres), 1 m wide, 0
to 40 m (the cut-in starts 20 m ahead; the proposal reads cars within 40 m,
:data:`pemviz.scenarios.cut_in.problem.CUT_IN_WINDOW_M`)."""
VIEW_OBJECT = 0
"""The object whose detections the proposal view follows: the cut-in car (object 0 of
:attr:`pemviz.scenarios.cut_in.scenario.CutInParams.vehicles`)."""


class CutInPanel:
    """What the panel draws of a cut-in rollout (the ``params`` attribute is the drawing object's): an
    :class:`~pemviz.scenarios.panel_data.ObjectsScene`."""

    params: CutInParams

    @property
    def n_steps(self) -> int:
        """T, the steps of a rollout."""
        return int(self.params.n_steps)

    def panel_scene(self) -> ObjectsScene:
        """The scene's constants: the cars' boxes, the lanes, the object rows' gap column and every car at the start
        seen from the ego (:func:`start_positions`)."""
        from pemviz.scenarios.cut_in.scenario import LANE_WIDTH_M
        from pemviz.scenarios.cut_in.story import car_labels

        return ObjectsScene(
            CAR_M[0],
            CAR_M[1],
            LANE_WIDTH_M,
            N_LANES,
            "gap_m",
            int(self.params.n_steps),
            start_positions(self.params),
            car_labels(self.params.n_objects),
        )

    def proposal_axis(self) -> ViewAxis:
        """The proposal view's bins: the cut-in car's gap ahead, 1 m wide (:data:`GAP_BINS_M`), over the states where
        the camera sees it."""
        return ViewAxis(
            "car 0's gap ahead (m), 1 m bins",
            "car 0 (the cut-in car)",
            None,
            "within",
            GAP_BINS_M,
            "car 0's gap (m)",
            VIEW_OBJECT,
            "gap_m",
            "visible",
        )

    def curve_axis(self) -> CurveAxis:
        """The reference-state curves' x axis: the range from the camera to the cut-in car placed straight ahead in the
        ego's lane, unoccluded (:func:`pemviz.scenarios.cut_in.problem.cut_in_problem`'s ``curve_rows``)."""
        return CurveAxis("range (m)", "range r (m) of car 0, straight ahead in the ego's lane", "p(detect | r)")

    def group_heading(self) -> tuple[str, str]:
        """The rollouts table's group column: its heading, and the start of each group's label that it says."""
        return "group", ""

    def objects_story(self, batch: RolloutBatch, names: tuple[str, ...]) -> CutInStory | None:
        """What happened in rollout 0 of ``batch`` (:func:`pemviz.scenarios.cut_in.story.cut_in_story`, the cut-in
        car named ``names[0]``), or None: its rows lack the columns the story reads."""
        from pemviz.scenarios.cut_in.story import cut_in_story, has_story_columns

        object_names = tuple(batch.object_names or ())
        if batch.objects is None or not has_story_columns(tuple(batch.observation_names), object_names):
            return None
        return cut_in_story(
            batch.observations[0],
            tuple(batch.observation_names),
            batch.objects[0],
            object_names,
            batch.detected[0],
            float(self.params.dt_s),
            VIEW_OBJECT,
            names[0],
        )


def start_positions(params: CutInParams) -> tuple[tuple[float, float], ...]:
    """Each of the M cars at step 0 seen from the ego's camera, in object order: (right, ahead) in metres, the rows'
    ``loc_x`` and ``loc_z`` at every rollout's start, from the scenario's own geometry
    (:func:`pemviz.scenarios.cut_in.scene.traffic_at`, :func:`~pemviz.scenarios.cut_in.scene.camera_view`) without
    highway-env."""
    from pemviz.scenarios.cut_in.scenario import LANE_WIDTH_M
    from pemviz.scenarios.cut_in.scene import CutInMemory, camera_view, traffic_at

    cars = params.vehicles
    length = params.vehicle_length_m
    x = np.array([length / 2 + v.gap_m + length / 2 for v in cars])
    y = np.array([v.lane * LANE_WIDTH_M for v in cars], dtype=np.float64)
    speed = np.array([v.speed_mps for v in cars], dtype=np.float64)
    traffic, _ = traffic_at(params, 0, x, y, np.zeros(len(cars)), speed, CutInMemory.initial(len(cars)))
    view = camera_view(params, traffic, np.zeros(1))
    return tuple((float(view.loc_x_m[j, 0]), float(view.loc_z_m[j, 0])) for j in range(len(cars)))

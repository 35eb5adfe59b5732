"""The panel draws what a scenario's drawing object gives it (:mod:`pemviz.app.drawing`): the built-in drawings have
the panel's hooks, and their data are the scenarios' constants (that the panel's code names no scene is
``tests/project/test_scene_words.py``'s)."""

from __future__ import annotations

import numpy as np
from pemviz.app.drawing import LanePanel, ObjectsPanel, lane_panel, objects_panel
from pemviz.app.panel import idle_drawing
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.failures import severity
from pemviz.scenarios.braking.simulator import OBSERVATION_NAMES, BrakingParams
from pemviz.scenarios.cut_in.drawing import CutInDrawing
from pemviz.scenarios.cut_in.scenario import LANE_WIDTH_M, CutInParams
from pemviz.scenarios.panel_data import LaneScene, ObjectsScene


def test_the_braking_drawing_gives_a_lane_scene_of_its_constants():
    p = BrakingParams()
    d = BrakingDrawing(p)
    assert isinstance(d, LanePanel) and lane_panel(d) is d and objects_panel(d) is None
    scene = d.panel_scene()
    assert isinstance(scene, LaneScene)
    assert (
        scene.ego_length_m,
        scene.object_length_m,
        scene.width_m,
        scene.sensor_offset_m,
        scene.start_distance_m,
    ) == (p.ego_length_m, p.lead_length_m, p.vehicle_width_m, p.camera_offset_m, p.gap0_m)
    assert [(z.role, z.length_m) for z in scene.zones] == [("window", p.braking_distance_m), ("margin", p.crash_gap_m)]
    assert scene.n_steps == d.n_steps == p.n_steps and scene.object_start_x == p.camera_offset_m + p.gap0_m + 2.48
    assert scene.strip_title == "gap and speeds" and d.curve_axis().label == "gap d (m)"
    # a rollout's hooks: positions, the strip chart's lines, the explanation, the caption, the outcome
    t = p.n_steps
    obs = np.zeros((1, t, len(OBSERVATION_NAMES)))
    obs[0, :, 0] = np.linspace(12.0, 1.0, t)
    obs[0, :, 1] = 5.0
    detected, zeros = np.zeros((1, t), bool), np.zeros((1, t))
    batch = RolloutBatch(obs, detected, zeros, zeros, tuple(OBSERVATION_NAMES))
    ego_x, object_x, ruler = d.lane_positions(batch, 0)
    np.testing.assert_allclose(ego_x, p.dt_s * 5.0 * np.arange(t))
    np.testing.assert_allclose(object_x - ego_x, p.camera_offset_m + obs[0, :, 0] + p.lead_length_m / 2)
    np.testing.assert_array_equal(ruler, obs[0, :, 0])
    lines = d.strip_series(batch, 0)
    assert [s.role for s in lines] == ["main", "ego", "object"] and lines[0].values is not None
    ex = d.lane_explanation(batch, 0)
    assert ex.contact.shape == (t,) and ex.crashed
    before, after = d.step_caption(batch, 0, ex, 3)
    assert before.startswith(f"gap {obs[0, 3, 0]:.2f} m · ego 5.00 m/s") and after.startswith("brake ")
    assert d.outcome(batch, 0).short == severity(obs[0, :, 0], p).short


def test_the_cut_in_drawing_gives_a_scene_of_several_objects():
    d = CutInDrawing(CutInParams())
    assert isinstance(d, ObjectsPanel) and objects_panel(d) is d and lane_panel(d) is None
    scene = d.panel_scene()
    assert isinstance(scene, ObjectsScene) and scene.lane_width_m == LANE_WIDTH_M and scene.n_lanes == 3
    axis = d.proposal_axis()
    assert axis.view_object == 0 and axis.standing_signal is None and axis.edges[-1] == 40.0
    assert d.curve_axis().y_label == "p(detect | r)" and d.group_heading() == ("group", "")


def test_the_idle_scene_is_the_configured_scenarios_else_the_first_that_draws_one_lane():
    assert isinstance(idle_drawing("braking"), BrakingDrawing)
    assert lane_panel(idle_drawing("cut-in")) is not None  # the cut-in draws several objects: another's lane scene

"""The panel names no scenario: it draws what a scenario's drawing object gives it (:mod:`pemviz.app.drawing`). The
built-in drawings have the panel's hooks, their data are the scenarios' constants, the panel's code (identifiers and
strings) holds no scene word and its docstrings and comments name a scene only as an example."""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import numpy as np

from pemviz.app.drawing import LanePanel, LaneScene, ObjectsPanel, ObjectsScene, lane_panel, objects_panel
from pemviz.app.panel import idle_drawing
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.braking import OBSERVATION_NAMES, BrakingParams
from pemviz.scenarios.braking_drawing import BrakingDrawing
from pemviz.scenarios.braking_failures import severity
from pemviz.scenarios.cut_in import LANE_WIDTH_M, CutInParams
from pemviz.scenarios.cut_in_drawing import CutInDrawing

APP = Path(__file__).resolve().parents[1] / "pemviz" / "app"
SCENE_WORDS = re.compile(r"braking|gap_m|\blead\b|cut[-_]in|BrakingParams|CutInParams", re.IGNORECASE)
"""The words that name a built-in scene or its columns."""
EXAMPLE = re.compile(r"\be\.g\.|\bfor example\b", re.IGNORECASE)
"""A docstring or comment line that names a scene as an example (allowed)."""


def forbidden_scene_words(path: Path) -> list[str]:
    """``file:line: text`` of each scene word of ``path`` in code (an identifier or a string that is not a docstring),
    and of each in a docstring or comment on a line that does not name it as an example (``e.g.``, ``for example``)."""
    src = path.read_text()
    lines = src.splitlines()
    docs = set()
    for node in ast.walk(ast.parse(src)):
        body = getattr(node, "body", None)
        for st in body if isinstance(body, list) else []:
            if isinstance(st, ast.Expr) and isinstance(st.value, ast.Constant) and isinstance(st.value.value, str):
                docs.update(range(st.lineno, st.end_lineno + 1))
    found = []
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        for k, part in enumerate(tok.string.split("\n")):
            line = tok.start[0] + k
            in_code = tok.type != tokenize.COMMENT and line not in docs
            if SCENE_WORDS.search(part) and (in_code or not EXAMPLE.search(lines[line - 1])):
                found.append(f"{path.name}:{line}: {lines[line - 1].strip()}")
    return found


def test_the_panels_code_names_no_scenario_and_its_docstrings_only_as_an_example():
    found = [hit for path in sorted(APP.glob("*.py")) for hit in forbidden_scene_words(path)]
    assert found == []


def test_the_braking_drawing_gives_a_lane_scene_of_its_constants():
    p = BrakingParams()
    d = BrakingDrawing(p)
    assert isinstance(d, LanePanel) and lane_panel(d) is d and objects_panel(d) is None
    scene = d.panel_scene()
    assert isinstance(scene, LaneScene)
    assert (scene.ego_length_m, scene.object_length_m, scene.width_m, scene.sensor_offset_m, scene.start_distance_m) \
        == (p.ego_length_m, p.lead_length_m, p.vehicle_width_m, p.camera_offset_m, p.gap0_m)
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

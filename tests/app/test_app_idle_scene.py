"""The panel's idle 3D scene follows the scenario chosen for the next run: a lane scene at its drawing's constants
(braking), a road of lanes with every car at its start seen from the ego (cut-in), no scene for a scenario that draws
none (toy); a rollout shown is drawn as before and *back to idle* goes to the chosen scenario's scene.

The first tests drive :class:`pemviz.app.scene_view.SceneView` with a stand-in viser client (no browser); the last,
in headless Chromium (the helpers of ``tests/app/test_app.py``), chooses the scenarios in the *Experiment* tab's
dropdown and reads the browser's scene graph. With ``PEMVIZ_IDLE_SHOTS=<folder>`` it saves ``idle_cut_in.png`` and
``idle_braking.png`` there.
"""

from __future__ import annotations

import contextlib
import html
import os
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from pemviz.app.drawing import scenario_drawing
from pemviz.app.scene_view import SceneView
from pemviz.core.problem_view import object_scene
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.cut_in.batched import BatchedCutIn
from pemviz.scenarios.cut_in.panel import start_positions
from pemviz.scenarios.cut_in.scenario import OBJECT_NAMES, CutInParams
from pemviz.sinks.colours import IDLE, OBJECT


class Node(SimpleNamespace):
    """A scene node or GUI handle as the scene view uses it: its name, properties, removal and callbacks."""

    removed = False

    def remove(self) -> None:
        assert not self.removed, f"{self.name} removed twice"
        self.removed = True

    def on_update(self, callback) -> None:
        self.callback = callback

    on_click = on_update


class StandInClient:
    """The parts of a viser client the scene view calls (``scene``, ``gui``, ``camera``, ``atomic``), keeping every
    node by name (the newest of a name)."""

    def __init__(self) -> None:
        self.nodes: dict[str, Node] = {}
        self.scene = SimpleNamespace(
            set_up_direction=lambda _: None,
            add_box=self._add,
            add_label=self._label,
            add_line_segments=self._segments,
            add_point_cloud=self._points,
        )
        self.gui = SimpleNamespace(
            add_slider=self._gui,
            add_button=self._gui,
            add_checkbox=self._gui,
            add_html=lambda content: Node(content=content),
        )
        self.camera = SimpleNamespace(aspect=0.6, fov=1.3, position=(0, 0, 0), look_at=(0, 0, 0))
        self.atomic = contextlib.nullcontext

    def _add(self, name: str, **props) -> Node:
        props.setdefault("visible", True)
        self.nodes[name] = Node(name=name, **props)
        return self.nodes[name]

    def _label(self, name: str, text: str, **props) -> Node:
        return self._add(name, text=text, **props)

    def _segments(self, name: str, points, **props) -> Node:
        return self._add(name, points=points, **props)

    def _points(self, name: str, points, **props) -> Node:
        return self._add(name, points=points, **props)

    def _gui(self, label: str, *args, **props) -> Node:
        return Node(label=label, value=props.get("initial_value", args[0] if args else None), **props)

    def shown(self, prefix: str) -> list[str]:
        """The names of the live, visible nodes under ``prefix`` whose parents are visible too."""

        def visible(name: str) -> bool:
            parent = name.rsplit("/", 1)[0]
            return self.nodes[name].visible and (not parent or parent not in self.nodes or visible(parent))

        return sorted(n for n, node in self.nodes.items() if n.startswith(prefix) and not node.removed and visible(n))


@pytest.fixture
def view():
    """A scene view built as a session builds it, on the braking lane scene, with a stand-in client."""
    client = StandInClient()
    explain = SimpleNamespace(cleared=[], clear=lambda why: explain.cleared.append(why))
    scene = SceneView(client, BrakingDrawing(BrakingParams()), threading.RLock(), explain)  # type: ignore[arg-type]
    scene.build_controls()
    scene.build_scene()
    return scene, client, explain


def caption(scene: SceneView) -> str:
    """The text under the scene (its HTML unescaped)."""
    return html.unescape(scene.scene_html.content)


def cars_at(client: StandInClient) -> list[tuple[float, float]]:
    """The visible cars of the scene of several objects: (ahead, left) of each box (metres, the ego at 0)."""
    return [tuple(client.nodes[n].position[:2]) for n in client.shown("/objects/car") if not n.endswith("/label")]


def test_the_cut_in_cars_start_where_every_rollout_of_it_starts():
    p = CutInParams()
    rows = BatchedCutIn(p, 1).objects()[0]  # [M, G] at step 0, the scenario's own simulator
    x, z = OBJECT_NAMES.index("loc_x"), OBJECT_NAMES.index("loc_z")
    assert start_positions(p) == tuple(zip(rows[:, x].tolist(), rows[:, z].tolist(), strict=False))
    assert scenario_drawing("cut-in").panel_scene().start_xy_m == start_positions(p)
    assert len(start_positions(CutInParams(n_objects=3))) == 3
    assert scenario_drawing("toy") is None and scenario_drawing("no-such-scenario") is None


def test_the_idle_scene_follows_the_chosen_scenario(view):
    scene, client, explain = view
    lane_nodes = ["/lead", "/road", "/gap_ruler", "/ego/brake_zone_10m"]
    scene.choose_scenario("braking")
    assert set(lane_nodes) <= set(client.shown("/")) and client.shown("/objects") == []
    assert client.nodes["/lead"].position[0] == pytest.approx(scene.lane.object_start_x)
    assert "No rollout chosen: the braking scenario" in caption(scene)

    scene.choose_scenario("cut-in")
    starts = scenario_drawing("cut-in").panel_scene().start_xy_m
    assert len(starts) == CutInParams().n_objects == 5
    assert not set(lane_nodes) & set(client.shown("/"))  # the lane scene's nodes hidden
    assert {"/ego", "/ego/label", "/objects/road", "/objects/lanes"} <= set(client.shown("/"))
    assert cars_at(client) == [(ahead, -right) for right, ahead in starts]  # the ego's right is -y
    assert [client.nodes[f"/objects/car{j}/label"].text for j in range(5)] == [f"car {j}" for j in range(5)]
    assert client.nodes["/ego"].color == IDLE and client.nodes["/objects/car0"].color == OBJECT
    assert "No rollout chosen: the cut-in scenario's 5 cars at their start" in caption(scene)
    assert client.nodes["/objects/road"].dimensions[1] == pytest.approx(3 * 4.0 + 1.0)  # its three 4 m lanes

    scene.choose_scenario("toy")
    assert client.shown("/") == [] and "The toy scenario draws no scene" in caption(scene)

    scene.choose_scenario("braking")
    assert set(lane_nodes) <= set(client.shown("/")) and client.shown("/objects") == []
    assert "/ego/label" in client.shown("/") and client.nodes["/ego"].color == IDLE
    assert explain.cleared == []  # choosing a scenario leaves Explain as it is


def test_back_to_idle_is_the_chosen_scenarios_scene_and_another_lane_scene_is_drawn_at_its_constants(view):
    scene, client, explain = view
    scene.choose_scenario("cut-in")
    scene.shown = object()  # a rollout shown: choosing a scenario waits until it is not
    scene.choose_scenario("braking")
    assert client.shown("/lead") == [] and len(cars_at(client)) == 5
    scene.clear("run 2 is going")  # back to idle: the scenario chosen now
    assert "/lead" in client.shown("/") and client.shown("/objects") == []
    assert explain.cleared == ["run 2 is going"] and "run 2 is going. No rollout chosen" in caption(scene)
    first_lead = client.nodes["/lead"]
    longer = BrakingDrawing(BrakingParams(gap0_m=20.0, braking_distance_m=14.0))
    scene.idle_drawing = longer
    scene.clear(None)  # a lane scene of other constants: made again at them
    assert first_lead.removed and scene.lane == longer.panel_scene()
    assert client.nodes["/lead"].position[0] == pytest.approx(longer.panel_scene().object_start_x)
    assert client.nodes["/ego/brake_zone_10m"].dimensions[0] == 14.0
    assert not any(n.removed for name, n in client.nodes.items() if name in client.shown("/"))


def test_a_rollouts_first_step_puts_the_cars_where_the_idle_scene_does():
    """The panel reads a rollout's object positions with :func:`pemviz.core.problem_view.object_scene` (what a shown
    rollout draws at step 0): the idle scene's cars."""
    p = CutInParams()
    rows = BatchedCutIn(p, 1).objects()  # [1, M, G]: step 0 of one rollout
    batch = SimpleNamespace(
        objects=rows[:, None], object_names=OBJECT_NAMES, detected=np.zeros((1, 1, 5), bool), noise=None
    )
    sc = object_scene(SimpleNamespace(objects_xy=("loc_x", "loc_z"), noise_xy=None), batch)
    assert [(float(sc.lateral_m[0, j]), float(sc.ahead_m[0, j])) for j in range(5)] == list(start_positions(p))


# -- in the browser ---------------------------------------------------------------------------------
try:  # the browser test needs playwright and chromium (test_app skips without them); the tests above do not
    from .test_app import app, browser, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)

    NO_BROWSER = ""
except pytest.skip.Exception as exc:
    NO_BROWSER = str(exc) or "no browser"

SCENE_STATE = """() => {
    const tree = window.__viserSceneTree.getState();
    const shown = (n) => { for (let p = n; p; p = p.slice(0, p.lastIndexOf('/'))) {
        if (tree[p] === undefined) { if (p === n) return false; continue; }
        if (tree[p].visibility === false || tree[p].message?.props?.visible === false) return false; } return true; };
    const m = window.__viserMutable.nodeRefFromName;
    const cars = Object.keys(tree).filter(n => /^\\/objects\\/car\\d+$/.test(n) && shown(n)).sort();
    return {lead: shown('/lead'), road: shown('/road'), zone: shown('/ego/brake_zone_10m'), ego: shown('/ego'),
            objects_road: shown('/objects/road'), cars: cars.map(n => [m[n].position.x, m[n].position.y])};
}"""
"""The browser's scene: which nodes show (their own and their parents' visibility) and the cars' places."""


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)
def test_choosing_a_scenario_in_the_browser_draws_its_idle_scene(browser, app):  # noqa: F811
    shots = Path(os.environ["PEMVIZ_IDLE_SHOTS"]) if os.environ.get("PEMVIZ_IDLE_SHOTS") else None

    def state(page):
        return page.evaluate(SCENE_STATE)

    def shoot(page, name: str) -> None:
        if shots is not None:
            page.wait_for_function("() => document.fonts.ready.then(() => true)")
            shots.mkdir(parents=True, exist_ok=True)
            page.screenshot(path=str(shots / name))

    for tab in open_tab(browser, app):
        page, scene = tab.page, tab.session.scene
        assert tab.session.choices["scenario"].value == "braking"
        wait_until(
            lambda page=page: state(page)["lead"] and state(page)["zone"] and not state(page)["objects_road"],
            what="the braking lane scene at first",
        )
        tab.choose("scenario", "cut-in")
        starts = scenario_drawing("cut-in").panel_scene().start_xy_m
        want = sorted((ahead, -right) for right, ahead in starts)

        def cut_in_drawn(page=page, want=want) -> bool:
            s = state(page)
            return (
                s["objects_road"]
                and not s["lead"]
                and not s["road"]
                and not s["zone"]
                and s["ego"]
                and sorted(map(tuple, s["cars"])) == want
            )

        wait_until(cut_in_drawn, what="the cut-in's road with its 5 cars at their start, no lane scene")
        assert "No rollout chosen: the cut-in scenario's 5 cars" in caption(scene)
        # the scene's own method and budget (the tilt, 7,280 rollouts), and the cost line says the run counts more
        wait_until(
            lambda: ("Cost: 7,280 simulations plus the proposal's look-aheads" in page.inner_text("body")),  # noqa: B023 (called within the iteration)
            what="the cut-in's cost line",
        )
        shoot(page, "cost_cut_in.png")
        tab.tab("Rollouts")
        shoot(page, "idle_cut_in.png")
        tab.tab("Experiment")
        tab.choose("scenario", "toy")
        wait_until(
            lambda: not any(
                state(page)[k]  # noqa: B023 (called within the iteration)
                for k in ("lead", "road", "ego", "objects_road")
            ),
            what="no scene for the toy",
        )
        assert "The toy scenario draws no scene" in caption(scene)
        tab.choose("scenario", "braking")
        wait_until(
            lambda: (
                lambda s: s["lead"]
                and s["road"]
                and s["zone"]
                and s["ego"]
                and not s["objects_road"]
                and s["cars"] == []
            )(state(page)),  # noqa: B023 (called within the iteration)
            what="the braking lane scene again",
        )
        tab.tab("Rollouts")
        shoot(page, "idle_braking.png")

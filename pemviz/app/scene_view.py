"""The 3D scene of a :class:`pemviz.app.session.Session`: the chosen rollout's cars, played step by step in sync with
*Explain*, as its drawing object gives them; before any rollout, the idle scene of the chosen scenario."""

from __future__ import annotations

import html
import math
import threading

import numpy as np
import viser

from pemviz.app import objects_view as OV
from pemviz.app._viser_compat import set_value
from pemviz.app.drawing import LanePanel, lane_panel, panel_scene, scenario_drawing
from pemviz.app.explain_tab import ExplainTab
from pemviz.app.html import BLUE, GREY, RED, box
from pemviz.app.runs import PanelRun, Trajectory
from pemviz.app.scene_layout import (
    CAR_HEIGHT_M,
    DEFAULT_ASPECT,
    DEFAULT_FOV,
    GROUND_M,
    LABEL_SCALE,
    ROW_Y_M,
    add_lane_nodes,
    camera_pose,
    floor_lines,
    framing_distance,
    ruler_segments,
)
from pemviz.core.problem_view import object_label
from pemviz.scenarios.panel_data import LaneScene, ObjectsScene
from pemviz.sinks import colours as C
from pemviz.sinks.colours import CRASH, DETECTED, IDLE, MISSED, OBJECT

TRAIL_POINT_M = 0.35
"""The side of a detection's square in the trail (metres)."""
DEFAULT_OBJECTS = ObjectsScene(1.0, 1.0, 4.0, 0, "", 0)
"""The scene of several objects of a problem whose drawing gives none: 1 m boxes on open ground (no road: the scene
may be a crosswalk, a warehouse or a field)."""
OBJECTS_FRAME_M = (-10.0, 60.0)
"""The stretch of road the camera frames in the scene of several objects, from behind the ego to ahead (metres)."""


def _plural(labels: list[str]) -> str:
    """What a scene's objects are, in the plural, from their labels: ``cars`` for ``car 0``, ``car 1``; else
    ``objects``."""
    kinds = {label.split(" ")[0] for label in labels}
    return f"{kinds.pop()}s" if len(kinds) == 1 and len(labels) > 0 and all(" " in x for x in labels) else "objects"


class SceneView:
    """The 3D scene and its playback (step slider, Play, follow cars, caption under *Rollouts*), the rollout shown and
    whether it plays; the :class:`pemviz.app.explain_tab.ExplainTab` it is given follows it.

    Raises:
        ValueError: ``drawing`` draws no lane scene."""

    def __init__(
        self, client: viser.ClientHandle, drawing: LanePanel, lock: threading.RLock, explain: ExplainTab
    ) -> None:
        lane = panel_scene(drawing)
        if not isinstance(lane, LaneScene):
            raise ValueError(f"the idle scene's drawing {type(drawing).__name__} draws no lane scene")
        self.client, self.drawing, self.lock, self.explain = client, drawing, lock, explain
        self.lane: LaneScene = lane
        """The constants of the lane scene drawn: the road's cars, zones and labels (the idle scene's, else the lane
        rollout's shown)."""
        self.idle_name = ""
        """The scenario chosen for the next run (:meth:`choose_scenario`; empty: none chosen yet)."""
        self.idle_drawing: object | None = drawing
        """Its drawing object, whose scene is the idle one (None: it draws none)."""
        self.shown_drawing: LanePanel | None = None
        """The drawing of the rollout shown in a lane scene (None: none, or one of several objects)."""
        self.shown: Trajectory | None = None
        """The rollout shown (None: the idle scene)."""
        self.shown_record: PanelRun | None = None
        """The run of :attr:`shown`."""
        self.shown_step = -1
        self._shown_x: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        """The rollout shown in a lane scene: the ego's and the object's centres and the ruler's length, [T] each."""
        self._shown_span = 0.0
        """Metres of road the scene frames for the rollout shown (its cars' longest stretch)."""
        self.playing = False

    def build_controls(self) -> None:
        """Add the playback controls to the tab open in ``client.gui`` (the *Rollouts* tab, below its list)."""
        gui = self.client.gui
        self.step_slider = gui.add_slider("step", min=0, max=self.lane.n_steps - 1, step=1, initial_value=0)
        self.play_button = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        self.follow = gui.add_checkbox("follow cars", True, hint="move the camera along with the cars")
        self.scene_html = gui.add_html("")
        self.step_slider.on_update(lambda _: self.render_step(int(self.step_slider.value)))
        self.play_button.on_click(lambda _: self._toggle_play())

    def show(self, record: PanelRun, traj: Trajectory) -> None:
        """Show ``traj`` of ``record`` (a rollout chosen under *Rollouts*), paused at its start; a rollout of several
        objects at its first decisive step; nothing for a problem without a scene (a toy)."""
        with self.lock:
            drawing = record.view.drawing if record is not None and record.view is not None else None
            lane = lane_panel(drawing)
            if lane is None:
                assert record.view is not None  # a rollout's run has started: it has its problem's view
                if traj.several and record.view.objects_xy is not None:  # a scene of several objects
                    self._show_objects(record, traj)
                else:  # a problem that draws no scene (a toy, a scenario of one's own): Explain says so too
                    self._scene_kind(None)
                    why = f"the {record.view.name} scenario draws no scene: its rollouts are under Rollouts and Live"
                    self.scene_html.content = box(html.escape(why), GREY)
                    self.explain.clear(why)
                return
            self.explain.explain_lane(traj, lane)
            self._use_lane(lane.panel_scene())
            self._scene_kind(0)
            self.shown = traj
            self.shown_record = record
            self.shown_drawing = lane
            self._shown_x = lane.lane_positions(traj.batch, 0)
            self.step_slider.max = traj.n_steps - 1
            self._set_playing(False)
            self.explain.fill(record, traj, lane)
            self._place_rollout()
            self.shown_step = -1
            if self.step_slider.value != 0:
                set_value(self.step_slider, 0)  # renders step 0 through the slider's callback
            else:
                self.render_step(0)

    def _show_objects(self, record: PanelRun, traj: Trajectory) -> None:
        """Show a rollout of a scene of several objects, paused at its first decisive step (else step 0)."""
        assert record.view is not None  # checked by show()
        ox = self.explain.explain_objects(record, traj)
        self.shown, self.shown_record, self._shown_x, self.shown_drawing = traj, record, None, None
        self.step_slider.max = traj.n_steps - 1
        self._set_playing(False)
        self.shown_step = -1
        scene = panel_scene(record.view.drawing)
        self.ego_box.color = OBJECT
        self._scene_kind(ox.detected.shape[1], scene if isinstance(scene, ObjectsScene) else DEFAULT_OBJECTS)
        self._frame_objects()
        self.scene_html.content = box(
            f"Scene: {html.escape(record.short_label)} {traj.name}, every object seen from the ego (blue-grey): green "
            "detected, orange missed, grey unseen. Explain draws them from above with where each was measured.",
            GREY,
        )
        decisive = ox.counterfactuals.decisive if ox.counterfactuals is not None else ()
        first = decisive[0].step if decisive else 0
        if self.step_slider.value != first:
            set_value(self.step_slider, first)  # renders it through the slider's callback
        else:
            self.render_step(first)

    def _toggle_play(self) -> None:
        with self.lock:
            if self.shown is None:
                return
            if not self.playing and int(self.step_slider.value) >= self.shown.n_steps - 1:
                set_value(self.step_slider, 0)
            self._set_playing(not self.playing)

    def _set_playing(self, playing: bool) -> None:
        self.playing = playing
        self.play_button.label = "Pause" if playing else "Play"
        self.play_button.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY

    def play_tick(self) -> None:
        """Advance the playback by one step (called every dt by the server's player thread)."""
        with self.lock:
            if not self.playing or self.shown is None:
                return
            step = int(self.step_slider.value) + 1
            if step > self.shown.n_steps - 1:
                self._set_playing(False)
                return
            set_value(self.step_slider, step)

    def build_scene(self) -> None:
        """Add the scene's nodes to ``client.scene``: the road, the cars, the zones and the ruler of the lane scene of
        :attr:`lane` (:func:`pemviz.app.scene_layout.add_lane_nodes`), the ego, the trail, the breach gate and the
        ego's label."""
        scene = self.client.scene
        p = self.lane
        scene.set_up_direction("+z")
        self.ego_box = scene.add_box(
            "/ego",
            color=IDLE,
            dimensions=(p.ego_length_m, p.width_m, CAR_HEIGHT_M),
            position=(0.0, 0, CAR_HEIGHT_M / 2),
        )
        self._lane_nodes: list = []
        """What only the lane scene shows (hidden while a scene of several objects is shown), last made last."""
        self._object_nodes: list = []
        """A scene of several objects: its road, its lane lines, then a box and a label per object, made when first
        shown."""
        self._objects_road: tuple = ()
        """The car sizes and lanes of :attr:`_object_nodes` (they are made again for other ones)."""
        self._use_lane(p, force=True)
        # past detections, on the road where the ego's rear was at each step; the breach: a red gate at the place
        # where the ego's sensor breached the failure margin
        self.trail = scene.add_point_cloud(
            "/trail",
            np.zeros((1, 3), np.float32),
            colors=IDLE,
            point_size=TRAIL_POINT_M,
            point_shape="square",
            precision="float32",
            point_shading="flat",
            visible=False,
        )
        self.breach_gate = scene.add_box(
            "/breach",
            color=CRASH,
            dimensions=(0.12, p.width_m + 1.0, CAR_HEIGHT_M + 0.7),
            opacity=0.7,
            position=(0.0, 0.0, (CAR_HEIGHT_M + 0.7) / 2),
            cast_shadow=False,
            receive_shadow=False,
            visible=False,
        )
        self.breach_label = scene.add_label(
            "/breach/label",
            "",
            position=(0.0, ROW_Y_M["left"], -(CAR_HEIGHT_M + 0.7) / 2),
            anchor="center-right",
            font_screen_scale=LABEL_SCALE,
        )
        self.scene_label = scene.add_label(
            "/ego/label",
            "ego: no rollout chosen",
            position=(0.0, ROW_Y_M["right"], -CAR_HEIGHT_M / 2),
            anchor="center-left",
            font_screen_scale=LABEL_SCALE,
        )
        object0 = p.object_start_x
        self._frame(0.0, object0, self._span(np.zeros(1), np.full(1, object0)))

    def _use_lane(self, lane: LaneScene, force: bool = False) -> None:
        """Draw lane scenes at ``lane``'s constants from now on (:attr:`lane`): its road, object, zones and ruler are
        made again where they differ from those drawn (``force``: made in any case)."""
        if lane == self.lane and not force:
            return
        for node in reversed(self._lane_nodes):  # children before their parents
            node.remove()
        self.lane = lane
        self._lane_nodes, self.object_box, self.gap_ruler, self.gap_label = add_lane_nodes(self.client.scene, lane)
        self.ego_box.dimensions = (lane.ego_length_m, lane.width_m, CAR_HEIGHT_M)

    def _scene_kind(self, objects: int | None, layout: ObjectsScene | None = None) -> None:
        """Show the lane scene (``objects`` 0, no ``layout``), a road of ``layout``'s lanes with its first ``objects``
        cars, or no scene (``objects`` None: a problem that draws none)."""
        scene = self.client.scene
        road = (
            None if layout is None else (layout.car_length_m, layout.car_width_m, layout.lane_width_m, layout.n_lanes)
        )
        if road is not None and (road != self._objects_road or len(self._object_nodes) < 2 + 2 * (objects or 0)):
            assert layout is not None  # road is layout's
            lane_m = layout.lane_width_m
            lanes = layout.n_lanes * lane_m if layout.n_lanes else GROUND_M[1]
            for node in self._object_nodes:
                node.remove()
            self._object_nodes = [
                scene.add_box(
                    "/objects/road",
                    color=C.ROAD if layout.n_lanes else C.GROUND,
                    dimensions=(GROUND_M[0], lanes + 1.0, 0.05),
                    position=(60.0, 0.0, -0.03),
                    cast_shadow=False,
                    visible=False,
                )
            ]
            self._object_nodes.append(
                scene.add_line_segments(
                    "/objects/lanes",
                    floor_lines(layout.n_lanes, lane_m),
                    colors=C.ROAD_MARKING,
                    thickness=0.12,
                    visible=False,
                )
            )
            for j in range(objects or 0):
                self._object_nodes.append(
                    scene.add_box(
                        f"/objects/car{j}",
                        color=IDLE,
                        dimensions=(layout.car_length_m, layout.car_width_m, CAR_HEIGHT_M),
                        position=(0.0, 0.0, CAR_HEIGHT_M / 2),
                        visible=False,
                    )
                )
                self._object_nodes.append(
                    scene.add_label(
                        f"/objects/car{j}/label",
                        object_label(layout.object_labels, j),
                        position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 0.2 + 0.7 * (j % 2)),  # neighbours' labels apart
                        anchor="bottom-center",
                        font_screen_scale=LABEL_SCALE,
                        visible=False,
                    )
                )
            self._objects_road = road
        lane = objects == 0 and layout is None
        with self.client.atomic():
            for node in self._lane_nodes:
                node.visible = lane
            for k, node in enumerate(self._object_nodes):  # the road and its lines, then each car and its label
                node.visible = road is not None and (k < 2 or (k - 2) // 2 < (objects or 0))
            self.ego_box.visible = self.scene_label.visible = objects is not None
            if not lane:
                self.trail.visible = self.breach_gate.visible = self.breach_label.visible = False

    def _place_objects(self, xy: list[tuple[float, float] | None], colours: list, texts: list[str], label: str) -> None:
        """Put car ``j`` of the scene of several objects at ``xy[j]`` (to the right, ahead of the ego, metres; None:
        hidden) in ``colours[j]`` with the label ``texts[j]``, the ego at the origin, hide the cars beyond them and
        write ``label`` beside the ego."""
        with self.client.atomic():
            self.ego_box.position = (0.0, 0.0, CAR_HEIGHT_M / 2)
            for j, place in enumerate(xy):
                box_, text = self._object_nodes[2 + 2 * j], self._object_nodes[3 + 2 * j]
                box_.visible = text.visible = place is not None
                if place is not None:
                    box_.position = (place[1], -place[0], CAR_HEIGHT_M / 2)
                    box_.color = colours[j]
                    text.text = texts[j]
            for node in self._object_nodes[2 + 2 * len(xy) :]:  # cars of a larger scene shown before
                node.visible = False
            self.scene_label.text = label

    def _render_objects_scene(self, ox, t: int, label: str) -> None:
        """The cars of an :class:`~pemviz.app.objects_view.ObjectsExplanation` at step ``t``, seen from the ego (which
        stays at the origin): green detected, orange missed, grey unseen, a label per car saying which (and
        decisive)."""
        decisive = {obj for obj, _ in ox.decisive_at(t)}
        xy, colours, texts = [], [], []
        for j in range(ox.detected.shape[1]):
            ahead, lateral = float(ox.ahead_m[t, j]), float(ox.lateral_m[t, j])
            xy.append((lateral, ahead) if math.isfinite(ahead) and math.isfinite(lateral) else None)
            det, seen = bool(ox.detected[t, j]), bool(ox.seen[t, j])
            colours.append(DETECTED if det else (MISSED if seen else IDLE))
            state = "detected" if det else ("missed" if seen else "unseen")
            texts.append(f"{ox.names[j]}: {state}" + (" (decisive)" if j in decisive else ""))
        self._place_objects(xy, colours, texts, label)

    def _frame_objects(self) -> None:
        """Point the camera at :data:`OBJECTS_FRAME_M` of the road of several objects."""
        lo, hi = OBJECTS_FRAME_M
        self._frame(lo + self.lane.ego_length_m / 2, hi - self.lane.object_length_m / 2, hi - lo)

    def _span(self, ego_x: np.ndarray, object_x: np.ndarray) -> float:
        """The longest stretch of road the scene must show at once (metres): from the ego's rear to the object's
        front."""
        p = self.lane
        return float(np.max(object_x + p.object_length_m / 2 - (ego_x - p.ego_length_m / 2)))

    def _frame(self, ego_x: float, object_x: float, span_m: float) -> None:
        """Point the camera at the two cars, far enough back that ``span_m`` metres of road fit the visible canvas
        (its width and field of view as the browser reports them)."""
        camera = self.client.camera
        try:
            aspect, fov = camera.aspect, camera.fov
        except (AssertionError, ZeroDivisionError):  # the browser has not reported its camera yet
            aspect, fov = DEFAULT_ASPECT, DEFAULT_FOV
        if not (math.isfinite(aspect) and aspect > 0 and 0 < fov < math.pi):
            aspect, fov = DEFAULT_ASPECT, DEFAULT_FOV
        p = self.lane
        middle = (ego_x - p.ego_length_m / 2 + object_x + p.object_length_m / 2) / 2
        position, look_at = camera_pose(middle, framing_distance(span_m, aspect, fov))
        try:
            with self.client.atomic():
                camera.position = tuple(position)
                camera.look_at = tuple(look_at)
        except (AssertionError, ValueError):  # the client has not reported its camera yet
            pass

    def _place_rollout(self) -> None:
        """Put the chosen rollout's fixed marks in the scene: the breach gate (a failing rollout) and the framing."""
        traj, xs, ex, drawing = self.shown, self._shown_x, self.explain.explanation, self.shown_drawing
        if traj is None or xs is None or ex is None or drawing is None:
            return
        p = self.lane
        sev = ex.severity
        self._shown_span = self._span(xs[0], xs[1])
        with self.client.atomic():
            if sev.breach_step is not None:
                b = sev.breach_step
                self.breach_gate.position = (float(xs[0][b]) + p.sensor_offset_m, 0.0, (CAR_HEIGHT_M + 0.7) / 2)
                self.breach_label.text = f"{drawing.panel_scene().breach_label}\nat {b * drawing.dt_s:.2f} s"
            self.breach_gate.visible = sev.breach_step is not None
            self.breach_label.visible = sev.breach_step is not None

    def choose_scenario(self, name: str) -> None:
        """``name`` is the scenario chosen for the next run (the *Experiment* tab's choice): its idle scene
        (:func:`pemviz.app.drawing.scenario_drawing`) is drawn now where no rollout is shown, else when none is
        (:meth:`clear`)."""
        with self.lock:
            self.idle_name, self.idle_drawing = name, scenario_drawing(name)
            if self.shown is None:
                self.clear(None)

    def clear(self, why: str | None) -> None:
        """Back to the idle scene of the scenario chosen for the next run (a lane scene at its start, the ego grey;
        a road of lanes seen from the ego; or none); ``why`` says so under the scene and in *Explain* (None: the
        idle scene's own caption)."""
        self.shown, self.shown_record, self._shown_x, self.shown_drawing = None, None, None, None
        self._set_playing(False)
        self.shown_step = -1
        scene, name = panel_scene(self.idle_drawing), self.idle_name or "chosen"
        with self.client.atomic():
            self.ego_box.position = (0.0, 0.0, CAR_HEIGHT_M / 2)
            self.ego_box.color = IDLE
        if isinstance(scene, ObjectsScene):
            starts = scene.start_xy_m
            self._scene_kind(len(starts), scene)
            labels = [object_label(scene.object_labels, j) for j in range(len(starts))]
            self._place_objects(list(starts), [OBJECT] * len(starts), labels, "ego: no rollout chosen")
            self._frame_objects()
            caption = (
                f"No rollout chosen: the {name} scenario's {len(starts)} {_plural(labels)} at their start, seen "
                "from the ego (grey)."
            )
        elif isinstance(scene, LaneScene):
            self._idle_lane(scene)
            caption = f"No rollout chosen: the {name} scenario's cars at their start."
        else:
            self._scene_kind(None)
            caption = f"The {name} scenario draws no scene: its rollouts are under Rollouts and Live."
        self.scene_html.content = box(html.escape(caption if why is None else f"{why}. {caption}"), GREY)
        if why is not None:
            self.explain.clear(why)

    def _idle_lane(self, lane: LaneScene) -> None:
        """The lane scene at ``lane``'s constants at its start: the object where it starts, the ruler at its starting
        length, no trail, no breach."""
        self._use_lane(lane)
        self._scene_kind(0)
        p = self.lane
        object0 = p.object_start_x
        with self.client.atomic():
            self.object_box.position = (object0, 0.0, CAR_HEIGHT_M / 2)
            self.gap_ruler.points = ruler_segments(p.sensor_offset_m, object0 - p.object_length_m / 2)
            self.gap_label.text = f"{p.ruler_label} {p.start_distance_m:.2f} m"
            self.gap_label.position = ((p.sensor_offset_m + object0 - p.object_length_m / 2) / 2, ROW_Y_M["right"], 0.0)
            self.trail.visible = self.breach_gate.visible = self.breach_label.visible = False
            self.scene_label.text = "ego: no rollout chosen"
        self._frame(0.0, object0, self._span(np.zeros(1), np.full(1, object0)))

    def render_step(self, step: int) -> None:
        """Draw ``step`` of the rollout shown, in the scene and in *Explain*."""
        if self.explain.objects_ex is not None:  # a rollout of several objects: Explain draws them
            with self.lock:
                traj, ox, record = self.shown, self.explain.objects_ex, self.shown_record
                if traj is None or ox is None or record is None:
                    return
                t = int(np.clip(step, 0, traj.n_steps - 1))
                self.shown_step = t
                self.explain.render_objects(record, traj, t)
                label = f"{record.short_label} {traj.name} step {t}\n{OV.state_counts(ox, t)}"
                self._render_objects_scene(ox, t, label)
            return
        with self.lock:
            traj, xs, ex, record = self.shown, self._shown_x, self.explain.explanation, self.shown_record
            drawing = self.shown_drawing
            if traj is None or xs is None or ex is None or record is None or drawing is None:
                return
            t = int(np.clip(step, 0, traj.n_steps - 1))
            self.shown_step = t
            p, dt = self.lane, drawing.dt_s
            ego_x, object_x = float(xs[0][t]), float(xs[1][t])
            detected = bool(traj.detected[t])
            colour = DETECTED if detected else MISSED
            distance = float(xs[2][t])
            ruler_label = drawing.panel_scene().ruler_label
            decisive = t in set(ex.decisive.tolist())
            seen = "detected" if detected else ("missed (decisive)" if decisive else "missed")
            cam_x, rear_x = ego_x + p.sensor_offset_m, object_x - p.object_length_m / 2
            past = np.asarray(xs[0][: t + 1]) - p.ego_length_m / 2 - TRAIL_POINT_M
            trail = np.stack([past, np.zeros_like(past), np.full_like(past, 0.03)], axis=1).astype(np.float32)
            trail_colours = np.where(traj.detected[: t + 1, None], DETECTED, MISSED).astype(np.uint8)
            with self.client.atomic():
                self.ego_box.position = (ego_x, 0.0, CAR_HEIGHT_M / 2)
                self.ego_box.color = colour
                self.object_box.position = (object_x, 0.0, CAR_HEIGHT_M / 2)
                self.gap_ruler.points = ruler_segments(cam_x, rear_x)
                self.gap_label.text = f"{ruler_label} {distance:.2f} m"
                self.gap_label.position = ((cam_x + rear_x) / 2, ROW_Y_M["right"], 0.0)
                self.trail.points = trail
                self.trail.colors = trail_colours
                self.trail.visible = True
                self.scene_label.text = f"{record.short_label} {traj.name} t={t * dt:.2f}s\n{seen}"
                self.explain.move_marker(t)
            if self.follow.value:
                self._frame(ego_x, object_x, self._shown_span)
            mark = {
                "detected": "detected",
                "missed": f"<b style='color:rgb{MISSED}'>missed</b>",
                "missed (decisive)": f"<b style='color:{RED}'>missed (decisive)</b>",
            }[seen]
            crash = f" · <b style='color:{RED}'>{html.escape(ex.severity.short)}</b>" if traj.crashed else ""
            before, after = drawing.step_caption(traj.batch, 0, ex, t)
            self.scene_html.content = box(
                f"Scene: <b>{html.escape(record.short_label)} {traj.name}</b>{crash} · step {t} "
                f"(t = {t * dt:.2f} s) · {html.escape(before)} · detector: "
                f"{mark} · {html.escape(after)}",
                RED if traj.crashed else BLUE,
            )

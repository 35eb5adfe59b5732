"""The 3D scene of a :class:`pemviz.app.session.Session`: the chosen rollout's cars on the road, played step by step
in sync with *Explain*."""

from __future__ import annotations

import html

import numpy as np
import viser

from pemviz.app import plots
from pemviz.app.html import BLUE, GREY, RED, box
from pemviz.sinks import colours as C
from pemviz.sinks.colours import BRAKE_ZONE, CRASH, DETECTED, IDLE, LEAD, MISSED


CAR_HEIGHT_M = 1.5
CAMERA_OFFSET_M = np.array([-5.0, -20.0, 13.0])
"""Initial camera position relative to the point between the cars (metres; behind-left, above)."""


class SceneView:
    """The 3D scene's part of a session (a mixin of :class:`pemviz.app.session.Session`)."""

    def _toggle_play(self) -> None:
        with self.lock:
            if self.shown is None:
                return
            if not self.playing and int(self.step_slider.value) >= self.shown.n_steps - 1:
                self.step_slider.value = 0
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
            self.step_slider.value = step

    def _build_scene(self) -> None:
        scene = self.client.scene
        p = self.params
        scene.set_up_direction("+z")
        road_len, x0, lane = 90.0, -15.0, 4.0
        scene.add_box(
            "/road", color=C.ROAD, dimensions=(road_len, lane + 1.0, 0.05),
            position=(x0 + road_len / 2, 0.0, -0.03), cast_shadow=False,
        )  # fmt: skip
        edges = np.array(
            [[[x0, s * lane / 2, 0.0], [x0 + road_len, s * lane / 2, 0.0]] for s in (-1, 1)], dtype=np.float32
        )
        scene.add_line_segments("/road/edges", edges, colors=C.ROAD_MARKING, thickness=0.12)
        ticks = np.array([[[x, -lane / 2, 0.01], [x, -lane / 2 - 0.6, 0.01]] for x in range(0, 75, 10)], np.float32)
        scene.add_line_segments("/road/ticks_10m", ticks, colors=C.ROAD_MARKING, thickness=0.08)
        size = (p.ego_length_m, p.vehicle_width_m, CAR_HEIGHT_M)
        lead0 = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        self.ego_box = scene.add_box("/ego", color=IDLE, dimensions=size, position=(0.0, 0, CAR_HEIGHT_M / 2))
        self.lead_box = scene.add_box(
            "/lead", color=LEAD, dimensions=(p.lead_length_m, p.vehicle_width_m, CAR_HEIGHT_M),
            position=(lead0, 0.0, CAR_HEIGHT_M / 2),
        )  # fmt: skip
        scene.add_label("/lead/label", "lead", position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 0.5), anchor="bottom-center")
        # zones ahead of the ego's camera, moving with it
        zones = (
            ("brake_zone_10m", p.braking_distance_m, BRAKE_ZONE, f"brakes if the lead is detected within {p.braking_distance_m:g} m"),
            ("crash_zone_2m", p.crash_gap_m, CRASH, f"crash: gap < {p.crash_gap_m:g} m"),
        )  # fmt: skip
        for i, (name, length, rgb, text) in enumerate(zones):
            scene.add_box(
                f"/ego/{name}", color=rgb, dimensions=(length, p.vehicle_width_m + 0.6, 0.02), opacity=0.35,
                position=(p.camera_offset_m + length / 2, 0.0, -CAR_HEIGHT_M / 2 + 0.02), cast_shadow=False,
                receive_shadow=False,
            )  # fmt: skip
            scene.add_label(
                f"/ego/{name}/label", text, position=(0.0, -(p.vehicle_width_m / 2 + 0.8 + 1.2 * i), 0.05),
                anchor="top-center",
            )  # fmt: skip
        cam = p.camera_height_m
        self.gap_line = scene.add_line_segments(
            "/gap", np.array([[[p.camera_offset_m, 0, cam], [lead0 - p.lead_length_m / 2, 0, cam]]], np.float32),
            colors=IDLE, thickness=0.08,
        )  # fmt: skip
        self.scene_label = scene.add_label(
            "/ego/label", "ego: no rollout chosen", position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 1.2), anchor="bottom-center"
        )
        target = np.array([lead0 / 2, 0.0, 0.0])
        self.client.camera.position = tuple(target + CAMERA_OFFSET_M)
        self.client.camera.look_at = tuple(target)

    def _clear_scene(self, why: str) -> None:
        """Back to the idle scene (no rollout shown): the cars at the start, the ego grey."""
        p = self.params
        self.shown, self.shown_record, self.explanation, self._shown_x = None, None, None, None
        self._set_playing(False)
        self.shown_step = -1
        lead0 = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        with self.client.atomic():
            self.ego_box.position = (0.0, 0.0, CAR_HEIGHT_M / 2)
            self.ego_box.color = IDLE
            self.lead_box.position = (lead0, 0.0, CAR_HEIGHT_M / 2)
            self.gap_line.colors = np.array(IDLE, dtype=np.uint8)
            self.scene_label.text = "ego: no rollout chosen"
            self.scene_html.content = box(html.escape(why), GREY)
            self.explain_html.content = box(html.escape(why), GREY)

    def _render_step(self, step: int) -> None:
        with self.lock:
            traj, xs, ex, record = self.shown, self._shown_x, self.explanation, self.shown_record
            if traj is None or xs is None or ex is None or record is None:
                return
            t = int(np.clip(step, 0, traj.n_steps - 1))
            self.shown_step = t
            p = self.params
            ego_x, lead_x = float(xs[0][t]), float(xs[1][t])
            detected = bool(traj.detected[t])
            colour = DETECTED if detected else MISSED
            gap = float(traj.gap_m[t])
            cam = p.camera_height_m
            decisive = t in set(ex.decisive.tolist())
            seen = "detected" if detected else ("missed (decisive)" if decisive else "missed")
            with self.client.atomic():
                self.ego_box.position = (ego_x, 0.0, CAR_HEIGHT_M / 2)
                self.ego_box.color = colour
                self.lead_box.position = (lead_x, 0.0, CAR_HEIGHT_M / 2)
                self.gap_line.points = np.array(
                    [[[ego_x + p.camera_offset_m, 0, cam], [lead_x - p.lead_length_m / 2, 0, cam]]], np.float32
                )
                self.gap_line.colors = np.array(colour, dtype=np.uint8)  # (3,): one colour (per-vertex shows white)
                self.scene_label.text = f"{record.short_label} {traj.key} t={t * p.dt_s:.2f}s gap {gap:.2f}m {seen}"
                plots.move_strip_marker(self.strip, t)
            if self.follow.value:
                target = np.array([(ego_x + lead_x) / 2, 0.0, 0.0])
                try:
                    with self.client.atomic():
                        self.client.camera.position = tuple(target + CAMERA_OFFSET_M)
                        self.client.camera.look_at = tuple(target)
                except (AssertionError, ValueError):  # the client has not reported its camera yet
                    pass
            mark = {"detected": "detected", "missed": f"<b style='color:rgb{MISSED}'>missed</b>",
                    "missed (decisive)": f"<b style='color:{RED}'>missed (decisive)</b>"}[seen]  # fmt: skip
            crash = f" · <b style='color:{RED}'>{html.escape(ex.severity.short)}</b>" if traj.crashed else ""
            c = ex.controller
            brake = "applied" if c.brake_applied[t] else ("commanded" if c.brake_command[t] else "off")
            self.scene_html.content = box(
                f"Scene: <b>{html.escape(record.short_label)} {traj.key}</b> (stage {traj.stage}, rollout "
                f"{traj.index}{crash}) · step {t} (t = {t * p.dt_s:.2f} s) · gap {gap:.2f} m · ego "
                f"{traj.ego_speed_mps[t]:.2f} m/s · lead {traj.lead_speed_mps[t]:.2f} m/s · detector: {mark} · "
                f"brake {brake} · acceleration {c.accel_mps2[t]:+.2f} m/s^2",
                RED if traj.crashed else BLUE,
            )



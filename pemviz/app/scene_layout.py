"""Where the 3D scene of :mod:`pemviz.app.scene_view` puts things, and the nodes it makes once. No state of its own."""

from __future__ import annotations

import math

import numpy as np
import viser

from pemviz.scenarios.panel_data import LaneScene
from pemviz.sinks import colours as C
from pemviz.sinks.colours import BRAKE_ZONE, CRASH, OBJECT

CAR_HEIGHT_M = 1.5
VIEW_DIRECTION = np.array([-1.0, -0.3, 1.2]) / np.linalg.norm([-1.0, -0.3, 1.2])
"""From the framed point towards the camera: behind the ego, a little to its right and above (unit vector), so that the
road runs up the canvas, which is taller than wide between the panels."""
FRAME_MARGIN = 1.05
"""The framed box, times this, fits the canvas (room for the labels' text beyond their anchors)."""
DEFAULT_ASPECT, DEFAULT_FOV = 0.6, math.radians(75.0)
"""The canvas' width / height and vertical field of view (radians) before the browser has reported its own (the
canvas between the panels at 1400 x 900)."""
MIN_DISTANCE_M = 10.0
ROW_Y_M = {"ruler": -1.6, "right": -2.6, "left": 2.6}
"""Lateral places (metres; negative: right of the road on screen) of the ruler and the two label columns, so that no
label covers a car or another label: right, the ego's, the ruler's and the zones'; left, the breach's alone."""
FRAMED_Y_M, FRAMED_Z_M = (-8.0, 6.0), (0.0, 3.0)
"""The lateral and vertical extent the camera keeps in view (metres): the road, the cars, the columns of labels."""
LABEL_SCALE = 0.85
"""The labels' font, relative to viser's."""
ZONE_COLOURS = {"window": BRAKE_ZONE, "margin": CRASH}
"""The colour of a zone of each :attr:`pemviz.scenarios.panel_data.Zone.role`."""
ZONE_COLOUR_NAMES = {"window": "yellow", "margin": "red"}
"""The colours' names in the zones' label."""
GROUND_M = (240.0, 120.0)
"""The open ground's length (ahead) and width (metres) of a scene of no lanes."""


def camera_pose(x_middle: float, distance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(position, look-at point) of the camera ``distance_m`` away along :data:`VIEW_DIRECTION` from the middle of
    the framed box at ``x_middle`` along the road (metres)."""
    target = np.array([x_middle, sum(FRAMED_Y_M) / 2, sum(FRAMED_Z_M) / 2])
    return target + distance_m * VIEW_DIRECTION, target


def _inside(points: np.ndarray, position: np.ndarray, target: np.ndarray, aspect: float, fov_rad: float) -> bool:
    """Whether every point [P, 3] projects inside the canvas shrunk by :data:`FRAME_MARGIN` (a pinhole camera at
    ``position`` looking at ``target``, +z up, vertical field of view ``fov_rad``)."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    rel = points - position
    depth = rel @ forward
    if np.any(depth <= 0.1):
        return False
    tan_v = math.tan(fov_rad / 2) / FRAME_MARGIN
    x, y = (rel @ right) / (depth * tan_v * aspect), (rel @ up) / (depth * tan_v)
    return bool(np.all(np.abs(x) <= 1.0) and np.all(np.abs(y) <= 1.0))


def framing_distance(span_m: float, aspect: float, fov_rad: float) -> float:
    """The least distance (metres, at least :data:`MIN_DISTANCE_M`) at which a box ``span_m`` metres along the road
    by :data:`FRAMED_Y_M` by :data:`FRAMED_Z_M` fits the canvas (``aspect``: width / height; ``fov_rad``: the
    vertical field of view), by bisection on the projection of its corners."""
    corners = np.array([[x, y, z] for x in (-span_m / 2, span_m / 2) for y in FRAMED_Y_M for z in FRAMED_Z_M])
    lo, hi = MIN_DISTANCE_M, 400.0
    position, target = camera_pose(0.0, lo)
    if _inside(corners, position, target, aspect, fov_rad):
        return lo
    for _ in range(40):
        mid = (lo + hi) / 2
        position, target = camera_pose(0.0, mid)
        lo, hi = (lo, mid) if _inside(corners, position, target, aspect, fov_rad) else (mid, hi)
    return hi


def ruler_segments(x_from: float, x_to: float) -> np.ndarray:
    """The ruler's segments [3, 2, 3]: the line and a tick at each end (metres)."""
    y, z, tick = ROW_Y_M["ruler"], 0.03, 0.35
    return np.array(
        [
            [[x_from, y, z], [x_to, y, z]],
            [[x_from, y - tick, z], [x_from, y + tick, z]],
            [[x_to, y - tick, z], [x_to, y + tick, z]],
        ],
        np.float32,
    )


def add_lane_nodes(
    scene: viser.SceneApi, p: LaneScene
) -> tuple[list, viser.BoxHandle, viser.LineSegmentsHandle, viser.LabelHandle]:
    """Add the lane scene ``p``'s nodes at its start to ``scene``: road, edges and 10 m ticks, the object and its
    label, the zones ahead of the ego's sensor (children of ``/ego``, which must exist) with their label, the ruler
    and its label.

    Returns:
        (every node made, in the order made; the object's box; the ruler; the ruler's label)."""
    road_len, x0, lane = 240.0, -60.0, 4.0
    road = scene.add_box(
        "/road",
        color=C.ROAD,
        dimensions=(road_len, lane + 1.0, 0.05),
        position=(x0 + road_len / 2, 0.0, -0.03),
        cast_shadow=False,
    )
    edges = np.array(
        [[[x0, s * lane / 2, 0.01], [x0 + road_len, s * lane / 2, 0.01]] for s in (-1, 1)], dtype=np.float32
    )  # world coordinates: not children of /road, whose frame is the box's centre
    road_edges = scene.add_line_segments("/road_edges", edges, colors=C.ROAD_MARKING, thickness=0.12)
    ticks = np.array([[[x, lane / 2, 0.01], [x, lane / 2 + 0.6, 0.01]] for x in range(0, 150, 10)], np.float32)
    road_ticks = scene.add_line_segments("/road_ticks_10m", ticks, colors=C.ROAD_MARKING, thickness=0.08)
    object0 = p.object_start_x
    object_box = scene.add_box(
        f"/{p.object_name}",
        color=OBJECT,
        dimensions=(p.object_length_m, p.width_m, CAR_HEIGHT_M),
        position=(object0, 0.0, CAR_HEIGHT_M / 2),
    )
    object_label = scene.add_label(
        f"/{p.object_name}/label",
        p.object_name,
        anchor="bottom-center",
        position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 0.2),
        font_screen_scale=LABEL_SCALE,
    )
    # zones ahead of the ego's sensor, moving with it; one label for all, in the right column at the middle of the first
    zones: list[viser.BoxHandle | viser.LabelHandle] = []
    for zone in p.zones:
        zones.append(
            scene.add_box(
                f"/ego/{zone.name}",
                color=ZONE_COLOURS[zone.role],
                dimensions=(zone.length_m, p.width_m + 0.6, 0.02),
                opacity=0.35,
                position=(p.sensor_offset_m + zone.length_m / 2, 0.0, -CAR_HEIGHT_M / 2 + 0.02),
                cast_shadow=False,
                receive_shadow=False,
            )
        )
    if p.zones:
        legend = ";\n".join(f"{ZONE_COLOUR_NAMES[zone.role]}: {zone.legend}" for zone in p.zones)
        zones.append(
            scene.add_label(
                f"/ego/{p.zones[0].name}/label",
                legend,
                position=(p.zones[0].length_m / 2, ROW_Y_M["right"], 0.0),
                anchor="center-left",
                font_screen_scale=LABEL_SCALE,
            )
        )
    # the ruler: on the road beside the cars, from the ego's sensor to the object's rear, ticks at both ends
    rear = object0 - p.object_length_m / 2
    gap_ruler = scene.add_line_segments(
        "/gap_ruler", ruler_segments(p.sensor_offset_m, rear), colors=C.ROAD_MARKING, thickness=0.08
    )
    gap_label = scene.add_label(
        "/gap_ruler/label",
        f"{p.ruler_label} {p.start_distance_m:.2f} m",
        anchor="center-left",
        font_screen_scale=LABEL_SCALE,
        position=((p.sensor_offset_m + rear) / 2, ROW_Y_M["right"], 0.0),
    )
    nodes = [road, road_edges, road_ticks, object_box, object_label, *zones, gap_ruler, gap_label]
    return nodes, object_box, gap_ruler, gap_label


def floor_lines(n_lanes: int, lane_m: float) -> np.ndarray:
    """The lines on the floor of a scene of several objects, float32 [L, 2, 3] (metres, x ahead, y to the left): a
    road's dashed lane lines and edges for ``n_lanes`` lanes of ``lane_m``; open ground's 10 m grid for no lanes."""
    if n_lanes == 0:
        half = GROUND_M[1] / 2
        along = [[[-60.0, y, 0.01], [180.0, y, 0.01]] for y in np.arange(-half, half + 1.0, 10.0)]
        across = [[[x, -half, 0.01], [x, half, 0.01]] for x in np.arange(-60.0, 181.0, 10.0)]
        return np.array(along + across, np.float32)
    lanes = n_lanes * lane_m
    lines_y = [(k - n_lanes / 2) * lane_m for k in range(1, n_lanes)]  # between the lanes
    dashes = [[[x, y, 0.01], [x + 3.0, y, 0.01]] for y in lines_y for x in np.arange(-60.0, 180.0, 9.0)]
    edges = [[[-60.0, y, 0.01], [180.0, y, 0.01]] for y in (-lanes / 2, lanes / 2)]
    return np.array(dashes + edges, np.float32)

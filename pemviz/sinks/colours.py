"""One colour scheme for the panel and the rerun recordings, as RGB 0..255 (HTML: :func:`css`, :func:`hex_colour`;
rerun: :func:`rgba`): a detection green and a miss orange everywhere; a failure and the failure threshold red; the
sampler window yellow; the object the ego reacts to blue-grey; an idle car neutral grey; stages from blue (early) to
orange (late). The panel's text uses :data:`BLUE`, :data:`GREEN`, :data:`AMBER`, :data:`RED` and :data:`GREY`; kept
runs take :data:`RUN_COLOURS` in turn."""

from __future__ import annotations

DETECTED = (40, 170, 80)
MISSED = (245, 130, 30)
CRASH = (214, 50, 40)
SAFE = (150, 150, 150)
OBJECT = (95, 125, 190)
"""The object the ego reacts to (e.g. the car ahead), in the scenes."""
IDLE = (190, 190, 195)
BRAKE_ZONE = (240, 200, 40)
"""The sampler window, e.g. the distance inside which the controller reacts to a detection."""
TAGGED = (250, 210, 60)
"""The least-robust rollouts of a stage, highlighted."""
BLUE = (31, 111, 209)
"""pemviz's blue: the panel's theme, its status text, mu_hat's curve."""
VIOLET = (120, 80, 200)
GREEN = (42, 157, 75)
"""A reliable verdict, a finished run."""
AMBER = (201, 138, 0)
"""A doubtful verdict, a warning."""
RED = (214, 64, 43)
"""An unreliable verdict, an error, a crash in the panel's text."""
GREY = (136, 136, 136)
"""Neutral text and placeholders."""
NEUTRAL = (150, 150, 150)
"""The failures' NLL curve."""
BLACK = (0, 0, 0)
"""The target PEM's curve and the current step's marker in the panel's plots."""
INTERVAL = (120, 160, 230)
"""The bounds of mu_hat's interval in the recordings."""
EGO_SPEED = BLUE
OBJECT_SPEED = VIOLET
"""The speed of the object the ego reacts to."""
PROPOSAL = BLUE
LOG_WEIGHT = VIOLET
RUN_COLOURS = (BLUE, RED, GREEN, (138, 79, 209), AMBER, (26, 163, 163))
"""Series colour of a kept run in the panel: its number modulo 6."""
FIGURE_BACKGROUND = (25, 28, 32)
"""The recordings' 2D views."""
ROAD = (70, 70, 75)
ROAD_MARKING = (235, 235, 235)
"""The panel's 3D road: its surface, its edges and the 10 m ticks."""
GROUND = (88, 92, 84)
"""Open ground: the floor of a scene of several objects without lanes (a drawing of no road)."""
ON_DARK = (245, 245, 245)
"""The target PEM's curve on the recordings' dark background (white)."""
AXIS = (170, 170, 170)
GRID = (90, 90, 90)
DARK = (30, 30, 30)
"""The PEM's curve in the paper-tables recording."""
FAILED_ROLLOUT = (230, 60, 50)
"""A failing rollout in ``pemviz estimate``'s recording."""
METRIC_COLOURS = {"classic": (40, 110, 230), "agm": (230, 120, 30), "smooth-cumulative": (40, 170, 80)}
"""The robustness metrics' curves in the paper-tables recording."""
OTHER = (120, 120, 120)
"""A series without a colour of its own."""
MODEL_COLOURS = {
    "ml-nn": (90, 160, 240),
    "lr": (170, 120, 220),
    "guess-mu": (150, 150, 150),
    "b-nn": (80, 200, 160),
    "gbt": (250, 170, 40),
    "authors": ON_DARK,
}
"""The PEM families in ``pemviz pem eval``'s recording."""
MODEL_OTHER = (200, 200, 200)
REFERENCE_LINE = (110, 110, 110)
"""The chance line and the diagonal of ``pemviz pem eval``'s recording."""
SKETCH_BACKGROUND = (244, 244, 244)
"""(also the report's headline, table heads and console block)"""
PAGE = (255, 255, 255)
"""The report's page and chart background."""
TEXT = (34, 34, 34)
"""The report's text."""
RULE = (204, 204, 204)
"""The report's table rules and chart grid."""
"""The background of the panel's drawings of a scene from above (light)."""
SKETCH_LANE = (187, 187, 187)
"""Lane lines in those drawings."""


def stage_rgb(stage: int, n_stages: int) -> tuple[int, int, int]:
    """Blue (stage 0) to orange (stage ``n_stages`` and later) for a stage's curves and points."""
    f = min(1.0, max(0.0, stage / max(1, n_stages)))
    return (int(40 + 215 * f), int(110 + 40 * f), int(230 - 200 * f))


def stage_span(plan: object | None) -> int:
    """The stage drawn orange by :func:`stage_rgb`: the last one a run plans (its
    :attr:`~pemviz.core.plan.RunPlan.last_stage`; 1 without a plan). The recording, the panel's charts and its
    proposal curves colour stages with it alike."""
    return max(1, int(getattr(plan, "last_stage", 1) or 1))


def stage_rgba(stage: int, n_stages: int) -> tuple[int, int, int, int]:
    """:func:`stage_rgb` opaque, for rerun: the curves and points of stage ``stage`` in the recordings."""
    return rgba(stage_rgb(stage, n_stages))


def css(rgb: tuple[int, ...], alpha: float | None = None) -> str:
    """``rgb(r, g, b)`` (or ``rgba(...)`` with ``alpha`` in [0, 1]) for HTML and uPlot."""
    r, g, b = rgb[:3]
    return f"rgb({r}, {g}, {b})" if alpha is None else f"rgba({r}, {g}, {b}, {alpha:g})"


def hex_colour(rgb: tuple[int, ...]) -> str:
    """``#rrggbb`` for HTML and uPlot."""
    return "#{:02x}{:02x}{:02x}".format(*rgb[:3])


def rgba(rgb: tuple[int, ...], a: int = 255) -> tuple[int, int, int, int]:
    """``rgb`` with an alpha 0..255 for rerun."""
    return (int(rgb[0]), int(rgb[1]), int(rgb[2]), int(a))

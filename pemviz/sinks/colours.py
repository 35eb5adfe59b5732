"""One colour scheme for the panel (``pemviz serve``) and the rerun recordings, as RGB 0..255.

A detection is green and a miss orange at every step, in the 3D scene, the recording's scene and the
strip charts; a crash (gap below 2 m) and the 2 m line are red; the 10 m braking distance is yellow;
the lead is blue-grey; a car before any step (idle) is neutral grey; stages go from blue (early) to
orange (late).
"""

from __future__ import annotations

DETECTED = (40, 170, 80)
MISSED = (245, 130, 30)
CRASH = (214, 50, 40)
SAFE = (150, 150, 150)
LEAD = (95, 125, 190)
IDLE = (190, 190, 195)
BRAKE_ZONE = (240, 200, 40)
"""The 10 m braking distance: the controller brakes only for a lead detected inside it."""
TAGGED = (250, 210, 60)
"""The least-robust rollouts of a stage, highlighted."""
EGO_SPEED = (31, 111, 209)
LEAD_SPEED = (120, 80, 200)
PROPOSAL = (31, 111, 209)
LOG_WEIGHT = (120, 80, 200)


def stage_rgb(stage: int, n_stages: int) -> tuple[int, int, int]:
    """Blue (stage 0) to orange (stage ``n_stages`` and later) for a stage's curves and points."""
    f = min(1.0, max(0.0, stage / max(1, n_stages)))
    return (int(40 + 215 * f), int(110 + 40 * f), int(230 - 200 * f))


def stage_rgba(stage: int, n_stages: int) -> tuple[int, int, int, int]:
    """:func:`stage_rgb` opaque, for rerun: the curves and points of stage ``stage`` in the recordings."""
    return rgba(stage_rgb(stage, n_stages))


def css(rgb: tuple[int, ...], alpha: float | None = None) -> str:
    """``rgb(r, g, b)`` (or ``rgba(...)`` with ``alpha`` in [0, 1]) for HTML and uPlot."""
    r, g, b = rgb[:3]
    return f"rgb({r}, {g}, {b})" if alpha is None else f"rgba({r}, {g}, {b}, {alpha:g})"


def rgba(rgb: tuple[int, ...], a: int = 255) -> tuple[int, int, int, int]:
    """``rgb`` with an alpha 0..255 for rerun."""
    return (int(rgb[0]), int(rgb[1]), int(rgb[2]), int(a))

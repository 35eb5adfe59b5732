"""uPlot figures of *Explain*: what the system under test did along the rollout explained (a lane scene's brake and
acceleration; for several objects, car 0's gap, lateral offset, track and the ACC's acceleration)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import add_chart, set_chart, show_chart
from pemviz.app.drawing import LaneExplanation
from pemviz.app.plots import LEGEND, _points, _ring, axes, off_scale_series, robust_range
from pemviz.sinks.colours import BLACK, BLUE, BRAKE_ZONE, CRASH, EGO_SPEED, GREY, MISSED, VIOLET, css, hex_colour

CONTROLLER_RULE: dict[str, Any] = {"min_gap": 10.0, "min_pad": 1.0, "at_least": (-4.0, 4.0)}
""":func:`pemviz.app.plots.robust_range` settings of the controller chart (m/s^2): an acceleration more than 10 m/s^2
(and twice the others' spread) from the others is off scale; at least 1 m/s^2 of room each side, -4..4 always shown."""


def controller_plot(gui: viser.GuiApi, order: float | None = None) -> viser.GuiUplotHandle:
    """The empty controller chart of *Explain*."""
    t = np.linspace(0, 5, 2)
    return add_chart(
        gui,
        data=(t, np.full(2, np.nan)),
        series=(up.Series(label="t (s)"), up.Series(label="acceleration (m/s^2)")),
        title="controller (choose a rollout)",
        caption="the ego's acceleration (m/s^2), and the steps at which the emergency brake was commanded and applied",
        scales={"x": up.Scale(time=False, auto=False, range=(0.0, 5.0))},
        axes=axes("time (s)", "m/s^2"),
        legend=LEGEND,
        height=170,
        order=order,
    )


def fill_controller_plot(plot: viser.GuiUplotHandle, ex: LaneExplanation, step: int, title: str) -> None:
    """The ego's acceleration (m/s^2), and as rows of dots above it the steps at which the emergency brake was
    commanded and applied; a marker at ``step``. The contact step is drawn at the edge, ringed, its value in the title.
    """
    c = ex.controller
    t = c.time_s
    a = np.asarray(c.accel_mps2, dtype=np.float64)
    # in contact the simulator stops the ego within one step (a = -v / dt): a collision, not the controller's doing;
    # those steps do not set the range
    contact = np.asarray(ex.contact, bool)
    rng = robust_range(a, ~contact, **CONTROLLER_RULE)
    top, bottom = rng.hi, rng.lo
    row = 0.07 * (top - bottom)  # two rows of dots above the curve, apart at any scale
    command = np.where(c.brake_command, top + 2 * row, np.nan)
    applied = np.where(c.brake_applied, top + row, np.nan)
    drawn = rng.drawn(a)  # the now marker (pemviz.app.plots.move_strip_marker) follows this series: on the chart
    now = np.full(t.size, np.nan)
    now[int(np.clip(step, 0, t.size - 1))] = drawn[int(np.clip(step, 0, t.size - 1))]
    dots: up.Series = {"width": 0}
    off = np.flatnonzero(rng.below(a) | rng.above(a))
    why = {True: " (contact: the ego stops within one step)", False: ""}
    note = (
        ""
        if off.size == 0
        else (
            f"; {off.size} step{'s' * (off.size != 1)} off scale, drawn at the edge: "
            + ", ".join(f"{a[i]:.1f} m/s^2 at {t[i]:.2f} s{why[bool(contact[i])]}" for i in off[:3])
            + (" ..." if off.size > 3 else "")
        )
    )
    set_chart(
        plot,
        "controller",
        f"{title}: the ego's acceleration (m/s^2), the steps at which the emergency brake was commanded (the object "
        f"detected within the window) and applied (one step later){note}",
    )
    plot.series = (
        up.Series(label="t (s)"),
        up.Series(label="acceleration (m/s^2)", stroke=css(EGO_SPEED), width=2),
        up.Series(label="brake commanded", stroke=css(BRAKE_ZONE), points=_points(BRAKE_ZONE), **dots),
        up.Series(label="brake applied", stroke=css(CRASH), points=_points(CRASH), **dots),
        *(
            [
                up.Series(
                    label=f"acceleration off scale ({off.size})", stroke=hex_colour(BLACK), points=_ring(BLACK), **dots
                )
            ]
            if off.size
            else []
        ),
        up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),  # the last series
    )
    ring = np.where(rng.below(a) | rng.above(a), drawn, np.nan)
    plot.data = (t, drawn, command, applied, *([ring] if off.size else []), now)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(0.0, float(t[-1]))),
        "y": up.Scale(auto=False, range=(bottom, top + 3 * row)),
    }


# -- Explain: a rollout of several objects with a story ----------------------------------------------
TRACK_GAP, TRACK_LATERAL, ACC = "track_gap", "track_lateral", "acc"
"""Keys of the charts of *Explain* for a rollout of several objects (:func:`object_plots`)."""
TRACK_RULE: dict[str, Any] = {"min_gap": 10.0, "min_pad": 0.5}
""":func:`pemviz.app.plots.robust_range` settings of the tracker charts (metres): a measurement more than 10 m (and
twice the others' spread) from the rest, a heavy tail of the noise PEM, is drawn at the edge."""


def object_plots(gui: viser.GuiApi, order: float | None = None) -> dict[str, viser.GuiUplotHandle]:
    """The three empty charts of *Explain* for a rollout of several objects, hidden until one whose drawing tells its
    story is shown (:func:`fill_object_plots`): car 0's gap ahead and lateral offset, truth against the tracker's
    estimate, and the ACC's acceleration with the car it follows."""
    t = np.linspace(0, 10, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 10.0))
    made = {}
    for i, (key, title, y, height) in enumerate(
        (
            (TRACK_GAP, "car 0's gap ahead", "gap (m)", 190),
            (TRACK_LATERAL, "car 0's lateral offset", "m, right +", 180),
            (ACC, "ACC: acceleration and the car it follows", "m/s^2", 180),
        )
    ):
        made[key] = add_chart(
            gui,
            data=(t, none),
            series=(up.Series(label="t (s)"), up.Series(label=y)),
            title=title,
            scales={"x": x_scale},
            axes=axes("time (s)", y),
            legend=LEGEND,
            height=height,
            visible=False,
            order=None if order is None else order + 0.01 * i,
        )
    return made


def _at(values: np.ndarray, step: int | None) -> np.ndarray:
    """nan everywhere but ``step`` (None: everywhere), where ``values`` holds."""
    out = np.full(np.shape(values), np.nan)
    if step is not None and 0 <= step < out.size:
        out[step] = values[step]
    return out


class _Frame(NamedTuple):
    """What every chart of :func:`fill_object_plots` shares: times (s), the marked step, the title, the missed steps,
    the failure step and its series, the time axis."""

    t: np.ndarray
    i: int
    title: str
    missed: np.ndarray
    fail: int | None
    failure_series: list[up.Series]
    x_scale: up.Scale


def _fill_track_chart(
    plot: viser.GuiUplotHandle,
    frame: _Frame,
    what: str,
    unit_label: str,
    truth: np.ndarray,
    track: np.ndarray,
    measured: np.ndarray,
    levels: list[tuple[str, float, tuple[int, ...]]],
    at_least: tuple[float, float],
) -> None:
    """One of :func:`fill_object_plots`' track charts: the truth, the tracker's estimate, the measurements, the
    misses, the ``levels`` (label, value, colour: dashed lines) and the failure and ``frame.i`` markers."""
    t, i, title, missed, fail, failure_series, x_scale = frame
    dots: up.Series = {"width": 0}
    values = [truth, track, measured]
    rng = robust_range(
        np.concatenate(values),
        **TRACK_RULE,
        at_least=(min(at_least[0], *(v for _, v, _ in levels)), max(at_least[1], *(v for _, v, _ in levels))),
    )
    drawn = [rng.drawn(v) for v in values]
    extra_series, extra_data = off_scale_series(t, rng, values)
    set_chart(
        plot,
        f"car 0's {what}",
        f"{title}: the truth, the detector's measurements and the tracker's estimate"
        f"{rng.note('value', '.1f', ' m')}",
    )
    plot.series = (
        up.Series(label="t (s)"),
        up.Series(label="truth", stroke=hex_colour(BLACK), width=2),
        up.Series(label="measured (detected)", stroke=css(BLUE), points=_points(BLUE, 4), **dots),
        up.Series(label="missed", stroke=css(MISSED), points=_points(MISSED, 5), **dots),
        up.Series(label="tracker (confirmed track)", stroke=css(VIOLET), width=2),  # over the dots
        *(up.Series(label=label, stroke=css(colour), width=1.5, dash=(6, 4)) for label, _, colour in levels),
        *failure_series,
        *extra_series,
        up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),  # the last series
    )
    plot.data = (
        t,
        drawn[0],
        drawn[2],
        np.where(missed, drawn[0], np.nan),
        drawn[1],
        *(np.full(t.size, v) for _, v, _ in levels),
        *([_at(drawn[0], fail)] if failure_series else []),
        *extra_data,
        _at(drawn[0], i),
    )
    plot.scales = {"x": x_scale, "y": up.Scale(auto=False, range=rng.range)}
    plot.axes = axes("time (s)", unit_label)
    show_chart(plot, True)


def fill_object_plots(plots: dict[str, viser.GuiUplotHandle], ox: Any, step: int, title: str) -> None:
    """Draw object 0 of ``ox`` (an :class:`pemviz.app.objects_view.ObjectsExplanation` with a story) in the charts of
    :func:`object_plots`, with a marker at ``step``: its gap ahead, its lateral offset with the lane's edges, and the
    ACC's acceleration."""
    st = ox.story
    t = np.asarray(ox.time_s, dtype=np.float64)
    i = int(np.clip(step, 0, t.size - 1))
    fail = st.severity.failure_step
    x_scale = up.Scale(time=False, auto=False, range=(0.0, float(t[-1])))
    dots: up.Series = {"width": 0}
    det, seen = ox.detected[:, 0], ox.seen[:, 0]
    missed = seen & ~det
    failure_series = (
        []
        if fail is None
        else [
            up.Series(
                label=f"failure at {fail * st.severity.dt_s:.2f} s",
                stroke=css(CRASH),
                points=_points(CRASH, 10),
                **dots,
            )
        ]
    )

    frame = _Frame(t, i, title, missed, fail, failure_series, x_scale)

    gap = ox.gap_ahead[:, 0]
    nan = np.full(t.size, np.nan)
    along = (ox.tracked[:, 0, 1] - ox.ahead_m[:, 0]) if ox.tracked is not None else nan
    meas_along = (ox.measured[:, 0, 1] - ox.ahead_m[:, 0]) if ox.measured is not None else np.where(det, 0.0, np.nan)
    _fill_track_chart(
        plots[TRACK_GAP],
        frame,
        "gap ahead",
        "gap (m)",
        gap,
        gap + along,
        gap + meas_along,
        [("contact 0 m", 0.0, CRASH)],
        (0.0, 5.0),
    )
    half = ox.lane_width_m / 2
    _fill_track_chart(
        plots[TRACK_LATERAL],
        frame,
        "lateral offset from the ego's lane centre",
        "m, right +",
        ox.lateral_m[:, 0],
        ox.tracked[:, 0, 0] if ox.tracked is not None else nan,
        ox.measured[:, 0, 0] if ox.measured is not None else np.where(det, ox.lateral_m[:, 0], np.nan),
        [(f"ego's lane edge +{half:g} m", half, BRAKE_ZONE), (f"ego's lane edge -{half:g} m", -half, BRAKE_ZONE)],
        (-half, half),
    )

    _fill_acc_plot(plots[ACC], st, step, title, x_scale, failure_series)


def _fill_acc_plot(
    plot: viser.GuiUplotHandle, st: Any, step: int, title: str, x_scale: up.Scale, failure_series: list[up.Series]
) -> None:
    """The ACC's acceleration chart of :func:`fill_object_plots`, with its rows of dots (the car it followed, car 0
    in the ego's lane) and the failure and ``step`` markers."""
    acc, fail = st.acc, st.severity.failure_step
    dots: up.Series = {"width": 0}
    ta, a = acc.time_s, acc.accel_mps2
    rng = robust_range(a, **CONTROLLER_RULE)
    row = 0.07 * (rng.hi - rng.lo)
    follows = np.where(acc.followed == 0, rng.hi + 2 * row, np.nan)
    other = np.where(acc.followed > 0, rng.hi + 2 * row, np.nan)
    in_lane = np.where(st.in_lane[: ta.size], rng.hi + row, np.nan)
    drawn = rng.drawn(a)
    ia = int(np.clip(step, 0, ta.size - 1))
    off = np.flatnonzero(rng.below(a) | rng.above(a))
    note = "" if off.size == 0 else f"; {off.size} step{'s' * (off.size != 1)} off scale, drawn at the edge"
    pairs: list[tuple[Any, np.ndarray]] = [
        (up.Series(label="acceleration (m/s^2)", stroke=css(EGO_SPEED), width=2), drawn),
        (up.Series(label="follows car 0", stroke=css(VIOLET), points=_points(VIOLET), **dots), follows),
    ]
    if np.isfinite(other).any():
        pairs.append(
            (up.Series(label="follows another car", stroke=hex_colour(GREY), points=_points(GREY), **dots), other)
        )
    pairs.append(
        (
            up.Series(label="car 0 in the ego's lane", stroke=css(BRAKE_ZONE), points=_points(BRAKE_ZONE), **dots),
            in_lane,
        )
    )
    if fail is not None and fail < ta.size:
        pairs.append((failure_series[0], _at(drawn, fail)))
    if off.size:
        pairs.append(
            (
                up.Series(
                    label=f"acceleration off scale ({off.size})", stroke=hex_colour(BLACK), points=_ring(BLACK), **dots
                ),
                np.where(rng.below(a) | rng.above(a), drawn, np.nan),
            )
        )
    pairs.append(
        (up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots), _at(drawn, ia))
    )  # the last series
    set_chart(plot, "ACC acceleration", f"{title}: the ACC's acceleration (IDM on the followed track){note}")
    plot.series = (up.Series(label="t (s)"), *(series for series, _ in pairs))
    plot.data = (ta, *(values for _, values in pairs))
    plot.scales = {"x": x_scale, "y": up.Scale(auto=False, range=(rng.lo, rng.hi + 3 * row))}
    plot.axes = axes("time (s)", "m/s^2")
    show_chart(plot, True)


def hide_object_plots(plots: dict[str, viser.GuiUplotHandle]) -> None:
    """Hide the charts of *Explain* for a rollout of several objects (another kind of rollout is shown, or none)."""
    for plot in plots.values():
        show_chart(plot, False)

"""The panel's HTML boxes: verdicts, the final estimate's accuracy, a failure's explanation and the advice after a
run without failures. Plain functions of a run; no viser."""

from __future__ import annotations

import html
from pathlib import Path

from pemviz.app import plots
from pemviz.app.captions import LOG_W_CAPTION
from pemviz.app.drawing import LaneExplanation
from pemviz.app.runs import PanelRun, Trajectory
from pemviz.core.estimate import error_text, format_probability
from pemviz.engine.events import FinalEstimate
from pemviz.methods import Method
from pemviz.sinks import colours as C
from pemviz.sinks.colours import hex_colour

NO_ROLLOUT = "(choose a rollout)"
"""The rollout dropdown's entry before a rollout is chosen."""
TABLE_STYLE = (
    "<style>.pemviz-table{border-collapse:collapse;text-align:right}"
    ".pemviz-table td,.pemviz-table th{padding:0.05em 0.3em}"
    ".pemviz-table tr:nth-child(even){background:#0000000a}</style>"
)
GREY, BLUE, GREEN, AMBER, RED = (hex_colour(c) for c in (C.GREY, C.BLUE, C.GREEN, C.AMBER, C.RED))
VERDICT_COLOURS = {"reliable": GREEN, "doubtful": AMBER, "unreliable": RED}


def box(text: str, colour: str) -> str:
    """``text`` (HTML) in a box with a left border of ``colour`` (``#rrggbb``) on a faint tint of it."""
    return (
        f'<div style="margin:0 0.6em 0.5em; padding:0.4em 0.6em; border-radius:4px; font-size:0.85em; '
        f'border-left:4px solid {colour}; background:{colour}14">{text}</div>'
    )


def field_error(text: str) -> str:
    """The error line under a field (empty: none)."""
    if not text:
        return ""
    return f'<div style="margin:-0.3em 0.8em 0.4em; color:{RED}; font-size:0.8em">{html.escape(text)}</div>'


def accuracy_html(record: PanelRun, ev: FinalEstimate) -> str:
    """The final estimate with its 95 % interval, verdict and reason, and the exact answer where known."""
    e = ev.estimate
    colour = VERDICT_COLOURS.get(e.verdict, GREY)
    lines = [
        f"<b>Final estimate of {html.escape(record.short_label)}</b>: mu_hat = "
        f"<b>{format_probability(e.log_mu_hat, 4)}</b> &nbsp;("
        + (f"95 % interval {html.escape(e.interval_text())}" if e.interval_backed else html.escape(e.bound_text()))
        + ")",
        f'<b style="color:{colour}">{html.escape(e.verdict)}</b>: {html.escape(e.reason)}',
    ]
    exact = record.exact_log_p
    if exact is not None:
        lines.append(
            f"exact answer {format_probability(exact, 4)}: {error_text(e.log_mu_hat, exact)}, "
            f"{e.holds_text(exact, '<b>outside</b>')}"
        )
    elif record.reference is not None:
        text = html.escape(record.reference.comparison(e, outside="OUTSIDE"))
        lines.append(text.replace("OUTSIDE", "<b>outside</b>"))
    if e.n_failures == 0:
        lines.append(
            f"no failure among {e.n} rollouts, so mu_hat = 0: " + no_failure_advice(record.config.method_record, e.n)
        )
    lines.append(
        f"failures {e.n_failures}/{e.n} · ESS {plots.finite_or_dash(e.ess, '.1f')} · k-hat "
        f"{plots.finite_or_dash(e.khat, '.2f')} · NLL {plots.finite_or_dash(e.nll_mean, '.1f')} nats · "
        f"{ev.n_simulations:,} simulations in {ev.wall_s:.1f} s"
    )
    prepared = getattr(ev, "prepared", None)
    if prepared:  # the tilt: its proposal solved by this run, or reused from an earlier one
        lines.append(f"proposal: {html.escape(prepared)}")
    curve = getattr(ev, "severity", None)
    if curve is not None and len(curve.points) > 1:
        lines.append(f"<b>{html.escape(curve.title())}</b>")
        lines.extend(f"{html.escape(label)}: {html.escape(text)}" for label, text in curve.rows())
    spread = getattr(ev, "pem_spread", None)
    if spread is not None:
        lines.extend(html.escape(line) for line in spread.lines())
    return box("<br>".join(lines), colour)


def log_w_html(log_w: float) -> str:
    """``importance log-weight log w -35.5 nats`` with :data:`pemviz.app.captions.LOG_W_CAPTION` as its tooltip."""
    return (
        f'<span title="{html.escape(LOG_W_CAPTION)}" style="border-bottom:1px dotted">importance log-weight log w '
        f"{log_w:.1f} nats</span> (log p - log q)"
    )


def explanation_html(record: PanelRun, traj: Trajectory, ex: LaneExplanation, title: str, dt: float) -> str:
    """Explain's header: the rollout, its severity, what happened in words, the minimal miss set, the last step at
    which one detection still saves it, and the counterfactual's summary."""
    best = record.most_likely_failure
    what = "the most likely failure found" if traj is best else ("a failure" if traj.crashed else "no failure")
    cf = ex.counterfactual
    lines = [
        f"<b>{html.escape(title)}</b>: {what} · <b>{html.escape(ex.severity.short)}</b> · robustness "
        f"{traj.robustness:+.4g} ({record.config.metric}) · under the PEM: {html.escape(traj.log_p_words())} · "
        f"{log_w_html(traj.log_weight)}",
        f"<b>What happened</b>: {html.escape(ex.sentence)}",
    ]
    if ex.crashed and ex.replay_matches:
        if cf.minimal_set.size:
            k = cf.minimal_set.size
            kind = "smallest" if cf.smallest else "minimal: none can be left out"
            steps = ", ".join(f"{t * dt:.2f}" for t in cf.minimal_set[:16]) + (" ..." * (k > 16))
            found = (
                f"<b>Minimal miss set</b> ({kind}): {k} miss{'es' * (k != 1)} at {steps} s; detected there, "
                f"{html.escape(ex.minimal_set_outcome)}"
            )
        else:
            found = "<b>Minimal miss set</b>: none: even a detection at every step fails"
        saving = (
            f"{cf.last_saving_step * dt:.2f} s (step {cf.last_saving_step})"
            if cf.last_saving_step is not None
            else "none: no single detection saves it"
        )
        lines.append(f"{found} · <b>last step at which one detection still saves it</b>: {saving}")
    lines.append(f"<b>Counterfactual</b> (misses flipped to detections, replayed): {html.escape(ex.summary())}")
    return box("<br>".join(lines), RED if traj.crashed else GREEN)


def no_failure_advice(record: Method, n: int) -> str:
    """What to try after a run without a failure, in the terms of its method ``record`` (its own words where it has
    them: :attr:`pemviz.methods.Method.no_failure_advice`)."""
    from pemviz.plugins import resolve

    if record.no_failure_advice is not None:
        return str(resolve(record.no_failure_advice)(n))
    return (
        f"this fixed sampler ({record.name}) reached no crash: more rollouts (N) or the adaptive method (state-ce "
        "preset), which learns where to miss."
    )


def display_path(path: Path) -> str:
    """``path`` relative to the working folder where it lies under it, else as given."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)

"""The map of a run over an operating design domain in the recording (``/odd/map``, ``/odd/<name>/...`` on the
``odd_bin`` timeline, and over two or more parameters ``/odd/pair``); the entities are listed in docs/recording.md."""

from __future__ import annotations

import math

import rerun as rr

from pemviz.core.estimate import format_probability
from pemviz.core.odd import OddMap


def odd_map_markdown(m: OddMap) -> str:
    """The map as a markdown table, with the region that carries most of p_ODD under it."""
    rows = [
        f"**Operating design domain**: {m.odd.text()}; p(failure | bin) from the final stage's {m.rollouts:,} "
        "rollouts.",
        "",
        "| bin | P(bin) | p(failure \\| bin) | 95 % interval | verdict | share of p_ODD |",
        "|---|---|---|---|---|---|",
    ]
    for b in m.bins:
        e = b.estimate
        p = format_probability(e.log_mu_hat) if e.n_failures else "no failure"
        rows.append(
            f"| {b.label} | {b.probability:.2f} | {p} | {e.interval_text()} | {e.verdict} | {100 * b.share:.1f} % |"
        )
    top = m.top()
    if top is not None:
        rows += ["", f"Most of p_ODD: **{top.label}** ({100 * top.share:.0f} % of it, P(bin) {top.probability:.2f})."]
    if m.pair is not None:  # the heat map of the first two parameters, as the console prints it
        rows += ["", "```text", *m.pair.lines(), "```"]
    return "\n".join(rows)


def log_odd_map(stream: rr.RecordingStream, m: OddMap) -> None:
    """Log ``m`` to ``stream`` (module docstring); nothing for a map without bins."""
    if not m.bins:
        return
    stream.log("odd/map", rr.TextDocument(odd_map_markdown(m), media_type=rr.MediaType.MARKDOWN), static=True)
    if m.pair is not None:  # log10 p(failure | cell), rows the second parameter's bins, columns the first's
        x, y = m.pair.names
        grid = m.pair.log10_p()
        stream.log("odd/pair", rr.Tensor(grid, dim_names=[f"{y} bin", f"{x} bin"]), static=True)
    for name in m.odd.names:
        for k, b in enumerate(x for x in m.bins if x.name == name):
            e = b.estimate
            lo, hi = e.shown_log_ci
            stream.set_time("odd_bin", sequence=k)
            values = {
                "log10_p": e.log_mu_hat / math.log(10) if e.n_failures else math.nan,
                "log10_low": lo / math.log(10) if math.isfinite(lo) else math.nan,
                "log10_high": hi / math.log(10) if math.isfinite(hi) else math.nan,
            }
            for key, value in values.items():
                if math.isfinite(value):
                    stream.log(f"odd/{name}/{key}", rr.Scalars(value))
    stream.reset_time()

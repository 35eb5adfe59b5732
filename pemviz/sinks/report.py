"""A safety-case report of one run: one self-contained HTML page (inline styles and SVG, no script) and its Markdown
twin, from the run's result document (:func:`pemviz.io.result.result_document`)."""

from __future__ import annotations

import hashlib
import html
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pemviz.core.severity import share_text
from pemviz.sinks import colours as C
from pemviz.sinks.colours import hex_colour

VERDICT_COLOURS = {"reliable": hex_colour(C.GREEN), "doubtful": hex_colour(C.AMBER), "unreliable": hex_colour(C.RED)}
Section = tuple[str, str, tuple[str, ...], Sequence[tuple[str, ...]]]
"""(title, intro text, table header, rows) of a section of the report and its Markdown twin."""

WHITE, PANEL, TEXT, RULE, MUTED = (hex_colour(c) for c in (C.PAGE, C.SKETCH_BACKGROUND, C.TEXT, C.RULE, C.GREY))


def _odd_section(odd_map: dict[str, Any]) -> Section:
    """The section of a run over an operating design domain: each parameter's bins with p(failure | bin), its interval
    or lower bound, verdict and share of p_ODD (:meth:`pemviz.core.odd.OddMap.document`)."""

    def exp(x: float | None) -> float | None:
        return None if x is None else math.exp(x)

    laws = ", ".join(f"{p['name']} ~ {p['text']}" for p in odd_map["odd"])
    rows = [
        (
            f"{b['parameter']} in [{b['lo']:.4g}, {b['hi']:.4g})",
            f"{b['probability']:.2f}",
            _p(exp(b["log_p"])),
            _interval([exp(x) for x in b["log_ci"]]),
            b["verdict"],
            f"{100 * b['share']:.1f} %",
        )
        for b in odd_map["bins"]
    ]
    intro = (
        f"p is p_ODD, the mean of p(theta) over the operating design domain {laws}: each rollout drew its own "
        f"parameters. Where it comes from, from the final stage's {odd_map['rollouts']:,} rollouts: p(failure | "
        "bin) of each parameter's bins of equal probability, and the bin's share of p_ODD."
    )
    return ("Operating design domain", intro, ("bin", "P(bin)", "p", "95 % interval", "verdict", "share of p"), rows)


def _p(x: float | None) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return "0" if x == 0 else f"{x:.3e}"


def _num(x: float | None, fmt: str = ".1f") -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def document_sha256(doc: dict[str, Any]) -> str:
    """sha256 of the result document as canonical JSON (sorted keys, no spaces): the report's fingerprint of its
    numbers."""
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _interval(ci: list[float | None]) -> str:
    """``[1.2e-15, 2.6e-15]``, or with no upper end (the run's weights back no interval: its lower bound alone)
    ``p >= 1.2e-15, no upper bound from this run``."""
    if ci[1] is None and ci[0] is not None:
        return f"p >= {_p(ci[0])}, no upper bound from this run"
    return f"[{_p(ci[0])}, {_p(ci[1])}]"


def _estimate_rows(doc: dict[str, Any]) -> list[tuple[str, str]]:
    e = doc["estimate"]
    bound = e.get("interval") == "lower_bound95"
    rows = [
        ("failure probability p (mu_hat)", _p(e["p"])),
        ("95 % lower bound (whatever the weights' tail)" if bound else "95 % interval", _interval(e["ci95"])),
        ("verdict", f"{e['verdict']}: {e['reason']}"),
        ("effective sample size (ESS)", _num(e["ess"])),
        ("Pareto k-hat", _num(e["k_hat"], ".2f")),
        ("failures / rollouts used", f"{e['n_failures']:,} / {e['n']:,}"),
        ("simulations", f"{doc['n_simulations']:,} in {_num(doc['wall_s'])} s"),
    ]
    if doc.get("exact"):
        rows.append(("exact answer", _p(doc["exact"]["p"])))
    if doc.get("reference"):
        ref = doc["reference"]
        rows.append(("reference", f"{_p(ref['p'])} ({ref.get('source', '')})"))
    if doc.get("requirement"):
        r = doc["requirement"]
        rows.append(("requirement", f"{r['text']}: {r['outcome']} ({r['why']})"))
    if doc.get("stop"):
        rows.append(("stop", doc["stop"]))
    return rows


def _marker(kind: str, x: float, y: float, colour: str, tip: str = "") -> str:
    """One mark of the severity chart: ``filled`` / ``hollow`` circle (an estimate), ``bound`` (an upward triangle: a
    lower bound alone), ``unreached`` (a downward triangle on the floor) or ``exact`` (a cross)."""
    title = f"<title>{html.escape(tip)}</title>" if tip else ""
    if kind == "exact":
        return (
            f'<path d="M{x - 5:.1f},{y - 5:.1f}L{x + 5:.1f},{y + 5:.1f}M{x - 5:.1f},{y + 5:.1f}'
            f'L{x + 5:.1f},{y - 5:.1f}" stroke="{colour}" stroke-width="1.5">{title}</path>'
        )
    if kind in ("bound", "unreached"):
        d = -1 if kind == "bound" else 1  # the bound points up (p is at least this), the floor mark down
        return (
            f'<path d="M{x:.1f},{y + 6 * d:.1f}L{x - 5.5:.1f},{y - 4 * d:.1f}L{x + 5.5:.1f},{y - 4 * d:.1f}Z" '
            f'fill="{colour if kind == "bound" else WHITE}" stroke="{colour}" stroke-width="1.5">{title}</path>'
        )
    fill = colour if kind == "filled" else WHITE
    return (
        f'<circle cx="{x:.1f}" cy="{y:.1f}" r="4.5" fill="{fill}" stroke="{colour}" stroke-width="2">{title}</circle>'
    )


LEGEND = {
    "filled": "estimate and its 95 % interval: reliable",
    "hollow": "estimate the verdict does not back",
    "bound": "95 % lower bound alone (not estimated)",
    "unreached": "not reached by any rollout",
    "exact": "exact answer",
}
"""The severity chart's legend: each mark it draws (:func:`_marker`) and what it means."""


def _log10(p: float | None) -> float | None:
    return math.log10(p) if p else None


def severity_svg(doc: dict[str, Any], width: int = 860, height: int = 300) -> str:
    """The severity curve as an inline SVG with its legend: log10 p against the level, each point as the run shows
    it (:meth:`pemviz.core.severity.SeverityCurve.shown`: an estimate with its interval, filled where ``reliable``;
    a lower bound as an upward triangle; a level not reached as a downward one), the exact answers as crosses,
    coloured by verdict; "" without anything to draw."""
    sev = doc.get("severity") or {}
    pts = [pt for pt in sev.get("points", []) if pt.get("level") is not None]
    values = _drawn_log10(pts)
    if len(pts) < 2 or not values:
        return ""
    lo, hi = math.floor(min(values)), math.ceil(max(values))
    lo -= any(pt["shown"] == "not reached" for pt in pts)  # a decade below for the floor's marks
    hi = hi if hi > lo else lo + 1
    levels = [pt["level"] for pt in pts]
    x0, x1 = min(levels), max(levels)
    x1 = x1 if x1 > x0 else x0 + 1
    plot_w = 520
    left, top, bottom = 70, 20, 45

    def sx(x: float) -> float:  # larger levels on the left: the curve falls as the failures get worse
        return left + 10 + (x1 - x) / (x1 - x0) * (plot_w - left - 20)

    def sy(log10p: float) -> float:
        return top + (hi - log10p) / (hi - lo) * (height - top - bottom)

    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" role="img" '
        f'aria-label="severity curve">',
        f'<rect width="{width}" height="{height}" fill="{WHITE}"/>',
    ]
    step = max(1, (hi - lo) // 6)
    for k in range(lo, hi + 1, step):
        y = sy(k)
        parts.append(f'<line x1="{left}" x2="{plot_w}" y1="{y:.1f}" y2="{y:.1f}" stroke="{RULE}"/>')
        parts.append(f'<text x="{left - 6}" y="{y + 4:.1f}" font-size="11" text-anchor="end">1e{k}</text>')
    for x in levels:
        parts.append(
            f'<text x="{sx(x):.1f}" y="{height - bottom + 16}" font-size="11" text-anchor="middle">{x:g}</text>'
        )
    unit = html.escape(sev.get("unit", ""))
    parts.append(
        f'<text x="{(left + plot_w) / 2:.1f}" y="{height - 8}" font-size="12" text-anchor="middle">'
        f'{html.escape(sev.get("label", "level"))} below x ({unit})</text>'
    )
    parts.append(
        f'<text x="14" y="{(top + height - bottom) / 2:.1f}" font-size="12" text-anchor="middle" '
        f'transform="rotate(-90 14 {(top + height - bottom) / 2:.1f})">probability</text>'
    )
    used: set[str] = set()

    def mark(kind: str, x: float, y: float, colour: str, tip: str) -> None:
        used.add(kind)
        parts.append(_marker(kind, x, y, colour, tip))

    for pt in pts:
        x, tip = sx(pt["level"]), f"{pt['text']}: {pt['says']}"
        colour = VERDICT_COLOURS.get(pt["verdict"], MUTED)
        if pt.get("exact") and pt["exact"]["p"]:
            mark("exact", x, sy(math.log10(pt["exact"]["p"])), MUTED, f"{pt['text']}: exact {_p(pt['exact']['p'])}")
        if pt["shown"] == "not reached":
            mark("unreached", x, height - bottom - 6, MUTED, tip)
        if pt["shown"] in ("estimate and bound", "bound") and pt["lower_bound95"]:
            mark("bound", x, sy(math.log10(pt["lower_bound95"])), colour, tip)
        if pt["shown"] in ("interval", "estimate and bound") and pt["p"]:
            a, b = pt["ci95"]
            if pt["shown"] == "interval" and a and b:
                parts.append(
                    f'<line x1="{x:.1f}" x2="{x:.1f}" y1="{sy(math.log10(b)):.1f}" y2="{sy(math.log10(a)):.1f}" '
                    f'stroke="{colour}" stroke-width="2"/>'
                )
            mark("filled" if pt["verdict"] == "reliable" else "hollow", x, sy(math.log10(pt["p"])), colour, tip)
    parts += _legend_svg(used, plot_w, top + 4)
    parts.append("</svg>")
    return "".join(parts)


def _drawn_log10(pts: list[dict[str, Any]]) -> list[float]:
    """log10 of every probability :func:`severity_svg` draws of the points ``pts`` (estimates, interval ends, bounds,
    exact answers), for its y range."""
    return [
        v
        for pt in pts
        for v in (
            (_log10(pt["p"]), *(_log10(c) for c in pt["ci95"]))
            if pt["shown"] in ("interval", "estimate and bound")
            else ()
        )
        + ((_log10(pt["lower_bound95"]),) if pt["shown"] in ("estimate and bound", "bound") else ())
        + ((_log10(pt["exact"]["p"]),) if pt.get("exact") else ())
        if v is not None
    ]


def _legend_svg(used: set[str], plot_w: int, y0: float) -> list[str]:
    """The severity curve's legend, right of the plot from ``y0`` down: the marks ``used``, then the colours' words."""
    parts, y = [], y0
    for kind, words in LEGEND.items():
        if kind in used:
            colour = (
                MUTED
                if kind in ("exact", "unreached")
                else VERDICT_COLOURS["reliable" if kind == "filled" else "doubtful"]
            )
            parts.append(_marker(kind, plot_w + 30, y, colour))
            parts.append(f'<text x="{plot_w + 44}" y="{y + 4:.1f}" font-size="11">{html.escape(words)}</text>')
            y += 20
    for line in ("colour: the verdict (green reliable,", "amber doubtful, red unreliable)"):
        parts.append(f'<text x="{plot_w + 24}" y="{y + 4:.1f}" font-size="11" fill="{MUTED}">{line}</text>')
        y += 16
    return parts


def _table_html(header: tuple[str, ...], rows: Sequence[tuple[str, ...]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _table_md(header: tuple[str, ...], rows: Sequence[tuple[str, ...]]) -> str:
    def cell(c: Any) -> str:
        return str(c).replace("|", "\\|").replace("\n", " ")

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _share(x: float | None) -> str:
    """A share of p in words (:func:`pemviz.core.severity.share_text`; ``-`` for null)."""
    return "-" if x is None else share_text(float(x))


def _failure_severity_intro(sev: dict[str, Any]) -> str:
    """The text above the failures' severity table: what a bin's share is, contact, the median min distance and how
    much of p the table covers."""
    unit, label = sev.get("unit", "m"), sev.get("label", "distance")
    median = sev.get("median_min_distance")
    kept = (
        f" It covers the {sev['n_kept']:,} failures whose rollouts were kept, {_share(sev.get('covered'))} of p."
        if sev.get("n_kept") != sev.get("n")
        else ""
    )
    return (
        f"p(severity | failure): the failures' share of p by impact speed, the closing speed into contact "
        f"(contact: {label} <= {sev.get('contact', 0):g} {unit}; the shares add up to 100 %). Share-weighted "
        f"median min {label}: {'-' if median is None else f'{median:.2f} {unit}'}.{kept}"
    )


MAX_GROUPS = 12
"""Groups of failures the report lists, largest share first (the rest in one row)."""


RESTS_ON = "What this number rests on"
"""The report's section saying what p is conditional on and what the verdict checked (:func:`_rests_on`)."""

LIMITS = (
    "failure is the specification as written, evaluated on the simulated signals; the detector's false "
    "positives are not modelled (a missed or mislocated object only), as in Innes & Ramamoorthy (2022); p is "
    "the probability under this PEM and these scenario parameters, not under the real detector"
)
"""The limits every p of pemviz carries, stated in the report."""


def _spread_text(spread: dict[str, Any] | None) -> str:
    """``members: median 2.856e-15, 90 % of them in [3.549e-19, 6.182e-12] (x1.74e+07 wide)`` of the result
    document's ``pem_spread``; where it was not computed, how to compute it."""
    members = (spread or {}).get("members")
    if not members:
        return (
            "not computed for this run: p is conditional on the one PEM; `pemviz run --pem-uncertainty` "
            "re-weighs the same rollouts under the PEM's bootstrap ensemble and logit shifts"
        )
    lo, hi = (r["log_p"] for r in members["range90"])
    wide = f" (x{math.exp(hi - lo):.3g} wide)" if lo is not None and hi is not None else ""
    return (
        f"{members['n']} ensemble members: median {_p(members['median']['p'])}, 90 % of them in "
        f"[{_p(members['range90'][0]['p'])}, {_p(members['range90'][1]['p'])}]{wide}"
    )


def _checks(e: dict[str, Any]) -> list[tuple[str, str]]:
    """The verdict's checks one by one (:func:`pemviz.core.verdict_checks.verdict_checks`), each with what it found,
    its rule and whether it passed; where each of them passed but the verdict is not ``reliable``, the check that
    decided it (its reason: the failures' own probability, collapsed failures, an ODD, a scene's cap) as failed; then
    the verdict and what the run backs."""
    from pemviz.core.verdict_checks import verdict_checks

    checks = verdict_checks(e["n"], e["n_failures"], e["ess"], e["k_hat"], e["sampling"])
    rows = [(f"check: {c.name}", c.text()) for c in checks]
    if e["verdict"] != "reliable" and not any(c.passed is False for c in checks):
        rows.append(("check: the verdict's other checks", f"failed ({e['verdict']}): {e['reason']}"))
    return [
        *rows,
        ("verdict", f"{e['verdict']}: {e['reason']}"),
        (
            "what is printed",
            "a 95 % lower bound that holds whatever the weights' tail, and no upper bound: the weights "
            "back no interval"
            if e.get("interval") == "lower_bound95"
            else "the 95 % interval",
        ),
    ]


def _rests_on(doc: dict[str, Any]) -> list[tuple[str, str]]:
    """The rows of :data:`RESTS_ON`: the PEM (file and sha256), p over the PEM's uncertainty (or that it was not
    computed), the scenario's parameters, the verdict's checks, a requirement's basis and the limits."""
    pems = [i for i in doc.get("inputs") or [] if "PEM" in i["what"] or "pem" in i["what"]]
    named = str((doc.get("settings") or {}).get("pem") or "the shipped default")
    own = "inputs" in doc and not pems  # a run that read no PEM file: the scene's detector is its own
    rows = [(f"PEM ({i['what']})", f"{i['path']}, sha256 {i['sha256']}") for i in pems] or [
        ("PEM", "the scenario's own detector (no PEM file read)" if own else named)
    ]
    rows.append(("p over the PEM's uncertainty", _spread_text(doc.get("pem_spread"))))
    params = (doc.get("settings") or {}).get("scenario_params") or []
    rows.append(("scenario parameters", ", ".join(f"{k} = {v}" for k, v in params) or "the scenario's defaults"))
    rows += _checks(doc["estimate"])
    req = doc.get("requirement")
    if req:
        rows.append(("requirement decided on", f"{req['text']}: {req['outcome']} at look {req['look']}, {req['why']}"))
    rows.append(("limits", LIMITS))
    return rows


def _failures_section(failures: dict[str, Any]) -> Section:
    """The failures in groups by share of p (at most :data:`MAX_GROUPS`, the rest in one row) and the failure
    carrying the largest share."""
    shown = failures["groups"][:MAX_GROUPS]
    rows = [(g["label"], f"{g['count']:,}", f"{100 * g['share']:.3g} %") for g in shown]
    rest = failures["groups"][MAX_GROUPS:]
    if rest:
        rows.append(
            (
                f"{len(rest)} more groups",
                f"{sum(g['count'] for g in rest):,}",
                f"{100 * sum(g['share'] for g in rest):.3g} %",
            )
        )
    top = failures["largest"][0] if failures.get("largest") else None
    largest = (
        f" The failure carrying the largest share: stage {top['stage']} rollout {top['rollout']}, "
        f"{100 * top['share']:.3g} % of p ({top['group']}), log-likelihood under the PEM before the "
        f"failure {_num(top['log_p'], '.2f')} nats (the log-probability of its detections plus, where the "
        "detector mislocates, the log-density of its measurement errors)."
        if top
        else ""
    )
    return (
        "Failures by share of p",
        f"The {failures['n']:,} failures of the estimate in "
        f"{len(failures['groups'])} groups by {failures['basis']}: each group's share of p (its "
        f"failures' importance weights over all the failures'; the shares add up to 100 %).{largest}",
        ("group", "failures", "share of p"),
        rows,
    )


def _sections(doc: dict[str, Any]) -> list[Section]:
    """(title, intro text, table header, rows) of each section both twins show."""
    problem = doc.get("problem") or {}
    scene = [
        ("scenario", f"{doc['scenario']}: {problem.get('description', '')}".rstrip(": ")),
        ("specification (STL)", problem.get("formula", "-")),
        ("method", doc["method"]),
        ("seed", str(doc["seed"])),
    ]
    inputs = [(i["what"], i["path"], i["sha256"]) for i in doc.get("inputs") or []]
    settings = sorted((k, json.dumps(v)) for k, v in (doc.get("settings") or {}).items())
    prov = [
        ("pemviz version", doc.get("pemviz_version", "-")),
        ("command", doc.get("command") or "-"),
        ("recording", doc.get("recording") or "-"),
        ("sha256 of the result document", document_sha256(doc)),
    ]
    sections: list[Section] = [
        ("Estimate", "", ("quantity", "value"), _estimate_rows(doc)),
        (
            RESTS_ON,
            "p is conditional on what follows: a safety case that cites p cites it with these.",
            ("item", "value"),
            _rests_on(doc),
        ),
    ]
    if doc.get("odd_map"):
        sections.append(_odd_section(doc["odd_map"]))
    if doc.get("severity"):
        title = doc["severity"].get("title", "severity: P(min signal < x), from the same rollouts")
        sections.append(
            (
                "Severity",
                f"{title.removeprefix('severity: ')}: how deep the failures go.",
                ("level", "what this run says (the console's words)"),
                [(pt["text"], pt["says"]) for pt in doc["severity"].get("points", [])],  # SeverityCurve.says
            )
        )
    failures = doc.get("failures")
    if failures and failures.get("groups"):
        sections.append(_failures_section(failures))
    severity = (failures or {}).get("severity")
    if severity and severity.get("bins") and severity.get("n_kept"):
        sections.append(
            (
                "Severity of the failures",
                _failure_severity_intro(severity),
                ("impact speed", "failures", "share of p"),
                [(b["label"], f"{b['count']:,}", _share(b["share"])) for b in severity["bins"]],
            )
        )
    sections += [
        ("Scenario, specification and PEM", "", ("item", "value"), scene),
        ("Inputs", "sha256 of every file the run read.", ("input", "path", "sha256"), inputs),
        ("Settings", "", ("setting", "value"), settings),
        ("Provenance", "", ("item", "value"), prov),
    ]
    return sections


def _title(doc: dict[str, Any]) -> str:
    return f"pemviz report: {doc['scenario']}, {doc['method']}, seed {doc['seed']}"


def _headline(doc: dict[str, Any]) -> str:
    """p with what the run backs, its ESS and verdict, and beside them the PEM spread where the run computed one."""
    e = doc["estimate"]
    shown = _interval(e["ci95"]) if e.get("interval") == "lower_bound95" else f"95 % interval {_interval(e['ci95'])}"
    line = f"p = {_p(e['p'])}, {shown}, ESS {_num(e['ess'])}: {e['verdict']}"
    if (doc.get("pem_spread") or {}).get("members"):
        line += f" | under the PEM's uncertainty: {_spread_text(doc['pem_spread'])}"
    return line


def report_html(doc: dict[str, Any]) -> str:
    """The report as one self-contained HTML page (no script, no external resource).

    Raises:
        KeyError: a document without the result's required fields (see the docs page "pemviz in CI")."""
    e = doc["estimate"]
    colour = VERDICT_COLOURS.get(e["verdict"], MUTED)
    body = [
        f"<h1>{html.escape(_title(doc))}</h1>",
        f'<p class="headline" style="border-left:6px solid {colour}">' f"{html.escape(_headline(doc))}</p>",
    ]
    for title, intro, header, rows in _sections(doc):
        body.append(f"<h2>{html.escape(title)}</h2>")
        if intro:
            body.append(f"<p>{html.escape(intro)}</p>")
        if title == "Severity":
            body.append(severity_svg(doc))
        body.append(_table_html(header, rows))
    if doc.get("console"):
        body.append("<h2>What the console printed</h2>")
        body.append(f"<pre>{html.escape(chr(10).join(doc['console']))}</pre>")
    style = (
        f"body{{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:{TEXT};"
        f"background:{WHITE}}}table{{border-collapse:collapse;margin:.5em 0 1.5em}}td,th{{border:1px solid {RULE};"
        f"padding:4px 8px;text-align:left;vertical-align:top;font-size:14px}}th{{background:{PANEL}}}"
        f".headline{{font-size:18px;padding:.4em .8em;background:{PANEL}}}pre{{background:{PANEL};padding:1em;"
        "overflow-x:auto;font-size:12px}"
    )
    return (
        f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(_title(doc))}</title>'
        f"<style>{style}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


def report_markdown(doc: dict[str, Any]) -> str:
    """The report's Markdown twin: the same sections and numbers as :func:`report_html`, without the chart."""
    out = [f"# {_title(doc)}", "", f"**{_headline(doc)}**", ""]
    for title, intro, header, rows in _sections(doc):
        out += [f"## {title}", ""] + ([intro, ""] if intro else []) + [_table_md(header, rows), ""]
    if doc.get("console"):
        out += ["## What the console printed", "", "```text", *doc["console"], "```", ""]
    return "\n".join(out)


def markdown_twin(path: Path) -> Path:
    """Where the Markdown twin of the report ``path`` goes: the same name with ``.md``."""
    return path.with_suffix(".md")


def check_report_paths(page: str | os.PathLike[str], flag: str, *, overwrite: bool = False) -> Path:
    """Refuse a report whose page or Markdown twin (:func:`markdown_twin`) cannot be written, before any work; an
    existing one (without ``overwrite``) gets one line naming both files and the flag, e.g. ``--report r.html:
    writes r.html and its Markdown twin r.md; r.md exists: give --overwrite to replace it``.

    Raises:
        ValueError: as :func:`pemviz.io.files.check_output_path` for either file (:class:`OutputExists`, naming both,
            for an existing one)."""
    from pemviz.core.files import OutputExists
    from pemviz.io.files import check_output_path

    page = Path(page)
    twin = markdown_twin(page)
    existing = []
    for path, suffix, what in ((page, ".html", flag), (twin, ".md", f"{flag} (its Markdown twin)")):
        try:
            check_output_path(path, suffix, what, overwrite=overwrite)
        except OutputExists:
            existing.append(path)
    if existing:
        which = (
            "both exist: give --overwrite to replace them"
            if len(existing) == 2
            else (f"{existing[0]} exists: give --overwrite to replace it")
        )
        raise OutputExists(f"{flag} {page}: writes {page} and its Markdown twin {twin}; {which}")
    return page


def write_report(path: str | os.PathLike[str], doc: dict[str, Any], *, overwrite: bool = False) -> tuple[Path, Path]:
    """Write the report (``path``, HTML) and its Markdown twin (:func:`markdown_twin`), each atomically.

    Raises:
        FileExistsError: a file there and not ``overwrite``; OSError: it cannot be written."""
    from pemviz.io.files import write_text_atomic

    page, text = report_html(doc), report_markdown(doc)
    written = write_text_atomic(path, page, overwrite=overwrite)
    return written, write_text_atomic(markdown_twin(Path(path)), text, overwrite=overwrite)

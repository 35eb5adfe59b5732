"""The paper's Tables II and III (Innes & Ramamoorthy 2022) with repetitions, standard errors and the exact answer: a
row is R repetitions of one config (:class:`RowSpec`), summarised by :func:`summarise_row`; ``pemviz tables`` is its
command line."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import format_probability
from pemviz.io.files import write_rrd
from pemviz.methods import CROSS_ENTROPY_METHOD, DEFAULT_METHOD, NAIVE_METHOD, PLAIN_METHOD
from pemviz.presets import PRESETS
from pemviz.scenarios.problems import PROBLEMS
from pemviz.settings import METRICS
from pemviz.sinks.colours import DARK, METRIC_COLOURS, OTHER, rgba, stage_rgba
from pemviz.studies.exact_answers import ExactAnswer
from pemviz.studies.validation import Job, RunRecord, ams_fields, csv_text

FIG4_STAGE = 3
"""The paper's Fig. 4 shows the proposal after stage kappa = 3."""

PEM_RGBA = rgba(DARK)
METRIC_RGBA = {metric: rgba(rgb) for metric, rgb in METRIC_COLOURS.items()}


@dataclass(frozen=True)
class RowSpec:
    """One table row: its label, the table it belongs to and the config fields of its runs."""

    table: str
    label: str
    fields: tuple[tuple[str, Any], ...]


@dataclass(frozen=True)
class Row:
    """A row's numbers over its repetitions (logs in nats)."""

    table: str
    label: str
    reps: int
    log_mean: float
    log_se: float
    mean_failures: float
    n: int
    nll_mean: float
    nll_lme: float
    ess: float
    log_truth: float
    wall_s: float
    covered: int = 0
    """Repetitions whose 95 % interval holds the exact answer."""
    reliable: int = 0
    """Repetitions whose verdict is ``reliable``."""


def log_mean_and_se(logs: Sequence[float]) -> tuple[float, float]:
    """log of the mean and of the standard error std/sqrt(n) (std with n - 1) of values given as logs.

    Exact for values far below float64's range: everything is scaled by the largest value first."""
    x = np.asarray(logs, dtype=np.float64)
    n = x.size
    m = float(np.max(x))
    if m == -math.inf:
        return -math.inf, -math.inf
    v = np.exp(x - m)
    mean = float(v.mean())
    sd = float(v.std(ddof=1)) if n > 1 else 0.0
    return m + math.log(mean), (m + math.log(sd / math.sqrt(n)) if sd > 0 else -math.inf)


def summarise_row(spec: RowSpec, records: Sequence[RunRecord], log_truth: float) -> Row:
    """A row's repetitions (``records``) against the exact answer ``log_truth`` (nats)."""
    log_mean, log_se = log_mean_and_se([r.log_mu_hat for r in records])
    nll = [r.nll_mean for r in records if r.n_failures > 0]
    lme = [r.nll_lme for r in records if r.n_failures > 0]
    return Row(
        spec.table,
        spec.label,
        len(records),
        log_mean,
        log_se,
        float(np.mean([r.n_failures for r in records])),
        records[0].n,
        float(np.mean(nll)) if nll else math.nan,
        float(np.mean(lme)) if lme else math.nan,
        float(np.mean([r.ess for r in records])),
        log_truth,
        float(np.sum([r.wall_s for r in records])),
        sum(r.covers(log_truth) for r in records),
        sum(r.verdict == "reliable" for r in records),
    )


def row_specs(
    base: dict[str, Any], extra: Sequence[str], mc_large: int, naive_large: int, ams: bool = True
) -> list[RowSpec]:
    """Table II then Table III (the classic row of Table III is Table II's adaptive_N row); ``ams``: with an AMS row
    at the adaptive sampler's budget."""
    n = ExperimentConfig.of(**base).n_per_stage
    sim = {k: v for k, v in base.items() if k in ("pem",)}
    specs = [
        RowSpec("II", f"MC_{n}", tuple(sorted({**sim, "method": PLAIN_METHOD, "n_per_stage": n}.items()))),
        RowSpec(
            "II", f"MC_{mc_large}", tuple(sorted({**sim, "method": PLAIN_METHOD, "n_per_stage": mc_large}.items()))
        ),
        RowSpec("II", f"naive-50_{n}", tuple(sorted({**sim, "method": NAIVE_METHOD, "n_per_stage": n}.items()))),
        RowSpec(
            "II",
            f"naive-50_{naive_large}",
            tuple(sorted({**sim, "method": NAIVE_METHOD, "n_per_stage": naive_large}.items())),
        ),
        RowSpec("II", f"adaptive_{n}", tuple(sorted(base.items()))),
    ]
    if ams:  # adaptive multilevel splitting at the adaptive sampler's budget (pemviz.studies.validation.ams_fields)
        budget = ExperimentConfig.of(**base).n_simulations
        specs.append(RowSpec("II", f"AMS_{budget}", tuple(sorted({**sim, **ams_fields(budget)}.items()))))
    for name in extra:
        specs.append(RowSpec("II", f"adaptive_{n} ({name})", tuple(sorted({**PRESETS[name], **base}.items()))))
    for metric in METRICS:
        if metric != "classic":
            specs.append(RowSpec("III", f"r_{metric}", tuple(sorted({**base, "metric": metric}.items()))))
    for name in extra:
        for metric in METRICS:
            if metric != "classic":
                fields = {**PRESETS[name], **base, "metric": metric}
                specs.append(RowSpec("III", f"r_{metric} ({name})", tuple(sorted(fields.items()))))
    return specs


def table_jobs(problem: str, specs: Sequence[RowSpec], reps: int, pem_path: str | None = None) -> list[Job]:
    """R repetitions (seeds 0..reps-1) of every row as jobs (:class:`~pemviz.studies.validation.Job`) that keep their
    proposal curves, the slow (adaptive) rows first so that parallel workers finish together."""
    jobs = [
        Job(problem, s.label, s.fields, seed, keep_curves=True, pem_path=pem_path)
        for s in specs
        for seed in range(reps)
    ]
    return sorted(jobs, key=lambda j: dict(j.fields).get("method", DEFAULT_METHOD) != CROSS_ENTROPY_METHOD)


def records_by_row(specs: Sequence[RowSpec], records: Sequence[RunRecord]) -> dict[str, list[RunRecord]]:
    """Row label -> its repetitions' records in seed order (every row of ``specs``, empty if none ran)."""
    by_label: dict[str, list[RunRecord]] = {s.label: [] for s in specs}
    for r in sorted(records, key=lambda r: r.seed):
        by_label[r.method].append(r)
    return by_label


def report(
    problem: str, reps: int, base: dict[str, Any], truth: ExactAnswer, rows: Sequence[Row], n_jobs: int, wall_s: float
) -> str:
    """The Markdown report of ``pemviz tables`` (``tables.md``): how rows are formed, Table II, Table III, the
    refinement of the exact answer, the wall time (seconds) on ``n_jobs`` processes; ``base``: the adaptive
    sampler's config fields given on the command line."""
    cfg = ExperimentConfig.of(**base)
    return (
        "\n".join(
            [
                f"# pemviz tables: {PROBLEMS[problem]}",
                "",
                f"{reps} repetitions per row (seeds 0..{reps - 1}); mu_hat is the mean over repetitions +- the "
                f"standard error std/sqrt({reps}); failures and ESS are means over repetitions; NLL is over failing "
                f"rollouts (nats), averaged over repetitions. Adaptive: K = {cfg.adaptive.n_stages}, "
                f"N = {cfg.n_per_stage}, N_e = {cfg.adaptive.n_final}, sigma = {cfg.adaptive.quantile_level}, "
                f"alpha = {cfg.adaptive.smoothing}, "
                f"{cfg.adaptive.ce_epochs} epochs per "
                "stage.",
                f"Exact p_fail {format_probability(truth.log_p_fail, 5)}: {truth.source}.",
                "",
                "## Table II: methods (metric: classic)",
                "",
                markdown(rows, "II"),
                "",
                "## Table III: robustness metrics (adaptive; paper settings, then each --extra preset)",
                "",
                markdown(rows, "III"),
                "",
                *(["## Exact answer: refinement", "", truth.table, ""] if truth.table else []),
                f"Wall time {wall_s:.0f} s on {n_jobs} process(es).",
            ]
        )
        + "\n"
    )


def _fmt_row(r: Row) -> list[str]:
    ratio = "-" if r.log_mean == -math.inf else f"{math.exp(r.log_mean - r.log_truth):.3g}"
    se = "" if r.log_se == -math.inf else f" (+-{format_probability(r.log_se, 2)})"
    nll = "-" if math.isnan(r.nll_mean) else f"{r.nll_mean:.1f}"
    lme = "-" if math.isnan(r.nll_lme) else f"{r.nll_lme:.1f}"
    return [
        r.label,
        f"{format_probability(r.log_mean, 3)}{se}",
        f"{r.mean_failures:.1f}/{r.n}",
        nll,
        lme,
        f"{r.ess:.1f}",
        format_probability(r.log_truth, 4),
        ratio,
        f"{r.covered}/{r.reps}",
        f"{r.reliable}/{r.reps}",
    ]


HEADER = (
    "method",
    "mu_hat (+- s.e.)",
    "failures",
    "NLL mean",
    "NLL -log-mean-exp",
    "ESS",
    "exact p_fail",
    "mean / exact",
    "95% CI covers",
    "reliable",
)


def markdown(rows: Sequence[Row], table: str) -> str:
    """The rows of ``table`` (``II`` or ``III``) as a Markdown table, columns :data:`HEADER`."""
    lines = ["| " + " | ".join(HEADER) + " |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    lines += ["| " + " | ".join(_fmt_row(r)) + " |" for r in rows if r.table == table]
    return "\n".join(lines)


def rows_csv(rows: Sequence[Row]) -> str:
    """Every row as CSV text, probabilities beside their logs (nats)."""
    header = (
        "table method reps mu_hat_mean mu_hat_se log_mu_hat_mean log_mu_hat_se mean_failures n nll_mean "
        "nll_log_mean_exp ess exact_p_fail log_exact_p_fail wall_s covered reliable"
    ).split()
    return csv_text(
        header,
        (
            [
                r.table,
                r.label,
                r.reps,
                format_probability(r.log_mean, 6),
                format_probability(r.log_se, 6),
                repr(r.log_mean),
                repr(r.log_se),
                r.mean_failures,
                r.n,
                r.nll_mean,
                r.nll_lme,
                r.ess,
                format_probability(r.log_truth, 6),
                repr(r.log_truth),
                f"{r.wall_s:.2f}",
                r.covered,
                r.reliable,
            ]
            for r in rows
        ),
    )


def write_recording(
    path: Path,
    specs: Sequence[RowSpec],
    records: dict[str, list[RunRecord]],
    grid: np.ndarray,
    pem_curve: np.ndarray,
    description: str,
) -> None:
    """Every adaptive repetition's per-stage proposal curves and Fig. 4 into a rerun file (atomic)."""
    gap_mm = rr.TimeColumn("gap_mm", sequence=np.round(grid * 1000).astype(np.int64))
    write_rrd(
        path, lambda stream: _log_tables(stream, gap_mm, specs, records, pem_curve, description), app_id="pemviz-tables"
    )


def _log_tables(stream, gap_mm, specs, records, pem_curve, description) -> None:  # type: ignore[no-untyped-def]
    def curve(entity: str, values: np.ndarray, colour, name: str) -> None:
        stream.log(entity, rr.SeriesLines(colors=[colour], names=[name], widths=[2.0]), static=True)
        stream.send_columns(entity, indexes=[gap_mm], columns=rr.Scalars.columns(scalars=np.asarray(values, float)))

    stream.log("description", rr.TextDocument(description, media_type=rr.MediaType.MARKDOWN), static=True)
    curve("fig4/pem", pem_curve, PEM_RGBA, "PEM p(detect | d)")
    for spec in specs:
        recs = [r for r in records[spec.label] if r.curves is not None]
        if not recs:
            continue
        key = spec.label.replace(" ", "_").replace("(", "").replace(")", "")
        for r in recs:
            n_stages = r.curves.shape[0] - 1
            for k, c in enumerate(r.curves):
                curve(
                    f"curves/{key}/rep_{r.seed:02d}/stage_{k:02d}",
                    c,
                    stage_rgba(k, n_stages),
                    f"{spec.label} rep {r.seed} stage {k}",
                )
        metric = dict(spec.fields).get("metric", "classic")
        preset = spec.label[spec.label.index("(") + 1 : -1] if spec.label.endswith(")") else None
        if spec.label.startswith((f"{CROSS_ENTROPY_METHOD}_", "r_")) and all(
            r.curves.shape[0] > FIG4_STAGE for r in recs
        ):
            mean = np.mean([r.curves[FIG4_STAGE] for r in recs], axis=0)
            where = f"fig4/{metric}" if preset is None else f"fig4/{preset}/{metric}"
            curve(
                where,
                mean,
                METRIC_RGBA.get(metric, rgba(OTHER)),
                f"{metric}{'' if preset is None else f' ({preset})'}: mean q(detect | d) at stage {FIG4_STAGE} "
                f"over {len(recs)} repetitions",
            )


def tables_rows(
    specs: Sequence[RowSpec], records: dict[str, list[RunRecord]], log_truth: float, extra: Sequence[str]
) -> list[Row]:
    """Every row of both tables in print order: Table II, then Table III, whose classic rows are Table II's adaptive
    rows (same settings, same seeds) relabelled, for the paper settings and then each ``extra`` preset."""
    rows = [summarise_row(s, records[s.label], log_truth) for s in specs]
    adaptive = next(s.label for s in specs if s.label.startswith("adaptive_"))
    table3 = []
    for suffix in ("", *(f" ({name})" for name in extra)):
        classic = next(r for r in rows if r.table == "II" and r.label == f"{adaptive}{suffix}")
        table3.append(
            Row("III", f"r_classic{suffix}", *[getattr(classic, f) for f in list(Row.__dataclass_fields__)[2:]])
        )
        table3 += [r for r in rows if r.table == "III" and r.label.endswith(suffix) and (suffix or "(" not in r.label)]
    return [r for r in rows if r.table == "II"] + table3

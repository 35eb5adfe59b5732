"""The rerun recording of ``pemviz pem eval`` (:mod:`pemviz.studies.pem_eval`'s cross-validation): pooled and
per-fold ROC curves, reliability diagrams, p(detect | gap) for the braking scenario's lead beside the authors' PEM,
and each fold's BCE and ROC-AUC, all static, in 2D figures of their own axes."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import expit

from pemviz.io.files import write_rrd
from pemviz.sinks.colours import MODEL_COLOURS, MODEL_OTHER, REFERENCE_LINE, rgba
from pemviz.studies.pem_eval import EvalResult, format_markdown, reliability_curve

MODEL_RGBA = {name: rgba(rgb) for name, rgb in MODEL_COLOURS.items()}
APP_ID = "pemviz_pem_eval"


def _roc_points(logits: np.ndarray, labels: np.ndarray, max_points: int = 400) -> np.ndarray:
    from sklearn.metrics import roc_curve

    fpr, tpr, _ = roc_curve(labels, logits)
    if fpr.shape[0] > max_points:
        keep = np.unique(np.linspace(0, fpr.shape[0] - 1, max_points).round().astype(np.int64))
        fpr, tpr = fpr[keep], tpr[keep]
    return np.column_stack([fpr, tpr])


def _legend(stream: Any, fig: Any, entries: Sequence[tuple[str, tuple[int, int, int, int]]]) -> None:
    """Coloured labels in the lower right of a figure's box (box coordinates, y down)."""
    import rerun as rr

    n = len(entries)
    pos = [[0.8 * fig.width, fig.height * (0.93 - 0.075 * (n - 1 - i))] for i in range(n)]
    stream.log(
        f"{fig.path}/legend",
        rr.Points2D(pos, colors=[c for _, c in entries], radii=-4.0, labels=[t for t, _ in entries], show_labels=True),
        static=True,
    )


def log_recording(result: EvalResult, stream: Any) -> None:
    """Log the evaluation into a rerun ``RecordingStream`` (all static, 2D figures in axis units): ``description``,
    ``roc/data/<model>`` (and ``/fold_K``), ``reliability/data/<model>`` (and ``/bins``, ``diagonal``),
    ``gap/data/<model>`` and ``gap/data/authors``, ``folds/{bce,auc}/data/<model>``, ``<figure>/legend`` and
    ``metrics/<model>``."""
    import rerun as rr
    import rerun.blueprint as rrb

    from pemviz.sinks.rerun_views import Figure

    roc_fig = Figure("roc", "false positive rate", "true positive rate")
    rel_fig = Figure("reliability", "mean predicted p(detect)", "observed detection rate")
    gap_fig = Figure("gap", "gap d (m)", "p(detect | d)")
    fold_figs = {k: Figure(f"folds/{k}", "fold", label, width=120.0) for k, label in (("bce", "BCE"), ("auc", "AUC"))}
    stream.log(
        "description",
        rr.TextDocument(
            "# PEM quality (pemviz pem eval)\n\n"
            + format_markdown(result)
            + "\n**ROC**: pooled out-of-fold curves (thick) and per fold (thin). **Reliability**: equal-width bins "
            "of the pooled out-of-fold p(detect), point area ~ rows; on the diagonal = calibrated. "
            "**p(detect | d)**: the braking scenario's lead (Car, not occluded, x = 0, y = 1.76, z = d + 2.48, "
            "rot_y = -pi/2), mean over the fold models; white = the authors' PEM. **Per fold**: each fold's BCE "
            "and ROC-AUC.\n",
            media_type=rr.MediaType.MARKDOWN,
        ),
        static=True,
    )
    _log_roc(stream, roc_fig, result)
    _log_reliability(stream, rel_fig, result)
    _log_gap(stream, gap_fig, result)
    _log_folds(stream, fold_figs, result)
    for m in result.models:
        stream.log(
            f"metrics/{m.name}",
            rr.AnyValues(
                bce=m.mean("bce"),
                roc_auc=m.mean("auc"),
                average_precision=m.mean("ap"),
                ece=m.mean("ece"),
                bce_per_fold=[f.bce for f in m.folds],
                auc_per_fold=[f.auc for f in m.folds],
            ),
            static=True,
        )

    stream.send_blueprint(
        rrb.Blueprint(
            rrb.Horizontal(
                rrb.Vertical(roc_fig.view("ROC (out-of-fold)"), rel_fig.view("Reliability (15 bins)")),
                rrb.Vertical(
                    gap_fig.view("p(detect | gap), braking scenario"),
                    rrb.TextDocumentView(origin="/description", name="Table"),
                ),
                rrb.Vertical(fold_figs["bce"].view("BCE per fold"), fold_figs["auc"].view("ROC-AUC per fold")),
                column_shares=[2, 2, 1.3],
            ),
            collapse_panels=True,
        )
    )


def _colour(name: str) -> tuple[int, int, int, int]:
    return MODEL_RGBA.get(name, rgba(MODEL_OTHER))


def _log_roc(stream: Any, roc_fig: Any, result: EvalResult) -> None:
    import rerun as rr

    y, grey = result.labels, rgba(REFERENCE_LINE)
    roc_fig.draw_axes(stream, (0.0, 1.0), (0.0, 1.0))
    stream.log("roc/data/chance", rr.LineStrips2D([[[0, 0], [1, 1]]], colors=grey, radii=-0.5), static=True)
    for m in result.models:
        pooled = _roc_points(m.logits, y[m.test_rows])
        stream.log(f"roc/data/{m.name}", rr.LineStrips2D([pooled], colors=_colour(m.name), radii=-2.0), static=True)
        for k in np.unique(m.test_fold):
            sel = m.test_fold == k
            strip = _roc_points(m.logits[sel], y[m.test_rows[sel]])
            stream.log(
                f"roc/data/{m.name}/fold_{k}",
                rr.LineStrips2D([strip], colors=_colour(m.name)[:3] + (110,), radii=-0.75),
                static=True,
            )
    _legend(stream, roc_fig, [(f"{m.name}  AUC {m.mean('auc'):.3f}", _colour(m.name)) for m in result.models])


def _log_reliability(stream: Any, rel_fig: Any, result: EvalResult) -> None:
    import rerun as rr

    y, grey = result.labels, rgba(REFERENCE_LINE)
    probs = {m.name: expit(m.logits) for m in result.models}
    lo = min(float(np.quantile(p, 0.001)) for p in probs.values())
    lo = max(0.0, math.floor(lo * 10) / 10)
    rel_fig.draw_axes(stream, (lo, 1.0), (lo, 1.0))
    diagonal: list[list[float]] = [[lo, lo], [1, 1]]
    stream.log("reliability/data/diagonal", rr.LineStrips2D([diagonal], colors=grey, radii=-0.5), static=True)
    for m in result.models:
        mean_p, rate, count = reliability_curve(probs[m.name], y[m.test_rows], result.config.n_bins)
        ok = (count > 0) & (mean_p >= lo) & (rate >= lo)
        pts = np.column_stack([mean_p[ok], rate[ok]])
        share = count[ok] / count.sum()
        stream.log(
            f"reliability/data/{m.name}", rr.LineStrips2D([pts], colors=_colour(m.name), radii=-1.0), static=True
        )
        stream.log(
            f"reliability/data/{m.name}/bins",
            rr.Points2D(
                pts,
                colors=_colour(m.name),
                radii=-(2.0 + 10.0 * np.sqrt(share)),
                labels=[
                    f"{m.name}: {int(c)} rows, p {p:.3f}, rate {r:.3f}"
                    for c, p, r in zip(count[ok], mean_p[ok], rate[ok], strict=False)
                ],
                show_labels=False,
            ),
            static=True,
        )
    _legend(stream, rel_fig, [(f"{m.name}  ECE {m.mean('ece'):.4f}", _colour(m.name)) for m in result.models])


def _log_gap(stream: Any, gap_fig: Any, result: EvalResult) -> None:
    import rerun as rr

    curves = {m.name: m.gap_prob.mean(axis=0) for m in result.models}
    if result.authors_gap_prob is not None:
        curves["authors"] = result.authors_gap_prob
    g_lo = max(0.0, math.floor(min(float(np.min(c)) for c in curves.values()) * 20) / 20)
    gap_fig.draw_axes(stream, (float(result.gaps_m[0]), float(result.gaps_m[-1])), (g_lo, 1.0))
    for name, curve in curves.items():
        stream.log(
            f"gap/data/{name}",
            rr.LineStrips2D(
                [np.column_stack([result.gaps_m, curve])],
                colors=_colour(name),
                radii=-2.0 if name == "authors" else -1.5,
            ),
            static=True,
        )
    _legend(stream, gap_fig, [(n if n != "authors" else "authors' PEM", _colour(n)) for n in curves])


def _log_folds(stream: Any, fold_figs: dict[str, Any], result: EvalResult) -> None:
    import rerun as rr

    fold_ids = np.array(result.config.fold_ids, dtype=np.float64)
    for key, fig in fold_figs.items():
        values = np.array([[getattr(f, key) for f in m.folds] for m in result.models])
        v_lo, v_hi = float(values.min()), float(values.max())
        pad = 0.08 * (v_hi - v_lo) if v_hi > v_lo else 0.01
        x_range = (fold_ids[0] - 0.3, fold_ids[-1] + 0.3)
        fig.draw_axes(stream, x_range, (v_lo - pad, v_hi + pad), x_ticks=fold_ids)
        for m, v in zip(result.models, values, strict=False):
            pts = np.column_stack([fold_ids, v])
            stream.log(
                f"{fig.path}/data/{m.name}", rr.LineStrips2D([pts], colors=_colour(m.name), radii=-1.0), static=True
            )
            stream.log(
                f"{fig.path}/data/{m.name}/points", rr.Points2D(pts, colors=_colour(m.name), radii=-3.0), static=True
            )


def write_recording(result: EvalResult, path: str | os.PathLike[str]) -> Path:
    """Write the rerun recording of :func:`log_recording` to ``path`` (:func:`pemviz.io.files.write_rrd`)."""
    return write_rrd(path, lambda stream: log_recording(result, stream), app_id=APP_ID)

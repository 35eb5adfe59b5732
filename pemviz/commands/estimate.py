"""``pemviz estimate ROLLOUTS.parquet``: the failure probability from logged rollouts (:mod:`pemviz.io.rollout_format`),
and a recording. log p and log q come from the file's columns, or are recomputed from a PEM (``--pem``) and what
sampled the rollouts (``--proposal``). Everything is checked before the recording is created: bad input writes nothing.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

import pemviz
from pemviz.commands import UsageError, add_command, add_setting, check_save_path, pem_argument
from pemviz.config import ExperimentConfig, default_of
from pemviz.core.estimate import format_probability
from pemviz.core.sampling import load_proposal
from pemviz.core.weights import CONVENTIONS
from pemviz.io.data import sha256_file
from pemviz.io.files import check_output_folder, check_output_path, free_default_path, write_rrd
from pemviz.io.rollout_estimate import detector_log_prob, estimate_rollouts, pem_log_prob, sampler_detector
from pemviz.io.rollout_format import SAMPLERS, RolloutFormatError
from pemviz.io.rollouts import read_rollouts
from pemviz.pem import load_pem
from pemviz.settings import SETTINGS
from pemviz.sinks.colours import FAILED_ROLLOUT, NEUTRAL, rgba
from pemviz.sinks.console import estimate_cells

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

MAX_TRACES = 300
"""Rollouts whose traces go into the recording: the least robust ones (every failure first)."""


DESCRIPTION = """
Importance-sampling estimate (failures, mu_hat, NLL, ESS) from a rollout file and its JSON sidecar (format:
pemviz.io.rollout_format), and a rerun recording of it.
"""
"""``pemviz estimate --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz estimate`` and its flags to the sub-command parsers ``sub``."""
    p = add_command(sub, "estimate", DESCRIPTION)
    p.add_argument(
        "rollouts",
        metavar="ROLLOUTS.parquet",
        help="rollout file (its sidecar ROLLOUTS.rollouts.json, or ROLLOUTS.json, beside it)",
    )
    lp = p.add_mutually_exclusive_group()
    lp.add_argument(
        "--pem",
        metavar="NAME|PATH",
        help=f"recompute log p from this PEM, {SETTINGS['pem'].allowed} (default: the log_p column, else "
        "the sidecar's PEM)",
    )
    lp.add_argument("--log-p-column", action="store_true", help="use the file's log_p column")
    lq = p.add_mutually_exclusive_group()
    lq.add_argument(
        "--proposal",
        metavar="CKPT|pem|naive50|mixed50",
        help="recompute log q from a proposal checkpoint or a named sampler "
        "(default: the log_q column, else the sidecar's proposal)",
    )
    lq.add_argument("--log-q-column", action="store_true", help="use the file's log_q column")
    add_setting(p, "metric", default=default_of("metric"))
    p.add_argument(
        "--failure",
        default="crash",
        choices=("crash", "metric"),
        help="failure event: crash = classic robustness < 0 (default); metric = the metric's < 0",
    )
    p.add_argument(
        "--weights",
        choices=CONVENTIONS,
        help="importance weights: to-failure = prod p/q over the steps before the failure step (pemviz's "
        "sampler); full = over every step but the last (the paper's eq. 6); both unbiased. Default: "
        "the convention the sidecar records, else to-failure",
    )
    add_setting(p, "pem_uncertainty")
    add_setting(p, "pem_shift")
    p.add_argument(
        "--json",
        dest="json_path",
        metavar="PATH.json",
        help="write the estimate as one JSON document (log mu_hat in full float64; the estimate's fields as in "
        "pemviz run --json, and each stage's; format: pemviz.io.result.estimate_document)",
    )
    rec = p.add_argument_group("recording (rerun)")
    rec.add_argument(
        "--save", metavar="PATH.rrd", help="write the recording here (default recordings/estimate-<name>-<time>.rrd)"
    )
    rec.add_argument("--no-record", action="store_true", help="write no recording")
    rec.add_argument(
        "--overwrite", action="store_true", help="replace an existing --save or --json file (only one pemviz wrote)"
    )
    p.set_defaults(func=main)


def _resolve(base: Path, ref: str) -> Path:
    p = Path(ref)
    return p if p.is_absolute() else base / p


def log_probabilities(data: Any, args: argparse.Namespace) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(log_p [N, T], log_q [N, T], where log p came from, where log q came from) for the options.

    Raises:
        UsageError: a column asked for or needed is absent and nothing names how to recompute it.
        FileNotFoundError / ValueError: a PEM or proposal that cannot be loaded."""
    meta, base = data.meta, (data.path.parent if data.path else Path("."))
    pem_ref = args.pem or meta.pem
    pem_cache: dict[str, Any] = {}

    def pem() -> Any:
        if pem_ref is None:
            raise UsageError(f"{data.path}: give --pem NAME to recompute log p (the file and its sidecar name no PEM)")
        if "pem" not in pem_cache:  # a path in the sidecar is relative to the sidecar's folder
            from_sidecar = args.pem is None and Path(pem_ref).suffix == ".pt"
            pem_cache["pem"] = load_pem(str(_resolve(base, pem_ref)) if from_sidecar else pem_ref)
        return pem_cache["pem"]

    if meta.per_object and (args.pem is not None or args.proposal is not None):
        flag = "--pem" if args.pem is not None else "--proposal"
        raise UsageError(
            f"{flag}: {data.path} holds {meta.objects} object(s) a step with errors "
            f"{list(meta.noise)}; it is estimated from its own log_p and log_q (each object's row, "
            "what the PEMs read, is not in the file)"
        )
    if args.log_p_column and data.log_p is None:
        raise UsageError(f"--log-p-column: {data.path} has no log_p column; give --pem NAME to recompute it")
    if args.pem is None and data.log_p is not None:
        log_p, p_src = data.log_p, "column log_p"
    else:
        log_p = pem_log_prob(data, pem())
        how = "salient variables" if data.salient is not None else "gap"
        p_src = f"PEM {pem_ref} (recomputed from the {how})"

    if args.log_q_column and data.log_q is None:
        raise UsageError(f"--log-q-column: {data.path} has no log_q column; give --proposal CKPT to recompute it")
    q_ref = args.proposal
    if q_ref is None and data.log_q is not None:
        return log_p, data.log_q, p_src, "column log_q"
    if q_ref is None:
        q_ref = meta.proposal
        if q_ref is None:
            raise UsageError(
                f"{data.path}: no log_q column and the sidecar names no proposal; give --proposal "
                f"CKPT or one of {', '.join(SAMPLERS)}"
            )
        if q_ref not in SAMPLERS:
            q_ref = str(_resolve(base, q_ref))
            if meta.proposal_sha256 and Path(q_ref).is_file() and sha256_file(q_ref) != meta.proposal_sha256:
                raise RolloutFormatError(
                    f"{q_ref}: not the proposal checkpoint the sidecar of {data.path} was "
                    "written with (proposal_sha256 differs); write the rollouts again"
                )
    if q_ref in SAMPLERS:
        detector = sampler_detector(q_ref, pem(), meta.window_m)
    else:
        detector = load_proposal(q_ref)
    return log_p, detector_log_prob(data, detector), p_src, f"{q_ref} (recomputed)"


def default_recording_path(rollouts: Path) -> Path:
    """``recordings/estimate-NAME-TIME.rrd`` (``-2``, ``-3`` ... when taken)."""
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return free_default_path(Path("recordings"), f"estimate-{rollouts.stem}-{stamp}")


WEIGHT_TEXT = {
    "to-failure": "prod p/q over the steps before the failure step",
    "full": "prod p/q over every step but the last (Innes & Ramamoorthy 2022, eq. 6)",
}


def weights_convention(meta: Any, requested: str | None) -> tuple[str, str]:
    """(the convention, why): ``--weights``, else the sidecar's ``weights``, else a version-1 file's run config,
    else ``to-failure`` (what pemviz's sampler weighs with)."""
    if requested is not None:
        said = f"; the file's writer used {meta.weights}" if meta.weights and meta.weights != requested else ""
        return requested, f"--weights{said}"
    if meta.weights is not None:
        return meta.weights, "the convention the sidecar records"
    config = (meta.provenance or {}).get("config")
    if isinstance(config, dict) and isinstance(config.get("weights_until_failure"), bool):
        return ("to-failure" if config["weights_until_failure"] else "full"), "the run's config in the sidecar"
    return "to-failure", "pemviz's default; the sidecar names none"


def run_problem(data: Any, failure: str, own: bool) -> Any:
    """The problem of the run that wrote the file (:func:`pemviz.scenarios.problems.problem_for` of the scenario, its
    parameters, PEM, margin and simulator its sidecar records), when the file is estimated as that run estimated it:
    under the run's own log p (``own``) and with a crash of its specification as the failure; None otherwise, when the
    sidecar records no run, or for a run of another version or a PEM no longer there."""
    config = ((data.meta.provenance or {}).get("config") if data.meta else None) or {}
    if not own or failure != "crash" or not isinstance(config, dict) or "scenario" not in config:
        return None
    from pemviz.config import ConfigError
    from pemviz.scenarios.parameters import as_pairs
    from pemviz.scenarios.registry import problem_for

    try:
        fields = {k: config[k] for k in ("scenario", "pem", "margin", "sim") if k in config}
        if "scenario_params" in config:  # a JSON list of [name, value] lists
            fields["scenario_params"] = as_pairs(config["scenario_params"])
        return problem_for(ExperimentConfig.of(**fields))
    except (ConfigError, OSError, ValueError, TypeError):
        return None


def known_answer(problem: Problem) -> tuple[float | None, Any]:
    """The exact log failure probability (nats) or the plain Monte Carlo reference that the run which wrote the file
    printed: those of its problem (:func:`run_problem`); ``(None, None)`` without one."""
    return (None, None) if problem is None else (problem.exact_log_p, problem.reference)


def summary_lines(
    data: Any, result: Any, p_src: str, q_src: str, why: str = "", known: tuple[float | None, Any] = (None, None)
) -> list[str]:
    """The printed report: the file, the weight convention, the sources of log p / log q, one row per stage, the
    pooled estimate and which stages it pools, the mean-weight check (and its warning), the verdict line with the
    exact answer or reference ``known`` (:func:`known_answer`)."""
    e = result.estimate
    failure = "crash (classic robustness < 0)" if result.failure == "crash" else f"{result.metric} robustness < 0"
    lines = [
        f"pemviz estimate: {data.path} ({data.n} rollouts x {data.n_steps} steps, dt {data.meta.dt_s:g} s), "
        f"spec {data.meta.formula}, failure = {failure}, metric {result.metric}",
        f"  weights: {result.weights}, {WEIGHT_TEXT[result.weights]} ({why or 'given'})",
        f"  log p: {p_src}",
        f"  log q: {q_src}",
        f"{'stage':>7} {'kind':>8} {'failures':>10} {'mu_hat':>11} {'95% CI':>21} {'NLL':>8} {'ESS':>7} {'k-hat':>6} "
        f"{'verdict':>10}",
    ]
    for row in result.stages:
        lines.append(
            f"{'-' if row.stage is None else row.stage:>7} {row.kind or '-':>8} {estimate_cells(row.estimate)}"
        )
    if result.pooled:
        which = ", ".join(map(str, result.pooled))
        lines.append(f"{'final':>7} {'':>8} {estimate_cells(e)}   <- stages {which} pooled ({result.rule})")
    elif len(result.stages) > 1:
        lines.append(
            f"{'final':>7} {'':>8} {estimate_cells(e)}   <- every rollout alike (the sidecar gives no pooling)"
        )
    nll = "-" if math.isnan(e.nll_mean) else f"{e.nll_mean:.4f}"
    lines.append(
        f"mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = {e.log_mu_hat:.4f} nats), "
        f"NLL mean {nll} / -log-mean-exp {e.nll_lme:.4f} nats, ESS {e.ess:.4f}, min robustness "
        f"{float(np.min(result.robustness)):.4f}"
    )
    lines.append(result.check.line())
    if result.check.warning():
        lines.append(result.check.warning())
    lines.append(e.summary(*known))
    return lines


def check_plausible(e: Any, q_src: str) -> None:
    """Refuse an impossible estimate: a mean importance weight so large (> 1000: probability <= 0.001 by Markov's
    inequality, since its expectation is 1) that log q cannot be the proposal that drew the rollouts. A mean a little
    above 1 is not refused: a run whose rollouts nearly all fail draws one as often as one below (mu_hat is then cut
    at 1, :func:`pemviz.core.estimate.estimate`).

    Raises:
        UsageError: one line naming the proposal and the numbers."""
    if e.log_mean_weight > math.log(1000.0):
        raise UsageError(
            f"mu_hat = {format_probability(e.log_mu_hat)} with mean importance weight "
            f"{format_probability(e.log_mean_weight)} (expected ~1): the proposal ({q_src}) does not match the one "
            "that sampled the file; give the right --proposal, or log_q columns"
        )


def pem_spread_lines(
    data: Any, args: argparse.Namespace, result: Any, log_q: np.ndarray, weights: str, cap: Any
) -> list[str]:
    """``--pem-uncertainty`` / ``--pem-shift``: the file's rollouts re-weighted under every member of the PEM's ensemble
    and the logit shifts (:mod:`pemviz.core.reweight`), each estimated as the file's own log p is, printed as ``pemviz
    run`` prints them.

    Raises:
        UsageError: a file of several objects or with measurement errors (its rows are not in it), a PEM without a
            shipped ensemble, or a PEM that cannot be read."""
    from pemviz.core.detectors import PEMDetector
    from pemviz.core.reweight import Alternative, PemSpread, ShiftedDetector
    from pemviz.pem.ensemble import ensemble_for, load_ensemble
    from pemviz.scenarios.braking.problem import braking_formula
    from pemviz.scenarios.braking.truth_known import known_log_failure_probability
    from pemviz.scenarios.problems import PEM_SHIFTS

    if data.n_objects > 1 or data.noise is not None:
        raise UsageError(
            f"--pem-uncertainty: {data.path} holds {data.n_objects} objects a step with measurement "
            "errors, whose salient rows are not in the file; re-weight in the run instead (pemviz run "
            "--pem-uncertainty)"
        )
    name = args.pem or (data.meta.pem if data.meta else None) or "ml-nn"
    try:
        pem = load_pem(name)
        members = load_ensemble(ensemble_for(name)) if args.pem_uncertainty else []
    except (FileNotFoundError, ValueError) as exc:
        raise UsageError(f"--pem-uncertainty: {exc}") from None
    config = ((data.meta.provenance or {}).get("config") if data.meta else None) or {}
    changed = isinstance(config, dict) and bool(config.get("scenario_params"))  # another scene: no kept truth
    braking = data.meta is not None and data.meta.formula == str(braking_formula()) and not changed
    shifts = list(PEM_SHIFTS) if args.pem_uncertainty else []
    if args.pem_shift is not None and args.pem_shift not in shifts:
        shifts.append(float(args.pem_shift))
    cap = tuple(cap) if isinstance(cap, list) and len(cap) == 2 else None

    def estimate_under(log_p_k: np.ndarray, logit_fn: Any) -> tuple[Any, float | None]:
        est = estimate_rollouts(
            data, log_p_k, log_q, metric=args.metric, failure=args.failure, weights=weights, verdict_cap=cap
        ).estimate
        return est, known_log_failure_probability(logit_fn) if braking else None

    made = [
        Alternative(f"member {k}", *estimate_under(pem_log_prob(data, m), m.logit_at_gap))
        for k, m in enumerate(members)
    ]
    moved = []
    for d in sorted(shifts):

        def shifted(g, d=d):
            return np.asarray(pem.logit_at_gap(g), dtype=np.float64) + d

        moved.append(
            Alternative(
                f"{d:+g}", *estimate_under(detector_log_prob(data, ShiftedDetector(PEMDetector(pem), d)), shifted)
            )
        )
    return PemSpread(result.estimate, tuple(made), tuple(moved), ensemble_for(name).name if members else "").lines()


def write_recording(path: Path, data: Any, result: Any, lines: list[str], *, overwrite: bool = False) -> Path:
    """A rerun recording of the estimate: description, estimate values, the least-robust rollouts' traces
    over ``step`` (red = failure), and robustness against importance log-weight. Encoded in memory, written
    under a unique temporary name and moved to ``PATH`` once complete (:func:`pemviz.core.files.atomic_write`).

    Raises:
        OSError: the file could not be written (nothing is left); OutputExists: ``PATH`` exists, no ``overwrite``."""
    import rerun as rr  # only when a recording is asked for

    def log(stream: rr.RecordingStream) -> None:
        stream.send_recording_name(f"pemviz estimate {data.path.name if data.path else ''}")
        e = result.estimate
        text = "# pemviz estimate from logged rollouts\n\n```\n" + "\n".join(lines) + "\n```\n"
        stream.log("description", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        stream.log(
            "estimate",
            rr.AnyValues(
                log_mu_hat=e.log_mu_hat,
                n_failures=e.n_failures,
                n=e.n,
                nll_mean=e.nll_mean,
                nll_lme=e.nll_lme,
                ess=e.ess,
                metric=result.metric,
                failure=result.failure,
                formula=data.meta.formula,
                pemviz_version=pemviz.__version__,
                weights=result.weights,
                pooled_stages=",".join(map(str, result.pooled)),
                log_mean_weight=result.check.log_mean,
            ),
            static=True,
        )
        order = np.argsort(np.where(result.failed, -np.inf, result.robustness), kind="stable")[:MAX_TRACES]
        colours = [rgba(FAILED_ROLLOUT, 160) if result.failed[i] else rgba(NEUTRAL, 80) for i in order]
        names = [f"rollout {data.rollout_ids[i]}{' failure' if result.failed[i] else ''}" for i in order]
        index = [rr.TimeColumn("step", sequence=np.arange(data.n_steps, dtype=np.int64))]
        for col in data.observation_names:
            entity = f"rollouts/{col}"
            stream.log(entity, rr.SeriesLines(colors=colours, names=names), static=True)
            stream.send_columns(entity, indexes=index, columns=rr.Scalars.columns(scalars=data.signal(col)[order].T))
        points = np.column_stack([result.robustness, result.log_weight])
        stream.log(
            "scores",
            rr.Points2D(
                points,
                colors=[rgba(FAILED_ROLLOUT) if f else rgba(NEUTRAL) for f in result.failed],
                labels=[f"rollout {i}: robustness, log w" for i in data.rollout_ids],
            ),
            static=True,
        )

    return write_rrd(path, log, overwrite=overwrite)


def main(args: argparse.Namespace) -> int:
    """``pemviz estimate``: re-estimate p(failure) from a rollout file, print the summary and write the recording and
    result document asked for.

    Returns:
        The exit status, 0.

    Raises:
        UsageError: a bad metric, PEM or output path, or a run weighed with a look-ahead this version cannot rebuild."""
    if not SETTINGS["metric"].accepts(args.metric):
        raise UsageError(f"--metric {args.metric!r}: use {SETTINGS['metric'].allowed}")
    pem_argument(args.pem)
    rollouts = Path(args.rollouts)
    save_path = None
    if args.save is not None and not args.no_record:
        save_path = check_save_path(Path(args.save), args.overwrite)
    elif not args.no_record:  # recordings/ is made only once there is an estimate to record
        save_path = default_recording_path(rollouts)
        try:
            check_output_folder(save_path.parent, (save_path.name,), "recording folder")
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    json_path = None
    if args.json_path is not None:
        try:
            json_path = check_output_path(args.json_path, ".json", "--json", overwrite=args.overwrite)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    data = read_rollouts(rollouts)
    log_p, log_q, p_src, q_src = log_probabilities(data, args)
    weights, why = weights_convention(data.meta, args.weights)
    run_estimate = ((data.meta.provenance or {}).get("estimate") or {}) if data.meta else {}
    own = p_src == "column log_p"  # the run's PEM: its bound and its sampler's cap apply
    cap = run_estimate.get("verdict_cap")
    problem = run_problem(data, args.failure, own)
    said = run_estimate.get("look_ahead") is True  # the run weighed with its problem's look-ahead
    look_ahead = problem.look_ahead if problem is not None and said else None
    if said and own and args.failure == "crash" and look_ahead is None:
        raise UsageError(
            f"{rollouts}: the run that wrote it weighed its rollouts with an exact look-ahead that this "
            "pemviz cannot rebuild (its scenario, parameters or PEM); estimate it with the version "
            "that wrote it"
        )
    result = estimate_rollouts(
        data,
        log_p,
        log_q,
        metric=args.metric,
        failure=args.failure,
        weights=weights,
        log_p_seen=run_estimate.get("log_p_seen") if own else None,
        verdict_cap=tuple(cap) if own and isinstance(cap, list) and len(cap) == 2 else None,
        look_ahead=look_ahead,
    )
    if result.weights != weights:
        why = f"{weights} needs a crash of a G[a,b](state predicate) formula; every step but the last instead"
    check_plausible(result.estimate, q_src)
    lines = summary_lines(data, result, p_src, q_src, why, known_answer(problem))
    if args.pem_uncertainty or args.pem_shift is not None:
        lines += pem_spread_lines(data, args, result, log_q, weights, cap if own else None)
    print("\n".join(lines), flush=True)
    if json_path is not None:
        from pemviz.io.result import estimate_document, write_result_json

        doc = estimate_document(
            result,
            rollouts=str(rollouts),
            sources=(p_src, q_src),
            known=known_answer(problem),
            command=shlex.join(["pemviz", *sys.argv[1:]]),
            console=lines,
        )
        print(f"result: {write_result_json(json_path, doc, overwrite=args.overwrite)}", file=sys.stderr)
    if save_path is not None:
        save_path.parent.mkdir(exist_ok=True)  # the default folder, as pemviz run makes it
        where = write_recording(save_path, data, result, lines, overwrite=args.overwrite)
        print(f"recording: {where}", file=sys.stderr)
    return 0

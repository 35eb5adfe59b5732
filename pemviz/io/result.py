"""A run's result as files a CI job reads: one JSON document (``pemviz run --json``, ``pemviz-result``,
:data:`RESULT_VERSION`; ``pemviz estimate --json`` holds the same ``estimate`` object) and a JUnit XML test case for a
requirement (``--junit``: passed when met, ``<failure>`` when violated, ``<error type="undecided">`` when undecided).
Probabilities are given as numbers and as natural logs; a non-finite value is ``null``; the JSON Schema is in the user
guide ("pemviz in CI")."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any
from xml.etree import ElementTree as ET

from pemviz.core.files import atomic_write
from pemviz.io.files import write_text_atomic

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig
    from pemviz.core.problems import Problem

RESULT_FORMAT = "pemviz-result"
RESULT_VERSION = 1


def _number(x: float | None) -> float | None:
    """A float for JSON: None for None, nan and +-inf."""
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _probability(log_p: float | None) -> dict[str, float | None]:
    return {"p": None if log_p is None or math.isnan(log_p) else math.exp(log_p), "log_p": _number(log_p)}


def _plain(value: Any) -> Any:
    if isinstance(value, float):
        return _number(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    return value if value is None or isinstance(value, (bool, int, str)) else str(value)


def estimate_fields(e: Any, sampling: str) -> dict[str, Any]:
    """The ``estimate`` object of a result document: of :class:`pemviz.core.estimate.Estimate` ``e``, p and log p
    (full float64: the console rounds log p to 4 decimals), the 95 % interval or lower bound alone, ESS, k-hat, the
    failures, the verdict and its reason, and ``sampling`` (``plain``, ``importance`` or ``splitting``)."""
    lo, hi = e.log_ci if e.interval_backed else (e.log_lower_bound, None)  # a bound alone: no upper end
    return {
        **_probability(e.log_mu_hat),
        "interval": "ci95" if e.interval_backed else "lower_bound95",
        "ci95": [_probability(lo)["p"], None if hi is None else _probability(hi)["p"]],
        "log_ci95": [_number(lo), _number(hi)],
        "lower_bound95": _probability(e.log_lower_bound)["p"],
        "log_lower_bound95": _number(e.log_lower_bound),
        "ess": _number(e.ess),
        "k_hat": _number(e.khat),
        "n_failures": int(e.n_failures),
        "n": int(e.n),
        "verdict": e.verdict,
        "reason": e.reason,
        "sampling": sampling,
    }


def result_document(
    config: ExperimentConfig,
    final: Any,
    *,
    exact_log_p: float | None = None,
    reference: Any = None,
    recording: str | None = None,
    command: str | None = None,
    problem: Problem | None = None,
    console: list[str] | None = None,
    inputs: list[dict[str, str]] | None = None,
    failures: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The JSON document of a finished run.

    Args:
        config: the run's :class:`pemviz.config.ExperimentConfig`.
        final: its :class:`pemviz.engine.events.FinalEstimate`.
        exact_log_p: the exact log p where the problem has one (nats).
        reference: its :class:`pemviz.core.estimate.Reference`, or None.
        recording: where the recording went (a path or a URL), or None.
        command: the command line, for the record.
        problem: the run's :class:`pemviz.core.problems.Problem`, or None.
        console: the lines the console printed after the table, or None.
        inputs: the files the run read, ``{"what", "path", "sha256"}`` each, or None.
        failures: the final estimate's failures in groups with their shares of p and severity
            (:func:`pemviz.sinks.population.grouping_document`), or None."""
    import pemviz

    doc: dict[str, Any] = {
        "format": RESULT_FORMAT,
        "version": RESULT_VERSION,
        "pemviz_version": pemviz.__version__,
        "command": command,
        "scenario": config.scenario,
        "method": config.method,
        "seed": config.seed,
        "estimate": estimate_fields(final.estimate, _sampling(config, final.estimate)),
        "n_simulations": int(final.n_simulations),
        "wall_s": _number(final.wall_s),
        "exact": None if exact_log_p is None else _probability(exact_log_p),
        "reference": None if reference is None else {**_probability(reference.log_p), "source": reference.source},
        "requirement": None,
        "stop": final.stop,
        "proposal_prepared": final.prepared,
        "recording": recording,
        "settings": _plain(config.flat()),
    }
    if problem is not None:
        doc["problem"] = {"name": problem.name, "description": problem.description, "formula": str(problem.formula)}
    if console is not None:
        doc["console"] = list(console)
    if inputs is not None:
        doc["inputs"] = list(inputs)
    if failures is not None:
        doc["failures"] = _plain(failures)
    doc["pem_spread"] = _pem_spread(getattr(final, "pem_spread", None))
    curve = getattr(final, "severity", None)
    if curve is not None:
        doc["severity"] = _severity_document(curve)
    d = getattr(final, "decision", None)
    if config.stop.require is not None and d is not None:
        doc["requirement"] = _requirement_document(config.stop.require, d)
    return doc


def _ci(log_ci: Any) -> list[float | None]:
    """An interval's two ends as probabilities (None for a non-finite log bound above 0)."""
    return [_probability(x)["p"] if math.isfinite(x) or x < 0 else None for x in log_ci]


def _severity_document(curve: Any) -> dict[str, Any]:
    """The severity curve's part of the result document: its scale, title and each level's estimate."""
    return {
        "signal": curve.scale.signal,
        "label": curve.scale.label,
        "unit": curve.scale.unit,
        "title": curve.title(),
        "points": [
            {
                "level": pt.level,
                "text": curve.point_text(pt),
                **_probability(pt.estimate.log_mu_hat),
                "ci95": _ci(pt.estimate.shown_log_ci),
                "ess": _number(pt.estimate.ess),
                "n_events": int(pt.estimate.n_failures),
                "verdict": pt.estimate.verdict,
                "exact": None if pt.exact_log_p is None else _probability(pt.exact_log_p),
                "lower_bound95": _probability(pt.estimate.log_lower_bound)["p"],
                "shown": curve.shown(pt),
                "says": curve.says(pt),
            }
            for pt in curve.points
        ],
    }


def _requirement_document(require: str, d: Any) -> dict[str, Any]:
    """The requirement's part of the result document: its text, the decision ``d`` and its exit code."""
    from pemviz.core.requirement import EXIT_CODES, parse_requirement

    req = parse_requirement(require)
    return {
        "text": str(req),
        "op": req.op,
        "threshold": req.threshold,
        "outcome": d.outcome,
        "exit_code": EXIT_CODES[d.outcome],
        "look": d.look,
        "level": d.level,
        "ci": _ci(d.log_ci),
        "why": d.why,
    }


ESTIMATE_FORMAT = "pemviz-estimate"


def estimate_document(
    result: Any,
    *,
    rollouts: str,
    sources: tuple[str, str],
    known: tuple[float | None, Any] = (None, None),
    command: str | None = None,
    console: list[str] | None = None,
) -> dict[str, Any]:
    """The JSON document of ``pemviz estimate --json`` (``pemviz-estimate``, :data:`RESULT_VERSION`): the estimate in a
    run document's fields (:func:`estimate_fields`) with the NLLs, log mean weight and least robustness, each
    stage's estimate, the weight convention, failure event, metric, the sources of log p and log q, and the exact
    answer or reference ``known`` of the run that wrote the file.

    Args:
        result: :class:`pemviz.io.rollout_estimate.RolloutEstimate` of the file.
        rollouts: the rollout file's path.
        sources: (log p's source, log q's source) as printed.
        known: (the exact log p in nats or None, the :class:`pemviz.core.estimate.Reference` or None) of the run.
        command: the command line, for the record.
        console: the lines ``pemviz estimate`` printed."""
    import pemviz

    def fields(e: Any) -> dict[str, Any]:
        return estimate_fields(e, "plain" if e.plain_mc else "importance")

    exact_log_p, reference = known
    e = result.estimate
    return {
        "format": ESTIMATE_FORMAT,
        "version": RESULT_VERSION,
        "pemviz_version": pemviz.__version__,
        "command": command,
        "rollouts": rollouts,
        "estimate": {
            **fields(e),
            "nll_mean": _number(e.nll_mean),
            "nll_lme": _number(e.nll_lme),
            "log_mean_weight": _number(result.check.log_mean),
            "min_robustness": _number(float(result.robustness.min())) if len(result.robustness) else None,
        },
        "stages": [
            {"stage": None if r.stage is None else int(r.stage), "kind": r.kind, "estimate": fields(r.estimate)}
            for r in result.stages
        ],
        "pooled_stages": [int(k) for k in result.pooled],
        "pooling": result.rule if result.pooled else None,
        "weights": result.weights,
        "failure": result.failure,
        "metric": result.metric,
        "log_p_source": sources[0],
        "log_q_source": sources[1],
        "exact": None if exact_log_p is None else _probability(exact_log_p),
        "reference": None if reference is None else {**_probability(reference.log_p), "source": reference.source},
        "console": None if console is None else list(console),
    }


def _sampling(config: ExperimentConfig, e: Any) -> str:
    """How the estimate's rollouts were drawn (:data:`pemviz.core.verdict_checks.SAMPLINGS`): ``plain`` (plain Monte
    Carlo, a method's or the fallback's), ``importance`` (a weighted method) or ``splitting`` (AMS: no weights)."""
    if e.plain_mc:
        return "plain"
    return "importance" if config.method_record.weighted else "splitting"


def _pem_spread(spread: Any) -> dict[str, Any] | None:
    """p under the PEM's own uncertainty (:class:`pemviz.core.reweight.PemSpread`) for the result document: the
    members' count, median and 90 % range (5th to 95th percentile) of p, and each logit shift's p; None where the run
    did not compute it (no ``--pem-uncertainty``)."""
    if spread is None:
        return None
    out: dict[str, Any] = {"source": spread.source, "members": None, "shifts": []}
    if spread.members:
        med, lo, hi = spread.spread()
        out["members"] = {
            "n": len(spread.members),
            "median": _probability(med),
            "range90": [_probability(lo), _probability(hi)],
        }
    out["shifts"] = [
        {"label": a.label, **_probability(a.estimate.log_mu_hat), "verdict": a.estimate.verdict} for a in spread.shifts
    ]
    return out


RESULT_BESIDE_SUFFIX = ".result.json"
"""A recording's result document lies beside it: ``run.rrd`` -> ``run.result.json`` (:func:`result_beside`)."""


def result_beside(recording: str | os.PathLike[str]) -> Path:
    """Where a saved recording's result document goes (``pemviz run`` writes it at the end of a run that saves a
    recording; ``pemviz report RUN.rrd`` reads it): the recording's name with ``.result.json`` for ``.rrd``."""
    path = Path(recording)
    return path.with_name(path.stem + RESULT_BESIDE_SUFFIX)


def write_result_json(path: str | os.PathLike[str], doc: dict[str, Any], *, overwrite: bool = False) -> Path:
    """Write ``doc`` (:func:`result_document`) atomically as JSON.

    Raises:
        OSError: the file could not be written (nothing is left); OutputExists: ``path`` exists, no ``overwrite``."""
    return write_text_atomic(path, json.dumps(doc, indent=1, allow_nan=False) + "\n", overwrite=overwrite)


def junit_xml(doc: dict[str, Any], console: str = "") -> bytes:
    """One JUnit test suite with one test case, the requirement of ``doc`` (:func:`result_document`).

    Raises:
        ValueError: ``doc`` has no requirement."""
    req = doc.get("requirement")
    if req is None:
        raise ValueError("a JUnit test case needs a requirement (--require)")
    outcome = req["outcome"]
    wall = f"{doc['wall_s'] or 0.0:.3f}"
    suite = ET.Element(
        "testsuite",
        name="pemviz",
        tests="1",
        failures=str(int(outcome == "violated")),
        errors=str(int(outcome == "undecided")),
        skipped="0",
        time=wall,
    )
    case = ET.SubElement(suite, "testcase", classname=f"pemviz.{doc['scenario']}", name=req["text"], time=wall)
    message = f"requirement {outcome}: {req['why']}"
    if outcome == "violated":
        ET.SubElement(case, "failure", type="violated", message=message).text = message
    elif outcome == "undecided":
        ET.SubElement(case, "error", type="undecided", message=message).text = doc.get("stop") or message
    ET.SubElement(case, "system-out").text = console
    root = ET.Element("testsuites")
    root.append(suite)
    return ET.tostring(root, encoding="utf-8", xml_declaration=True)


def write_junit(
    path: str | os.PathLike[str], doc: dict[str, Any], console: str = "", *, overwrite: bool = False
) -> Path:
    """Write :func:`junit_xml` atomically.

    Raises:
        ValueError: ``doc`` has no requirement; OSError, OutputExists: as :func:`write_result_json`."""
    data = junit_xml(doc, console)

    def write(tmp: str) -> None:
        Path(tmp).write_bytes(data)

    return atomic_write(path, write, overwrite=overwrite)

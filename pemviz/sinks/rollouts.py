"""Engine listener that saves the rollouts of the run's estimate as a rollout file (``pemviz run --save-rollouts``).

The file format (Parquet table, JSON sidecar, proposal checkpoint) is :mod:`pemviz.io.rollout_format`'s."""

from __future__ import annotations

import copy
import dataclasses
import os
import sys
import types
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from pemviz.core.detectors import ArrayRQMC, ConstantDetector, SamplerView, WindowDetector
from pemviz.core.sampling import Proposal
from pemviz.core.weights import convention, stage_log_q
from pemviz.engine.events import (
    FinalEstimate,
    RolloutChunk,
    RunCancelled,
    RunFinished,
    RunStarted,
    StageFinished,
    StageStarted,
)
from pemviz.estimators.pooling import pool_stage_weights
from pemviz.io.rollout_writer import RolloutWriter, check_rollouts_path
from pemviz.io.run_rollouts import run_meta, run_salient, run_severity
from pemviz.pem.recipes import DEFAULT_PEM_NAME
from pemviz.settings import setting_of
from pemviz.sinks import Sink

SAY_SIZE_ABOVE_BYTES = 100 * 10**6
"""A run with ``--save-rollouts`` says, after its first chunk and before the rest, how large the file will be when it
may grow above this (100 MB): :meth:`RolloutSink.size_line`."""

STAGES = ("used", "all")
"""Which stages ``--save-rollouts`` writes: those the run's estimate uses, or every stage (pretraining included)."""


def _estimate_json(e: Any) -> dict[str, Any]:
    return {
        "log_mu_hat": e.log_mu_hat,
        "n_failures": e.n_failures,
        "n": e.n,
        "log_ci": list(e.log_ci),
        "ess": e.ess,
        "khat": e.khat,
        "verdict": e.verdict,
        "reason": e.reason,
        "interval_backed": e.interval_backed,
        "log_lower_bound": e.log_lower_bound,
    }


class RolloutSink(Sink):
    """Engine listener for ``pemviz run --save-rollouts``: writes every stage the run's estimate uses (``stages =
    "used"``) or every stage (``"all"``), so that ``pemviz estimate`` on the file reproduces the run's estimate.

    Each rollout is written with its stage, component, severity and as ``log_q`` the density the run weighed it with
    (:func:`pemviz.core.weights.stage_log_q`), chunk by chunk (:class:`pemviz.io.rollout_writer.RolloutWriter`);
    nothing is left after a cancelled or failed run, and an interrupted one keeps its last finished stage.

    Attributes:
        written: the Parquet path once written, else None.
    Raises:
        ValueError: a bad path, an unknown ``stages``, or (at the run's start) a method without importance weights."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        pem: str | None = None,
        overwrite: bool = False,
        stages: str = "used",
        out: TextIO | None = None,
    ) -> None:
        if stages not in STAGES:
            raise ValueError(f"stages = {stages!r}: use one of {', '.join(STAGES)}")
        self.path = check_rollouts_path(path, overwrite=overwrite, what="--save-rollouts")
        self.pem, self.overwrite, self.stages = pem, overwrite, stages
        self.problem: Any = None
        """The run's :class:`pemviz.core.problems.Problem`: its sidecar, salient variables and severity columns
        (:mod:`pemviz.io.run_rollouts`); None: not known (that module says which file it writes then)."""
        self.written: Path | None = None
        self._formula: str | None = None
        self._config: Any = None
        self._writer: RolloutWriter | None = None
        self._sizes: dict[int, int] = {}
        self._infos: dict[int, dict[str, Any]] = {}
        self._proposals: dict[int, Any] = {}
        self._results: dict[int, dict[str, Any]] = {}
        self._out = out
        self._planned: tuple[int, int] = (0, 0)
        """(rollouts the run plans in the stages saved, the most it may add after them: a retry, plain Monte Carlo)."""
        self.size_said: str | None = None
        """The line :meth:`size_line` printed, or None."""
        self._finished: dict[int, Any] = {}
        """Each finished stage's own estimate (:class:`pemviz.core.estimate.Estimate`), as its row printed it."""

    def _saves(self, kind: str) -> bool:
        """Whether a stage of this kind can enter the run's estimate (pretraining never does), or all are saved."""
        return self.stages == "all" or kind != "pretrain"

    def on_run_started(self, event: RunStarted) -> None:
        if not event.config.method_record.weighted:
            raise ValueError(
                f"--save-rollouts: method {event.config.method} estimates without importance weights; "
                "its rollouts cannot be estimated from again"
            )
        self._formula, self._config = event.formula, event.config
        from pemviz.engine.cost import then_adds

        plan = event.plan
        planned = sum(st.n_rollouts for st in plan.stages if self._saves(st.kind))
        self._planned = (planned, then_adds(event.config, plan.n_simulations or 0)[0] if plan.stages else 0)

    def on_stage_started(self, event: StageStarted) -> None:
        self._sizes[event.stage] = event.n_rollouts

    def on_rollout_chunk(self, event: RolloutChunk) -> None:
        if self._saves(event.kind):
            self._append(event)

    def on_stage_finished(self, event: StageFinished) -> None:
        self._results[event.result.stage] = _estimate_json(event.result.estimate)
        self._finished[event.result.stage] = event.result.estimate

    def on_run_finished(self, event: RunFinished) -> None:
        if self._writer is not None:
            self.write(event)

    def on_run_cancelled(self, event: RunCancelled) -> None:
        self.close()

    def _append(self, chunk: Any) -> None:
        if self._writer is None:
            self._writer = RolloutWriter(self.path, self._meta(), overwrite=self.overwrite)
        if chunk.stage not in self._infos:
            n = self._sizes.get(chunk.stage, chunk.batch.n)
            parts = list(chunk.parts) or [(n, chunk.sampler)]
            n_target = sum(k for k, d in parts if d is chunk.target and d is not None)
            self._infos[chunk.stage] = {
                "stage": chunk.stage,
                "kind": chunk.kind,
                "n": n,
                "components": [{"sampler": describe(d, chunk.target), "n": k} for k, d in parts],
                "max_weight": n / n_target if n_target else None,
            }
            if isinstance(chunk.sampler, Proposal):  # trained in place afterwards: keep the one that sampled
                self._proposals[chunk.stage] = copy.deepcopy(chunk.sampler)
        log_q, component, log_q_params = stage_log_q(
            chunk.batch, chunk.parts, chunk.target, chunk.start, getattr(self.problem, "features", None)
        )
        batch = chunk.batch.with_changes(log_q=log_q, log_q_params=log_q_params)  # no object rows: none rebuilt
        before = self._writer.bytes_written
        self._writer.append(
            batch,
            salient=run_salient(self.problem, batch),
            stage=chunk.stage,
            component=component,
            severity=run_severity(self.problem, batch),
        )
        if self.size_said is None and chunk.kind != "pretrain":  # pretraining's rollouts pack 2-3 times tighter
            line = self.size_line(self._writer.bytes_written - before, batch.n, self._writer.n_rollouts)
            self.size_said = line or ""
            if line:
                print(line, file=self._out or sys.stderr, flush=True)

    def size_line(self, chunk_bytes: int, chunk: int, written: int) -> str | None:
        """The line that says how large the rollout file will be, from the bytes a rollout took in a stage's first
        chunk after pretraining and the rollouts the run plans and may add (:func:`pemviz.engine.cost.then_adds`);
        None where even the most stays within :data:`SAY_SIZE_ABOVE_BYTES`."""
        if chunk <= 0:
            return None
        per = chunk_bytes / chunk
        planned, more = self._planned
        planned = max(planned, written)
        if per * (planned + more) <= SAY_SIZE_ABOVE_BYTES:
            return None
        size = f"about {_mb(per * planned)} for the {planned:,} rollouts planned"
        if more:
            size += f", up to {_mb(per * (planned + more))} if {more:,} more follow (the retry and plain Monte Carlo)"
        return f"--save-rollouts: {self.path.name} will be {size}, {per / 1e3:.2f} kB a rollout"

    def _meta(self) -> Any:
        cfg = self._config
        proposal = None if cfg is None else cfg.method_record.sampler  # a fixed sampler's name, or a fitted one
        provenance: dict[str, Any] = {} if cfg is None else {"config": cfg.flat()}
        pem = self.pem or setting_of(cfg, "pem", None) or DEFAULT_PEM_NAME
        return run_meta(self.problem, self._formula, pem=pem, proposal=proposal, provenance=provenance)

    def write(self, finished: Any) -> Path:
        """Commit the stages the run's estimate used (or all), with the sidecar's weight convention, stages, pooling
        rule and the run's estimates, and the proposal snapshot of a single stage; returns the Parquet path."""
        writer, cfg = self._writer, self._config
        used = [k for k in finished.final.stages_used if k in self._infos] or sorted(self._infos)  # none said: all
        keep = sorted(self._infos) if self.stages == "all" else used
        sizes = [self._infos[k]["n"] for k in used]
        rule = "single" if len(used) == 1 else setting_of(cfg, "pool_weights", "rollouts")
        given = finished.final.pooling  # the estimator's own (added final batches), else the config's rule
        lam: np.ndarray | None
        if given is not None and len(given[1]) == len(used) and len(used) > 1:
            rule, lam = given[0], np.asarray(given[1], dtype=np.float64)
        else:
            lam = None if rule == "single" else pool_stage_weights(rule, sizes)
        lam = np.asarray(sizes, dtype=np.float64) / sum(sizes) if lam is None else lam
        assert writer is not None  # a run's rollouts were appended
        provenance = dict(writer.meta.provenance or {})
        cap = finished.final.verdict_cap  # the verdict's bound and cap: pemviz estimate applies them as the run did
        provenance["estimate"] = {
            **_estimate_json(finished.final.estimate),
            "stages_used": used,
            "log_p_seen": finished.final.log_p_seen,
            "verdict_cap": list(cap) if cap else None,
            **({"look_ahead": True} if finished.final.look_ahead else {}),
        }
        provenance["stage_estimates"] = {str(k): v for k, v in sorted(self._results.items())}
        writer.meta = dataclasses.replace(
            writer.meta,
            provenance=provenance,
            weights=convention(getattr(cfg, "weights_until_failure", True)),
            stages=tuple(self._infos[k] for k in keep),
            pooling={"rule": rule, "stages": used, "stage_weights": [float(x) for x in lam]},
        )
        proposal = self._proposals.get(keep[0]) if len(keep) == 1 else None
        try:
            self.written = writer.commit(proposal, keep_stages=keep)
        finally:
            self._writer = None
        return self.written

    def keep_finished(self) -> tuple[Path, int, Any] | None:
        """After an interrupt (Ctrl-C, SIGTERM): commit the last finished stage this file saves, whole, as a run
        whose estimate is that stage's own (with the finished stages before it where ``stages`` is ``all``); the
        stage being drawn is dropped. Returns (the Parquet path, the stage, its estimate), or None where no saved
        stage finished."""
        done = [k for k in self._finished if k in self._infos]
        if self._writer is None or not done:
            return None
        stage, est = max(done), self._finished[max(done)]
        for k in [k for k in self._infos if k not in self._finished]:  # the stage cut short: not a stage's rollouts
            del self._infos[k]
        cap = getattr(self.problem, "verdict_cap", None)
        final = FinalEstimate(est, n_simulations=est.n, wall_s=0.0, stages_used=(stage,), verdict_cap=cap)
        return self.write(types.SimpleNamespace(final=final)), stage, est

    def close(self) -> None:
        """Drop what was written and not committed (a cancelled or failed run leaves no file)."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None


def _mb(n_bytes: float) -> str:
    """``624 MB``, ``1.2 GB``, ``1.71 MB``, ``85 kB``: a file's size in decimal units, three figures."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes / 1e3:.3g} kB"


def describe(detector: Any, target: Any = None) -> str:
    """A short name of a sampler for the sidecar: ``target``, ``proposal within 10 m, target beyond`` ..."""
    from pemviz.estimators.cross_entropy import DefensiveDetector  # the sampler classes above the core
    from pemviz.estimators.tilt import SceneProposal

    if detector is target:
        return "target"
    if isinstance(detector, SamplerView):
        return detector.samplers.describe(detector.index)
    if isinstance(detector, WindowDetector):
        return (
            f"{describe(detector.inside, target)} within {detector.radius_m:g} m, "
            f"{describe(detector.outside, target)} beyond"
        )
    if isinstance(detector, DefensiveDetector):
        return f"(1 - {detector.eps:g}) {describe(detector.detector, target)} + {detector.eps:g} x 50 %"
    if isinstance(detector, SceneProposal):
        return "the scenario's tilted proposal"
    if isinstance(detector, ConstantDetector):
        return f"{detector.p_detect:g} everywhere"
    if isinstance(detector, Proposal):
        return "proposal"
    if isinstance(detector, ArrayRQMC):
        return describe(detector.detector, target)
    inner = getattr(detector, "detector", None)
    return type(detector).__name__ + ("" if inner is None else f" of {describe(inner, target)}")

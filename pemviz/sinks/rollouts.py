"""Engine listener that saves the rollouts of the final estimate as a rollout file (``pemviz run --save-rollouts``).

The file format (Parquet table, JSON sidecar, proposal checkpoint) is :mod:`pemviz.rollout_io`'s.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from pathlib import Path
from typing import Any

from pemviz.engine import RolloutChunk, RunCancelled, RunFinished, RunStarted
from pemviz.pem import DEFAULT_PEM_NAME
from pemviz.rollout_io import RolloutWriter, braking_meta, braking_salient, check_rollouts_path
from pemviz.sampling import Proposal



class RolloutSink:
    """Engine listener for ``pemviz run --save-rollouts``: writes the batch the final estimate comes from.

    That batch is the fresh final batch, the last CE stage's with ``final_estimate="last-stage"``, or a
    baseline's one batch. Its rollouts are written chunk by chunk as the engine simulates them
    (:class:`pemviz.engine.RolloutChunk`, Parquet row groups of a :class:`pemviz.rollout_io.RolloutWriter`), with
    ``log_p`` / ``log_q`` and the salient variables, so memory stays that of a chunk whatever N is; the unit is
    moved into place when the run finishes, and nothing is left after a cancelled or failed run. If the
    detector that sampled the batch is a proposal, a snapshot of it taken when the batch was sampled is saved as
    ``NAME.proposal.pt`` and named in the sidecar.

    Attributes:
        written: the Parquet path once written, else None.
    """

    def __init__(self, path: str | os.PathLike[str], *, pem: str | None = None, overwrite: bool = False) -> None:
        self.path = check_rollouts_path(path, overwrite=overwrite, what="--save-rollouts")
        self.pem = pem
        self.overwrite = overwrite
        self.written: Path | None = None
        self._formula: str | None = None
        self._config: Any = None
        self._writer: RolloutWriter | None = None
        self._stage: tuple[int, str] | None = None
        self._proposal: Any = None

    def _saves(self, stage: int, kind: str) -> bool:
        """Whether the final estimate comes from this stage's batch (known from the run's settings)."""
        cfg = self._config
        if kind == "final" or getattr(cfg, "method", "adaptive") != "adaptive":
            return True
        return kind == "ce" and not cfg.has_final_batch and stage == cfg.n_stages

    def __call__(self, event: Any) -> None:
        if isinstance(event, RunStarted):
            self._formula, self._config = event.formula, event.config
        elif isinstance(event, RolloutChunk) and self._saves(event.stage, event.kind):
            if self._stage != (event.stage, event.kind):  # a new batch: start over (a single-batch method's last)
                self.close()
                self._stage = (event.stage, event.kind)
                self._proposal = copy.deepcopy(event.sampler) if isinstance(event.sampler, Proposal) else None
                self._writer = RolloutWriter(self.path, self._meta(event), overwrite=self.overwrite)
            self._writer.append(event.batch, salient=braking_salient(event.batch.gap_m))
        elif isinstance(event, RunFinished) and self._writer is not None:
            self.write(event)
        elif isinstance(event, RunCancelled):
            self.close()

    def _meta(self, chunk: Any) -> Any:
        cfg = self._config
        method = getattr(cfg, "method", None)
        proposal = {"mc": "pem", "naive50": "naive50", "mixed50": "mixed50"}.get(method)
        provenance: dict[str, Any] = {"stage": chunk.stage, "kind": chunk.kind}
        if cfg is not None:
            provenance["config"] = dataclasses.asdict(cfg)
        return braking_meta(self._formula, pem=self.pem or getattr(cfg, "pem", None) or DEFAULT_PEM_NAME,
                            proposal=proposal, provenance=provenance)  # fmt: skip

    def write(self, finished: Any = None) -> Path:
        """Commit the rollouts written so far (and the proposal snapshot, if any), with the run's estimate in
        the sidecar's provenance; returns the Parquet path."""
        writer = self._writer
        if finished is not None:
            e = finished.final.estimate
            provenance = dict(writer.meta.provenance or {})
            provenance["estimate"] = {
                "log_mu_hat": e.log_mu_hat, "n_failures": e.n_failures, "n": e.n, "log_ci": list(e.log_ci),
                "ess": e.ess, "khat": e.khat, "verdict": e.verdict, "reason": e.reason,
                "stages_used": list(finished.final.stages_used),
            }  # the run's estimate: with a pooled estimate it uses more stages than this file's final batch
            writer.meta = dataclasses.replace(writer.meta, provenance=provenance)
        try:
            self.written = writer.commit(self._proposal)
        finally:
            self._writer = None
        return self.written

    def close(self) -> None:
        """Drop what was written and not committed (a cancelled or failed run leaves no file)."""
        if self._writer is not None:
            self._writer.abort()
            self._writer = None

"""Engine listener that saves the rollouts of the final estimate as a rollout file (``pemviz run --save-rollouts``).

The file format (Parquet table, JSON sidecar, proposal checkpoint) is :mod:`pemviz.rollout_io`'s.
"""

from __future__ import annotations

import copy
import dataclasses
import os
from pathlib import Path
from typing import Any

from pemviz.engine import RolloutsSampled, RunFinished, RunStarted, StageStarted
from pemviz.pem import DEFAULT_PEM_NAME
from pemviz.rollout_io import braking_meta, braking_salient, check_rollouts_path, write_rollouts
from pemviz.sampling import Proposal



class RolloutSink:
    """Engine listener for ``pemviz run --save-rollouts``: writes the batch the final estimate comes from.

    It keeps the last :class:`pemviz.engine.RolloutsSampled` batch (the fresh final batch, or the last CE
    stage's with ``final_estimate="last-stage"``) and writes it with ``log_p`` / ``log_q`` and the salient
    variables when the run finishes (nothing after a cancelled run). If the detector that sampled the batch
    (the event's ``sampler``) is a proposal, a snapshot of it taken when the batch was sampled is saved as
    ``NAME.proposal.pt`` and named in the sidecar.

    A final batch the engine streams in chunks (more than ``pemviz.engine.STREAM_ABOVE`` rollouts) reaches
    listeners only as its first chunk: then nothing is written and :attr:`skipped` says why.

    Attributes:
        written: the Parquet path once written, else None.
        skipped: why nothing was written after a finished run, else None.
    """

    def __init__(self, path: str | os.PathLike[str], *, pem: str | None = None, overwrite: bool = False) -> None:
        self.path = check_rollouts_path(path, overwrite=overwrite, what="--save-rollouts")
        self.pem = pem
        self.overwrite = overwrite
        self.written: Path | None = None
        self.skipped: str | None = None
        self._formula: str | None = None
        self._config: Any = None
        self._started_n = 0
        self._last: Any = None
        self._proposal: Any = None

    def __call__(self, event: Any) -> None:
        if isinstance(event, RunStarted):
            self._formula, self._config = event.formula, event.config
        elif isinstance(event, StageStarted):
            self._started_n = event.n_rollouts
        elif isinstance(event, RolloutsSampled):
            self._last = event
            self._proposal = copy.deepcopy(event.sampler) if isinstance(event.sampler, Proposal) else None
        elif isinstance(event, RunFinished) and self._last is not None:
            if self._last.batch.n != self._started_n:
                self.skipped = (f"the final batch of {self._started_n} rollouts was streamed in chunks; only "
                                f"{self._last.batch.n} reached listeners")  # fmt: skip
            else:
                self.write(event)

    def write(self, finished: Any = None) -> Path:
        """Write the kept batch (and the proposal snapshot, if any); returns the Parquet path."""
        ev, cfg = self._last, self._config
        method = getattr(cfg, "method", None)
        proposal = {"mc": "pem", "naive50": "naive50", "mixed50": "mixed50"}.get(method)
        provenance: dict[str, Any] = {"stage": ev.stage, "kind": ev.kind}
        if cfg is not None:
            provenance["config"] = dataclasses.asdict(cfg)
        if finished is not None:
            e = finished.final.estimate
            provenance["estimate"] = {
                "log_mu_hat": e.log_mu_hat, "n_failures": e.n_failures, "n": e.n, "log_ci": list(e.log_ci),
                "ess": e.ess, "khat": e.khat, "verdict": e.verdict, "reason": e.reason,
                "stages_used": list(finished.final.stages_used),
            }  # the run's estimate: with a pooled estimate it uses more stages than this file's final batch
        meta = braking_meta(self._formula, pem=self.pem or getattr(cfg, "pem", None) or DEFAULT_PEM_NAME,
                            proposal=proposal, provenance=provenance)  # fmt: skip
        batch = ev.batch
        self.written = write_rollouts(self.path, batch, meta, salient=braking_salient(batch.gap_m),
                                      proposal=self._proposal, overwrite=self.overwrite)
        return self.written

"""Rollout files written: one unit (``NAME.parquet``, its sidecar ``NAME.rollouts.json``, optionally the proposal
checkpoint ``NAME.proposal.pt``) chunk by chunk (:class:`RolloutWriter`) or at once (:func:`write_rollouts`), the table
of a batch (:func:`rollouts_table`) and the check of a path before any work (:func:`check_rollouts_path`).

Every chunk is checked as :func:`pemviz.io.rollouts.read_rollouts` checks a file (:mod:`pemviz.io.rollout_table`)
before it is written. Writers write to temporary files and move them into place, sidecar last: no half file."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pemviz.core.files import temp_file
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import write_proposal_file
from pemviz.io.data import sha256_file
from pemviz.io.files import check_free_name, check_output_path, commit_files
from pemviz.io.rollout_format import (
    SALIENT_COLUMNS,
    RolloutFormatError,
    RolloutMeta,
    check_stage_counts,
    proposal_path,
    sidecar_path,
)
from pemviz.io.rollout_table import SEVERITY_COLUMNS, _Table


def check_rollouts_path(path: str | os.PathLike[str], *, overwrite: bool = False, what: str = "rollout file") -> Path:
    """Refuse a path where a rollout file cannot be written, before any work (nothing is created); its sidecar and
    checkpoint are replaced only with ``overwrite`` and only if pemviz wrote them.

    Raises:
        ValueError: not ``.parquet``, a directory, a folder that does not exist / is not writable, a name too
            long, or an existing file (:class:`pemviz.core.files.OutputExists` without ``overwrite``)."""
    p = check_output_path(path, ".parquet", what, overwrite=overwrite)
    check_output_path(proposal_path(p), ".pt", f"{what} checkpoint", overwrite=overwrite)
    check_free_name(sidecar_path(p), f"{what} sidecar", overwrite=overwrite)
    return p


def rollouts_table(
    batch: RolloutBatch,
    *,
    rollout_ids: np.ndarray | None = None,
    salient: np.ndarray | None = None,
    log_probs: bool = True,
    stage: int | np.ndarray | None = None,
    component: np.ndarray | None = None,
    severity: tuple[np.ndarray, np.ndarray] | None = None,
) -> Any:
    """The Parquet table of a batch: rollout, step, observations, detected (or each object's ``detected_<m>`` and
    ``<error>_<m>``), [salient], [log_p, log_q, [log_q_params]], [stage, component], [min_distance_m,
    impact_speed_mps].

    Args:
        batch: N rollouts [N, T].
        rollout_ids: int [N] (default 0..N-1).
        salient: float64 [N, T, 11] salient variables (:func:`~pemviz.io.rollout_table.braking_salient`) or None.
        log_probs: include ``log_p`` and ``log_q``.
        stage: the stage of all N rollouts, or int [N] each rollout's, or None (no stage column).
        component: int [N] each rollout's mixture component (with ``stage``; default 0).
        severity: (min distance [N] in metres, impact speed [N] in m/s, NaN: no contact) as
            :data:`SEVERITY_COLUMNS`, or None.
    Raises:
        ValueError: arrays of the wrong shape."""
    n, n_steps = batch.n, batch.n_steps
    ids = np.arange(n, dtype=np.int64) if rollout_ids is None else np.asarray(rollout_ids, dtype=np.int64)
    if ids.shape != (n,):
        raise ValueError(f"rollout_ids must have shape ({n},), got {ids.shape}")
    cols: dict[str, np.ndarray] = {
        "rollout": np.repeat(ids, n_steps),
        "step": np.tile(np.arange(n_steps, dtype=np.int64), n),
    }
    for k, name in enumerate(batch.observation_names):
        cols[name] = np.ascontiguousarray(batch.observations[:, :, k], dtype=np.float64).reshape(-1)
    detected = np.asarray(batch.detected, dtype=bool)
    if batch.n_objects > 1 or batch.noise is not None:  # each object's detection and errors (format version 3)
        for m in range(batch.n_objects):
            cols[f"detected_{m}"] = np.ascontiguousarray(detected[:, :, m]).reshape(-1)
            if batch.noise is not None:
                for d, name in enumerate(batch.noise_names):
                    cols[f"{name}_{m}"] = np.ascontiguousarray(batch.noise[:, :, m, d], dtype=np.float64).reshape(-1)
        if salient is not None:
            raise ValueError("salient variables are written for one object per step without errors only")
    else:
        cols["detected"] = detected.reshape(-1)
    if salient is not None:
        s = np.asarray(salient, dtype=np.float64)
        if s.shape != (n, n_steps, len(SALIENT_COLUMNS)):
            raise ValueError(f"salient must have shape ({n}, {n_steps}, {len(SALIENT_COLUMNS)}), got {s.shape}")
        for k, name in enumerate(SALIENT_COLUMNS):
            cols[name] = np.ascontiguousarray(s[:, :, k]).reshape(-1)
    if log_probs:
        cols["log_p"] = np.asarray(batch.log_p, dtype=np.float64).reshape(-1)
        cols["log_q"] = np.asarray(batch.log_q, dtype=np.float64).reshape(-1)
        if batch.log_q_params is not None:  # over an ODD, the parameters' term of each rollout's log q
            cols["log_q_params"] = np.repeat(np.asarray(batch.log_q_params, dtype=np.float64), n_steps)
    if stage is not None:
        comp = np.zeros(n, np.int64) if component is None else np.asarray(component, dtype=np.int64)
        if comp.shape != (n,):
            raise ValueError(f"component must have shape ({n},), got {comp.shape}")
        cols["stage"] = np.repeat(np.broadcast_to(np.asarray(stage, dtype=np.int64), (n,)), n_steps)
        cols["component"] = np.repeat(comp, n_steps)
    if severity is not None:
        dist, speed = (np.asarray(x, dtype=np.float64) for x in severity)
        if dist.shape != (n,) or speed.shape != (n,):
            raise ValueError(f"severity must be two arrays of shape ({n},), got {dist.shape} and {speed.shape}")
        cols[SEVERITY_COLUMNS[0]] = np.repeat(dist, n_steps)
        speed = np.repeat(speed, n_steps)
        cols[SEVERITY_COLUMNS[1]] = pa.array(speed, type=pa.float64(), mask=np.isnan(speed))  # null: no contact
    return pa.table(cols)


class RolloutWriter:
    """Writes one rollout unit (``NAME.parquet``, its sidecar ``NAME.rollouts.json``, optionally ``NAME.proposal.pt``)
    chunk by chunk, one Parquet row group an :meth:`append`. Nothing appears under ``path`` before :meth:`commit`,
    which moves the files into place sidecar last (it holds the SHA-256 of the others, so a unit cut short is told
    from a complete one); :meth:`abort`, or leaving a ``with`` block without a commit, removes everything written
    and leaves an existing unit untouched.

    Args:
        path: ``NAME.parquet``, checked at once (:func:`check_rollouts_path`).
        meta: the sidecar (:func:`~pemviz.io.rollout_sidecars.braking_meta`,
            :func:`~pemviz.io.rollout_sidecars.problem_meta`); its counts and columns are filled in from the
            rollouts.
        log_probs: write ``log_p`` and ``log_q``.
        overwrite: replace existing files of the unit (only ones pemviz wrote).
    Raises:
        ValueError: a bad path (an existing file without ``overwrite``)."""

    def __init__(
        self, path: str | os.PathLike[str], meta: RolloutMeta, *, log_probs: bool = True, overwrite: bool = False
    ) -> None:
        self.path = check_rollouts_path(path, overwrite=overwrite)
        self.meta, self.log_probs, self.overwrite = meta, log_probs, overwrite
        self.n_rollouts = 0
        self.stage_counts: dict[int, list[int]] = {}
        """Rollouts written per stage and component (chunks appended with a ``stage``)."""
        self._shape: tuple[Any, ...] | None = None
        """(steps, observation names, objects, error names) of the chunks so far."""
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(temp_file(self.path))
        self._writer: Any = None

    def __enter__(self) -> RolloutWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.abort()

    def append(
        self,
        batch: RolloutBatch,
        *,
        rollout_ids: np.ndarray | None = None,
        salient: np.ndarray | None = None,
        stage: int | np.ndarray | None = None,
        component: np.ndarray | None = None,
        severity: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        """Validate and write the next rollouts (default ids: continuing from the last chunk's).

        Args:
            batch: rollouts [n, T] with the same T and observation columns as the chunks before.
            rollout_ids: int [n], as :func:`rollouts_table` (default: continuing from the last chunk's).
            salient: as :func:`rollouts_table`.
            stage: as :func:`rollouts_table` (for every chunk or for none).
            component: as :func:`rollouts_table`.
            severity: as :func:`rollouts_table` (for every chunk or for none).
        Raises:
            ValueError: wrong shapes, a batch unlike the earlier ones, or a :class:`RolloutFormatError` (NaN, a
                positive log-probability ...) naming the rollout and step; nothing of this chunk is written."""
        names = tuple(batch.observation_names)
        objects = (batch.n_objects, tuple(batch.noise_names) if batch.noise is not None else ())
        if self._shape is not None and self._shape != (batch.n_steps, names, *objects):
            raise ValueError(
                f"RolloutWriter: a chunk of {batch.n_steps} steps of {names}, {objects[0]} object(s) "
                f"with errors {list(objects[1])}, after chunks of {self._shape[0]} steps of "
                f"{self._shape[1]}, {self._shape[2]} object(s) with errors "
                f"{list(self._shape[3])}"
            )
        self.meta = dataclasses.replace(self.meta, objects=objects[0], noise=objects[1])
        if not names:
            raise ValueError("write_rollouts: the batch has no observation columns")
        self.meta = dataclasses.replace(self.meta, h_column=names[0])  # h(s): the first observation, whatever its name
        meta = dataclasses.replace(
            self.meta, n_rollouts=None, n_steps=batch.n_steps, observation_columns=names, stages=(), pooling=None
        )  # checked against the whole table at commit
        if meta.columns != names:
            raise ValueError(
                f"write_rollouts: the spec's signals {dict(meta.signals)} name columns the batch's "
                f"observations {names} lack"
            )
        if rollout_ids is None:
            rollout_ids = np.arange(self.n_rollouts, self.n_rollouts + batch.n, dtype=np.int64)
        table = rollouts_table(
            batch,
            rollout_ids=rollout_ids,
            salient=salient,
            log_probs=self.log_probs,
            stage=stage,
            component=component,
            severity=severity,
        )
        _Table(table, meta, f"{self.path} (not written)").parse(None)
        if self._writer is None:
            self._writer = pq.ParquetWriter(self._tmp, table.schema)
        self._writer.write_table(table)
        self._shape = (batch.n_steps, names, *objects)
        self.n_rollouts += batch.n
        if stage is not None:
            stages = np.broadcast_to(np.asarray(stage, dtype=np.int64), (batch.n,))
            comps = np.zeros(batch.n, np.int64) if component is None else np.asarray(component, np.int64)
            for k in np.unique(stages).tolist():
                comp = np.bincount(comps[stages == k])
                held = self.stage_counts.get(k, [])
                held = held + [0] * (comp.size - len(held))
                self.stage_counts[k] = [a + (int(comp[i]) if i < comp.size else 0) for i, a in enumerate(held)]

    @property
    def bytes_written(self) -> int:
        """The bytes of the table written so far (the temporary file's size; 0 before the first chunk)."""
        return os.path.getsize(self._tmp) if self._writer is not None else 0

    def commit(self, proposal: Any = None, keep_stages: Any = None) -> Path:
        """Close the table and move the unit into place; returns the Parquet path.

        Args:
            proposal: a :class:`pemviz.core.sampling.Proposal` that sampled the rollouts, saved as ``NAME.proposal.pt``
                and named in the sidecar; None: none saved.
            keep_stages: the stages to keep (the others are dropped, row group by row group, before the table moves
                into place); None: every rollout written.
        Raises:
            ValueError: no rollouts were appended, or none of ``keep_stages``; the sidecar's ``stages`` or
                ``pooling`` do not match the table (a :class:`RolloutFormatError`).
            OutputExists: a file of the unit appeared meanwhile (without ``overwrite``).
            OSError: the folder is not writable, the disk is full (nothing is left behind)."""
        try:
            if self._writer is None:
                raise ValueError(f"{self.path}: no rollouts to write")
            self._writer.close()
            self._writer = None
            assert self._shape is not None  # set with the writer, by the first append
            n_steps, names = self._shape[:2]
            n_rollouts = self.n_rollouts
            if keep_stages is not None and set(self.stage_counts) - set(keep_stages):
                n_rollouts = self._keep(set(keep_stages))
            meta = dataclasses.replace(self.meta, n_rollouts=n_rollouts, n_steps=n_steps, observation_columns=names)
            if self.stage_counts or meta.stages or meta.pooling:
                kept = {k: c for k, c in self.stage_counts.items() if keep_stages is None or k in keep_stages}
                check_stage_counts(meta, kept, lambda msg: RolloutFormatError(f"{self.path} (not written): {msg}"))
            p, side, ckpt = self.path, sidecar_path(self.path), proposal_path(self.path)
            pairs = []
            if proposal is not None:
                tmp_ckpt = self._stack.enter_context(temp_file(ckpt))
                write_proposal_file(proposal, tmp_ckpt)
                meta = dataclasses.replace(meta, proposal=ckpt.name, proposal_sha256=sha256_file(tmp_ckpt))
                pairs.append((tmp_ckpt, ckpt))
            meta = dataclasses.replace(meta, table_sha256=sha256_file(self._tmp))
            pairs.append((self._tmp, p))
            tmp_side = self._stack.enter_context(temp_file(side))
            Path(tmp_side).write_text(json.dumps(meta.to_json(), indent=2, allow_nan=False) + "\n", encoding="utf-8")
            pairs.append((tmp_side, side))
            commit_files(pairs, overwrite=self.overwrite)
            return p
        finally:
            self.abort()

    def _keep(self, stages: set) -> int:
        """Rewrite the temporary table with the rollouts of ``stages`` only, row group by row group; returns their
        number."""
        kept = self._stack.enter_context(temp_file(self.path))
        source = pq.ParquetFile(self._tmp)
        writer, n_rows = None, 0
        try:
            for g in range(source.num_row_groups):
                group = source.read_row_group(g)
                group = group.filter(pc.is_in(group.column("stage"), pa.array(sorted(stages), pa.int64())))
                if group.num_rows:
                    writer = writer or pq.ParquetWriter(kept, group.schema)
                    writer.write_table(group)
                    n_rows += group.num_rows
        finally:
            if writer is not None:
                writer.close()
        if writer is None:
            raise ValueError(f"{self.path}: none of stages {sorted(stages)} was written")
        self._tmp = kept
        assert self._shape is not None  # close() calls this after the first append
        return n_rows // self._shape[0]

    def abort(self) -> None:
        """Stop writing and remove the temporary files (nothing under ``path`` changes); safe to call twice."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        self._stack.close()


def write_rollouts(
    path: str | os.PathLike[str],
    batch: RolloutBatch,
    meta: RolloutMeta,
    *,
    rollout_ids: np.ndarray | None = None,
    salient: np.ndarray | None = None,
    log_probs: bool = True,
    proposal: Any = None,
    overwrite: bool = False,
    stage: int | np.ndarray | None = None,
    component: np.ndarray | None = None,
    severity: tuple[np.ndarray, np.ndarray] | None = None,
) -> Path:
    """Write ``NAME.parquet``, its sidecar ``NAME.rollouts.json`` and (with ``proposal``) ``NAME.proposal.pt`` as one
    unit (a :class:`RolloutWriter` with one chunk), validated before anything is written.

    Args:
        path: ``NAME.parquet``.
        batch: N rollouts [N, T] (observations, detected, log_p, log_q in nats).
        meta: the sidecar (:func:`~pemviz.io.rollout_sidecars.braking_meta` for the braking scenario).
        rollout_ids: int [N], as :func:`rollouts_table` (default 0..N-1).
        salient: as :func:`rollouts_table`.
        log_probs: include ``log_p`` and ``log_q``.
        stage: as :func:`rollouts_table`.
        component: as :func:`rollouts_table`.
        severity: as :func:`rollouts_table`, the optional :data:`SEVERITY_COLUMNS`.
        proposal: a :class:`pemviz.core.sampling.Proposal` that sampled the batch, saved as ``NAME.proposal.pt``;
            None: none.
        overwrite: replace existing files of the unit (only ones pemviz wrote).
    Returns:
        the Parquet path.
    Raises:
        ValueError: a bad path, wrong shapes, or a :class:`RolloutFormatError` naming the rollout and step; nothing
            is written.
        OSError: the folder is not writable, the disk is full (nothing is left behind)."""
    with RolloutWriter(path, meta, log_probs=log_probs, overwrite=overwrite) as writer:
        writer.append(
            batch, rollout_ids=rollout_ids, salient=salient, stage=stage, component=component, severity=severity
        )
        return writer.commit(proposal)

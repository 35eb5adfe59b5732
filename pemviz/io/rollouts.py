"""Logged rollouts on disk: read and validate a rollout file (:func:`read_rollouts`), write one chunk by chunk
(:class:`RolloutWriter`, :func:`write_rollouts`).

The format (the Parquet table's columns, the JSON sidecar's fields, the units) is :mod:`pemviz.io.rollout_format`'s.
Bad input raises :class:`~pemviz.io.rollout_format.RolloutFormatError`: one message naming the file, the column, and
the rollout and step where the problem is. Writers write to a temporary file and ``os.replace`` it: no half file.

Two optional columns carry each rollout's severity, the same value on all its rows (:data:`SEVERITY_COLUMNS`,
:func:`pemviz.core.severity.rollout_severity`; ``pemviz run --save-rollouts`` writes them): ``min_distance_m`` (float,
metres, finite: the smallest value of the problem's severity signal, the braking gap or the cut-in clearance) and
``impact_speed_mps`` (float, m/s, > 0: the closing speed over the step into contact; null where the rollout never
reaches contact, and a NaN is read alike). Give both or neither. They are a record, not an input: estimates do not read them, and a file
without them (every file before them) reads as before, with :attr:`RolloutData.min_distance` and
:attr:`RolloutData.impact_speed` None; readers that ignore other columns read a file with them unchanged, so the
format version stays.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pemviz.io.data import sha256_file
from pemviz.io.files import check_free_name, check_output_path, commit_files, temp_file
from pemviz.io.rollout_format import (
    KITTI_COLUMNS,
    SALIENT_COLUMNS,
    RolloutFormatError,
    RolloutMeta,
    check_stage_counts,
    proposal_path,
    read_sidecar,
    sidecar_path,
)
from pemviz.pem import braking_salient_inputs
from pemviz.core.sampling import write_proposal_file
from pemviz.scenarios import RolloutBatch

SEVERITY_COLUMNS = ("min_distance_m", "impact_speed_mps")
"""The optional per-rollout severity columns (module docstring): min distance (m), impact speed (m/s, null: no
contact)."""


def braking_salient(gap_m: np.ndarray) -> np.ndarray:
    """The PEM's salient variables of the lead at each gap, float64 [N, T, 11] for gaps [N, T] (metres).

    :func:`pemviz.pem.braking_salient_inputs` row by row (the lead's KITTI salient variables at each gap).
    """
    gap = np.asarray(gap_m, dtype=np.float64)
    return braking_salient_inputs(gap).reshape(*gap.shape, len(KITTI_COLUMNS))


@dataclass(frozen=True)
class RolloutData(RolloutBatch):
    """N logged rollouts of T steps as :func:`read_rollouts` returns them: a :class:`~pemviz.scenarios.RolloutBatch`
    (its accessors ``n``, ``n_steps``, ``signal``, ``gap_m``) with one difference, plus what the file adds.

    The difference: ``log_p`` / ``log_q`` are None when the file has no such column (the format makes them
    optional; ``pemviz estimate`` recomputes them), so :meth:`log_weight` needs both columns and :meth:`to_batch`
    gives the plain :class:`~pemviz.scenarios.RolloutBatch`, with the file's or recomputed log-probabilities, that
    the estimators take.

    Attributes:
        observations: float64 [N, T, F], columns ``observation_names`` (``gap_m`` first).
        detected: bool [N, T, M] (M = the sidecar's ``objects``).
        log_p, log_q: float64 [N, T] (nats) or None when the file has no such column (:meth:`to_batch` fills them).
        observation_names: the F state columns.
        meta: the sidecar.
        rollout_ids: int64 [N], in file order.
        salient: float64 [N, T, 11] (:data:`SALIENT_COLUMNS`) or None.
        path: the Parquet file (None for data not read from disk).
        stage, component: int64 [N], each rollout's stage and mixture component (version 2), or None.
        noise, noise_names: float64 [N, T, M, D] each object's measurement errors (metres, 0 where missed) and their
            D names (version 3, the sidecar's ``noise``), or None and ().
        min_distance, impact_speed: float64 [N] each rollout's min distance (metres) and impact speed (m/s; NaN
            exactly where the file says no contact, a null), or None where the file has no such columns
            (:data:`SEVERITY_COLUMNS`).
    """

    log_p: np.ndarray | None
    log_q: np.ndarray | None
    meta: RolloutMeta | None = None
    rollout_ids: np.ndarray | None = None
    salient: np.ndarray | None = None
    path: Path | None = None
    stage: np.ndarray | None = None
    component: np.ndarray | None = None
    min_distance: np.ndarray | None = None
    impact_speed: np.ndarray | None = None

    def log_weight(self, n_factors: int | None = None) -> np.ndarray:
        """:meth:`pemviz.scenarios.RolloutBatch.log_weight` of the file's columns, float64 [N] (nats).

        Raises:
            ValueError: the file has no ``log_p`` or no ``log_q`` column.
        """
        return self.to_batch().log_weight(n_factors)

    def to_batch(self, log_p: np.ndarray | None = None, log_q: np.ndarray | None = None) -> RolloutBatch:
        """A :class:`RolloutBatch` with the given (default: the file's) log-probabilities [N, T].

        Raises:
            ValueError: a log-probability that is neither given nor in the file.
        """
        log_p = self.log_p if log_p is None else log_p
        log_q = self.log_q if log_q is None else log_q
        if log_p is None or log_q is None:
            raise ValueError("to_batch: give log_p and log_q, the file has no such column")
        return RolloutBatch(self.observations, self.detected, log_p, log_q, self.observation_names, noise=self.noise,
                            noise_names=self.noise_names)  # fmt: skip


def _first_index(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


class _Table:
    """Checks a pyarrow table against the format and holds its columns as numpy arrays."""

    def __init__(self, table: Any, meta: RolloutMeta, where: str) -> None:
        self.table, self.meta, self.where = table, meta, where
        self.rid = np.zeros(0, np.int64)
        self.step = np.zeros(0, np.int64)

    def error(self, msg: str) -> RolloutFormatError:
        return RolloutFormatError(f"{self.where}: {msg}")

    def at(self, row: int) -> str:
        return f"rollout {self.rid[row]}, step {self.step[row]} (row {row})"

    def _nulls(self, name: str, located: bool) -> None:
        col = self.table.column(name)
        if col.null_count:
            row = _first_index(pc.is_null(col).to_numpy(zero_copy_only=False))
            where = self.at(row) if located else f"row {row}"
            raise self.error(f"column {name!r} is missing a value (null) at {where}")

    def _type_error(self, name: str, allowed: str, located: bool) -> RolloutFormatError:
        col = self.table.column(name)
        first = col[0].as_py() if len(col) else None
        where = f" at {self.at(0)}" if located and len(col) else ""
        return self.error(f"column {name!r} has type {col.type} (e.g. {first!r}{where}); it must hold {allowed}")

    def structure(self) -> tuple[np.ndarray, np.ndarray]:
        """Check rollout ids and steps; returns (rollout ids [N], T)."""
        names = self.table.column_names
        needed = ["rollout", "step", *self.meta.columns, *self.meta.detection_columns,
                  *(c for cols in self.meta.noise_columns for c in cols)]  # fmt: skip
        missing = [c for c in needed if c not in names]
        if missing:
            raise self.error(
                f"missing column{'s' * (len(missing) > 1)} {', '.join(map(repr, missing))}; required: "
                f"{', '.join(needed)} (the sidecar's observation_columns / signals name the state columns); "
                f"present: {', '.join(names)}"
            )
        if self.meta.per_object and not {"log_p", "log_q"} <= set(names):
            raise self.error(f"a file of {self.meta.objects} object(s) a step with errors {list(self.meta.noise)} must "
                             "hold log_p and log_q: the PEMs' inputs (each object's row) are not in it")  # fmt: skip
        partial = [c for c in SALIENT_COLUMNS if c in names]
        if partial and len(partial) != len(SALIENT_COLUMNS):
            absent = [c for c in SALIENT_COLUMNS if c not in names]
            raise self.error(f"salient-variable columns incomplete: missing {', '.join(absent)} (give all 11 or none)")
        if self.table.num_rows == 0:
            raise self.error("the table has no rows")
        for name in ("rollout", "step"):
            if not pa.types.is_integer(self.table.column(name).type):
                raise self._type_error(name, "integers", located=False)
            self._nulls(name, located=False)
        rid = self.table.column("rollout").to_numpy().astype(np.int64)
        step = self.table.column("step").to_numpy().astype(np.int64)
        self.rid, self.step = rid, step
        n_rows = rid.size
        new = np.ones(n_rows, dtype=bool)
        new[1:] = rid[1:] != rid[:-1]
        starts = np.flatnonzero(new)
        seg_ids = rid[starts]
        if np.unique(seg_ids).size != seg_ids.size:
            seen: set[int] = set()
            for s0 in starts:
                if int(rid[s0]) in seen:
                    raise self.error(
                        f"{self.at(s0)}: rollout {rid[s0]} appears again after other rollouts; the rows of a "
                        f"rollout must be contiguous"
                    )
                seen.add(int(rid[s0]))
        seg_of_row = np.cumsum(new) - 1
        expected = np.arange(n_rows) - starts[seg_of_row]
        bad = step != expected
        if bad.any():
            row = _first_index(bad)
            raise self.error(
                f"{self.at(row)}: steps out of order, expected step {expected[row]}; each rollout's rows must "
                f"hold steps 0, 1, ..., T-1 in this order"
            )
        lengths = np.diff(np.append(starts, n_rows))
        n_0 = int(lengths[0])
        if (lengths != n_0).any():
            k = _first_index(lengths != n_0)
            n_k = int(lengths[k])
            tail = f"ends after step {n_k - 1}" if n_k < n_0 else f"has extra steps {n_0}..{n_k - 1}"
            raise self.error(
                f"rollout {seg_ids[k]} has {n_k} steps but rollout {seg_ids[0]} has {n_0}: rollout {seg_ids[k]} "
                f"{tail}; every rollout must have the same number of steps"
            )
        for key, value in (("n_rollouts", seg_ids.size), ("n_steps", n_0)):
            declared = getattr(self.meta, key)
            if declared is not None and declared != value:
                raise self.error(f"the sidecar says {key} = {declared} but the table holds {value}")
        return seg_ids, n_0

    def floats(self, name: str, *, log_prob: bool = False) -> np.ndarray:
        """A numeric column as float64 [rows]: finite (and <= 0 for log-probabilities)."""
        col = self.table.column(name)
        if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
            raise self._type_error(name, "numbers (float64)", located=True)
        self._nulls(name, located=True)
        x = col.to_numpy().astype(np.float64)
        bad = ~np.isfinite(x)
        if bad.any():
            row = _first_index(bad)
            what = "NaN" if np.isnan(x[row]) else str(x[row])
            raise self.error(f"{name} is {what} at {self.at(row)}; values must be finite numbers")
        if log_prob and (x > 0).any():
            row = _first_index(x > 0)
            raise self.error(f"{name} = {float(x[row])!r} > 0 at {self.at(row)}: a log-probability (nats) must be <= 0")
        return x

    def per_rollout(self, name: str, n: int, n_steps: int) -> np.ndarray:
        """An integer column >= 0 that holds one value per rollout (the same on all its rows), as int64 [N]."""
        col = self.table.column(name)
        if not pa.types.is_integer(col.type):
            raise self._type_error(name, "integers >= 0", located=True)
        self._nulls(name, located=True)
        x = col.to_numpy().astype(np.int64)
        if (x < 0).any():
            row = _first_index(x < 0)
            raise self.error(f"{name} = {int(x[row])} at {self.at(row)}; it must be an integer >= 0")
        per = x.reshape(n, n_steps)
        differs = (per != per[:, :1]).any(axis=1)
        if differs.any():
            i = _first_index(differs)
            t = _first_index(per[i] != per[i, 0])
            raise self.error(f"{name} = {per[i, t]} at {self.at(i * n_steps + t)} but {per[i, 0]} at its step 0; "
                             f"a rollout has one {name}")
        return per[:, 0].copy()

    def severity(self, n: int, n_steps: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """The per-rollout severity columns (:data:`SEVERITY_COLUMNS`) as float64 [N] each, or (None, None) without
        them: the min distance finite, the impact speed > 0 or null (or NaN: no contact, read as NaN), each the same
        on all of a rollout's rows."""
        names = self.table.column_names
        present = [c for c in SEVERITY_COLUMNS if c in names]
        if not present:
            return None, None
        if len(present) != len(SEVERITY_COLUMNS):
            absent = [c for c in SEVERITY_COLUMNS if c not in names]
            raise self.error(f"severity columns incomplete: {present[0]!r} without {absent[0]!r} (give both or "
                             "neither)")  # fmt: skip
        dist = self.floats(SEVERITY_COLUMNS[0])
        col = self.table.column(SEVERITY_COLUMNS[1])
        if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
            raise self._type_error(SEVERITY_COLUMNS[1], "numbers (float64, null: no contact)", located=True)
        speed = col.to_numpy(zero_copy_only=False).astype(np.float64)  # a null reads as NaN: no contact
        bad = np.isinf(speed) | (speed <= 0)
        if bad.any():
            row = _first_index(bad)
            raise self.error(f"{SEVERITY_COLUMNS[1]} = {float(speed[row])!r} at {self.at(row)}: an impact speed is a "
                             "positive number of m/s, or null where the rollout makes no contact")  # fmt: skip
        out = []
        for name, x in zip(SEVERITY_COLUMNS, (dist, speed)):
            per = x.reshape(n, n_steps)
            differs = ~((per == per[:, :1]) | (np.isnan(per) & np.isnan(per[:, :1]))).all(axis=1)
            if differs.any():
                i = _first_index(differs)
                t = _first_index(~((per[i] == per[i, 0]) | (np.isnan(per[i]) & np.isnan(per[i, 0]))))
                raise self.error(f"{name} = {per[i, t]} at {self.at(i * n_steps + t)} but {per[i, 0]} at its step 0; "
                                 f"a rollout has one {name}")  # fmt: skip
            out.append(per[:, 0].copy())
        return out[0], out[1]

    def stages(self, stage: np.ndarray | None, component: np.ndarray | None) -> None:
        """Check the stage / component columns against the sidecar's ``stages`` and ``pooling``."""
        if stage is None:
            if self.meta.stages or self.meta.pooling:
                raise self.error("the sidecar lists stages or a pooling rule but the table has no stage column")
            if component is not None:
                raise self.error("a component column needs a stage column")
            return
        comp = np.zeros(stage.size, np.int64) if component is None else component
        counts = {int(k): np.bincount(comp[stage == k]).tolist() for k in np.unique(stage)}
        check_stage_counts(self.meta, counts, self.error)

    def booleans(self, name: str) -> np.ndarray:
        """A bool column (or integers 0 / 1) as bool [rows]."""
        col = self.table.column(name)
        if not (pa.types.is_boolean(col.type) or pa.types.is_integer(col.type)):
            raise self._type_error(name, "booleans (or integers 0 / 1)", located=True)
        self._nulls(name, located=True)
        x = col.to_numpy(zero_copy_only=False)
        if not pa.types.is_boolean(col.type):
            bad = (x != 0) & (x != 1)
            if bad.any():
                row = _first_index(bad)
                raise self.error(f"{name} = {int(x[row])} at {self.at(row)}; it must be true / false or 0 / 1")
        return np.asarray(x, dtype=bool)

    def parse(self, path: Path | None) -> RolloutData:
        ids, n_steps = self.structure()
        n = ids.size
        names = self.table.column_names
        cols = self.meta.columns
        obs = np.stack([self.floats(c) for c in cols], axis=-1).reshape(n, n_steps, len(cols))
        m = self.meta.objects
        detected = np.stack([self.booleans(c) for c in self.meta.detection_columns], axis=-1).reshape(n, n_steps, m)
        noise = None
        if self.meta.noise:
            noise = np.stack([np.stack([self.floats(c) for c in cols], axis=-1) for cols in self.meta.noise_columns],
                             axis=1).reshape(n, n_steps, m, len(self.meta.noise))  # fmt: skip
        salient = None
        if SALIENT_COLUMNS[0] in names:
            salient = np.stack([self.floats(c) for c in SALIENT_COLUMNS], axis=-1).reshape(n, n_steps, -1)
        probability = not self.meta.noise  # with measurement errors a step's log_p / log_q hold log densities
        log_p = self.floats("log_p", log_prob=probability).reshape(n, n_steps) if "log_p" in names else None
        log_q = self.floats("log_q", log_prob=probability).reshape(n, n_steps) if "log_q" in names else None
        stage, component = (self.per_rollout(c, n, n_steps) if c in names else None for c in ("stage", "component"))
        self.stages(stage, component)
        min_distance, impact_speed = self.severity(n, n_steps)
        return RolloutData(obs, detected, log_p, log_q, tuple(cols), noise=noise, noise_names=self.meta.noise,
                           meta=self.meta, rollout_ids=ids, salient=salient, path=path, stage=stage,
                           component=component, min_distance=min_distance, impact_speed=impact_speed)  # fmt: skip


RECORDING_MAGIC = b"RRF"
"""The first bytes of a rerun recording (``.rrd``): ``RRF2`` today, ``RRF0`` / ``RRF1`` in older rerun versions."""


def check_not_a_recording(path: Path) -> None:
    """Refuse a rerun recording given where a rollout file is expected, saying how to write a rollout file.

    Raises:
        RolloutFormatError: ``path`` ends in ``.rrd`` or starts with :data:`RECORDING_MAGIC`.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(len(RECORDING_MAGIC))
    except OSError:
        head = b""
    if path.suffix.lower() == ".rrd" or head == RECORDING_MAGIC:
        raise RolloutFormatError(
            f"{path}: a rerun recording, not a rollout file; `pemviz estimate` reads the Parquet rollout file that "
            "`pemviz run --save-rollouts NAME.parquet` writes (with its sidecar NAME.json), and `rerun "
            f"{path.name}` opens the recording"
        )


def read_rollouts(path: str | os.PathLike[str]) -> RolloutData:
    """Read and validate a rollout file and its sidecar.

    Returns:
        :class:`RolloutData`: observations [N, T, F], detected [N, T, M], optional salient [N, T, 11] and errors
        [N, T, M, D], log_p / log_q [N, T] (nats).
    Raises:
        FileNotFoundError: no such file.
        RolloutFormatError: the sidecar or the table breaks the format (module docstring); the message
            names the column and the rollout and step.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"rollout file {p} not found")
    check_not_a_recording(p)
    meta = read_sidecar(p)
    try:
        table = pq.read_table(p)
    except (pa.ArrowException, OSError) as exc:
        raise RolloutFormatError(f"{p}: not a readable Parquet file ({exc})") from None
    data = _Table(table, meta, str(p)).parse(p)
    if meta.table_sha256 is not None and sha256_file(p) != meta.table_sha256:
        raise RolloutFormatError(
            f"{p}: the table is not the one its sidecar {sidecar_path(p).name} was written with (table_sha256 "
            "differs): an interrupted or concurrent write; write it again (or drop table_sha256 from the sidecar "
            "if the table was changed on purpose)"
        )
    return data


def check_rollouts_path(path: str | os.PathLike[str], *, overwrite: bool = False, what: str = "rollout file") -> Path:
    """Refuse a path where a rollout file cannot be written, before any work (nothing is created).

    The sidecar ``NAME.json`` and checkpoint ``NAME.proposal.pt`` are checked too: an existing one is replaced
    only with ``overwrite`` and only if pemviz wrote it.

    Raises:
        ValueError: not ``.parquet``, a directory, a folder that does not exist / is not writable, a name too
            long, or an existing file (:class:`pemviz.io.files.OutputExists` without ``overwrite``).
    """
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
    """The Parquet table of a batch: rollout, step, observations, detected (or, for several objects or errors, each
    object's ``detected_<m>`` and ``<error>_<m>``), [salient], [log_p, log_q], [stage, component], [min_distance_m,
    impact_speed_mps].

    Args:
        batch: N rollouts [N, T].
        rollout_ids: int [N] (default 0..N-1).
        salient: float64 [N, T, 11] salient variables (:func:`braking_salient`) or None.
        log_probs: include ``log_p`` and ``log_q``.
        stage: the stage of all N rollouts, or int [N] each rollout's, or None (no stage column).
        component: int [N] each rollout's mixture component (with ``stage``; default 0).
        severity: (min distance float64 [N] in metres, impact speed float64 [N] in m/s, NaN: no contact), written as
            :data:`SEVERITY_COLUMNS` (the impact speed null where NaN), or None: not written.
    Raises:
        ValueError: arrays of the wrong shape.
    """
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
            for d, name in enumerate(batch.noise_names if batch.noise is not None else ()):
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
    """Writes one rollout unit (``NAME.parquet``, its sidecar ``NAME.json``, optionally ``NAME.proposal.pt``) chunk
    by chunk: each :meth:`append` validates a chunk and writes it as a Parquet row group, so memory holds one chunk
    whatever the number of rollouts. Nothing appears under ``path`` before :meth:`commit`, which moves the files
    into place sidecar last (the sidecar holds the SHA-256 of the table and checkpoint, so :func:`read_rollouts`
    tells a unit cut short by a kill from a complete one); :meth:`abort`, or leaving a ``with`` block without a
    commit, removes everything written so far and leaves an existing unit untouched.

    Args:
        path: ``NAME.parquet``, checked at once (:func:`check_rollouts_path`).
        meta: the sidecar (:func:`braking_meta` for the braking scenario, :func:`problem_meta` for another
            problem); ``n_rollouts`` / ``n_steps`` / ``observation_columns`` and ``objects`` / ``noise`` are filled in
            from the rollouts.
        log_probs: write ``log_p`` and ``log_q``.
        overwrite: replace existing files of the unit (only ones pemviz wrote).
    Raises:
        ValueError: a bad path (an existing file without ``overwrite``).
    """

    def __init__(self, path: str | os.PathLike[str], meta: RolloutMeta, *, log_probs: bool = True,
                 overwrite: bool = False) -> None:  # fmt: skip
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

    def __enter__(self) -> "RolloutWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.abort()

    def append(self, batch: RolloutBatch, *, rollout_ids: np.ndarray | None = None,
               salient: np.ndarray | None = None, stage: int | np.ndarray | None = None,
               component: np.ndarray | None = None,
               severity: tuple[np.ndarray, np.ndarray] | None = None) -> None:  # fmt: skip
        """Validate and write the next rollouts (default ids: continuing from the last chunk's).

        Args:
            batch: rollouts [n, T] with the same T and observation columns as the chunks before.
            rollout_ids, salient, stage, component, severity: see :func:`rollouts_table` (give ``stage`` and
                ``severity`` for every chunk or for none).
        Raises:
            ValueError: wrong shapes, a batch unlike the earlier ones, or a :class:`RolloutFormatError` (NaN, a
                positive log-probability ...) naming the rollout and step; nothing of this chunk is written.
        """
        names = tuple(batch.observation_names)
        objects = (batch.n_objects, tuple(batch.noise_names) if batch.noise is not None else ())
        if self._shape is not None and self._shape != (batch.n_steps, names, *objects):
            raise ValueError(f"RolloutWriter: a chunk of {batch.n_steps} steps of {names}, {objects[0]} object(s) "
                             f"with errors {list(objects[1])}, after chunks of {self._shape[0]} steps of "
                             f"{self._shape[1]}, {self._shape[2]} object(s) with errors {list(self._shape[3])}")  # fmt: skip
        self.meta = dataclasses.replace(self.meta, objects=objects[0], noise=objects[1])
        meta = dataclasses.replace(self.meta, n_rollouts=None, n_steps=batch.n_steps, observation_columns=names,
                                   stages=(), pooling=None)  # checked against the whole table at commit
        if meta.columns != names:
            raise ValueError(f"write_rollouts: the batch's first observation must be gap_m, got {names}")
        if rollout_ids is None:
            rollout_ids = np.arange(self.n_rollouts, self.n_rollouts + batch.n, dtype=np.int64)
        table = rollouts_table(batch, rollout_ids=rollout_ids, salient=salient, log_probs=self.log_probs, stage=stage,
                               component=component, severity=severity)  # fmt: skip
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
            OSError: the folder is not writable, the disk is full (nothing is left behind).
        """
        try:
            if self._writer is None:
                raise ValueError(f"{self.path}: no rollouts to write")
            self._writer.close()
            self._writer = None
            n_steps, names = self._shape[:2]
            n_rollouts = self.n_rollouts
            if keep_stages is not None and set(self.stage_counts) - set(keep_stages):
                n_rollouts = self._keep(set(keep_stages))
            meta = dataclasses.replace(self.meta, n_rollouts=n_rollouts, n_steps=n_steps,
                                       observation_columns=names)  # fmt: skip
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
    """Write ``NAME.parquet``, its sidecar ``NAME.json`` and (with ``proposal``) ``NAME.proposal.pt`` as one unit
    (a :class:`RolloutWriter` with one chunk).

    The table is validated as :func:`read_rollouts` validates it before anything is written; ``meta.n_rollouts``
    / ``n_steps`` / ``observation_columns`` are filled in.

    Args:
        path: ``NAME.parquet``.
        batch: N rollouts [N, T] (observations, detected, log_p, log_q in nats).
        meta: the sidecar (:func:`braking_meta` for the braking scenario).
        rollout_ids, salient, log_probs, stage, component, severity: see :func:`rollouts_table` (``stage`` /
            ``component`` of a version-2 file: ``RolloutData.stage`` / ``.component``; ``severity``: the optional
            :data:`SEVERITY_COLUMNS`).
        proposal: a :class:`pemviz.core.sampling.Proposal` that sampled the batch, saved as ``NAME.proposal.pt`` and
            named in the sidecar; None: none saved.
        overwrite: replace existing files of the unit (only ones pemviz wrote).
    Returns:
        the Parquet path.
    Raises:
        ValueError: a bad path (:func:`check_rollouts_path`; an existing file without ``overwrite``), wrong
            shapes, or a :class:`RolloutFormatError` (NaN, a positive log-probability ...) naming the rollout
            and step; nothing is written.
        OSError: the folder is not writable, the disk is full (nothing is left behind).
    """
    with RolloutWriter(path, meta, log_probs=log_probs, overwrite=overwrite) as writer:
        writer.append(batch, rollout_ids=rollout_ids, salient=salient, stage=stage, component=component,
                      severity=severity)  # fmt: skip
        return writer.commit(proposal)

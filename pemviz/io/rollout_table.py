"""A rollout file's Parquet table checked against the format and read into numpy (:class:`RolloutData`), with the same
checks for the reader and the writer, and its optional columns: the severity (:data:`SEVERITY_COLUMNS`: min distance in
metres, impact speed in m/s, null without contact; both or neither, not read by estimates) and the braking lead's
salient variables (:func:`braking_salient`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from pemviz.core.rollouts import RolloutBatch
from pemviz.io.rollout_format import SALIENT_COLUMNS, RolloutFormatError, RolloutMeta, check_stage_counts
from pemviz.pem import braking_salient_inputs
from pemviz.pem.encoding import INPUT_COLUMNS

SEVERITY_COLUMNS = ("min_distance_m", "impact_speed_mps")
"""The optional per-rollout severity columns (module docstring): min distance (m), impact speed (m/s, null: no
contact)."""


def braking_salient(gap_m: np.ndarray) -> np.ndarray:
    """The PEM's salient variables of the lead at each gap, float64 [N, T, 11] for gaps [N, T] (metres).

    :func:`pemviz.pem.braking_salient_inputs` row by row (the lead's KITTI salient variables at each gap)."""
    gap = np.asarray(gap_m, dtype=np.float64)
    return braking_salient_inputs(gap).reshape(*gap.shape, len(INPUT_COLUMNS))


@dataclass(frozen=True)
class RolloutData(RolloutBatch):
    """N logged rollouts of T steps as :func:`~pemviz.io.rollouts.read_rollouts` returns them: a
    :class:`~pemviz.core.rollouts.RolloutBatch` whose ``log_p`` / ``log_q`` may be None (no such column;
    :meth:`to_batch` fills them), plus what the file adds.

    Attributes:
        observations: float64 [N, T, F], columns ``observation_names`` (``gap_m`` first).
        detected: bool [N, T, M] (M = the sidecar's ``objects``).
        log_p, log_q: float64 [N, T] (nats) or None; ``log_p`` is -inf at an action the PEM cannot take, ``log_q``
            finite.
        observation_names: the F state columns.
        meta: the sidecar.
        rollout_ids: int64 [N], in file order.
        salient: float64 [N, T, 11] (:data:`SALIENT_COLUMNS`) or None.
        path: the Parquet file (None for data not read from disk).
        stage, component: int64 [N], each rollout's stage and mixture component (version 2), or None.
        noise, noise_names: float64 [N, T, M, D] measurement errors (metres, 0 where missed) and their D names
            (version 3), or None and ().
        min_distance, impact_speed: float64 [N] min distance (metres) and impact speed (m/s; NaN: no contact), or
            None (:data:`SEVERITY_COLUMNS`)."""

    # Optional here, unlike RolloutBatch's (the class docstring's one difference): an override mypy cannot accept
    log_p: np.ndarray | None  # type: ignore[assignment]
    log_q: np.ndarray | None  # type: ignore[assignment]
    meta: RolloutMeta | None = None
    rollout_ids: np.ndarray | None = None
    salient: np.ndarray | None = None
    path: Path | None = None
    stage: np.ndarray | None = None
    component: np.ndarray | None = None
    min_distance: np.ndarray | None = None
    impact_speed: np.ndarray | None = None

    def log_weight(self, n_factors: int | None = None) -> np.ndarray:
        """:meth:`pemviz.core.rollouts.RolloutBatch.log_weight` of the file's columns, float64 [N] (nats).

        Raises:
            ValueError: the file has no ``log_p`` or no ``log_q`` column."""
        return self.to_batch().log_weight(n_factors)

    def to_batch(self, log_p: np.ndarray | None = None, log_q: np.ndarray | None = None) -> RolloutBatch:
        """A :class:`RolloutBatch` with the given (default: the file's) log-probabilities [N, T].

        Raises:
            ValueError: a log-probability that is neither given nor in the file."""
        log_p = self.log_p if log_p is None else log_p
        log_q = self.log_q if log_q is None else log_q
        if log_p is None or log_q is None:
            raise ValueError("to_batch: give log_p and log_q, the file has no such column")
        return RolloutBatch(
            self.observations,
            self.detected,
            log_p,
            log_q,
            self.observation_names,
            noise=self.noise,
            noise_names=self.noise_names,
            log_q_params=self.log_q_params,
        )


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

    def at(self, row: int | np.integer) -> str:
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

    def structure(self) -> tuple[np.ndarray, int]:
        """Check rollout ids and steps; returns (rollout ids [N], T)."""
        names = self.table.column_names
        needed = [
            "rollout",
            "step",
            *self.meta.columns,
            *self.meta.detection_columns,
            *(c for cols in self.meta.noise_columns for c in cols),
        ]
        missing = [c for c in needed if c not in names]
        if missing:
            raise self.error(
                f"missing column{'s' * (len(missing) > 1)} {', '.join(map(repr, missing))}; required: "
                f"{', '.join(needed)} (the sidecar's observation_columns / signals name the state columns); "
                f"present: {', '.join(names)}"
            )
        if self.meta.per_object and not {"log_p", "log_q"} <= set(names):
            raise self.error(
                f"a file of {self.meta.objects} object(s) a step with errors {list(self.meta.noise)} must "
                "hold log_p and log_q: the PEMs' inputs (each object's row) are not in it"
            )
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

    def floats(self, name: str, *, log_prob: bool = False, impossible: bool = False) -> np.ndarray:
        """A numeric column as float64 [rows]: finite (and <= 0 for log-probabilities).

        Args:
            name: the column.
            log_prob: a log-probability column (nats): a value > 0 is refused (a log density may be > 0: False).
            impossible: ``log_p``: -inf is allowed too, an action the PEM cannot take (p = 0, importance weight 0);
                NaN and +inf are still refused.
        Raises:
            RolloutFormatError: a wrong type, a null, a value that is not allowed, in one line naming the column,
                rollout and step."""
        col = self.table.column(name)
        if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
            raise self._type_error(name, "numbers (float64)", located=True)
        self._nulls(name, located=True)
        x = col.to_numpy().astype(np.float64)
        ok = np.isfinite(x)
        if impossible:
            ok |= x == -np.inf
        bad = ~ok
        if bad.any():
            row = _first_index(bad)
            what = "NaN" if np.isnan(x[row]) else str(x[row])
            allowed = (
                "finite numbers or -inf (an action the PEM cannot take: weight 0)"
                if impossible
                else "finite numbers (a proposal drew each action: q > 0)"
                if name == "log_q"
                else "finite numbers"
            )
            raise self.error(f"{name} is {what} at {self.at(row)}; values must be {allowed}")
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
            raise self.error(
                f"{name} = {per[i, t]} at {self.at(i * n_steps + t)} but {per[i, 0]} at its step 0; "
                f"a rollout has one {name}"
            )
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
            raise self.error(
                f"severity columns incomplete: {present[0]!r} without {absent[0]!r} (give both or neither)"
            )
        dist = self.floats(SEVERITY_COLUMNS[0])
        col = self.table.column(SEVERITY_COLUMNS[1])
        if not (pa.types.is_floating(col.type) or pa.types.is_integer(col.type)):
            raise self._type_error(SEVERITY_COLUMNS[1], "numbers (float64, null: no contact)", located=True)
        speed = col.to_numpy(zero_copy_only=False).astype(np.float64)  # a null reads as NaN: no contact
        bad = np.isinf(speed) | (speed <= 0)
        if bad.any():
            row = _first_index(bad)
            raise self.error(
                f"{SEVERITY_COLUMNS[1]} = {float(speed[row])!r} at {self.at(row)}: an impact speed is a "
                "positive number of m/s, or null where the rollout makes no contact"
            )
        return self.one_per_rollout(SEVERITY_COLUMNS[0], dist, n), self.one_per_rollout(SEVERITY_COLUMNS[1], speed, n)

    def one_per_rollout(self, name: str, x: np.ndarray, n: int) -> np.ndarray:
        """float64 [N]: a column [N T] that holds one value per rollout (the same on all its rows, NaN alike)."""
        per = x.reshape(n, -1)
        differs = ~((per == per[:, :1]) | (np.isnan(per) & np.isnan(per[:, :1]))).all(axis=1)
        if differs.any():
            i = _first_index(differs)
            t = _first_index(~((per[i] == per[i, 0]) | (np.isnan(per[i]) & np.isnan(per[i, 0]))))
            raise self.error(
                f"{name} = {per[i, t]} at {self.at(i * per.shape[1] + t)} but {per[i, 0]} at its step 0; "
                f"a rollout has one {name}"
            )
        return per[:, 0].copy()

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
            noise = np.stack(
                [np.stack([self.floats(c) for c in cols], axis=-1) for cols in self.meta.noise_columns], axis=1
            ).reshape(n, n_steps, m, len(self.meta.noise))
        salient = None
        if SALIENT_COLUMNS[0] in names:
            salient = np.stack([self.floats(c) for c in SALIENT_COLUMNS], axis=-1).reshape(n, n_steps, -1)
        probability = not self.meta.noise  # with measurement errors a step's log_p / log_q hold log densities
        log_p = (
            self.floats("log_p", log_prob=probability, impossible=True).reshape(n, n_steps)
            if "log_p" in names
            else None
        )
        log_q = self.floats("log_q", log_prob=probability).reshape(n, n_steps) if "log_q" in names else None
        log_q_params = (
            self.one_per_rollout("log_q_params", self.floats("log_q_params"), n) if "log_q_params" in names else None
        )
        stage, component = (self.per_rollout(c, n, n_steps) if c in names else None for c in ("stage", "component"))
        self.stages(stage, component)
        min_distance, impact_speed = self.severity(n, n_steps)
        return RolloutData(
            obs,
            detected,
            log_p,
            log_q,
            tuple(cols),
            noise=noise,
            noise_names=self.meta.noise,
            log_q_params=log_q_params,
            meta=self.meta,
            rollout_ids=ids,
            salient=salient,
            path=path,
            stage=stage,
            component=component,
            min_distance=min_distance,
            impact_speed=impact_speed,
        )

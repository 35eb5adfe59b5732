"""Logged rollouts on disk: a Parquet table, one row per step, and a JSON sidecar (spec, dt, units).

pemviz estimates from rollouts produced anywhere (CARLA, a user's simulator, ``pemviz run
--save-rollouts``): :func:`write_rollouts` / :func:`read_rollouts` here, ``pemviz estimate`` on the
command line. Both validate with the same code, so a file pemviz writes is one pemviz reads.

Format, version 2
-----------------
``NAME.parquet``: one row per (rollout, step). The rows of a rollout are contiguous, hold steps
0, 1, ..., T-1 in this order, and every rollout has the same T.

============================  ===========================  =====  ==========================================
column                        type                         unit   meaning
============================  ===========================  =====  ==========================================
``rollout``                   integer                      -      rollout id (any distinct integers)
``step``                      integer                      -      step t = 0..T-1 (time t * dt_s)
``gap_m``                     float                        m      the gap: h(s) of the proposal (required)
signals of the spec           float                        SI     e.g. ``ego_speed_mps``, ``lead_speed_mps``
``detected``                  bool (or integer 0/1)        -      the detector output a_t taken at step t
``salient_<name>`` (11)       float                        m/rad  optional: the PEM's salient variables, KITTI
                                                                  columns :data:`SALIENT_COLUMNS`
``log_p``                     float                        nats   optional: log p_PEM(a_t | s_t)
``log_q``                     float                        nats   optional: log q(a_t | s_t, a_0..a_{t-1}),
                                                                  the density the rollout was drawn from and
                                                                  weighed with (for a mixture over whole
                                                                  rollouts its per-step conditional,
                                                                  :func:`pemviz.weights.mixture_step_log_q`)
``stage``                     integer >= 0                 -      optional (version 2): the stage that drew the
                                                                  rollout, the same on all its rows
``component``                 integer >= 0                 -      optional (version 2): which sampler of the
                                                                  stage's mixture drew it (index into the
                                                                  sidecar's ``stages[].components``)
============================  ===========================  =====  ==========================================

Floats must be finite; log-probabilities <= 0. Other columns are ignored.

``NAME.json`` (the sidecar, same name with suffix ``.json``), a JSON object:

- ``formula`` (required): the safety spec in STL, e.g. ``"G[0,99](d >= 2)"``; failure = classic
  robustness < 0 (Innes & Ramamoorthy 2022).
- ``dt_s`` (required): seconds per step.
- ``signals``: STL signal name -> column (default ``{"d": "gap_m"}``); ``signal_ranges``: per STL
  signal ``[lo, hi]`` for AGM's normalisation; ``observation_columns``: the state columns in the order
  detectors see them (default ``gap_m`` then the signals' columns); ``units``: column -> unit (informative).
- ``pem``: the PEM ``log_p`` was computed under (a shipped name or a path); ``proposal``: a proposal
  checkpoint (:func:`pemviz.sampling.save_proposal`, path relative to the sidecar) or ``pem`` / ``naive50`` / ``mixed50``,
  what sampled the rollouts; ``window_m``: mixed50's 50 % window (metres, default 10).
- ``n_rollouts``, ``n_steps``: checked against the table when present.
- ``weights`` (version 2): the weight convention the writer weighed with, ``to-failure`` (the product of p / q
  over the steps before the failure step) or ``full`` (over every step but the last; Innes & Ramamoorthy 2022,
  eq. 6); ``pemviz estimate`` uses it unless ``--weights`` says otherwise (absent: ``to-failure``).
- ``stages`` (version 2): one object per stage in the table: ``stage``, ``kind``, ``n`` (its rollouts),
  ``components`` (``[{"sampler": text, "n": rollouts}, ...]`` in the order of the ``component`` column; the
  rollouts were drawn from the mixture sum_k (n_k / n) q_k), ``max_weight`` (n / n_target when the target itself is a
  component, the bound of every weight; else null).
- ``pooling`` (version 2): how the writer's estimate combines the stages: ``rule`` (``quadratic``, ``linear``,
  ``rollouts`` or ``single``), ``stages`` (the pooled stages) and ``stage_weights`` (lambda_k >= 0, summing to 1):
  mu_hat = sum_k lambda_k mu_hat_k (absent: every rollout alike).
- ``format`` (``"pemviz-rollouts"``), ``version`` (2; version 1 files, without ``weights``, ``stages``,
  ``pooling`` and the two integer columns, are read too), ``pemviz_version``, ``provenance`` (free-form:
  the run's config, its estimate and its per-stage estimates).

Importance weights use at most the first T - 1 steps (the last action affects nothing; Innes & Ramamoorthy 2022,
Algorithm 1), as the engine does, so an estimate from a file written by ``pemviz run`` equals the run's to float64
rounding.
Bad input raises :class:`RolloutFormatError`: one message naming the file, the column, and the rollout
and step where the problem is. Writers write to a temporary file and ``os.replace`` it: no half file.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

import pemviz
from pemviz import stl
from pemviz.data import sha256_file
from pemviz.files import check_free_name, check_output_path, commit_files, temp_file
from pemviz.pem import braking_salient_inputs
from pemviz.problems import BRAKING_SIGNAL_RANGES, BRAKING_SIGNALS, braking_formula
from pemviz.sampling import write_proposal_file
from pemviz.scenarios import RolloutBatch
from pemviz.scenarios.braking import OBSERVATION_NAMES, BrakingParams

FORMAT_TAG = "pemviz-rollouts"
FORMAT_VERSION = 2
READ_VERSIONS = (1, 2)
"""Versions this pemviz reads: 1 (one batch, ``log_q`` its sampler's density) and 2 (adds ``stage``, ``component``,
``weights``, ``stages``, ``pooling``)."""
WEIGHTS = ("to-failure", "full")
"""Weight conventions (:mod:`pemviz.weights`)."""

KITTI_COLUMNS = ("class", "truncation", "occlusion", "alpha", "dim_w", "dim_l", "dim_h", "loc_x", "loc_y", "loc_z",
                 "rot_y")  # fmt: skip
"""The 11 salient-variable columns of the KITTI files (:data:`pemviz.data.INPUT_COLUMNS`)."""
SALIENT_COLUMNS = tuple(f"salient_{c}" for c in KITTI_COLUMNS)
"""Parquet names of the PEM's salient variables, in the KITTI order :meth:`pemviz.pem.PEM.logit` reads."""
SALIENT_UNITS = {"alpha": "rad", "rot_y": "rad", "dim_w": "m", "dim_l": "m", "dim_h": "m", "loc_x": "m",
                 "loc_y": "m", "loc_z": "m"}  # fmt: skip
BRAKING_UNITS = {"gap_m": "m", "ego_speed_mps": "m/s", "lead_speed_mps": "m/s", "log_p": "nats", "log_q": "nats",
                 **{f"salient_{k}": u for k, u in SALIENT_UNITS.items()}}  # fmt: skip
SAMPLERS = ("pem", "naive50", "mixed50")
"""Named samplers a file's log q can be recomputed from besides a proposal checkpoint."""


class RolloutFormatError(ValueError):
    """A rollout file or its sidecar is malformed: the message says where and why."""


# ----------------------------------------------------------------------------------------- metadata


@dataclass(frozen=True)
class RolloutMeta:
    """The JSON sidecar of a rollout file (module docstring). Units: seconds, metres, nats.

    Attributes:
        formula: the safety spec (STL text); failure = classic robustness < 0.
        dt_s: seconds per step.
        signals: STL signal name -> column.
        signal_ranges: STL signal name -> (lo, hi), AGM's predicate normalisation.
        observation_columns: state columns in the order detectors see them (``gap_m`` first); the
            signals' columns are added after them (:attr:`columns`).
        units: column -> unit (informative).
        pem: the PEM ``log_p`` was computed under (name or path), if known.
        proposal: what sampled the rollouts: a checkpoint path relative to the sidecar, or one of
            :data:`SAMPLERS`; None if unknown.
        window_m: the mixed50 sampler's 50 % window (metres).
        n_rollouts, n_steps: N and T, checked against the table when set.
        pemviz_version: the writer's version.
        provenance: free-form JSON (the run's config, the stage the rollouts come from, its estimate).
        weights: the writer's weight convention, one of :data:`WEIGHTS`, or None (not said).
        stages: per stage in the table: ``{"stage", "kind", "n", "components": [{"sampler", "n"}], "max_weight"}``.
        pooling: ``{"rule", "stages", "stage_weights"}``: how the writer pooled the stages, or None.
        version: the file's format version (:data:`READ_VERSIONS`).
    """

    formula: str
    dt_s: float
    signals: Mapping[str, str] = field(default_factory=lambda: {"d": "gap_m"})
    signal_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    observation_columns: tuple[str, ...] = ()
    units: Mapping[str, str] = field(default_factory=dict)
    pem: str | None = None
    proposal: str | None = None
    window_m: float = 10.0
    n_rollouts: int | None = None
    n_steps: int | None = None
    pemviz_version: str = pemviz.__version__
    provenance: Mapping[str, Any] = field(default_factory=dict)
    table_sha256: str | None = None
    proposal_sha256: str | None = None
    weights: str | None = None
    stages: tuple[Mapping[str, Any], ...] = ()
    pooling: Mapping[str, Any] | None = None
    version: int = FORMAT_VERSION

    def stage_info(self, stage: int) -> Mapping[str, Any] | None:
        """The sidecar's ``stages`` entry of ``stage``, or None."""
        return next((s for s in self.stages if s["stage"] == stage), None)

    @property
    def columns(self) -> tuple[str, ...]:
        """The observation columns: ``gap_m``, then ``observation_columns``, then the signals' columns."""
        return tuple(dict.fromkeys(["gap_m", *self.observation_columns, *self.signals.values()]))

    def to_json(self) -> dict[str, Any]:
        """The sidecar as a JSON object."""
        return {
            "format": FORMAT_TAG,
            "version": FORMAT_VERSION,
            "pemviz_version": self.pemviz_version,
            "formula": self.formula,
            "dt_s": self.dt_s,
            "signals": dict(self.signals),
            "signal_ranges": {k: [float(lo), float(hi)] for k, (lo, hi) in self.signal_ranges.items()},
            "observation_columns": list(self.columns),
            "units": dict(self.units),
            "pem": self.pem,
            "proposal": self.proposal,
            "window_m": self.window_m,
            "n_rollouts": self.n_rollouts,
            "n_steps": self.n_steps,
            "provenance": _plain(self.provenance),
            **({"weights": self.weights} if self.weights else {}),
            **({"stages": [_plain(st) for st in self.stages]} if self.stages else {}),
            **({"pooling": _plain(self.pooling)} if self.pooling else {}),
            **({"table_sha256": self.table_sha256} if self.table_sha256 else {}),
            **({"proposal_sha256": self.proposal_sha256} if self.proposal_sha256 else {}),
        }

    @classmethod
    def from_json(cls, obj: Any, where: str = "sidecar") -> "RolloutMeta":
        """Parse and check a sidecar object.

        Raises:
            RolloutFormatError: not an object, wrong format tag or version, a missing or invalid field.
        """
        def bad(msg: str) -> RolloutFormatError:
            return RolloutFormatError(f"{where}: {msg}")

        if not isinstance(obj, dict):
            raise bad(f"must be a JSON object, got {type(obj).__name__}")
        if obj.get("format", FORMAT_TAG) != FORMAT_TAG:
            raise bad(f"format is {obj.get('format')!r}, expected {FORMAT_TAG!r}")
        version = obj.get("version", FORMAT_VERSION)
        if isinstance(version, bool) or version not in READ_VERSIONS:
            raise bad(f"format version {version!r}; this pemviz reads versions {', '.join(map(str, READ_VERSIONS))}: "
                      "a newer pemviz wrote the file, upgrade pemviz to read it")
        for key in ("formula", "dt_s"):
            if key not in obj:
                raise bad(f"field {key!r} is missing (required: formula, dt_s)")
        formula = obj["formula"]
        if not isinstance(formula, str):
            raise bad(f"formula must be STL text such as 'G[0,99](d >= 2)', got {formula!r}")
        try:
            stl.parse(formula)
        except ValueError as exc:
            raise bad(f"formula {formula!r} is not valid STL: {exc}") from None
        dt = obj["dt_s"]
        if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
            raise bad(f"dt_s must be a number of seconds > 0, got {dt!r}")
        signals = obj.get("signals") or {"d": "gap_m"}
        if not isinstance(signals, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                     for k, v in signals.items()):
            raise bad(f"signals must map STL names to column names, got {signals!r}")
        for key in ("signal_ranges", "units", "provenance"):
            if not isinstance(obj.get(key) or {}, dict):
                raise bad(f"{key} must be a JSON object, got {obj[key]!r}")
        units = obj.get("units") or {}
        if not all(isinstance(v, str) for v in units.values()):
            raise bad(f"units must map column names to unit text such as 'm', got {units!r}")
        ranges: dict[str, tuple[float, float]] = {}
        for k, v in (obj.get("signal_ranges") or {}).items():
            if not (isinstance(v, (list, tuple)) and len(v) == 2 and all(_is_number(x) for x in v) and v[0] < v[1]):
                raise bad(f"signal_ranges[{k!r}] must be [lo, hi] with lo < hi, got {v!r}")
            ranges[k] = (float(v[0]), float(v[1]))
        cols = obj.get("observation_columns") or []
        if not isinstance(cols, list) or not all(isinstance(c, str) for c in cols):
            raise bad(f"observation_columns must be a list of column names, got {cols!r}")
        for key in ("n_rollouts", "n_steps"):
            v = obj.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise bad(f"{key} must be an integer >= 1, got {v!r}")
        for key in ("pem", "proposal", "pemviz_version"):
            v = obj.get(key)
            if v is not None and not isinstance(v, str):
                raise bad(f"{key} must be a string, got {v!r}")
        window = obj.get("window_m", 10.0)
        if not _is_number(window) or window < 0:
            raise bad(f"window_m must be a number of metres >= 0, got {window!r}")
        for key in ("table_sha256", "proposal_sha256"):
            v = obj.get(key)
            if v is not None and not (isinstance(v, str) and len(v) == 64):
                raise bad(f"{key} must be a SHA-256 hex digest (64 characters), got {v!r}")
        weights = obj.get("weights")
        if weights is not None and weights not in WEIGHTS:
            raise bad(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
        stages = _parse_stages(obj.get("stages"), bad)
        pooling = _parse_pooling(obj.get("pooling"), bad)
        return cls(
            formula=formula,
            dt_s=float(dt),
            signals=dict(signals),
            signal_ranges=ranges,
            observation_columns=tuple(cols),
            units=dict(units),
            pem=obj.get("pem"),
            proposal=obj.get("proposal"),
            window_m=float(window),
            n_rollouts=obj.get("n_rollouts"),
            n_steps=obj.get("n_steps"),
            pemviz_version=obj.get("pemviz_version") or "unknown",
            provenance=dict(obj.get("provenance") or {}),
            table_sha256=obj.get("table_sha256"),
            proposal_sha256=obj.get("proposal_sha256"),
            weights=weights,
            stages=stages,
            pooling=pooling,
            version=int(version),
        )


def _is_count(x: Any, least: int = 0) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and x >= least


def _parse_stages(value: Any, bad: Any) -> tuple[dict[str, Any], ...]:
    """The sidecar's ``stages``: a list of ``{"stage", "kind", "n", "components", "max_weight"}``, distinct stages."""
    if value is None:
        return ()
    if not isinstance(value, list):
        raise bad(f"stages must be a list of objects, got {value!r}")
    out: list[dict[str, Any]] = []
    for k, st in enumerate(value):
        where = f"stages[{k}]"
        if not isinstance(st, dict):
            raise bad(f"{where} must be a JSON object, got {st!r}")
        if not _is_count(st.get("stage")) or not _is_count(st.get("n"), 1):
            raise bad(f"{where} needs stage (an integer >= 0) and n (an integer >= 1), got {st!r}")
        comps = st.get("components", [])
        if not isinstance(comps, list) or not all(isinstance(c, dict) and _is_count(c.get("n"))
                                                  and isinstance(c.get("sampler", ""), str) for c in comps):
            raise bad(f"{where}.components must be a list of {{\"sampler\": text, \"n\": rollouts}}, got {comps!r}")
        if comps and sum(c["n"] for c in comps) != st["n"]:
            raise bad(f"{where}: its components hold {sum(c['n'] for c in comps)} rollouts, not n = {st['n']}")
        bound = st.get("max_weight")
        if bound is not None and not (_is_number(bound) and bound >= 1.0):
            raise bad(f"{where}.max_weight must be a number >= 1 or null, got {bound!r}")
        if not isinstance(st.get("kind", ""), str):
            raise bad(f"{where}.kind must be text, got {st.get('kind')!r}")
        out.append({"stage": st["stage"], "kind": st.get("kind", ""), "n": st["n"],
                    "components": [{"sampler": c.get("sampler", ""), "n": c["n"]} for c in comps],
                    "max_weight": None if bound is None else float(bound)})  # fmt: skip
    numbers = [st["stage"] for st in out]
    if len(set(numbers)) != len(numbers):
        raise bad(f"stages lists stage {next(x for x in numbers if numbers.count(x) > 1)} twice")
    return tuple(out)


def _parse_pooling(value: Any, bad: Any) -> dict[str, Any] | None:
    """The sidecar's ``pooling``: ``{"rule": text, "stages": [k...], "stage_weights": [lambda_k...]}``."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise bad(f"pooling must be a JSON object, got {value!r}")
    stages, lam, rule = value.get("stages"), value.get("stage_weights"), value.get("rule", "")
    if not (isinstance(stages, list) and stages and all(_is_count(k) for k in stages)
            and len(set(stages)) == len(stages)):
        raise bad(f"pooling.stages must be a non-empty list of distinct stage numbers, got {stages!r}")
    if not (isinstance(lam, list) and len(lam) == len(stages) and all(_is_number(x) and x >= 0 for x in lam)
            and abs(math.fsum(lam) - 1.0) <= 1e-9):
        raise bad(f"pooling.stage_weights must be {len(stages)} numbers >= 0 summing to 1, got {lam!r}")
    if not isinstance(rule, str):
        raise bad(f"pooling.rule must be text, got {rule!r}")
    return {"rule": rule, "stages": list(stages), "stage_weights": [float(x) for x in lam]}


def braking_meta(
    formula: str | None = None,
    *,
    pem: str | None = None,
    proposal: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> RolloutMeta:
    """The sidecar of braking-scenario rollouts (Innes & Ramamoorthy 2022): dt 0.05 s, signals d / v / vl, units.

    ``formula`` defaults to ``G[0,T-1](d >= 2)`` of :func:`pemviz.problems.braking_formula`.
    """
    p = BrakingParams()
    return RolloutMeta(
        formula=formula or str(braking_formula(p)),
        dt_s=p.dt_s,
        signals=dict(BRAKING_SIGNALS),
        signal_ranges=dict(BRAKING_SIGNAL_RANGES),
        observation_columns=tuple(OBSERVATION_NAMES),
        units=dict(BRAKING_UNITS),
        pem=pem,
        proposal=proposal,
        window_m=p.braking_distance_m,
        provenance=dict(provenance or {}),
    )


def braking_salient(gap_m: np.ndarray) -> np.ndarray:
    """The PEM's salient variables of the lead at each gap, float64 [N, T, 11] for gaps [N, T] (metres).

    :func:`pemviz.pem.braking_salient_inputs` row by row (the lead's KITTI salient variables at each gap).
    """
    gap = np.asarray(gap_m, dtype=np.float64)
    return braking_salient_inputs(gap).reshape(*gap.shape, len(KITTI_COLUMNS))


# ---------------------------------------------------------------------------------------- the data


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
        detected: bool [N, T].
        log_p, log_q: float64 [N, T] (nats) or None when the file has no such column (:meth:`to_batch` fills them).
        observation_names: the F state columns.
        meta: the sidecar.
        rollout_ids: int64 [N], in file order.
        salient: float64 [N, T, 11] (:data:`SALIENT_COLUMNS`) or None.
        path: the Parquet file (None for data not read from disk).
        stage, component: int64 [N], each rollout's stage and mixture component (version 2), or None.
    """

    log_p: np.ndarray | None
    log_q: np.ndarray | None
    meta: RolloutMeta | None = None
    rollout_ids: np.ndarray | None = None
    salient: np.ndarray | None = None
    path: Path | None = None
    stage: np.ndarray | None = None
    component: np.ndarray | None = None

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
        return RolloutBatch(self.observations, self.detected, log_p, log_q, self.observation_names)


def sidecar_path(path: str | os.PathLike[str]) -> Path:
    """``NAME.parquet`` -> ``NAME.json``."""
    return Path(path).with_suffix(".json")


def _plain(value: Any) -> Any:
    """JSON-able copy: numpy scalars and arrays as Python values, unknown objects as text."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, (np.generic,)):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


# ----------------------------------------------------------------------------------------- validation


def _first_index(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def check_stage_counts(meta: RolloutMeta, counts: Mapping[int, list[int]], error: Any) -> None:
    """Check a table's rollouts per stage and component, ``{stage: [rollouts of component 0, 1, ...]}``, against the
    sidecar's ``stages`` (each stage listed, its n and its components' n) and ``pooling`` (each pooled stage held).

    Raises:
        what ``error(message)`` returns (a :class:`RolloutFormatError` naming the file).
    """
    for k, held in sorted(counts.items()):
        info = meta.stage_info(k)
        if meta.stages and info is None:
            raise error(f"stage {k} is in the table but not in the sidecar's stages")
        if info is None:
            continue
        if info["n"] != sum(held):
            raise error(f"the sidecar says stage {k} has n = {info['n']} rollouts but the table holds {sum(held)}")
        declared = [c["n"] for c in info["components"]]
        if declared and len(held) > len(declared):
            raise error(f"stage {k} has component {len(held) - 1} but the sidecar lists {len(declared)} for it")
        if declared and held + [0] * (len(declared) - len(held)) != declared:
            raise error(f"stage {k}: the table holds {held} rollouts per component, the sidecar says {declared}")
    for k in (meta.pooling or {}).get("stages", []):
        if k not in counts:
            raise error(f"the sidecar pools stage {k} but the table holds no rollout of it")


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
        needed = ["rollout", "step", *self.meta.columns, "detected"]
        missing = [c for c in needed if c not in names]
        if missing:
            raise self.error(
                f"missing column{'s' * (len(missing) > 1)} {', '.join(map(repr, missing))}; required: "
                f"{', '.join(needed)} (the sidecar's observation_columns / signals name the state columns); "
                f"present: {', '.join(names)}"
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
        detected = self.booleans("detected").reshape(n, n_steps)
        salient = None
        if SALIENT_COLUMNS[0] in names:
            salient = np.stack([self.floats(c) for c in SALIENT_COLUMNS], axis=-1).reshape(n, n_steps, -1)
        log_p = self.floats("log_p", log_prob=True).reshape(n, n_steps) if "log_p" in names else None
        log_q = self.floats("log_q", log_prob=True).reshape(n, n_steps) if "log_q" in names else None
        stage, component = (self.per_rollout(c, n, n_steps) if c in names else None for c in ("stage", "component"))
        self.stages(stage, component)
        return RolloutData(obs, detected, log_p, log_q, tuple(cols), meta=self.meta, rollout_ids=ids, salient=salient,
                           path=path, stage=stage, component=component)


# ---------------------------------------------------------------------------------------- read / write


def read_sidecar(path: str | os.PathLike[str]) -> RolloutMeta:
    """The sidecar of the rollout file ``path`` (``NAME.json`` beside ``NAME.parquet``).

    Raises:
        RolloutFormatError: no sidecar, not JSON, or an invalid field.
    """
    side = sidecar_path(path)
    if not side.is_file():
        raise RolloutFormatError(
            f"{side}: sidecar not found; a rollout file NAME.parquet needs NAME.json with at least "
            f'{{"formula": "G[0,99](d >= 2)", "dt_s": 0.05}} (see pemviz.rollout_io)'
        )
    try:
        obj = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise RolloutFormatError(f"{side}: not a readable JSON file ({exc})") from None
    return RolloutMeta.from_json(obj, str(side))


def read_rollouts(path: str | os.PathLike[str]) -> RolloutData:
    """Read and validate a rollout file and its sidecar.

    Returns:
        :class:`RolloutData`: observations [N, T, F], detected [N, T], optional salient [N, T, 11],
        log_p / log_q [N, T] (nats).
    Raises:
        FileNotFoundError: no such file.
        RolloutFormatError: the sidecar or the table breaks the format (module docstring); the message
            names the column and the rollout and step.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"rollout file {p} not found")
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


def proposal_path(path: str | os.PathLike[str]) -> Path:
    """``NAME.parquet`` -> ``NAME.proposal.pt``, the proposal checkpoint written beside a rollout file."""
    return Path(path).with_suffix(".proposal.pt")


def check_rollouts_path(path: str | os.PathLike[str], *, overwrite: bool = False, what: str = "rollout file") -> Path:
    """Refuse a path where a rollout file cannot be written, before any work (nothing is created).

    The sidecar ``NAME.json`` and checkpoint ``NAME.proposal.pt`` are checked too: an existing one is replaced
    only with ``overwrite`` and only if pemviz wrote it.

    Raises:
        ValueError: not ``.parquet``, a directory, a folder that does not exist / is not writable, a name too
            long, or an existing file (:class:`pemviz.files.OutputExists` without ``overwrite``).
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
) -> Any:
    """The Parquet table of a batch: rollout, step, observations, detected, [salient], [log_p, log_q], [stage,
    component].

    Args:
        batch: N rollouts [N, T].
        rollout_ids: int [N] (default 0..N-1).
        salient: float64 [N, T, 11] salient variables (:func:`braking_salient`) or None.
        log_probs: include ``log_p`` and ``log_q``.
        stage: the stage of all N rollouts, or int [N] each rollout's, or None (no stage column).
        component: int [N] each rollout's mixture component (with ``stage``; default 0).
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
    cols["detected"] = np.asarray(batch.detected, dtype=bool).reshape(-1)
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
        meta: the sidecar (:func:`braking_meta` for the braking scenario); ``n_rollouts`` / ``n_steps`` /
            ``observation_columns`` are filled in.
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
        self._shape: tuple[int, tuple[str, ...]] | None = None
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(temp_file(self.path))
        self._writer: Any = None

    def __enter__(self) -> "RolloutWriter":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.abort()

    def append(self, batch: RolloutBatch, *, rollout_ids: np.ndarray | None = None,
               salient: np.ndarray | None = None, stage: int | np.ndarray | None = None,
               component: np.ndarray | None = None) -> None:  # fmt: skip
        """Validate and write the next rollouts (default ids: continuing from the last chunk's).

        Args:
            batch: rollouts [n, T] with the same T and observation columns as the chunks before.
            rollout_ids, salient, stage, component: see :func:`rollouts_table` (give ``stage`` for every chunk or
                for none).
        Raises:
            ValueError: wrong shapes, a batch unlike the earlier ones, or a :class:`RolloutFormatError` (NaN, a
                positive log-probability ...) naming the rollout and step; nothing of this chunk is written.
        """
        names = tuple(batch.observation_names)
        if self._shape is not None and self._shape != (batch.n_steps, names):
            raise ValueError(f"RolloutWriter: a chunk of {batch.n_steps} steps of {names} after chunks of "
                             f"{self._shape[0]} steps of {self._shape[1]}")  # fmt: skip
        meta = dataclasses.replace(self.meta, n_rollouts=None, n_steps=batch.n_steps, observation_columns=names,
                                   stages=(), pooling=None)  # checked against the whole table at commit
        if meta.columns != names:
            raise ValueError(f"write_rollouts: the batch's first observation must be gap_m, got {names}")
        if rollout_ids is None:
            rollout_ids = np.arange(self.n_rollouts, self.n_rollouts + batch.n, dtype=np.int64)
        table = rollouts_table(batch, rollout_ids=rollout_ids, salient=salient, log_probs=self.log_probs, stage=stage,
                               component=component)  # fmt: skip
        _Table(table, meta, f"{self.path} (not written)").parse(None)
        if self._writer is None:
            self._writer = pq.ParquetWriter(self._tmp, table.schema)
        self._writer.write_table(table)
        self._shape = (batch.n_steps, names)
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
            proposal: a :class:`pemviz.sampling.Proposal` that sampled the rollouts, saved as ``NAME.proposal.pt``
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
            n_steps, names = self._shape
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
) -> Path:
    """Write ``NAME.parquet``, its sidecar ``NAME.json`` and (with ``proposal``) ``NAME.proposal.pt`` as one unit
    (a :class:`RolloutWriter` with one chunk).

    The table is validated as :func:`read_rollouts` validates it before anything is written; ``meta.n_rollouts``
    / ``n_steps`` / ``observation_columns`` are filled in.

    Args:
        path: ``NAME.parquet``.
        batch: N rollouts [N, T] (observations, detected, log_p, log_q in nats).
        meta: the sidecar (:func:`braking_meta` for the braking scenario).
        rollout_ids, salient, log_probs, stage, component: see :func:`rollouts_table` (``stage`` / ``component`` of
            a version-2 file: ``RolloutData.stage`` / ``.component``).
        proposal: a :class:`pemviz.sampling.Proposal` that sampled the batch, saved as ``NAME.proposal.pt`` and
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
        writer.append(batch, rollout_ids=rollout_ids, salient=salient, stage=stage, component=component)
        return writer.commit(proposal)

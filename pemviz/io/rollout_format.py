"""The logged-rollout file format: a Parquet table, one row per step, and a JSON sidecar (spec, dt, units).

pemviz estimates from rollouts produced anywhere (CARLA, a user's simulator, ``pemviz run --save-rollouts``); the writer
(:mod:`pemviz.io.rollout_writer`) and the reader (:mod:`pemviz.io.rollouts`) validate with the same code. This module
holds the format's constants and its sidecar (:class:`RolloutMeta`). The format (version 3; 1 and 2 are read too) is
documented in docs/own-simulator.md, "Logged rollout files". Importance weights use at most the first T - 1 steps
(Innes & Ramamoorthy 2022, Algorithm 1), as the engine does. Bad input raises :class:`RolloutFormatError` naming the
file, the column, and the rollout and step."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import pemviz
from pemviz import stl
from pemviz.methods import MIXED_METHOD, NAIVE_METHOD
from pemviz.pem.encoding import INPUT_COLUMNS

FORMAT_TAG = "pemviz-rollouts"

FORMAT_VERSION = 2
"""The version of a file of one object per step without measurement errors (a file of several objects, or with
errors, is version :data:`OBJECTS_VERSION`)."""

OBJECTS_VERSION = 3

READ_VERSIONS = (1, FORMAT_VERSION, OBJECTS_VERSION)
"""Versions this pemviz reads: 1 (one batch, ``log_q`` its sampler's density), 2 (adds ``stage``, ``component``,
``weights``, ``stages``, ``pooling``) and 3 (adds ``objects`` and ``noise``: several objects a step, errors)."""

WEIGHTS = ("to-failure", "full")
"""Weight conventions (:mod:`pemviz.core.weights`)."""

SALIENT_COLUMNS = tuple(f"salient_{c}" for c in INPUT_COLUMNS)
"""Parquet names of the PEM's salient variables, in the KITTI order :meth:`pemviz.pem.PEM.logit` reads
(:data:`pemviz.pem.encoding.INPUT_COLUMNS`)."""

SAMPLERS = ("pem", NAIVE_METHOD, MIXED_METHOD)
"""Named samplers a file's log q can be recomputed from besides a proposal checkpoint."""


class RolloutFormatError(ValueError):
    """A rollout file or its sidecar is malformed: the message says where and why."""


@dataclass(frozen=True)
class RolloutMeta:
    """The JSON sidecar of a rollout file (module docstring). Units: seconds, metres, nats.

    Attributes:
        formula: the safety spec (STL text); failure = classic robustness < 0.
        dt_s: seconds per step.
        signals: STL signal name -> column.
        signal_ranges: STL signal name -> (lo, hi), AGM's predicate normalisation.
        observation_columns: state columns in the order detectors see them (:attr:`h_column` first); the
            signals' columns are added after them (:attr:`columns`).
        h_column: the first state column, h(s), which the proposal and the window read (default ``gap_m``).
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
        objects: M, the objects perceived at each step.
        noise: the names of a detected object's measurement-error components (metres); empty: none.
        odd_parameters: the columns of the parameters drawn per rollout from an ODD; empty: none.
        version: the file's format version (:data:`READ_VERSIONS`)."""

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
    objects: int = 1
    noise: tuple[str, ...] = ()
    odd_parameters: tuple[str, ...] = ()
    version: int = FORMAT_VERSION
    h_column: str = "gap_m"

    def stage_info(self, stage: int) -> Mapping[str, Any] | None:
        """The sidecar's ``stages`` entry of ``stage``, or None."""
        return next((s for s in self.stages if s["stage"] == stage), None)

    @property
    def per_object(self) -> bool:
        """Whether each object's detection and errors have their own columns (several objects, or errors)."""
        return self.objects > 1 or bool(self.noise)

    @property
    def detection_columns(self) -> tuple[str, ...]:
        """The detection columns: ``detected``, or ``detected_0`` .. ``detected_<M-1>`` (:attr:`per_object`)."""
        return tuple(f"detected_{m}" for m in range(self.objects)) if self.per_object else ("detected",)

    @property
    def noise_columns(self) -> tuple[tuple[str, ...], ...]:
        """Per object m, the columns of its errors ``<e>_<m>`` in the order of :attr:`noise`."""
        return tuple(tuple(f"{e}_{m}" for e in self.noise) for m in range(self.objects))

    @property
    def columns(self) -> tuple[str, ...]:
        """The observation columns: :attr:`h_column`, then ``observation_columns``, then the signals' columns."""
        return tuple(dict.fromkeys([self.h_column, *self.observation_columns, *self.signals.values()]))

    def to_json(self) -> dict[str, Any]:
        """The sidecar as a JSON object."""
        return {
            "format": FORMAT_TAG,
            "version": OBJECTS_VERSION if self.per_object else FORMAT_VERSION,
            "pemviz_version": self.pemviz_version,
            "formula": self.formula,
            "dt_s": self.dt_s,
            "signals": dict(self.signals),
            "signal_ranges": {k: [float(lo), float(hi)] for k, (lo, hi) in self.signal_ranges.items()},
            "observation_columns": list(self.columns),
            **({"h_column": self.h_column} if self.h_column != "gap_m" else {}),
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
            **({"objects": self.objects, "noise": list(self.noise)} if self.per_object else {}),
            **({"odd_parameters": list(self.odd_parameters)} if self.odd_parameters else {}),
            **({"table_sha256": self.table_sha256} if self.table_sha256 else {}),
            **({"proposal_sha256": self.proposal_sha256} if self.proposal_sha256 else {}),
        }

    @classmethod
    def from_json(cls, obj: Any, where: str = "sidecar") -> RolloutMeta:
        """Parse and check a sidecar object.

        Raises:
            RolloutFormatError: not an object, wrong format tag or version, a missing or invalid field."""

        def bad(msg: str) -> RolloutFormatError:
            return RolloutFormatError(f"{where}: {msg}")

        version, formula, dt = _check_header(obj, bad)
        signals = obj.get("signals") or {"d": "gap_m"}
        if not isinstance(signals, dict) or not all(
            isinstance(k, str) and isinstance(v, str) for k, v in signals.items()
        ):
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
        h_column = obj.get("h_column", "gap_m")
        if not isinstance(h_column, str) or not h_column:
            raise bad(f"h_column must be a column name such as 'gap_m', got {h_column!r}")
        window = _check_plain_fields(obj, bad)
        weights = obj.get("weights")
        if weights is not None and weights not in WEIGHTS:
            raise bad(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
        stages = _parse_stages(obj.get("stages"), bad)
        pooling = _parse_pooling(obj.get("pooling"), bad)
        objects = obj.get("objects", 1)
        if not _is_count(objects, 1):
            raise bad(f"objects must be an integer >= 1 (the objects perceived at each step), got {objects!r}")
        noise = obj.get("noise") or []
        if not (
            isinstance(noise, list) and all(isinstance(e, str) and e for e in noise) and len(set(noise)) == len(noise)
        ):
            raise bad(f"noise must be a list of distinct error names such as ['range_error_m'], got {noise!r}")
        odd_parameters = obj.get("odd_parameters") or []
        if not (isinstance(odd_parameters, list) and all(isinstance(c, str) and c for c in odd_parameters)):
            raise bad(f"odd_parameters must be a list of column names such as ['gap0_m'], got {odd_parameters!r}")
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
            objects=objects,
            noise=tuple(noise),
            odd_parameters=tuple(odd_parameters),
            version=int(version),
            h_column=h_column,
        )


def parse_formula(formula: str, bad: Callable[[str], Exception]) -> Any:
    """The STL formula of a sidecar's ``formula`` text, parsed (:func:`pemviz.stl.parse`).

    Raises:
        ``bad(message)``: not valid STL, the message in one line (``formula 'G[0,99](d >= ' is not valid STL: ...
            at column 12``)."""
    try:
        return stl.parse(formula)
    except ValueError as exc:
        why = exc.brief if isinstance(exc, stl.STLSyntaxError) else exc
        raise bad(f"formula {formula!r} is not valid STL: {why}") from None


def _check_header(obj: Any, bad: Callable[[str], RolloutFormatError]) -> tuple[Any, str, Any]:
    """A sidecar's format tag and version, and its two required fields (``formula``: valid STL, ``dt_s``: seconds
    > 0); ``bad`` makes the error to raise."""
    if not isinstance(obj, dict):
        raise bad(f"must be a JSON object, got {type(obj).__name__}")
    if obj.get("format", FORMAT_TAG) != FORMAT_TAG:
        raise bad(f"format is {obj.get('format')!r}, expected {FORMAT_TAG!r}")
    version = obj.get("version", FORMAT_VERSION)
    if isinstance(version, bool) or version not in READ_VERSIONS:
        raise bad(
            f"format version {version!r}; this pemviz reads versions {', '.join(map(str, READ_VERSIONS))}: "
            "a newer pemviz wrote the file, upgrade pemviz to read it"
        )
    for key in ("formula", "dt_s"):
        if key not in obj:
            raise bad(f"field {key!r} is missing (required: formula, dt_s)")
    formula = obj["formula"]
    if not isinstance(formula, str):
        raise bad(f"formula must be STL text such as 'G[0,99](d >= 2)', got {formula!r}")
    parse_formula(formula, bad)
    dt = obj["dt_s"]
    if isinstance(dt, bool) or not isinstance(dt, (int, float)) or not (math.isfinite(dt) and dt > 0):
        raise bad(f"dt_s must be a number of seconds > 0, got {dt!r}")
    return version, formula, dt


def _check_plain_fields(obj: Any, bad: Callable[[str], RolloutFormatError]) -> Any:
    """A sidecar's optional counts, names and digests, checked; its ``window_m`` (metres, default 10)."""
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
    return window


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
        if not isinstance(comps, list) or not all(
            isinstance(c, dict) and _is_count(c.get("n")) and isinstance(c.get("sampler", ""), str) for c in comps
        ):
            raise bad(f'{where}.components must be a list of {{"sampler": text, "n": rollouts}}, got {comps!r}')
        if comps and sum(c["n"] for c in comps) != st["n"]:
            raise bad(f"{where}: its components hold {sum(c['n'] for c in comps)} rollouts, not n = {st['n']}")
        bound = st.get("max_weight")
        if bound is not None and not (_is_number(bound) and bound >= 1.0):
            raise bad(f"{where}.max_weight must be a number >= 1 or null, got {bound!r}")
        if not isinstance(st.get("kind", ""), str):
            raise bad(f"{where}.kind must be text, got {st.get('kind')!r}")
        out.append(
            {
                "stage": st["stage"],
                "kind": st.get("kind", ""),
                "n": st["n"],
                "components": [{"sampler": c.get("sampler", ""), "n": c["n"]} for c in comps],
                "max_weight": None if bound is None else float(bound),
            }
        )
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
    if not (
        isinstance(stages, list) and stages and all(_is_count(k) for k in stages) and len(set(stages)) == len(stages)
    ):
        raise bad(f"pooling.stages must be a non-empty list of distinct stage numbers, got {stages!r}")
    if not (
        isinstance(lam, list)
        and len(lam) == len(stages)
        and all(_is_number(x) and x >= 0 for x in lam)
        and abs(math.fsum(lam) - 1.0) <= 1e-9
    ):
        raise bad(f"pooling.stage_weights must be {len(stages)} numbers >= 0 summing to 1, got {lam!r}")
    if not isinstance(rule, str):
        raise bad(f"pooling.rule must be text, got {rule!r}")
    return {"rule": rule, "stages": list(stages), "stage_weights": [float(x) for x in lam]}


SIDECAR_SUFFIX = ".rollouts.json"
"""A rollout file's sidecar is ``NAME.rollouts.json`` beside ``NAME.parquet``: a name no other output suggests (a run's
result document is what ``--json NAME.json`` names). Files written before read back from ``NAME.json`` too."""


def sidecar_path(path: str | os.PathLike[str]) -> Path:
    """``NAME.parquet`` -> ``NAME.rollouts.json``, the sidecar a rollout file is written with."""
    return Path(path).with_suffix(SIDECAR_SUFFIX)


def existing_sidecar(path: str | os.PathLike[str]) -> Path:
    """The sidecar of the rollout file ``path`` that is read: ``NAME.rollouts.json``, or where only that exists the
    ``NAME.json`` of a file written before the sidecar had its own name (:data:`SIDECAR_SUFFIX`)."""
    side, legacy = sidecar_path(path), Path(path).with_suffix(".json")
    return legacy if not side.is_file() and legacy.is_file() else side


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


def json_float(value: Any) -> float | None:
    """The number a sidecar holds, the inverse of how it writes one: a float, or a non-finite one written as text
    (``"-inf"``, ``"inf"``, ``"nan"``); None for None or anything else (a field the sidecar does not have)."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, str) and value.strip().lower() in ("-inf", "inf", "+inf", "nan"):
        return float(value)
    return None


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_stage_counts(meta: RolloutMeta, counts: Mapping[int, list[int]], error: Any) -> None:
    """Check a table's rollouts per stage and component, ``{stage: [rollouts of component 0, 1, ...]}``, against the
    sidecar's ``stages`` (each stage listed, its n and its components' n) and ``pooling`` (each pooled stage held).

    Raises:
        what ``error(message)`` returns (a :class:`RolloutFormatError` naming the file)."""
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


def read_sidecar(path: str | os.PathLike[str]) -> RolloutMeta:
    """The sidecar of the rollout file ``path`` (``NAME.rollouts.json`` beside ``NAME.parquet``, or ``NAME.json``:
    :func:`existing_sidecar`).

    Raises:
        RolloutFormatError: no sidecar, not JSON, or an invalid field."""
    side = existing_sidecar(path)
    if not side.is_file():
        raise RolloutFormatError(
            f"{side}: sidecar not found; a rollout file NAME.parquet needs NAME.rollouts.json (or NAME.json) with at "
            "least "
            f'{{"formula": "G[0,99](d >= 2)", "dt_s": 0.05}} (see pemviz.io.rollout_format)'
        )
    try:
        obj = json.loads(side.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise RolloutFormatError(f"{side}: not a readable JSON file ({exc})") from None
    return RolloutMeta.from_json(obj, str(side))


def proposal_path(path: str | os.PathLike[str]) -> Path:
    """``NAME.parquet`` -> ``NAME.proposal.pt``, the proposal checkpoint written beside a rollout file."""
    return Path(path).with_suffix(".proposal.pt")

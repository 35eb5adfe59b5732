"""What the viser panel knows about a run, built from the engine's events; no viser here.

:class:`RunRecord` is an engine listener (``record(event)``): it keeps the stage results, the proposal
curves, the final estimate, the least-robust rollouts of the whole run (:class:`Trajectory`) and the
event log for the ``.rrd`` export. :func:`scene_positions` turns a rollout's observations back into the
two cars' positions for the 3D scene, and :func:`export_path` / :func:`export_run` write a run into
``recordings/`` without letting a name from the browser escape that folder.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pemviz.config import PRESETS, ConfigError, ExperimentConfig
from pemviz.engine import (
    Event,
    FinalEstimate,
    RolloutsSampled,
    RunCancelled,
    RunFinished,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
)
from pemviz.scenarios.braking import BrakingParams

MAX_RUNS = 3
"""Runs kept side by side for comparison (the oldest is dropped when a fourth starts)."""

N_TRAJECTORIES = 20
"""Least-robust rollouts listed per run."""

QUICK: dict[str, Any] = PRESETS["quick"]
"""The ``quick`` preset (:data:`pemviz.config.PRESETS`): a run of a few seconds on 2 cores, to try the panel."""

PANEL_PRESETS: dict[str, dict[str, Any]] = PRESETS
"""Presets offered in the panel: :data:`pemviz.config.PRESETS`."""

INT_FIELDS = ("n_stages", "n_per_stage", "n_final", "seed", "ce_epochs", "pretrain_rollouts", "pretrain_epochs")
_EXPORT_NAME_OK = re.compile(r"[^A-Za-z0-9._-]")


def config_has(field_name: str) -> bool:
    """Whether :class:`ExperimentConfig` has a field (``sim`` arrives in a later version)."""
    return any(f.name == field_name for f in dataclasses.fields(ExperimentConfig))


def config_from_values(values: dict[str, Any]) -> ExperimentConfig:
    """Build and validate a config from the panel's control values.

    Integer fields given as integral floats (``20.0``) become ints; everything else goes to
    :class:`ExperimentConfig` unchanged, so its validation decides. Keys that the config does not have
    (e.g. ``sim`` before the simulator field exists) are dropped.

    Raises:
        ConfigError: the message of :class:`ExperimentConfig`'s validation (what, the value, allowed).
    """
    known = {f.name for f in dataclasses.fields(ExperimentConfig)}
    fields: dict[str, Any] = {}
    for name, value in values.items():
        if name not in known:
            continue
        if name in INT_FIELDS and isinstance(value, float) and value.is_integer():
            value = int(value)
        if name == "pem" and value in ("", None):
            value = None
        fields[name] = value
    try:
        return ExperimentConfig(**fields)
    except TypeError as exc:  # a wrong field type that __post_init__ did not catch
        raise ConfigError(str(exc)) from None


@dataclass(frozen=True)
class Trajectory:
    """One rollout kept for the panel's list and 3D playback.

    Attributes:
        stage: the stage that sampled it (0 = pretraining, K+1 = final batch).
        index: its row in that stage's batch.
        robustness: under the run's metric (classic: metres; AGM: [-1, 1]).
        log_weight: importance log-weight log p_PEM - log q over T - 1 steps (nats).
        crashed: classic robustness < 0 (the gap dropped below 2 m).
        gap_m, ego_speed_mps, lead_speed_mps: float64 [T] observations (metres, m/s).
        detected: bool [T], the detector's output at each step.
    """

    stage: int
    index: int
    robustness: float
    log_weight: float
    crashed: bool
    gap_m: np.ndarray
    ego_speed_mps: np.ndarray
    lead_speed_mps: np.ndarray
    detected: np.ndarray

    @property
    def key(self) -> str:
        """``s<stage>r<index>``: unique within a run."""
        return f"s{self.stage}r{self.index}"

    @property
    def n_steps(self) -> int:
        return int(self.gap_m.shape[0])


def least_robust(kept: list[Trajectory], event: RolloutsSampled, n: int = N_TRAJECTORIES) -> list[Trajectory]:
    """Merge a stage's rollouts into the kept list; the ``n`` least robust, least first.

    Ties keep the earlier stage / lower index first (a stable sort on robustness).
    """
    batch = event.batch
    if n <= 0 or batch.n == 0:
        return list(kept)
    r = np.asarray(event.robustness, dtype=np.float64)
    take = np.argsort(r, kind="stable")[:n]
    names = batch.observation_names
    cols = {name: names.index(name) for name in ("gap_m", "ego_speed_mps", "lead_speed_mps") if name in names}
    new = []
    for i in take:
        obs = batch.observations[i]
        gap = obs[:, cols["gap_m"]] if "gap_m" in cols else obs[:, 0]
        ego = obs[:, cols["ego_speed_mps"]] if "ego_speed_mps" in cols else np.full(gap.shape, np.nan)
        lead = obs[:, cols["lead_speed_mps"]] if "lead_speed_mps" in cols else np.full(gap.shape, np.nan)
        new.append(
            Trajectory(
                stage=event.stage,
                index=int(i),
                robustness=float(r[i]),
                log_weight=float(event.log_weight[i]),
                crashed=bool(event.failed[i]),
                gap_m=np.array(gap, dtype=np.float64),
                ego_speed_mps=np.array(ego, dtype=np.float64),
                lead_speed_mps=np.array(lead, dtype=np.float64),
                detected=np.array(batch.detected[i], dtype=bool),
            )
        )
    merged = sorted(list(kept) + new, key=lambda t: t.robustness)  # sorted() is stable
    return merged[:n]


def scene_positions(traj: Trajectory, params: BrakingParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Centre x of the ego and of the lead at every step, float64 [T] each (metres; ego starts at 0).

    The ego moves by explicit Euler on its recorded speed, as highway-env's ``Vehicle.step`` does
    (``x[t+1] = x[t] + v[t] * dt``); the lead's rear is ``camera_offset_m`` plus the gap ahead of the
    ego's centre, so ``lead = ego + camera_offset_m + gap_m + lead_length_m / 2``
    (:class:`pemviz.scenarios.braking.BrakingScenario`).
    """
    p = params or BrakingParams()
    v = np.nan_to_num(traj.ego_speed_mps, nan=0.0)
    ego_x = np.concatenate([[0.0], np.cumsum(v[:-1] * p.dt_s)])
    lead_x = ego_x + p.camera_offset_m + traj.gap_m + p.lead_length_m / 2
    return ego_x, lead_x


class RunRecord:
    """One run as the panel shows it; an engine listener (call it with each event).

    Thread-safe: the engine calls it from the worker thread while the panel reads it from viser's
    threads; readers take :attr:`lock` or copy the (replaced, never mutated) lists.
    """

    def __init__(self, run_id: int, config: ExperimentConfig) -> None:
        self.run_id = run_id
        self.config = config
        self.lock = threading.RLock()
        self.status = "starting"
        """``starting`` | ``running`` | ``finished`` | ``cancelled`` | ``failed``."""
        self.message = ""
        self.formula = ""
        self.curve_grid_m = np.zeros(0)
        self.pem_curve = np.zeros(0)
        self.stages: list[StageResult] = []
        self.current_stage: StageStarted | None = None
        self.sampled_current = False
        self.final: FinalEstimate | None = None
        self.trajectories: list[Trajectory] = []
        self.events: list[Event] = []

    @property
    def n_stage_events(self) -> int:
        """Stages the run will report: pretraining, K CE stages and the final batch (adaptive), else 1."""
        cfg = self.config
        if cfg.method != "adaptive":
            return 1
        return cfg.n_stages + (2 if cfg.has_final_batch else 1)

    @property
    def label(self) -> str:
        cfg = self.config
        return f"run {self.run_id}: {cfg.metric}, alpha {cfg.smoothing:g}, sigma {cfg.quantile_level:g}"

    @property
    def done(self) -> bool:
        return self.status in ("finished", "cancelled", "failed")

    def __call__(self, event: Event) -> None:
        with self.lock:
            self.events.append(event)
            if isinstance(event, RunStarted):
                self.status = "running"
                self.formula = event.formula
                self.curve_grid_m = np.asarray(event.curve_grid_m, dtype=np.float64)
                self.pem_curve = np.asarray(event.pem_curve, dtype=np.float64)
            elif isinstance(event, StageStarted):
                self.current_stage = event
                self.sampled_current = False
            elif isinstance(event, RolloutsSampled):
                self.sampled_current = True
                self.trajectories = least_robust(self.trajectories, event)
            elif isinstance(event, StageFinished):
                self.stages = self.stages + [event.result]
            elif isinstance(event, FinalEstimate):
                self.final = event
            elif isinstance(event, RunFinished):
                self.status = "finished"
            elif isinstance(event, RunCancelled):
                self.status = "cancelled"
                self.message = event.reason

    def fail(self, message: str) -> None:
        with self.lock:
            self.status = "failed"
            self.message = message

    def progress(self) -> tuple[float, float]:
        """(run, stage) progress in percent: finished stages of all; 0 / 50 / 100 within a stage
        (started, rollouts sampled, finished)."""
        with self.lock:
            total = self.n_stage_events
            done = len(self.stages)
            if self.status == "finished":
                return 100.0, 100.0
            stage = 0.0
            if self.current_stage is not None and done < total:
                finished_current = bool(self.stages) and self.stages[-1].stage == self.current_stage.stage
                stage = 100.0 if finished_current else (50.0 if self.sampled_current else 5.0)
            return 100.0 * done / max(1, total), stage

    def stage_series(self, name: str) -> dict[int, float]:
        """Stage -> value of ``gamma`` | ``failure_rate`` | ``log10_mu_hat`` | ``nll`` (finite values only)."""
        out = {}
        for res in self.stages:
            e = res.estimate
            value = {
                "gamma": res.gamma,
                "failure_rate": e.n_failures / e.n if e.n else math.nan,
                "log10_mu_hat": e.log10_mu_hat,
                "nll": e.nll_mean,
            }[name]
            if math.isfinite(value):
                out[res.stage] = float(value)
        return out


def sanitize_export_name(name: str) -> str:
    """A recording file name from what a user typed: ``'../x'`` -> ``'x.rrd'``.

    Folders are dropped (only the last path component counts, ``/`` and ``\\`` alike), characters
    other than letters, digits, ``.``, ``_`` and ``-`` become ``_``, leading dots are stripped (no
    hidden files, no ``..``), and ``.rrd`` is appended unless present.

    Raises:
        ValueError: nothing usable is left (e.g. ``''``, ``'..'``, ``'/'``).
    """
    base = str(name).replace("\\", "/").split("/")[-1].strip()
    base = _EXPORT_NAME_OK.sub("_", base).lstrip(".")
    if base.lower().endswith(".rrd"):
        base = base[:-4]
    base = base.rstrip(".")
    if not base.strip("_-"):
        raise ValueError(
            f"export name {name!r} is invalid: use letters, digits, '.', '_' and '-' (a file name, no folders)"
        )
    return base[:120] + ".rrd"


def export_path(recordings_dir: str | os.PathLike, name: str) -> Path:
    """``recordings_dir / sanitize_export_name(name)``, checked to lie inside ``recordings_dir``.

    Raises:
        ValueError: an unusable name, or a path that would leave ``recordings_dir``.
    """
    root = Path(recordings_dir).resolve()
    path = root / sanitize_export_name(name)
    if path.resolve().parent != root:  # e.g. a symlink planted under the name
        raise ValueError(f"export name {name!r} would write outside {root}")
    return path


def export_run(record: RunRecord, path: Path) -> Path:
    """Replay a run's events into a rerun recording at ``path`` (written to a temp file, then moved).

    Returns:
        ``path``. Nothing is left at ``path`` (or beside it) if writing fails.
    """
    from pemviz.sinks.recording import RerunSink

    with record.lock:
        events = list(record.events)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.{threading.get_ident()}.tmp.rrd")
    leftovers = (tmp, tmp.with_name(tmp.name + ".partial"))
    try:
        sink = RerunSink.to_file(tmp)
        try:
            for event in events:
                sink(event)
        finally:
            sink.close()
        os.replace(tmp, path)
    except BaseException:
        for leftover in leftovers:
            leftover.unlink(missing_ok=True)
        raise
    return path

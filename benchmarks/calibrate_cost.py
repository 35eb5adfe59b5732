"""Calibrate the cost model of :mod:`pemviz.engine.cost` (the panel's "about N s", the time left in the console
and panel).

    python benchmarks/calibrate_cost.py              # predicted vs measured seconds of each run, and the ratio
    python benchmarks/calibrate_cost.py --fit        # also the constants fitted to these runs, ready to paste
    python benchmarks/calibrate_cost.py --repeat 3   # the median of 3 runs of each configuration
    python benchmarks/calibrate_cost.py --tilt --repeat 3   # the tilt's constants from the cut-in's rollouts
    python benchmarks/calibrate_cost.py --parts crossing     # a scene's cost parts against braking's, in CPU seconds
    python benchmarks/calibrate_cost.py --probe braking crossing cut-in --repeat 3   # each scene's ``probe`` part
    python benchmarks/calibrate_cost.py --speed braking cut-in --repeat 3   # S and the crowding against the runs

What it does: runs a handful of configurations (the default, ``--preset quick``, N = 1000, plain Monte Carlo with
N = 10,000, ``--preset paper``, the agm run of the panel's screenshots, a small highway-env run) as the panel runs
them (:class:`pemviz.engine.experiment.Experiment` with a :class:`pemviz.app.runs.PanelRun` listener, torch on one
thread), after a warm-up run, and prints per configuration the seconds :func:`pemviz.engine.cost.run_cost` predicts, the
seconds the run took and their ratio (predicted / measured). With ``--fit`` it also records each stage (simulating: from
its start to its rollouts; after: the rest) and each proposal fit (its rows, epochs and seconds, by wrapping
:func:`pemviz.core.sampling.fit_proposal` where :mod:`pemviz.estimators.ce_fit` calls it), fits every constant of
:class:`pemviz.engine.cost.CostConstants` to them by least squares, scales the simulating and the fitting constants so
that the runs' predicted totals meet the measured ones, and prints the constants and the table again with them. The
whole takes under 2 minutes on 2 cores. Measure on a quiet machine: `uptime` beside the figures.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.app.runs import PanelRun  # noqa: E402
from pemviz.config import ExperimentConfig  # noqa: E402
from pemviz.engine import cost  # noqa: E402
from pemviz.engine import experiment as engine  # noqa: E402
from pemviz.engine.resources import torch_threads  # noqa: E402
from pemviz.estimators import ce_fit, run_plan  # noqa: E402
from pemviz.presets import PRESETS  # noqa: E402
from pemviz.scenarios.problems import problem_for  # noqa: E402
from pemviz.sinks import Sink  # noqa: E402

CONFIGS: dict[str, tuple[str, dict]] = {
    "default": ("state-ce", {}),
    "quick preset": ("quick", {}),
    "N = 1000": ("state-ce", {"n_per_stage": 1000}),
    "method mc N = 10000": ("state-ce", {"method": "mc", "n_per_stage": 10_000}),
    "paper preset": ("paper", {}),
    "metric agm alpha 0.2 sigma 0.9": ("state-ce", {"metric": "agm", "smoothing": 0.2, "quantile_level": 0.9}),
    "highway-env mc N = 100": ("state-ce", {"sim": "highway-env", "method": "mc", "n_per_stage": 100}),
}
"""name -> (preset, settings over it): the configurations measured."""


@dataclass
class StageRecord:
    """One stage as it ran: kind, rollouts, seconds simulating (start to rollouts) and after (to its end), and the
    proposal fits inside it as (rows, epochs run, seconds)."""

    kind: str
    stage: int
    n: int
    simulate_s: float = math.nan
    after_s: float = math.nan
    fits: list[tuple[int, int, float]] = field(default_factory=list)


class Recorder(Sink):
    """Times each stage of a run (see :class:`StageRecord`)."""

    def __init__(self) -> None:
        self.stages: list[StageRecord] = []
        self._t0 = self._t1 = 0.0

    def on_stage_started(self, event) -> None:
        self._t0 = CLOCK()
        self.stages.append(StageRecord(event.kind, event.stage, event.n_rollouts))

    def on_rollouts_sampled(self, event) -> None:
        self._t1 = CLOCK()
        self.stages[-1].n = event.n_rollouts
        self.stages[-1].simulate_s = self._t1 - self._t0

    def on_stage_finished(self, event) -> None:
        self.stages[-1].after_s = CLOCK() - self._t1


RECORDER: Recorder | None = None

CLOCK = time.perf_counter
"""The clock of the measurements: wall seconds, what the console's and the panel's estimates promise. (CPU seconds, used
before, are about twice the wall time of a default run on 2 cores: its proposal fits' products run on every BLAS
thread; they also vary less with other work on the machine, so measure on a quiet one.)"""


def _timed_fit(original):
    def fit_proposal(proposal, inputs, objective, epochs, *args, **kwargs):
        t0 = CLOCK()
        losses = original(proposal, inputs, objective, epochs, *args, **kwargs)
        if RECORDER is not None and RECORDER.stages:
            RECORDER.stages[-1].fits.append((int(inputs.shape[0]), len(losses), CLOCK() - t0))
        return losses

    return fit_proposal


ce_fit.fit_proposal = _timed_fit(ce_fit.fit_proposal)


def config_of(preset: str, settings: dict) -> ExperimentConfig:
    return ExperimentConfig.of(**{**PRESETS[preset], **settings})


def measure(cfg: ExperimentConfig, panel: bool = True) -> tuple[float, float, Recorder]:
    """:data:`CLOCK` (wall) and CPU seconds of one run as the panel runs it (``panel`` False: with no listener but the
    records, as ``pemviz run --no-record`` apart from its console lines; the problem loaded before the clocks start),
    and its stage records (:data:`CLOCK` seconds)."""
    global RECORDER
    problem = problem_for(cfg)
    RECORDER = Recorder()
    with torch_threads(1):
        t0, c0 = CLOCK(), time.process_time()
        engine.Experiment(cfg, [PanelRun(0, cfg), RECORDER] if panel else [RECORDER], problem=problem).run()
        seconds, cpu = CLOCK() - t0, time.process_time() - c0
    recorder, RECORDER = RECORDER, None
    return seconds, cpu, recorder


def predicted_s(cfg: ExperimentConfig, constants: cost.CostConstants) -> float:
    return cost.run_cost(cfg, run_plan(cfg), c=constants).seconds


def table(rows: list[tuple[str, ExperimentConfig, float]], constants: cost.CostConstants, title: str) -> float:
    """Print config, predicted s, measured s, ratio; returns the largest |ratio - 1|."""
    print(f"\n{title}")
    print(f"{'config':<36} {'predicted s':>11} {'measured s':>10} {'ratio':>6}   (measured: wall seconds)")
    worst = 0.0
    for name, cfg, measured in rows:
        p = predicted_s(cfg, constants)
        worst = max(worst, abs(p / measured - 1.0))
        print(f"{name:<36} {p:>11.2f} {measured:>10.2f} {p / measured:>6.2f}")
    print(f"largest |predicted / measured - 1| = {worst:.2f}")
    return worst


def _lstsq(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Least squares with non-negative results (a negative constant is set to 0 and the rest fitted again)."""
    w = np.ones(len(y)) if w is None else w
    keep = np.ones(x.shape[1], bool)
    while True:
        beta = np.zeros(x.shape[1])
        beta[keep] = np.linalg.lstsq(x[:, keep] * w[:, None], y * w, rcond=None)[0]
        if (beta >= 0).all() or not keep.any():
            return np.maximum(beta, 0.0)
        keep &= beta > 0


def fit_constants(runs: list[tuple[ExperimentConfig, Recorder]], n_steps: int = cost.N_STEPS) -> cost.CostConstants:
    """Every constant of :class:`pemviz.engine.cost.CostConstants` fitted to the stage and fit records of ``runs``."""
    c0 = cost.COST
    # simulating: T x (a_pem [the PEM draws] + a_proposal [a proposal draws] + (b_sim + b_proposal [a proposal
    # draws]) x n)
    sims = sorted({cfg.sim for cfg, _ in runs})
    x, y = [], []
    for cfg, rec in runs:
        for s in rec.stages:
            proposal = cfg.method == "adaptive" and s.kind in ("ce", "final")
            x.append(
                [n_steps * (not proposal), n_steps * proposal, n_steps * s.n * proposal]
                + [n_steps * s.n * (cfg.sim == m) for m in sims]
            )
            y.append(s.simulate_s)
    sim = _lstsq(np.array(x, float), np.array(y), 1.0 / np.maximum(np.array(y), 1e-3))  # relative errors
    # after the rollouts: epochs x (c + d x rows) + e x rows + f (per stage)
    x, y = [], []
    for _cfg, rec in runs:
        for s in rec.stages:
            rows = sum(r for r, _, _ in s.fits)
            epochs = sum(e for _, e, _ in s.fits)
            x.append([epochs, sum(r * e for r, e, _ in s.fits), rows, 1.0])
            y.append(s.after_s)
    after = _lstsq(np.array(x, float), np.array(y), 1.0 / np.sqrt(np.maximum(np.array(y), 1e-2)))
    # the rows of the fits: per pretraining rollout; of CE stage k, P (N / 100)^gamma (1 - exp(-(k - 1) / tau)),
    # fitted in log space over a grid of gamma and tau; the share of epochs the early-stopped fits run
    pretrain, ce, share = {}, {}, []
    for cfg, rec in runs:
        for s in rec.stages:
            for rows, epochs, _ in s.fits:
                if s.kind == "pretrain":
                    pretrain.setdefault(cfg.adaptive.proposal_inputs, []).append(rows / s.n)
                elif s.kind == "ce":
                    if s.stage > 1:
                        ce.setdefault(cfg.adaptive.proposal_inputs, []).append((s.stage, s.n, rows))
                    if cfg.adaptive.fit_tolerance is not None and cfg.adaptive.fit == "adam":
                        share.append(epochs / cfg.adaptive.ce_epochs)
    best = (math.inf, c0.ce_rows_exponent, c0.ce_rows_stages)
    for gamma in np.linspace(0.0, 0.6, 31):
        for tau in np.linspace(0.3, 20.0, 198):
            sse = 0.0
            for points in ce.values():
                k, n, rows = (np.array(v, float) for v in zip(*points, strict=False))
                resid = np.log(rows) - gamma * np.log(n / 100.0) - np.log1p(-np.exp(-(k - 1) / tau))
                sse += float(np.sum((resid - resid.mean()) ** 2))
            best = min(best, (sse, float(gamma), float(tau)))
    _, exponent, tau = best
    ce_rows = {}
    for inputs, points in ce.items():  # the plateau that gives the rows' sum (the cost is linear in the rows)
        k, n, rows = (np.array(v, float) for v in zip(*points, strict=False))
        ce_rows[inputs] = float(rows.sum() / np.sum((n / 100.0) ** exponent * -np.expm1(-(k - 1) / tau)))
    return cost.CostConstants(
        pem_step_s=float(sim[0]),
        proposal_step_s=float(sim[1]),
        rollout_step_s={**c0.rollout_step_s, **{m: float(b) for m, b in zip(sims, sim[3:], strict=False)}},
        proposal_rollout_step_s=float(sim[2]),
        stage_s=float(after[3]),
        epoch_s=float(after[0]),
        row_epoch_s=float(after[1]),
        row_s=float(after[2]),
        pretrain_rows={**c0.pretrain_rows, **{k: float(np.mean(v)) for k, v in pretrain.items()}},
        ce_rows={**c0.ce_rows, **ce_rows},
        ce_rows_exponent=exponent,
        ce_rows_stages=tau,
        early_stop_share=float(np.mean(share)) if share else c0.early_stop_share,
        ams_rollouts=c0.ams_rollouts,
    )


def scale_to_totals(c: cost.CostConstants, rows: list[tuple[str, ExperimentConfig, float]]) -> cost.CostConstants:
    """``c`` with its simulating and its after-the-rollouts constants each scaled by the factor (least squares on
    the relative errors of the runs' totals) that makes the predicted totals of ``rows`` meet the measured ones: the
    stage-by-stage fits leave the parts' shapes, the totals set their sizes."""
    parts = []
    for _, cfg, measured in rows:
        costs = cost.plan_costs(cfg, run_plan(cfg), c=c).values()
        parts.append([sum(x.simulate_s for x in costs) / measured, sum(x.after_s for x in costs) / measured])
    a, b = _lstsq(np.array(parts), np.ones(len(parts)))
    a, b = (a or 1.0), (b or 1.0)
    return replace(
        c,
        pem_step_s=c.pem_step_s * a,
        proposal_step_s=c.proposal_step_s * a,
        rollout_step_s={k: v * a for k, v in c.rollout_step_s.items()},
        proposal_rollout_step_s=c.proposal_rollout_step_s * a,
        stage_s=c.stage_s * b,
        epoch_s=c.epoch_s * b,
        row_epoch_s=c.row_epoch_s * b,
        row_s=c.row_s * b,
    )


def literal(c: cost.CostConstants, measured: str) -> str:
    """``COST = CostConstants(...)`` to paste into pemviz/engine/cost.py."""

    def g(v):
        return "{" + ", ".join(f'"{k}": {g(x)}' for k, x in v.items()) + "}" if isinstance(v, dict) else f"{v:.3g}"

    parts = [f"    {name}={g(getattr(c, name))}," for name in c.__dataclass_fields__ if name != "measured"]
    return "COST = CostConstants(\n" + "\n".join(parts) + f'\n    measured="{measured}",\n)'


def calibrate_tilt(repeat: int) -> None:
    """The tilt's two constants (``tilt_rollouts``, ``tilt_solve_s``) from per-rollout costs measured in one process,
    in CPU seconds (the machine's load cancels: every part is the same kind of work): plain cut-in rollouts (an
    ``mc`` run of 20,000), then a default cut-in tilt run with its solve and its draws timed inside
    (:meth:`pemviz.scenarios.cut_in.tilt.CutInTilt.solve`, ``draw``; the rest is its weights and estimate). A tilted
    rollout costs (draw + rest) in the model's seconds of plain cut-in rollouts over the model's seconds of as many
    plain rollouts held whole (as the tilt's batch is); the solve, its CPU seconds in the model's seconds of plain
    cut-in rollouts (:func:`pemviz.engine.cost.stage_cost`), priced as the engine draws them: streamed (the
    cut-in streams above 4,000 rollouts), at :attr:`pemviz.engine.cost.CostConstants.streamed_share` of a held
    batch's. Both constants are then in the held rollouts' seconds the model prices the tilt's batch at."""
    import functools

    from pemviz.scenarios.cut_in import tilt as cut_in_tilt

    parts: dict[str, float] = {}

    def timed(name, f):
        @functools.wraps(f)
        def wrapper(*a, **k):
            c0 = time.process_time()
            try:
                return f(*a, **k)
            finally:
                parts[name] = parts.get(name, 0.0) + time.process_time() - c0

        return wrapper

    cut_in_tilt.CutInTilt.solve = timed("solve", cut_in_tilt.CutInTilt.solve)
    cut_in_tilt.CutInTilt.draw = timed("draw", cut_in_tilt.CutInTilt.draw)
    plain_cfg = ExperimentConfig.of(scenario="cut-in", method="mc", n_per_stage=20_000)
    tilt_cfg = ExperimentConfig.of(scenario="cut-in", method="tilt", n_per_stage=7_280)
    problem = problem_for(plain_cfg)
    n_steps = problem.n_steps or cost.N_STEPS
    # the plain rollouts as the engine draws them: streamed above the scene's own threshold (4,000 five-car rollouts)
    above = engine.stream_above(plain_cfg, problem.n_objects)
    plain_model = cost.stage_cost(plain_cfg, "final", 20_000, n_steps, model="plain", stream_above=above).simulate_s
    # the tilt's batch is held whole: its rollouts are priced as held plain ones (no streamed share)
    held = cost.stage_cost(plain_cfg, "final", 7_280, n_steps, model="plain", stream_above=7_280).simulate_s
    rollouts, solves = [], []
    for _ in range(repeat):
        _, plain_cpu, _ = measure(plain_cfg, panel=False)
        cut_in_tilt._SOLVED.clear()  # a fresh solve, as a new process's run
        parts.clear()
        _, tilt_cpu, _ = measure(tilt_cfg, panel=False)
        solve, draw = parts.get("solve", 0.0), parts.get("draw", 0.0)
        speed = plain_cpu / plain_model  # CPU seconds per model second, as the plain rollouts read it
        rollouts.append((tilt_cpu - solve) / speed / held)
        solves.append(solve / speed)
        print(
            f"  CPU s: 20,000 plain cut-in rollouts {plain_cpu:.2f} (model {plain_model:.2f}); a default tilt run "
            f"{tilt_cpu:.2f}: solve {solve:.2f}, draw {draw:.2f}, weights and the rest {tilt_cpu - solve - draw:.2f}; "
            f"tilt_rollouts {rollouts[-1]:.2f}, tilt_solve_s {solves[-1]:.2f} (now {cost.COST.tilt_rollouts}, "
            f"{cost.COST.tilt_solve_s})",
            flush=True,
        )
    print(f"median: tilt_rollouts={statistics.median(rollouts):.2f}, tilt_solve_s={statistics.median(solves):.2f}")


def part_seconds(argv: list[str]) -> dict[str, list[float]]:
    """CPU seconds and the model's seconds (:func:`pemviz.engine.cost.stage_cost` with the scene's parts left out) per
    part of the stages of one ``pemviz run`` of ``argv`` in this process: ``simulate:`` + the stage's kind, ``after:``
    + its kind."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.scenarios.registry import problem_for as registered_problem
    from pemviz.settings import SCENARIO_COST_PARTS

    cfg = config_from_args(build_parser("run").parse_args(argv))
    problem = registered_problem(cfg)
    n_steps = problem.n_steps or cost.N_STEPS
    parts: dict[str, list[float]] = {}
    marks: dict[str, float] = {}

    class PartClock(Sink):
        def on_stage_started(self, event) -> None:
            marks["start"], marks["kind"], marks["stage"] = time.process_time(), event.kind, event.stage

        def on_rollouts_sampled(self, event) -> None:
            marks["sampled"], marks["n"] = time.process_time(), event.n_rollouts

        def on_stage_finished(self, event) -> None:
            declared = SCENARIO_COST_PARTS.pop(cfg.scenario, None)  # the model as the reference prices it
            try:
                m = cost.stage_cost(cfg, str(marks["kind"]), int(marks["n"]), n_steps, stage=int(marks["stage"]))
            finally:
                if declared is not None:
                    SCENARIO_COST_PARTS[cfg.scenario] = declared
            now = time.process_time()
            for part, cpu, model in (
                (f"simulate:{marks['kind']}", marks["sampled"] - marks["start"], m.simulate_s),
                (f"after:{marks['kind']}", now - marks["sampled"], m.after_s),
            ):
                row = parts.setdefault(part, [0.0, 0.0])
                row[0] += cpu
                row[1] += model

    experiment = engine.Experiment(cfg, problem=problem)
    experiment.listeners[:0] = [PartClock()]
    with torch_threads(1, blas=1):
        experiment.run()
    return parts


def calibrate_parts(scene: str, repeat: int) -> None:
    """A scene's cost parts (:attr:`pemviz.scenarios.registry.Scenario.cost_parts`): the CPU seconds of each part of
    its default run's planned stages (``--plain-fallback 0 --retry-factor 0``) over the model's, divided by the same
    of braking's default run in the same process just before (the machine's speed cancels): ``simulate:ce`` gives
    ``step`` (its batches of 100 are mostly the fixed cost of a step), ``after:ce`` gives ``fit``. The first run of
    each is a warm-up (imports, torch)."""
    braking = ["run", "--no-record"]
    other = ["run", "--scenario", scene, "--no-record", "--plain-fallback", "0", "--retry-factor", "0"]
    part_seconds(braking), part_seconds(other)
    for _ in range(repeat):
        base, seen = part_seconds(braking), part_seconds(other)
        ratios = {
            k: (cpu / model) / (base[k][0] / base[k][1])
            for k, (cpu, model) in seen.items()
            if k in base and model > 0 and base[k][1] > 0 and base[k][0] > 0
        }
        print(
            f"  {scene} over braking, CPU / model per part: "
            + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items())
            + f" (load average {os.getloadavg()[0]:.1f})",
            flush=True,
        )


PROBE_RUNS = {
    "braking": ["run", "--no-record"],
    "crossing": ["run", "--scenario", "crossing", "--no-record", "--plain-fallback", "0", "--retry-factor", "0"],
    "cut-in": ["run", "--scenario", "cut-in", "--no-record"],
    "cut-in-mc": ["run", "--scenario", "cut-in", "--method", "mc", "--n", "40000", "--workers", "1", "--no-record"],
}
"""Scene -> the run whose CPU seconds over the model's its pilot is set against (``--probe``): its default's planned
stages; ``cut-in-mc``: the cut-in's plain rollouts streamed block by block in one process, as plain Monte Carlo of a
million draws them (its tilt's constants are measured against them, ``--tilt``: the two readings should agree)."""


def calibrate_probe(scenes: list[str], repeat: int) -> None:
    """Each scene's ``probe`` part (:attr:`pemviz.scenarios.registry.Scenario.cost_parts`,
    :func:`pemviz.engine.cost.pilot_seconds`): the pilot of :func:`pemviz.engine.cost.pilot_speed` (its CPU
    seconds over the model's, the part left out), over the CPU seconds of the scene's default run (:data:`PROBE_RUNS`)
    over its model's, the pilot just before the run in the same process (the machine's speed cancels). A fresh
    process per reading, as ``pemviz run`` (torch's import counted where the model counts it)."""
    import subprocess

    code = (
        "import sys, time; from pemviz.cli import build_parser; from pemviz.commands.run import config_from_args;"
        "from pemviz.engine import cost, experiment as engine; from pemviz.engine.resources import torch_threads;"
        "from pemviz.estimators import run_plan; from pemviz.scenarios.registry import problem_for;"
        "from pemviz.settings import SCENARIO_COST_PARTS as P;"
        "cfg = config_from_args(build_parser('run').parse_args(sys.argv[1:])); pb = problem_for(cfg);"
        "T = pb.n_steps or cost.N_STEPS; share = P.get(cfg.scenario, {}).get('probe', cost.COST.probe_share);"
        "raw = cost.pilot_speed(cfg, engine.scene_pilot(pb), T) * share;"
        "model = cost.run_cost(cfg, run_plan(cfg), T, look_ahead_s=pb.look_ahead_s).seconds;"
        "ex = engine.Experiment(cfg, problem=pb); c0 = time.process_time();"
        "exec('with torch_threads(1, blas=1): ex.run()'); cpu = time.process_time() - c0;"
        "print(f'{raw:.3f} {cpu:.3f} {model:.3f} {raw / (cpu / model):.3f}')"
    )
    for scene in scenes:
        shares = []
        for _ in range(repeat):
            out = subprocess.run(
                [sys.executable, "-c", code, *PROBE_RUNS[scene]], capture_output=True, text=True, check=True
            ).stdout.split()
            raw, cpu, model, share = map(float, out[-4:])
            shares.append(share)
            print(
                f"  {scene}: pilot {raw:.2f} times the model's, the run {cpu:.2f} CPU s for {model:.2f} model s "
                f"({cpu / model:.2f} times): probe {share:.3f} (load average {os.getloadavg()[0]:.1f})",
                flush=True,
            )
        print(f"{scene}: probe {statistics.median(shares):.3g} (median of {len(shares)})")


SPEED_CODE = (
    "import sys, time; from pemviz.cli import build_parser; from pemviz.commands.run import config_from_args;"
    "from pemviz.engine import cost, experiment as engine; from pemviz.engine import resources as r;"
    "from pemviz.estimators import run_plan; from pemviz.scenarios.registry import problem_for;"
    "cfg = config_from_args(build_parser('run').parse_args(sys.argv[1:]));"
    "exec('with r.torch_threads(1, blas=1):\\n t0 = r.tasks_now(); pb = problem_for(cfg); T = pb.n_steps or 100;"
    " s = cost.pilot_speed(cfg, engine.scene_pilot(pb), T); load = r.load_slowdown(since=t0, speed=s);"
    " model = cost.run_cost(cfg, run_plan(cfg), T, look_ahead_s=pb.look_ahead_s, speed=s).seconds;"
    " ex = engine.Experiment(cfg, problem=pb); c0, w0 = time.process_time(), time.perf_counter(); ex.run();"
    " cpu, wall = time.process_time() - c0, time.perf_counter() - w0');"
    "print(f'{s:.3f} {load / s:.3f} {model:.3f} {cpu:.3f} {wall:.3f}')"
)
"""One ``pemviz run`` of ``sys.argv[1:]`` as the command runs it, printing S (the pilot), the crowding read at its
start, the model's seconds, and the run's CPU and wall seconds."""


def check_speed(scenes: list[str], repeat: int) -> None:
    """Where a run's first estimate errs (``--speed``): the pilot's S against the run's CPU seconds over the model's,
    and the crowding read before the run against its wall over its CPU seconds, a fresh process per reading."""
    import subprocess

    for scene in scenes:
        for _ in range(repeat):
            out = subprocess.run(
                [sys.executable, "-c", SPEED_CODE, *PROBE_RUNS[scene]], capture_output=True, text=True, check=True
            ).stdout.split()
            speed, crowd, model, cpu, wall = map(float, out[-5:])
            print(
                f"  {scene}: S {speed:.2f} against the run's CPU / model {cpu / model:.2f}; crowding {crowd:.2f} "
                f"against its wall / CPU {wall / cpu:.2f}; estimate {model * speed * crowd:.1f} s, wall {wall:.1f} s "
                f"(load average {os.getloadavg()[0]:.1f})",
                flush=True,
            )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", action="store_true", help="fit the constants to these runs and print them")
    ap.add_argument("--repeat", type=int, default=1, help="runs per configuration; the median counts (default 1)")
    ap.add_argument("--only", default=None, help="comma-separated names of CONFIGS to run (default all)")
    ap.add_argument("--tilt", action="store_true", help="measure the tilt's constants (the cut-in's) only")
    ap.add_argument("--parts", metavar="SCENE", default=None, help="measure a scene's cost parts against braking's")
    ap.add_argument("--probe", nargs="+", choices=list(PROBE_RUNS), help="measure each scene's probe part")
    ap.add_argument("--speed", nargs="+", choices=list(PROBE_RUNS), help="the pilot and the crowding against runs")
    args = ap.parse_args()
    if args.probe:
        calibrate_probe(args.probe, args.repeat)
        return 0
    if args.speed:
        check_speed(args.speed, args.repeat)
        return 0
    if args.tilt:
        calibrate_tilt(args.repeat)
        return 0
    if args.parts is not None:
        calibrate_parts(args.parts, args.repeat)
        return 0
    names = list(CONFIGS) if args.only is None else [n.strip() for n in args.only.split(",")]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    print(
        f"pemviz cost model: {len(names)} configurations x {args.repeat}, load average {load:.2f}, "
        f"{os.cpu_count()} CPUs; constants measured: {cost.COST.measured}"
    )
    for warm in (
        ExperimentConfig.of(**{**PRESETS["quick"], "n_stages": 2, "n_per_stage": 40}),
        ExperimentConfig.of(method="mc", sim="highway-env", n_per_stage=4),
    ):
        measure(warm)  # imports, the first network, the first highway-env simulator
    rows, records = [], []
    t_all = time.perf_counter()
    for name in names:
        cfg = config_of(*CONFIGS[name])
        times, cpus = [], []
        for _ in range(args.repeat):
            seconds, cpu, rec = measure(cfg)
            times.append(seconds)
            cpus.append(cpu)
            records.append((cfg, rec))
        rows.append((name, cfg, statistics.median(times)))
        print(
            f"  {name}: wall {', '.join(f'{t:.2f}' for t in times)} s, CPU {', '.join(f'{t:.2f}' for t in cpus)} s",
            flush=True,
        )
    table(rows, cost.COST, "with the constants of pemviz.engine.cost.COST")
    if args.fit:
        fitted = scale_to_totals(fit_constants(records), rows)
        stamp = time.strftime("%Y-%m-%d")
        measured = (
            f"{stamp}, benchmarks/calibrate_cost.py --fit --repeat {args.repeat}, {os.cpu_count()} cores, "
            f"load average {load:.1f}"
        )
        fitted = replace(fitted, measured=measured)
        table(rows, fitted, "with the constants fitted to these runs")
        print("\n" + literal(fitted, measured))
    print(f"\n{time.perf_counter() - t_all:.0f} s in all (load average now {os.getloadavg()[0]:.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

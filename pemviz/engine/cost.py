"""What a run costs: its simulations, its largest batch in memory, and its seconds, before it starts and while it runs.

The seconds follow what a run does (:mod:`pemviz.engine`, :mod:`pemviz.estimators.cross_entropy`,
:mod:`pemviz.estimators.ce_fit`), stage by stage of its :class:`~pemviz.core.plan.RunPlan`:

- simulating a batch of n rollouts of T steps: T x (a fixed cost per step of each block of the batch, larger when a
  proposal network and its mixture decide the detections than when the PEM alone does, times the scene's ``step``
  part, + a cost per rollout and step of the simulator, times the cost factor the scenario declares:
  :data:`pemviz.settings.SCENARIO_COST_FACTORS`, :data:`pemviz.settings.SCENARIO_COST_PARTS`);
- after the rollouts, a fixed cost per stage (robustness, estimate, listeners) and, in pretraining and each
  cross-entropy stage, the proposal's fit: epochs x (a fixed cost per Adam epoch + a cost per fitted row and epoch) +
  a cost per fitted row (gathering and weighing the pool). The rows are the distinct fitted steps, at most
  ``fit_rows``: per pretraining rollout a fixed number; per CE stage k a number that grows with k towards a plateau,
  as failures are pooled from the failure level on, and slowly with N. A fit with ``fit_tolerance`` stops early,
  on average after a share of ``ce_epochs`` (of ``pretrain_epochs`` in pretraining). The fit costs the scene's
  ``fit`` part times that; a scene whose proposal fits on torch adds torch's import to the first pretraining of a
  process that has not imported it.

:data:`COST` holds the constants, measured by ``python benchmarks/calibrate_cost.py`` (which prints the predicted and
measured seconds of a handful of runs and, with ``--fit``, the constants fitted to them). :class:`StageClock
<pemviz.sinks.StageClock>` scales the prediction by what the run has measured so far, for the whole run's time
left. No numpy, no torch."""

from __future__ import annotations

import math
import statistics
import sys
from dataclasses import dataclass, field
from typing import Any

from pemviz.config import ExperimentConfig
from pemviz.core.plan import RunPlan
from pemviz.engine.resources import BASE_BYTES, POOL_BLOCK, LoadReading, pool_workers, run_memory, usable_cpus
from pemviz.methods.adaptive import STATE_INPUTS
from pemviz.methods.ams import AMS_STAGE
from pemviz.settings import SCENARIO_COST_FACTORS, SCENARIO_COST_PARTS

N_STEPS = 100
"""T, the steps of a rollout, where the caller states no problem's horizon: the default of the model (e.g. the braking
scenario's 100 steps, on which the constants were measured)."""

CONFIRM_SIMULATIONS = 500_000
CONFIRM_SECONDS = 120.0
CONFIRM_BYTES = 2 * 1024**3


@dataclass(frozen=True)
class CostConstants:
    """The seconds of each part of a run, on one core with torch on one thread (as the panel and ``pemviz run`` run).

    Attributes:
        pem_step_s: per time step of a batch whose detections the PEM (or a fixed detector) decides, seconds.
        proposal_step_s: per time step of a batch drawn by the proposal (its network and mixture), seconds.
        rollout_step_s: per rollout and time step of each simulator (:data:`pemviz.settings.SIMULATORS`), seconds.
        proposal_rollout_step_s: per rollout and time step more when a proposal draws the batch, seconds.
        stage_s: per stage after its rollouts, besides the fit (robustness, estimate, listeners), seconds.
        epoch_s: per Adam epoch of a fit, whatever its rows, seconds.
        row_epoch_s: per fitted row and Adam epoch, seconds.
        row_s: per fitted row of a fit, outside the epochs (gathering and weighing the failures), seconds.
        pretrain_rows: distinct fitted rows per pretraining rollout, by :data:`pemviz.methods.adaptive.PROPOSAL_INPUTS`.
        ce_rows: distinct fitted rows of a late CE stage's fit at N = 100 (the plateau), by proposal inputs.
        ce_rows_exponent: the CE rows grow as (N / 100) to this power.
        ce_rows_stages: stage k's rows are the plateau times 1 - exp(-(k - 1) / this) (stage 1 fits the few rollouts
            of pretraining's proposal; the pool of failures grows over the next stages).
        early_stop_share: the mean share of ``ce_epochs`` a CE fit with ``fit_tolerance`` runs before it stops.
        pretrain_stop_share: the same of ``pretrain_epochs`` in pretraining.
        torch_import_s: the seconds of importing torch (a scene whose proposal fits on torch, in a process that has
            not imported it yet, on its first pretraining).
        streamed_share: a rollout's seconds in a batch streamed chunk by chunk (above ``stream_above``) over its
            seconds in a batch held whole (whose arrays outgrow the caches).
        ams_rollouts: rollout-equivalents AMS simulates per particle (its continuations), about.
        tilt_rollouts: the seconds of a rollout of ``method = "tilt"`` in plain rollouts' of its scene held whole
            (its draw, its look-aheads and its weights; the tilt's batch is held whole), about.
        tilt_solve_s: the seconds of the tilt's solve, once a run (on its first stage), about.
        probe_share: a pilot of the reference scene's plain rollouts' CPU seconds over the model's where its run takes
            the model's (:func:`pilot_seconds`; another scene may declare its own ``probe`` part).
        pool_share: a pooled batch's CPU seconds over the same rollouts' in one process (the workers' start, the
            blocks' hand-off, the run's process collecting them while they simulate); the workers share the CPUs
            as the load allows (:meth:`pemviz.engine.resources.LoadReading.pool_speedup`).
        measured: when, where and how the constants were measured."""

    pem_step_s: float
    proposal_step_s: float
    rollout_step_s: dict[str, float]
    proposal_rollout_step_s: float
    stage_s: float
    epoch_s: float
    row_epoch_s: float
    row_s: float
    pretrain_rows: dict[str, float]
    ce_rows: dict[str, float]
    ce_rows_exponent: float
    ce_rows_stages: float
    early_stop_share: float
    pretrain_stop_share: float = 1.0
    torch_import_s: float = 0.0
    streamed_share: float = 1.0
    ams_rollouts: float = 5.0
    tilt_rollouts: float = 6.0
    tilt_solve_s: float = 4.0
    probe_share: float = 1.0
    pool_share: float = 1.0
    measured: str = field(default="", compare=False)


COST = CostConstants(
    pem_step_s=7.19e-05,
    proposal_step_s=0.00035,
    rollout_step_s={"batched": 3.53e-07, "highway-env": 3.59e-05},
    proposal_rollout_step_s=2e-08,
    stage_s=0.000617,
    epoch_s=9.86e-05,
    row_epoch_s=2.98e-07,
    row_s=8.16e-06,
    pretrain_rows={STATE_INPUTS: 12.2, "gap": 0.91},
    ce_rows={STATE_INPUTS: 2.21e03, "gap": 130},
    ce_rows_exponent=0.32,
    ce_rows_stages=3.4,
    early_stop_share=0.88,
    pretrain_stop_share=0.2,
    torch_import_s=0.7,
    streamed_share=0.75,
    ams_rollouts=5,
    tilt_rollouts=1.94,
    tilt_solve_s=1.34,
    probe_share=0.49,
    pool_share=1.13,
    measured="2026-11-28, benchmarks/calibrate_cost.py --fit --repeat 1 (wall seconds), 2 cores, load average 0.5; "
    "tilt_rollouts and tilt_solve_s from CPU seconds against the model's of a scene's plain rollouts streamed as "
    "the engine draws them, in the same process (2026-11-30, benchmarks/calibrate_cost.py --tilt, load average 9-10: "
    "a tilted rollout 1.87-2.11 plain ones held whole, a fresh process's solve 1.25-1.68 model seconds); "
    "proposal_step_s, proposal_rollout_step_s, pretrain_stop_share and torch_import_s from CPU seconds per part of "
    "the reference scene's and a two-pedestrian scene's default runs against the model's in one process, on 2 "
    "loaded cores (2026-11-29, benchmarks/calibrate_cost.py --parts: "
    "the reference scene's proposal steps 1.8-2.1 times, its pretraining fit 0.4-0.6 times, the rest's 1.0); "
    "streamed_share from the CPU seconds of the two-pedestrian scene's plain rollouts, 40,000 streamed against "
    "10,000 held whole (0.64-0.82, 4 readings); probe_share 0.37-0.51, 3 readings (2026-11-30, calibrate_cost.py "
    "--probe, load average 6.5); pool_share: 10^6 plain rollouts of the two-pedestrian scene on 2 workers 1.79 and "
    "1.74 times as fast as on 1, 2 idle cores (2026-11-30, two sittings: 2 / 1.79 = 1.12, 2 / 1.74 = 1.15), against "
    "the two workers' 1.05 times one process's CPU seconds",
)
"""The constants of the model (see :class:`CostConstants`); ``benchmarks/calibrate_cost.py --fit`` measures them."""


@dataclass(frozen=True)
class StageCost:
    """Predicted seconds of one stage: simulating its rollouts, and after them (the fit and the stage's bookkeeping)."""

    simulate_s: float
    after_s: float

    @property
    def seconds(self) -> float:
        return self.simulate_s + self.after_s


def _fit_s(epochs: float, rows: float, c: CostConstants) -> float:
    return epochs * (c.epoch_s + c.row_epoch_s * rows) + c.row_s * rows


def ce_rows(cfg: ExperimentConfig, stage: int, n: int, c: CostConstants = COST) -> float:
    """The distinct rows CE stage ``stage`` (1..K) of ``n`` rollouts fits, about (at most ``fit_rows``)."""
    cap = math.inf if cfg.adaptive.fit_rows is None else float(cfg.adaptive.fit_rows)
    ramp = 1.0 - math.exp(-max(0, stage - 1) / max(1e-9, c.ce_rows_stages))
    return min(
        cap, max(1.0, c.ce_rows.get(cfg.adaptive.proposal_inputs, 1.0) * (n / 100.0) ** c.ce_rows_exponent * ramp)
    )


def stage_cost(
    cfg: ExperimentConfig,
    kind: str,
    n: int,
    n_steps: int = N_STEPS,
    c: CostConstants = COST,
    stage: int | None = None,
    model: str | None = None,
    stream_above: int = 20_000,
    speed: float = 1.0,
    load: LoadReading | None = None,
) -> StageCost:
    """Predicted seconds of a stage of ``kind`` (``pretrain`` | ``ce`` | ``final`` | ``ams``) with ``n`` rollouts.

    Args:
        cfg: the run's settings (method, simulator, scenario, proposal inputs, epochs, fit rows, tolerance); the
            per-rollout seconds scale by the cost factor the scenario declares
            (:data:`pemviz.settings.SCENARIO_COST_FACTORS`, 1 for one that declares none), the per-step seconds and
            the fit by its parts (:data:`pemviz.settings.SCENARIO_COST_PARTS`).
        kind: ``pretrain`` | ``ce`` | ``final`` | ``ams``.
        n: the stage's rollouts.
        n_steps: T, steps per rollout.
        c: the constants (default :data:`COST`).
        stage: the stage's number, for a CE stage's rows (:func:`ce_rows`); None: the mean over the K stages.
        model: the stage's cost model (:data:`pemviz.methods.COST_MODELS`); None: ``cfg.method``'s.
        stream_above: rollouts above which the stage is streamed chunk by chunk, its rollouts at
            :attr:`CostConstants.streamed_share` of a whole batch's (:func:`pemviz.engine.experiment.stream_above`:
            :data:`pemviz.engine.experiment.STREAM_ABOVE` over the objects a rollout perceives; the default: a rollout
            of one object).
        speed: how many times the model's seconds the run's work takes here now: the pool starts where ``speed``
            times the model's seconds pay for it (:func:`pemviz.engine.resources.pool_workers`, as it starts on a
            block's measured seconds); the seconds returned are the model's.
        load: the machine's load (:func:`pemviz.engine.resources.read_load`; None: idle on
            :func:`pemviz.engine.resources.usable_cpus`): a pooled batch's simulation is its seconds in one process
            times :attr:`CostConstants.pool_share` over what the workers gain at that load
            (:meth:`pemviz.engine.resources.LoadReading.pool_speedup`: W x crowding(1) / crowding(W)), one process's
            crowding left to the caller's slowdown as for every other part."""
    model = cfg.method_record.cost_model if model is None else model
    proposal = model == "proposal" and kind in ("ce", "final")
    parts = SCENARIO_COST_PARTS.get(cfg.scenario, {})  # what the scene declares (none: the reference's)
    per_step = (c.proposal_step_s if proposal else c.pem_step_s) * parts.get("step", 1.0)
    per_rollout = c.rollout_step_s.get(cfg.sim, max(c.rollout_step_s.values())) + proposal * c.proposal_rollout_step_s
    per_rollout *= SCENARIO_COST_FACTORS.get(cfg.scenario, 1.0)  # what the scenario declares (1: none)
    tilt = model == "look-ahead"
    per_rollout *= c.streamed_share if n > stream_above and not tilt else 1.0  # the tilt draws its batch whole
    rollouts = n * (c.ams_rollouts if kind == AMS_STAGE else c.tilt_rollouts if tilt else 1.0)
    blocks = max(1, math.ceil(n / POOL_BLOCK))  # a large batch is simulated block by block, each its steps
    simulate = n_steps * (per_step * blocks + per_rollout * rollouts)
    workers = pool_workers(cfg.execution, n, simulate * speed)  # worker processes share a large batch
    if workers > 1:
        simulate *= c.pool_share / (load or LoadReading(usable_cpus())).pool_speedup(workers)
    simulate += c.tilt_solve_s if tilt and stage == 1 else 0.0
    cap = math.inf if cfg.adaptive.fit_rows is None else float(cfg.adaptive.fit_rows)
    inputs = cfg.adaptive.proposal_inputs
    fit, share = c.stage_s, parts.get("fit", 1.0)
    if model == "proposal" and kind == "pretrain":
        epochs = cfg.adaptive.pretrain_epochs * (c.pretrain_stop_share if cfg.adaptive.fit_tolerance is not None else 1)
        fit += share * _fit_s(epochs, min(cap, n * c.pretrain_rows.get(inputs, 1.0)), c)
        if parts.get("torch") and "torch" not in sys.modules:  # the first fit on torch in this process imports it
            fit += c.torch_import_s
    elif model == "proposal" and kind == "ce":
        stages = [stage] if stage is not None else range(1, cfg.adaptive.n_stages + 1)
        rows = sum(ce_rows(cfg, k, n, c) for k in stages) / len(stages)
        if cfg.adaptive.fit == "lbfgs":
            epochs = float(cfg.adaptive.fit_max_steps)
        else:
            epochs = cfg.adaptive.ce_epochs * (c.early_stop_share if cfg.adaptive.fit_tolerance is not None else 1.0)
        fit += share * _fit_s(epochs, rows, c)
    return StageCost(simulate, fit)


def pilot_seconds(cfg: ExperimentConfig, n: int, n_steps: int = N_STEPS, c: CostConstants = COST) -> float:
    """The CPU seconds the model expects ``n`` plain rollouts of ``cfg``'s scene (:func:`stage_cost` of a plain final
    batch), drawn alone, to take at the speed its constants hold: their model seconds times the scene's ``probe`` part
    (:data:`pemviz.settings.SCENARIO_COST_PARTS`), else :attr:`CostConstants.probe_share`."""
    share = SCENARIO_COST_PARTS.get(cfg.scenario, {}).get("probe", c.probe_share)
    return stage_cost(cfg, "final", n, n_steps, c, model="plain").simulate_s * share


def pilot_speed(cfg: ExperimentConfig, pilot: list[tuple[int, float]], n_steps: int = N_STEPS) -> float:
    """How many times the model's CPU seconds a run of ``cfg`` takes here now, its share of the CPUs left out
    (:func:`pemviz.engine.resources.load_slowdown` adds it): the median over ``pilot``'s batches of plain rollouts of
    the run's scene (``(rollouts, CPU seconds)``, :func:`pemviz.engine.experiment.scene_pilot`) of their seconds over
    :func:`pilot_seconds`; 1 without a pilot (docs/validation.md, "Time estimates")."""
    if not pilot:
        return 1.0
    return statistics.median(seconds / max(pilot_seconds(cfg, n, n_steps), 1e-12) for n, seconds in pilot)


def start_reading(
    cfg: ExperimentConfig, pilot: list[tuple[int, float]], n_steps: int = N_STEPS, since: Any = None
) -> tuple[float, float, LoadReading]:
    """``(speed, slowdown, load)`` a run of ``cfg`` is priced at before it has measured anything of its own, read
    alike by the console's first progress line (:class:`pemviz.sinks.StageClock`) and the panel's cost line
    (:func:`pemviz.app.form.run_cost`): the speed of ``pilot``'s plain rollouts (:func:`pilot_speed`: how many times
    the model's CPU seconds the run's work takes, 1 without a pilot), the machine's load
    (:func:`pemviz.engine.resources.read_load`, its window opened at ``since``, a
    :func:`pemviz.engine.resources.tasks_now` reading; None: now), and the slowdown: that load's crowding of one
    thread times the speed. ``load`` also prices a pooled batch (:func:`stage_cost`): one reading for both."""
    from pemviz.engine import resources

    speed = pilot_speed(cfg, pilot, n_steps)
    load = resources.read_load(since)
    return speed, load.crowding(1) * speed, load


def plan_costs(
    cfg: ExperimentConfig,
    plan: RunPlan,
    n_steps: int = N_STEPS,
    c: CostConstants = COST,
    speed: float = 1.0,
    load: LoadReading | None = None,
    stream_above: int = 20_000,
) -> dict[int, StageCost]:
    """Stage number -> :func:`stage_cost` of each stage of ``plan`` (``speed``, ``load``, ``stream_above``: as
    there)."""
    kw: dict[str, Any] = {"speed": speed, "load": load, "stream_above": stream_above}
    return {s.stage: stage_cost(cfg, s.kind, s.n_rollouts, n_steps, c, s.stage, **kw) for s in plan.stages}


def then_adds(cfg: ExperimentConfig, simulations: int) -> tuple[int, str]:
    """The most simulations a run of ``cfg`` may add after the ``simulations`` it plans, and the cost line's words
    for them (:attr:`pemviz.methods.Method.then_most`; ``(0, "")``: none)."""
    from pemviz.methods import resolve

    record = cfg.method_record
    if record.then_most is None:
        return 0, ""
    most, words = resolve(record.then_most)(cfg, simulations)
    return int(most), str(words) if most > 0 else ""


@dataclass(frozen=True)
class FollowOn:
    """What a run may draw after its planned stages when they end in a way its method names
    (:attr:`pemviz.methods.Method.then`): its stages once more (``retry``, numbered from ``offset`` on, as the engine
    numbers them: :class:`pemviz.estimators.fallback.Shifted`), then at most ``plain_most`` plain rollouts.

    Attributes:
        retry: the plan of the stages run again (:attr:`pemviz.methods.Method.then_plan`; stage numbers from 0), or
            None.
        offset: the engine's number of the retry's first stage (the planned stages' last + 1).
        plain_most: the most plain rollouts after the stages (and their retry).
        simulations: all the simulations it may add (the retry's and the plain rollouts).
        words: the cost line's words for them (:func:`then_adds`)."""

    retry: RunPlan | None
    offset: int
    plain_most: int
    simulations: int
    words: str

    @property
    def retry_last(self) -> int:
        """The engine's number of the retry's last stage (the planned stages' last without a retry)."""
        return self.offset - 1 + (0 if self.retry is None else self.retry.stages[-1].stage + 1)

    def text(self) -> str:
        """``1,005,100 rollouts if the stages' weights back no interval (...)``: how many, and when."""
        return f"{self.simulations:,} {self.words}"


def follow_on(cfg: ExperimentConfig, plan: RunPlan, problem: Any = None) -> FollowOn | None:
    """What a run of ``cfg`` and ``plan`` may draw after the plan's stages (:class:`FollowOn`), or None: nothing
    (its method has no :attr:`~pemviz.methods.Method.then_most`, or it is 0). With ``problem`` (a
    :class:`~pemviz.core.problems.Problem` or the run's :class:`~pemviz.engine.events.RunStarted`), what its method
    would draw on that scene (:attr:`~pemviz.methods.Method.then_drawn`, where it has one): e.g. no plain rollouts
    where they could decide nothing (e.g. braking at ``--margin 0``,
    :func:`pemviz.estimators.fallback.plain_cannot_decide`)."""
    from pemviz.methods import resolve

    if not plan.stages:
        return None
    record = cfg.method_record
    sims = int(cfg.n_simulations)
    if problem is not None and record.then_drawn is not None:
        retry, most, words = resolve(record.then_drawn)(cfg, sims, problem)
    else:
        most, words = then_adds(cfg, sims)
        retry = None if record.then_plan is None or most <= 0 else resolve(record.then_plan)(cfg)
    if most <= 0:
        return None
    again = 0 if retry is None else sum(s.n_rollouts for s in retry.stages)
    return FollowOn(retry, plan.stages[-1].stage + 1, max(0, most - again), int(most), str(words))


def follow_on_seconds(
    cfg: ExperimentConfig,
    follow: FollowOn,
    n_steps: int = N_STEPS,
    look_ahead_s: float = 0.0,
    c: CostConstants = COST,
    speed: float = 1.0,
    load: LoadReading | None = None,
    stream_above: int = 20_000,
) -> float:
    """The model's seconds of all of ``follow``: the retry's stages (:func:`stage_cost`, each rollout's look-ahead
    ``look_ahead_s`` added) and ``plain_most`` plain rollouts (``stage_cost`` of a ``plain`` final batch; ``speed``,
    ``load``, ``stream_above``: as there)."""
    kw: dict[str, Any] = {"speed": speed, "load": load, "stream_above": stream_above}
    again = 0.0
    for s in () if follow.retry is None else follow.retry.stages:
        cost = stage_cost(cfg, s.kind, s.n_rollouts, n_steps, c, s.stage, **kw)
        again += cost.seconds + s.n_rollouts * look_ahead_s
    most = follow.plain_most
    plain = stage_cost(cfg, "final", most, n_steps, c, model="plain", **kw).seconds if most else 0.0
    return again + plain


Z_95 = 1.96
"""The standard normal's 97.5 % quantile: a 95 % interval's half-width in standard errors."""

MC_REL_ERROR = 0.2
"""The relative half-width of the 95 % interval the console's advice sizes plain Monte Carlo for (``--rel-error
0.2``): about 96 failures."""


def mc_rollouts(log_p: float, rel_error: float = MC_REL_ERROR) -> float:
    """Rollouts plain Monte Carlo needs for a 95 % interval of half-width ``rel_error`` times p at the failure
    probability p = e^``log_p`` (``log_p`` in nats): n = ceil(z^2 (1 - p) / (rel_error^2 p)), z = :data:`Z_95`, from the
    binomial standard error sqrt(p (1 - p) / n) (the normal approximation to the binomial; the crude Monte Carlo
    estimator's relative error sqrt((1 - p) / (n p)), Rubinstein & Kroese, "Simulation and the Monte Carlo Method", 3rd
    ed., 2017; about 96 / p at 20 %, i.e. about 96 failures). A whole number as a float; inf where p underflows float64
    (p < ~1e-300)."""
    p = math.exp(log_p)
    if not p > 1e-300:
        return math.inf
    return float(math.ceil(Z_95**2 * (1.0 - p) / (rel_error**2 * p)))


def duration_text(seconds: float) -> str:
    """``0.8 s``, ``42 s``, ``9.8 min``, ``63 min``, ``3.1 h``, ``12 days``, ``3.0e+05 years``: a duration given in
    seconds, in the unit that reads best."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 600:
        return f"{seconds / 60:.1f} min"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    if seconds < 730 * 86400:
        return f"{seconds / 86400:.0f} days"
    years = seconds / (365.25 * 86400)
    return f"{years:,.0f} years" if years < 10_000 else f"{years:.1e} years"


LOAD_DRIFT = 0.4
"""How much longer than its first estimate a run on a loaded machine may take, nothing following its stages, as a
share: the estimate is the model's seconds times the load read over a fraction of a second at the start
(:func:`pemviz.engine.resources.load_slowdown`), whose speed reading drifts by 10-40 % within seconds, and whose
sharing moves as the other sessions' jobs start and end. A run with one stage and nothing after it took 0.75-1.30
times its first estimate in 9 runs at load average 4-15 (e.g. the cut-in's tilt) where its CPU seconds were the
model's times the probe's reading (the Validation page, "Time estimates")."""
LOAD_WORDS = "as the machine's load varies"
"""What the upper end of a range says where it is the load's drift alone (:func:`with_drift`)."""


def with_drift(seconds: float, slowdown: float) -> float:
    """The most ``seconds`` (a run's, the model's times ``slowdown``, the load read at its start) may become as the
    load varies: ``seconds`` times 1 + :data:`LOAD_DRIFT` on a loaded machine (``slowdown`` > 1), else ``seconds``."""
    return seconds * (1.0 + LOAD_DRIFT) if slowdown > 1.0 else seconds


def range_text(low_s: float, high_s: float = math.nan, then: str = "", left: str = "", why: str = "") -> str:
    """``~1.2 s left, up to ~6.5 min with 1,005,100 rollouts if ...``: a run's seconds from ``low_s`` (as planned) up
    to ``high_s`` (with what may follow, ``then``: :meth:`FollowOn.text`; or, without it, ``why``, e.g.
    :data:`LOAD_WORDS`; both empty: not said), in the words of both the console's progress line and the panel's cost
    line (``left``: after the first figure, e.g. `` left``). The upper end is left out where it is not finite or
    reads as the lower."""
    text = f"~{duration_text(low_s)}{left}"
    if math.isfinite(high_s) and duration_text(high_s) != duration_text(low_s):
        text += f", up to ~{duration_text(high_s)}" + (f" with {then}" if then else f" {why}" if why else "")
    return text


@dataclass(frozen=True)
class RunCost:
    """What a run will take: simulations, the largest batch in memory (bytes), expected seconds, and what the run will
    count on top of the simulations (``adds``: e.g. a tilted proposal's look-aheads; ``""``: nothing).

    ``then_simulations`` and ``then_seconds``: the most a run may add after its planned stages, when they end in a
    way it names (``then_words``: e.g. the cross-entropy sampler's retry and plain Monte Carlo where its weights back
    no interval, :mod:`pemviz.estimators.fallback`; :class:`FollowOn`); not in :attr:`needs_confirm` (a run may well
    not need them). ``slowdown``: how many times the model's seconds on an idle machine ``seconds`` and
    ``then_seconds`` are (the machine's load when priced, :func:`pemviz.engine.resources.load_slowdown`)."""

    simulations: int
    memory_bytes: int
    seconds: float
    adds: str = ""
    then_simulations: int = 0
    then_seconds: float = 0.0
    then_words: str = ""
    slowdown: float = 1.0

    @property
    def needs_confirm(self) -> bool:
        """Above any limit (:data:`CONFIRM_SIMULATIONS`, :data:`CONFIRM_SECONDS` on an idle machine,
        :data:`CONFIRM_BYTES`): what the run is, not how loaded the machine is at the moment it is priced."""
        return (
            self.simulations > CONFIRM_SIMULATIONS
            or self.seconds / max(self.slowdown, 1e-12) > CONFIRM_SECONDS
            or self.memory_bytes > CONFIRM_BYTES
        )

    def time_text(self, left: str = "") -> str:
        """The run's seconds as a range (:func:`range_text`): as planned, up to the most that may follow, or where
        nothing may, up to the load's drift (:func:`with_drift`)."""
        if self.then_simulations <= 0:
            return range_text(self.seconds, with_drift(self.seconds, self.slowdown), left=left, why=LOAD_WORDS)
        then = f"{self.then_simulations:,} {self.then_words}"
        return range_text(self.seconds, self.seconds + self.then_seconds, then, left)

    def text(self) -> str:
        mem = self.memory_bytes / 1024**2
        adds = f" {self.adds}" if self.adds else ""
        return f"{self.simulations:,} simulations{adds}, {mem:,.1f} MB per batch, {self.time_text()}"


def run_cost(
    cfg: ExperimentConfig,
    plan: RunPlan,
    n_steps: int = N_STEPS,
    stream_above: int = 20_000,
    c: CostConstants = COST,
    look_ahead_s: float = 0.0,
    problem: Any = None,
    speed: float = 1.0,
    load: LoadReading | None = None,
) -> RunCost:
    """Simulations (:attr:`ExperimentConfig.n_simulations`), memory of the largest batch, and the seconds of ``plan``
    (the sum of :func:`stage_cost`, each rollout's look-ahead ``look_ahead_s`` added, as
    :class:`pemviz.sinks.StageClock` adds it; an open-ended plan counts its first stage only) and of what may follow
    it (:func:`follow_on` on ``problem``, :func:`follow_on_seconds`; ``problem`` None: whatever the scene), in the
    model's seconds (``speed``, ``load``: as :func:`stage_cost` takes them).

    A stage above ``stream_above`` rollouts (:func:`pemviz.engine.experiment.stream_above` of the problem's objects)
    is simulated in chunks: its rollouts are priced streamed (:func:`stage_cost`), and it does not count in full
    towards memory. The memory is the run's memory check's model
    (:func:`pemviz.engine.resources.run_memory`, :data:`pemviz.engine.resources.BYTES_PER_ROLLOUT_STEP`) without the
    process's own :data:`pemviz.engine.resources.BASE_BYTES`: one model of a step's bytes for both."""
    seconds = sum(cost.seconds for cost in plan_costs(cfg, plan, n_steps, c, speed, load, stream_above).values())
    seconds += look_ahead_s * sum(s.n_rollouts for s in plan.stages)
    batch = run_memory(plan, n_steps, cfg.adaptive.quantile_level, stream_above=stream_above) - BASE_BYTES
    follow = follow_on(cfg, plan, problem)
    if follow is None:
        return RunCost(int(cfg.n_simulations), int(batch), float(seconds), cfg.method_record.run_adds)
    then_s = follow_on_seconds(cfg, follow, n_steps, look_ahead_s, c, speed, load, stream_above)
    sims, adds = int(cfg.n_simulations), cfg.method_record.run_adds
    return RunCost(sims, int(batch), float(seconds), adds, follow.simulations, then_s, follow.words)

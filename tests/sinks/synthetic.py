"""Hand-made engine events for the sinks' tests: no engine, no simulator, no PEM."""

from __future__ import annotations

import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import estimate
from pemviz.core.plan import RunPlan
from pemviz.core.problem_view import ProblemView, SignalView, Thresholds
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.cost import CostConstants
from pemviz.engine.events import RolloutsSampled, RunStarted, StageFinished, StageResult
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.simulator import BrakingParams

PLAN = RunPlan.of([(0, "pretrain", 20), (1, "ce", 30), (2, "ce", 30), (3, "final", 50)])
"""Pretraining, K = 2 CE stages, the final batch: 130 simulations."""

BRAKING = ProblemView(
    "braking",
    "a lead car ahead",
    (SignalView("d", "gap_m", "m"), SignalView("v", "ego_speed_mps", "m/s")),
    Thresholds(2.0, 10.0, "m", "crash gap", "braking distance"),
    drawing=BrakingDrawing(BrakingParams()),
)
TOY = ProblemView(
    "toy-1e-3",
    "toy braking",
    (SignalView("d", "gap_m", "units"),),
    Thresholds(3.0, 5.0, "units", "failure below", "braking within"),
)
GRID = np.linspace(0.0, 13.0, 14)
SIMPLE = CostConstants(
    pem_step_s=0.0,
    proposal_step_s=0.0,
    rollout_step_s={"batched": 1e-7},
    proposal_rollout_step_s=0.0,
    stage_s=0.0,
    epoch_s=1e-3,
    row_epoch_s=0.0,
    row_s=0.0,
    pretrain_rows={"state": 1.0},
    ce_rows={"state": 1.0},
    ce_rows_exponent=0.0,
    ce_rows_stages=1.0,
    early_stop_share=1.0,
)
"""Constants to compute by hand: simulating n rollouts of T = 100 steps takes n x 1e-5 s, a fit 1 ms per epoch."""


def run_started(view: ProblemView = BRAKING, plan: RunPlan = PLAN, **config) -> RunStarted:
    cfg = ExperimentConfig.of(**{"n_stages": 2, "n_per_stage": 30, "n_final": 50, "pretrain_rollouts": 20, **config})
    return RunStarted(cfg, "G[0,4](d >= 2)", GRID, np.full(GRID.size, 0.9), view, plan, exact_log_p=None)


def batch(gaps: np.ndarray, columns: tuple[str, ...] = ("gap_m", "ego_speed_mps")) -> RolloutBatch:
    """Rollouts with the gap rows ``gaps`` [N, T] (metres), ego speed 5 m/s, every step detected, log p = log q =
    -0.1 (nats)."""
    gaps = np.asarray(gaps, dtype=np.float64)
    obs = np.stack([gaps] + [np.full(gaps.shape, 5.0)] * (len(columns) - 1), axis=2)
    return RolloutBatch(obs, np.ones(gaps.shape, bool), np.full(gaps.shape, -0.1), np.full(gaps.shape, -0.1), columns)


def sampled(stage: int, kind: str, b: RolloutBatch, n_total: int | None = None) -> RolloutsSampled:
    """The batch's rollouts with robustness min gap - 2 m (failure below 0), log-weights 0."""
    r = b.signal("gap_m").min(axis=1) - 2.0
    index = None if n_total is None else np.arange(b.n)
    return RolloutsSampled(stage, kind, b, r, {"classic": r}, r < 0, np.zeros(b.n), n_total=n_total, index=index)


def finished(
    stage: int, kind: str, n: int, n_failures: int, gamma: float = float("nan"), wall_s: float = 1.0
) -> StageFinished:
    """A stage of ``n`` rollouts, ``n_failures`` of them failing, every importance weight 1 (mu_hat = n_failures /
    n)."""
    failed = np.arange(n) < n_failures
    e = estimate(np.zeros(n), failed, np.full(n, -1.0))
    curve = np.full(GRID.size, 0.5)
    return StageFinished(StageResult(stage, kind, gamma, n_failures, e, curve, np.full(GRID.size, np.nan), wall_s))

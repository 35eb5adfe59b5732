"""The engine: sequences an estimator's stages and tells listeners; same seed, same numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.engine.events import RolloutsSampled
from pemviz.engine.experiment import Experiment
from pemviz.presets import PRESETS
from pemviz.scenarios.problems import build_problem

nan, inf = math.nan, math.inf

SMALL = dict(n_stages=3, n_per_stage=50, n_final=100, ce_epochs=100, pretrain_epochs=100)
"""A run of a few seconds: K = 3 stages of N = 50, N_e = 100, 100 Adam epochs per fit."""

# Recorded before the estimators moved out of the engine (commit 004482e; ``rollout-mixture``: the default sampler
# when it became the default, the others with the per-step defensive mixture alone; the braking runs of a state
# proposal re-recorded when the scenario's observation gained ``brake_pending``, and ``rollout-mixture`` with the
# linear pool weights, both bit-identical across two runs; ``fit-mixture``: the default since the fits weigh the
# failures by the mixture of the stages' samplers; ``renyi-fit``: the default since the fits at the failure level
# raise the weights to alpha 1.2 and the last to 1.0, bit-identical across two runs; ``window-rqmc``: the default
# since Array-RQMC couples only the rollouts inside the sampler's window, ranked by one packed key, a mixture's target
# share draws i.i.d. and a fit sees at most 5,000 steps (before it, ``early-stop``: every CE fit starts from the last
# one and stops once converged, with Adam at 1e-2, and the proposal gives way to the PEM once the outcome is
# decided), with float64 fits, bit-identical across two runs; all re-recorded when the proposal's sampling and fits
# became exact, order-free arithmetic, the same on every CPU): key -> (log mu_hat, failures, N,
# stages used, simulations, (stage, gamma, elites) per stage). Any change to the rollouts' stream, the weights, the
# elites, the fits or the pooling moves these numbers.
PINNED = {
    "braking/state-ce/0": (
        -33.6501628042221,
        80,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 1.7331782684715016, 3), (2, 0.0, 12), (3, 0.0, 15), (4, nan, 65)),
    ),
    "braking/state-ce/1": (
        -35.27676289960758,
        83,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 2.168889557137515, 3), (2, 0.0, 17), (3, 0.0, 29), (4, nan, 54)),
    ),
    "braking/paper/0": (
        -inf,
        0,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 3.3448187147363484, 3), (2, 3.3357005795923413, 3), (3, 3.170121544617622, 3), (4, nan, 0)),
    ),
    "braking/paper/1": (
        -inf,
        0,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 3.605276073653105, 3), (2, 3.5078852094923363, 3), (3, 3.082375304466666, 3), (4, nan, 0)),
    ),
    "braking/authors-code/0": (
        -inf,
        0,
        50,
        (3,),
        250,
        ((0, nan, 0), (1, 3.3448187147363484, 3), (2, 3.3357005795923413, 3), (3, 3.511415532719294, 3)),
    ),
    "braking/authors-code/1": (
        -inf,
        0,
        50,
        (3,),
        250,
        ((0, nan, 0), (1, 3.605276073653105, 3), (2, 3.5078852094923363, 3), (3, 3.097067091344499, 3)),
    ),
    "braking/quick/0": (
        -36.162255820302505,
        149,
        150,
        (3, 4),
        300,
        ((0, nan, 0), (1, 1.390010839197359, 3), (2, 0.0, 10), (3, 0.0, 50), (4, nan, 99)),
    ),
    "braking/quick/1": (
        -36.80117423790563,
        110,
        150,
        (3, 4),
        300,
        ((0, nan, 0), (1, 1.1756267103298654, 3), (2, 0.0, 8), (3, 0.0, 44), (4, nan, 66)),
    ),
    "toy/state-ce/0": (
        -48.33957121992181,
        11,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 19.0, 3), (2, 13.0, 3), (3, 4.0, 3), (4, nan, 11)),
    ),
    "toy/state-ce/1": (
        -48.21878174082067,
        12,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 18.0, 3), (2, 13.0, 3), (3, 1.0, 3), (4, nan, 12)),
    ),
    "toy/paper/0": (-inf, 0, 100, (4,), 350, ((0, nan, 0), (1, 19.0, 6), (2, 19.0, 4), (3, 20.0, 50), (4, nan, 0))),
    "braking/mc/0": (-inf, 0, 500, (1,), 500, ((1, nan, 0),)),
    "braking/mc-paper/0": (-inf, 0, 500, (1,), 500, ((1, nan, 0),)),
    "braking/naive50/0": (-61.41067706229729, 367, 500, (1,), 500, ((1, nan, 367),)),
    "braking/naive50-paper/0": (-110.05290715050994, 367, 500, (1,), 500, ((1, nan, 367),)),
    "braking/mixed50/0": (-33.73266933500028, 367, 500, (1,), 500, ((1, nan, 367),)),
    "braking/mixed50-paper/0": (-78.53820890572328, 367, 500, (1,), 500, ((1, nan, 367),)),
    "toy-1e-3/mc/0": (-7.600902459542082, 1, 2000, (1,), 2000, ((1, nan, 1),)),
    "braking/state-ce-streamed/0": (
        -33.86618066893059,
        25366,
        100001,
        (2,),
        100151,
        ((0, nan, 0), (1, 1.7331782684715016, 3), (2, nan, 25366)),
    ),
    "braking/rollout-mixture/0": (
        -36.743561993176925,
        47,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 2.662242742737181, 3), (2, 0.1618225703611742, 3), (3, 0.0, 25), (4, nan, 47)),
    ),
    "toy/rollout-mixture/0": (
        -48.40860816702972,
        47,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 19.0, 3), (2, 8.0, 3), (3, 0.0, 19), (4, nan, 47)),
    ),
    "braking/fit-mixture/0": (
        -36.743561993176925,
        47,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 2.662242742737181, 3), (2, 0.1618225703611742, 3), (3, 0.0, 25), (4, nan, 47)),
    ),
    "braking/fit-mixture/1": (
        -34.94242219824203,
        83,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 2.1010082873038485, 3), (2, 0.0, 6), (3, 0.0, 36), (4, nan, 53)),
    ),
    "braking/renyi-fit/0": (
        -36.743561993176925,
        47,
        100,
        (4,),
        350,
        ((0, nan, 0), (1, 2.662242742737181, 3), (2, 0.1618225703611742, 3), (3, 0.0, 25), (4, nan, 47)),
    ),
    "braking/renyi-fit/1": (
        -34.93184210242251,
        82,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 2.1010082873038485, 3), (2, 0.0, 6), (3, 0.0, 35), (4, nan, 53)),
    ),
    "braking/array-rqmc/0": (
        -37.03650871595938,
        84,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 2.1145748565087814, 3), (2, 0.0, 4), (3, 0.0, 29), (4, nan, 59)),
    ),
    "braking/array-rqmc/1": (
        -33.551592741030014,
        63,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 2.0341764480288447, 3), (2, 0.0, 3), (3, 0.0, 26), (4, nan, 40)),
    ),
    "braking/window-rqmc/0": (
        -35.129977522741626,
        90,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 1.3649714792495367, 3), (2, 0.0, 19), (3, 0.0, 44), (4, nan, 65)),
    ),
    "braking/window-rqmc/1": (
        -34.73174201870015,
        105,
        150,
        (3, 4),
        350,
        ((0, nan, 0), (1, 1.9607052156063247, 3), (2, 0.0, 6), (3, 0.0, 36), (4, nan, 75)),
    ),
}


def pinned_config(key: str) -> tuple[ExperimentConfig, str]:
    """The config and problem name of a key of :data:`PINNED` (recorded before the cross-entropy runs whose weights
    back no interval were followed by plain Monte Carlo: ``plain_fallback`` = 0)."""
    config, problem = _pinned_config(key)
    return config.replace(plain_fallback=0), problem


def _pinned_config(key: str) -> tuple[ExperimentConfig, str]:
    problem, preset, seed = key.split("/")
    if preset == "window-rqmc":  # the default sampler (every CE fit stops once converged, Adam at 1e-2, decided steps
        # drawn from the PEM, Array-RQMC inside the window)
        return ExperimentConfig.of(**{**SMALL, "seed": int(seed)}), problem
    if preset == "array-rqmc":  # Array-RQMC uniforms, stages pooled by j^2 n_j, fits of every epoch at 1e-3
        return ExperimentConfig.of(**{**SMALL, **FIT_RECORDED, "seed": int(seed)}), problem
    return ExperimentConfig.of(**{**RECORDED, **_pinned_fields(problem, preset), "seed": int(seed)}), problem


FIT_RECORDED = {"learning_rate": 1e-3, "fit_tolerance": None, "skip_decided": False, "fit_rows": 10_000}
"""The defaults before every CE fit stopped once converged (Adam at 1e-3; fits of at most ``fit_rows`` steps, all of
these, ran every epoch, subsampling above 10,000 steps) and before the proposal gave way to the PEM where the outcome
is decided."""
RECORDED = {"uniforms": "iid", "pool_weights": "linear", **FIT_RECORDED}
"""The defaults when the other numbers were recorded: i.i.d. uniforms, the stages pooled by j n_j, the fits above."""


def _pinned_fields(problem: str, preset: str) -> dict:
    step = PRESETS["state-ce-step"]  # the numbers were recorded with the per-step defensive mixture alone
    if preset == "state-ce-streamed":  # a final batch above STREAM_ABOVE: simulated chunk by chunk
        return {**step, **SMALL, "n_stages": 1, "n_final": 100_001}
    full = {"smoothing_at_failure": 1.0, "final_smoothing": None}  # every fit at the failure level with alpha = 1
    if preset == "rollout-mixture":  # the default sampler when it became the default (each failure weighed by its own
        # stage's samplers in the fits)
        return {**SMALL, **full, "fit_weights": "sampler"}
    if preset == "fit-mixture":  # the fits weigh the failures by the mixture of the stages
        return {**SMALL, **full}
    if preset == "renyi-fit":  # alpha 1.2 at the failure level, 1.0 in the last fit
        return dict(SMALL)
    method, _, base = preset.partition("-")
    if method in ("mc", "naive50", "mixed50"):
        return {**PRESETS[base or "state-ce"], "method": method, "n_per_stage": 2000 if problem == "toy-1e-3" else 500}
    return {**step, **PRESETS[preset], **SMALL}


def run_pinned(key: str):
    config, name = pinned_config(key)
    problem = build_problem("main" if name == "braking" else name, config.perception.pem)
    return Experiment(config, problem=problem).run()


@pytest.mark.parametrize("key", list(PINNED))
def test_same_seed_gives_the_estimates_recorded_before_the_estimators_moved(key):
    log_mu, n_failures, n, used, n_sims, stages = PINNED[key]
    done = run_pinned(key)
    est = done.final.estimate
    if log_mu == -inf:
        assert est.log_mu_hat == -inf
    else:
        assert est.log_mu_hat == pytest.approx(log_mu, abs=1e-9)
    assert (est.n_failures, est.n, done.final.stages_used, done.final.n_simulations) == (n_failures, n, used, n_sims)
    assert [(s.stage, s.n_elites) for s in done.stages] == [(k, e) for k, _, e in stages]
    assert [s.gamma for s in done.stages] == pytest.approx([g for _, g, _ in stages], abs=1e-9, nan_ok=True)


def test_the_first_event_describes_the_problem_and_no_thread_setting_changes():
    import torch
    from pemviz.engine.events import RunStarted

    events: list = []
    threads = torch.get_num_threads()
    Experiment(
        ExperimentConfig.of(method="mc", n_per_stage=50), [events.append], problem=build_problem("toy-1e-3")
    ).run()
    first = events[0]
    assert isinstance(first, RunStarted) and first.problem.name == "toy-1e-3" and first.problem.signal_names == ("d",)
    assert "toy braking" in first.problem.description and torch.get_num_threads() == threads
    assert first.problem.drawing is None and first.problem.thresholds.labels() == (
        "failure below 3 units",
        "braking within 5 units",
    )
    assert [(s.stage, s.kind, s.label, s.n_rollouts) for s in first.plan.stages] == [(1, "final", "final batch", 50)]
    assert first.plan.n_simulations == 50 and first.plan.has_final_batch
    view = build_problem("main").view
    assert view.name == "braking" and view.signal_names == ("d", "v", "vl") and "braking" in view.description
    assert [(s.column, s.unit) for s in view.signals] == [
        ("gap_m", "m"),
        ("ego_speed_mps", "m/s"),
        ("lead_speed_mps", "m/s"),
    ]
    assert view.thresholds.labels() == ("crash gap 2 m", "braking distance 10 m") and view.drawing.params.n_steps == 100


def test_torch_threads_sets_and_restores_the_process_setting():
    import torch
    from pemviz.engine.resources import torch_threads

    before = torch.get_num_threads()
    with torch_threads(2):
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("name,uniforms", [("main", "iid"), ("main", "array-rqmc"), ("toy", "iid")])
def test_stages_streamed_in_chunks_give_the_estimates_of_whole_batches(name, uniforms, monkeypatch):
    """Above STREAM_ABOVE every stage is simulated chunk by chunk and never held whole: same rollouts, same elites,
    same fits, same answer as one batch per stage. With Array-RQMC too: the rollouts are coupled within fixed blocks
    of 8,192, whatever the chunks they are handed out in."""
    import dataclasses

    import pemviz.engine.experiment as engine

    cfg = ExperimentConfig.of(
        **{**SMALL, "n_per_stage": 400, "n_final": 600, "pretrain_rollouts": 300, "seed": 2, "uniforms": uniforms},
        plain_fallback=0,  # the stages are compared; plain Monte Carlo's batches stream as any method's do
    )
    problem = build_problem(name, cfg.perception.pem)
    whole = Experiment(cfg, problem=problem).run()
    monkeypatch.setattr(engine, "STREAM_ABOVE", 100)
    if problem.stream is None:  # the toy: stream in chunks of 64 from one batch's uniforms

        def stream(n, sampler, target, rng):
            batch = problem.simulate(n, sampler, target, rng)
            return (batch.select(np.arange(a, min(a + 64, n))) for a in range(0, n, 64))
    else:
        from pemviz.scenarios.braking.batched import iter_batched

        def stream(n, sampler, target, rng):
            return iter_batched(None, n, sampler, target, rng, chunk_size=64)

    problem = dataclasses.replace(problem, stream=stream)
    samples = []
    streamed = Experiment(cfg, [lambda e: isinstance(e, RolloutsSampled) and samples.append(e)], problem=problem).run()
    a, b = whole.final.estimate, streamed.final.estimate
    assert (a.log_mu_hat, a.n_failures, a.n) == (b.log_mu_hat, b.n_failures, b.n)
    assert [(repr(s.gamma), s.n_elites) for s in whole.stages] == [(repr(s.gamma), s.n_elites) for s in streamed.stages]
    assert [s.n_total for s in samples] == [300, 400, 400, 400, 600]
    last = samples[-1]
    assert last.batch.n <= engine.SAMPLE_LEAST_ROBUST + engine.SAMPLE_FAILURES + engine.SAMPLE_UNIFORM
    assert last.stage_robustness.shape == (600,)
    np.testing.assert_array_equal(last.robustness, last.stage_robustness[last.index])
    least = np.argsort(last.stage_robustness, kind="stable")[: engine.SAMPLE_LEAST_ROBUST]
    assert set(least) <= set(last.index.tolist())


@pytest.mark.parametrize("name", ["toy", "crowd", "main", "cut-in"])
def test_a_problems_horizon_is_the_steps_of_its_rollouts(name):
    """``Problem.n_steps`` (and its view's), the one horizon the memory check, the cost model and the sinks read, is
    the number of steps its simulator draws."""
    from pemviz.scenarios.problems import problem_for

    problem = problem_for(ExperimentConfig.of(scenario="cut-in")) if name == "cut-in" else build_problem(name)
    batch = problem.simulate(3, problem.target, problem.target, np.random.default_rng(0))
    assert problem.n_steps == problem.view.n_steps == batch.n_steps > 1

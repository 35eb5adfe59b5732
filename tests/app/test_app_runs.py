"""The panel's bookkeeping without a browser: scene geometry, the least-robust list and the most likely
failure, run records and which runs are kept, the form's parsing and cost, the failure explanation's
counterfactual, one stage numbering, export names and files."""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pemviz.app.form import (
    FIELDS_BY_KEY,
    NUMBER_FIELDS,
    PANEL_ROWS,
    panel_rows,
    parse_form,
    parse_number,
    run_cost,
    run_label,
)
from pemviz.app.runs import (
    PanelRun,
    export_path,
    export_run,
    keep_runs,
    least_robust,
    most_likely_failure,
    sanitize_export_name,
)
from pemviz.config import ExperimentConfig
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.cost import CONFIRM_SECONDS, duration_text, stage_cost
from pemviz.engine.events import RolloutsSampled, StageFinished, StageStarted
from pemviz.engine.experiment import Experiment
from pemviz.methods import CROSS_ENTROPY_METHOD, ROW, setting
from pemviz.methods.adaptive import CrossEntropySettings
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.panel import explain
from pemviz.scenarios.braking.simulator import OBSERVATION_NAMES, BrakingParams, BrakingScenario
from pemviz.scenarios.problems import problem_for
from pemviz.settings import SETTINGS, MethodSettings, rows_of
from pemviz.sinks.console import ConsoleSink

TINY = ExperimentConfig.of(
    n_stages=2, n_per_stage=20, n_final=20, ce_epochs=20, pretrain_rollouts=10, pretrain_epochs=20, plain_fallback=0
)
"""The cross-entropy stages of a tiny run, without the plain Monte Carlo that would follow them (their weights back no
interval): the panel's record of the stages the plan names."""


# -- scene geometry -------------------------------------------------------------------------------
def test_the_lane_positions_reproduce_the_highway_env_vehicles_positions():
    """Both cars' centres, rebuilt by the drawing's panel hook from the recorded (gap, speeds), equal highway-env's own
    positions."""
    params = BrakingParams()
    sim = BrakingScenario(params)
    detections = np.ones(params.n_steps, dtype=bool)
    detections[38:47] = False  # a run of misses inside 10 m: the ego brakes late, speeds vary
    obs, ego_x, lead_x = [], [], []
    for a in detections:
        obs.append(sim.observation())
        ego_x.append(float(sim.ego.position[0]))
        lead_x.append(float(sim.lead.position[0]))
        sim.step(bool(a))
    obs = np.array(obs)
    zeros = np.zeros((1, params.n_steps))
    batch = RolloutBatch(obs[None], detections[None], zeros, zeros, tuple(OBSERVATION_NAMES))
    got_ego, got_lead, gap = BrakingDrawing(params).lane_positions(batch, 0)
    np.testing.assert_array_equal(gap, obs[:, 0])
    np.testing.assert_allclose(got_ego, ego_x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_lead, lead_x, rtol=0, atol=1e-9)
    assert got_ego[-1] > 20.0  # the ego really moved (not a trivially-zero comparison)


# -- the least-robust list ------------------------------------------------------------------------
def _sampled(stage: int, robustness: list[float], log_p: list[float] | None = None) -> RolloutsSampled:
    n, t = len(robustness), 4
    obs = np.zeros((n, t, 3))
    obs[:, :, 0] = np.arange(n)[:, None] + 5.0  # gap = 5 + rollout index, to check the rows travel along
    names = ("gap_m", "ego_speed_mps", "lead_speed_mps")
    lp = np.zeros((n, t))
    if log_p is not None:
        lp[:, 0] = log_p  # the whole rollout's log p in its first step
    batch = RolloutBatch(obs, np.ones((n, t), bool), lp, np.zeros((n, t)), names)
    r = np.array(robustness)
    return RolloutsSampled(stage, "ce", batch, r, {"classic": r}, r < 0, -np.arange(n, dtype=float))


def test_least_robust_keeps_the_n_smallest_over_all_stages_least_first():
    kept = least_robust([], _sampled(0, [3.0, -1.0, 2.0, 0.5]), n=3)
    kept = least_robust(kept, _sampled(1, [1.5, -2.0, 4.0]), n=3)
    assert [(t.stage, t.index, t.robustness) for t in kept] == [(1, 1, -2.0), (0, 1, -1.0), (0, 3, 0.5)]
    assert [t.crashed for t in kept] == [True, True, False]
    assert [t.log_weight for t in kept] == [-1.0, -1.0, -3.0]
    assert kept[2].signal("gap_m")[0] == 8.0  # rollout 3's own row
    assert kept[0].key == "s1r1"


# -- run records ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_record() -> PanelRun:
    record = PanelRun(1, TINY)
    progress = []

    def listen(event):
        record(event)
        if isinstance(event, (StageStarted, RolloutsSampled, StageFinished)) and event_stage(event) == 0:
            progress.append(record.progress())

    Experiment(TINY, [listen], problem=problem_for(TINY)).run()
    record.first_stage_progress = progress
    return record


def event_stage(event) -> int:
    return event.result.stage if isinstance(event, StageFinished) else event.stage


def test_run_record_follows_the_run_and_its_progress(tiny_record):
    r = tiny_record
    assert r.status == "finished" and r.final is not None
    assert [s.stage for s in r.stages] == [0, 1, 2, 3] and len(r.plan.stages) == 4
    # stage 0: started, rollouts sampled, finished -> (run %, stage %)
    assert r.first_stage_progress == [(0.0, 5.0), (0.0, 50.0), (25.0, 100.0)]
    assert r.progress() == (100.0, 100.0)
    gamma = r.stage_series("gamma")
    assert sorted(gamma) == [1, 2]  # only CE stages have a threshold
    assert gamma[1] == r.stages[1].gamma
    rate = r.stage_series("failure_rate")
    assert rate[3] == r.stages[3].estimate.n_failures / r.stages[3].estimate.n
    assert len(r.trajectories) == 20
    everything = np.concatenate([e.robustness for e in r.events if isinstance(e, RolloutsSampled)])
    assert [t.robustness for t in r.trajectories] == sorted(everything)[:20]


def test_most_likely_failure_is_the_failing_rollout_with_the_highest_pem_log_probability():
    best = most_likely_failure(None, _sampled(0, [1.0, -1.0, -2.0], log_p=[-1.0, -30.0, -20.0]))
    assert (best.stage, best.index, best.log_p_total) == (0, 2, -20.0)  # rollout 0 does not fail
    best = most_likely_failure(best, _sampled(1, [-1.0, 2.0], log_p=[-25.0, -2.0]))
    assert (best.stage, best.index) == (0, 2)  # -25 < -20
    best = most_likely_failure(best, _sampled(2, [-0.5], log_p=[-19.5]))
    assert (best.stage, best.index) == (2, 0)
    assert most_likely_failure(None, _sampled(0, [1.0, 2.0])) is None


# -- which runs are kept --------------------------------------------------------------------------
def _run(i: int, status: str, pinned: bool = False) -> PanelRun:
    r = PanelRun(i, ExperimentConfig.of())
    r.status, r.pinned = status, pinned
    return r


def test_new_runs_drop_stopped_runs_before_finished_ones_and_never_pinned_ones():
    runs = [_run(1, "finished", pinned=True), _run(2, "finished"), _run(3, "cancelled"), _run(4, "finished")]
    kept = keep_runs(runs, _run(5, "starting"))
    assert [r.run_id for r in kept] == [1, 2, 4, 5]  # the stopped run 3 went first
    kept = keep_runs(kept, _run(6, "starting"))
    assert [r.run_id for r in kept] == [1, 4, 5, 6]  # then the oldest unpinned finished run
    pinned = [_run(i, "finished", pinned=True) for i in range(1, 5)]
    assert [r.run_id for r in keep_runs(pinned, _run(9, "starting"))] == [1, 2, 3, 4, 9]  # all pinned: grows


# -- the form -------------------------------------------------------------------------------------
def test_the_form_parses_exactly_what_was_typed_and_reports_every_error():
    ok = parse_form(
        {"smoothing": "1e-3", "quantile_level": " 0.9 ", "n_per_stage": "1e5", "n_stages": "3"},
        {"metric": "agm", "pem": ""},
    )
    cfg = ok.config
    assert (
        cfg.adaptive.smoothing,
        cfg.adaptive.quantile_level,
        cfg.n_per_stage,
        cfg.adaptive.n_stages,
        cfg.metric,
        cfg.perception.pem,
    ) == (
        0.001,
        0.9,
        100000,
        3,
        "agm",
        None,
    )
    assert isinstance(cfg.n_per_stage, int)
    bad = parse_form({"smoothing": "abc", "quantile_level": "1", "n_stages": "", "n_per_stage": "12.5"}, {})
    assert bad.config is None
    assert bad.errors == {
        "smoothing": "alpha: 'abc' is not a number; type a number in (0, 1] (the smoothing alpha)",
        "quantile_level": "sigma: 1 is out of range; the quantile level sigma must be a number in [0.5, 1)",
        "n_stages": "K: empty; type a whole number in [1, 1000] (the number of cross-entropy stages K)",
        "n_per_stage": "N: 12.5 is not a whole number; the rollouts per stage N must be a whole number >= 2",
    }


@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e6, max_value=1e6))
def test_a_typed_number_is_accepted_exactly_when_it_is_in_range(x):
    f = FIELDS_BY_KEY["smoothing"]
    value, error = parse_number(f, repr(x))
    assert (value == x and error == "") if 0.0 < x <= 1.0 else (value is None and error.startswith("alpha: "))


@given(st.integers(min_value=-(10**7), max_value=10**7), st.sampled_from(["", ".0", ".5", "e0"]))
def test_a_whole_number_field_takes_whole_numbers_only(n, suffix):
    value, error = parse_number(FIELDS_BY_KEY["n_per_stage"], f"{n}{suffix}")
    if suffix == ".5" or n < 2:
        assert value is None and error.startswith("N: ")
    else:
        assert value == n and isinstance(value, int)


def test_run_cost_counts_the_simulations_and_asks_above_the_limits():
    cfg = ExperimentConfig.of(n_stages=3, n_per_stage=50, n_final=70, pretrain_rollouts=20)
    cost = run_cost(cfg)
    assert cost.simulations == 20 + 3 * 50 + 70 and not cost.needs_confirm
    from pemviz.engine.resources import BASE_BYTES, BYTES_PER_ROLLOUT_STEP, run_memory
    from pemviz.estimators import run_plan

    assert cost.memory_bytes == 70 * 100 * BYTES_PER_ROLLOUT_STEP  # the largest batch, T = 100 steps
    plan = run_plan(cfg)  # the memory check's model, less the process's own
    assert cost.memory_bytes == run_memory(plan, 100, cfg.adaptive.quantile_level, stream_above=20_000) - BASE_BYTES
    assert run_cost(cfg.replace(n_stages=1000, n_per_stage=1000)).needs_confirm
    # whether a run asks first is what it is, not how loaded the machine is when it is priced: 1,000 times slower
    # than the model's idle machine, this run is priced above the limit of seconds and still starts at once
    loaded = run_cost(cfg, slowdown=1000.0)
    assert loaded.seconds > CONFIRM_SECONDS > run_cost(cfg, slowdown=1.0).seconds and not loaded.needs_confirm
    assert cost.text().startswith("240 simulations, ")  # the rollouts are all a cross-entropy run counts
    # then, where the stages' weights back no interval, whatever the scene (the model on T = 100 steps, no problem):
    model = functools.partial(run_cost, n_steps=100)
    # plain Monte Carlo: 500 times the stages' 240, at most a million
    alone = model(cfg.replace(retry_factor=0), slowdown=1.0)
    plain = stage_cost(cfg.replace(method="mc"), "final", 120_000).seconds
    assert (alone.then_simulations, alone.then_seconds) == (120_000, pytest.approx(plain, rel=1e-12))
    said = f"~{duration_text(alone.seconds)}, up to ~{duration_text(alone.seconds + plain)} with 120,000 plain rollouts"
    assert f"{said} if the stages' weights back no interval" in alone.text()
    # before it, their retry at 4 N = 200: 20 + 3 x 200 + 70 = 690 more, and 500 times 240 + 690 plain rollouts; the
    # retry's seconds are its stages' (a learned proposal's), the rest plain rollouts'
    cost = model(cfg, slowdown=1.0)
    assert cost.then_simulations == 690 + 465_000
    again = cfg.replace(n_per_stage=200)
    retry = sum(stage_cost(again, s.kind, s.n_rollouts, stage=s.stage).seconds for s in run_plan(again).stages)
    plain = stage_cost(cfg.replace(method="mc"), "final", 465_000).seconds
    assert cost.then_seconds == pytest.approx(retry + plain, rel=1e-12) and retry > 690 * plain / 465_000
    said = "with 465,690 rollouts if the stages' weights back no interval (their retry at N = 200, then plain"
    assert said in cost.text()
    assert model(cfg, slowdown=2.0).then_seconds == pytest.approx(2.0 * cost.then_seconds, rel=1e-12)
    default = model(ExperimentConfig.of())  # 2,100 simulations: 5,100 and the million cap, no confirmation asked
    assert default.then_simulations == 5_100 + 1_000_000 and not default.needs_confirm
    assert model(cfg.replace(plain_fallback=3)).then_simulations == 690 + 3 * 930
    odd = cfg.replace(scenario="toy", scenario_params=(("total", 10), ("safe", 3), ("braking", "~choice(5, 6, 7)")))
    for none in (cfg.replace(plain_fallback=0), odd):  # none over an operating design domain
        assert model(none).then_simulations == 0 and "up to" not in model(none, slowdown=1.0).text()  # idle
    capped = cfg.replace(rel_error=0.1, max_sims=1_000)  # the run's own cap holds for the fallback too
    assert model(capped).then_simulations == 1_000 - capped.n_simulations
    # a tilt run and a splitting run count more than their rollouts: the line says so before the run
    assert (
        run_cost(cfg.replace(method="tilt", n_per_stage=1280))
        .text()
        .startswith("1,280 simulations plus the proposal's look-aheads, ")
    )
    assert (
        run_cost(cfg.replace(method="ams", n_per_stage=200))
        .text()
        .startswith("200 simulations plus the branches' continuations, ")
    )
    assert parse_number(FIELDS_BY_KEY["n_stages"], "100000")[1].startswith("K: 100000 is out of range")
    assert parse_number(FIELDS_BY_KEY["seed"], str(2**64 - 1)) == (2**64 - 1, "")


@dataclasses.dataclass(frozen=True)
class _CoinSettings(MethodSettings):
    """A method's settings: one row placed in the panel's folder, one not placed."""

    coin_share: float = setting(0.5, "the coin's share eps", "the share drawn by the coin", lo=0.0, panel="advanced")
    coin_flips: int = setting(3, "the coin's flips", "flips per step", kind="int", lo=1)


def test_the_forms_fields_are_the_settings_rows_that_name_a_panel_place():
    # the default method's settings and the fallback's: exactly the fields whose row names a place are in the form,
    # at that place
    from pemviz.settings import FALLBACK, FallbackSettings

    for cls, owner, named in (
        (CrossEntropySettings, CROSS_ENTROPY_METHOD, {"n_stages": "main"}),
        (FallbackSettings, FALLBACK, {"plain_fallback": "advanced", "retry_factor": "advanced"}),
    ):
        placed = {f.name: f.metadata[ROW].get("panel", "") for f in dataclasses.fields(cls)}
        shown = {s.name: s.panel for s in PANEL_ROWS if s.owner == owner}
        assert shown == {name: where for name, where in placed.items() if where}
        assert named.items() <= shown.items()
    assert {s.name for s in NUMBER_FIELDS} == {s.name for s in PANEL_ROWS} - {"weights", "final_estimate"}
    # a setting added to a method's settings class: its row alone puts it in the form, parsed by its own range
    rows = rows_of(_CoinSettings, "coin")
    advanced = panel_rows([*SETTINGS.values(), *rows.values()], "advanced")
    assert advanced[-1] is rows["coin_share"] and rows["coin_flips"] not in advanced
    assert panel_rows(rows.values(), "main") == ()
    assert parse_number(advanced[-1], " 0.25 ") == (0.25, "")
    assert parse_number(advanced[-1], "-1") == (
        None,
        "coin share: -1 is out of range; the coin's share eps must be a number >= 0",
    )


def test_a_run_label_names_every_setting_that_differs_from_the_defaults():
    assert run_label(3, ExperimentConfig.of()) == "run 3 · classic"
    cfg = ExperimentConfig.of(metric="agm", smoothing=0.2, n_stages=4, sim="highway-env", seed=7)
    assert run_label(4, cfg) == "run 4 · agm, K 4, alpha 0.2, seed 7, simulator highway-env"


# -- the failure explanation ----------------------------------------------------------------------
def test_decisive_misses_are_the_misses_whose_flip_avoids_the_crash_in_highway_env():
    """The counterfactual (batched twin) against the black-box highway-env scenario, flip by flip."""
    params = BrakingParams()
    detected = np.ones(params.n_steps, dtype=bool)
    detected[46:69] = False  # 23 misses from about 9 m: a detection early among them still stops in time
    obs = []
    sim = BrakingScenario(params)
    for a in detected:
        obs.append(sim.observation())
        sim.step(bool(a))
    gap = np.array(obs)[:, 0]
    assert gap.min() < params.crash_gap_m
    log_p = np.log(np.full(params.n_steps, 0.5))
    ex = explain(gap, detected, log_p, log_p - 0.1, params)
    assert ex.replay_matches and ex.crashed

    def crashes_with_flip(t: int) -> bool:
        d = detected.copy()
        d[t] = True
        s = BrakingScenario(params)
        gaps = []
        for a in d:
            gaps.append(s.observation()[0])
            s.step(bool(a))
        return min(gaps) < params.crash_gap_m

    truth = [t for t in np.flatnonzero(~detected) if not crashes_with_flip(int(t))]
    assert ex.decisive.tolist() == truth and 0 < len(truth) < 23
    np.testing.assert_allclose(ex.p_detect, 0.5)
    np.testing.assert_allclose(ex.cum_log_weight, 0.1 * np.arange(1, params.n_steps + 1))


# -- one stage numbering --------------------------------------------------------------------------
def test_console_progress_names_stages_as_the_panel_and_recording_do(tiny_record):
    progress = io.StringIO()
    Experiment(TINY, [ConsoleSink(io.StringIO(), progress)], problem=problem_for(TINY)).run()
    lines = [line.split(":")[0].strip() for line in progress.getvalue().splitlines()]
    assert lines == ["pretraining", "CE stage 1/2", "CE stage 2/2", "final batch"]  # K = 2 (TINY)
    panel = [tiny_record.plan.label(s.stage, s.kind) for s in tiny_record.stages]
    assert panel == ["pretraining", "CE stage 1/2", "CE stage 2/2", "final batch"]
    text = progress.getvalue().splitlines()
    # the stage's and the whole run's time left, from the plan before any stage has run (on a loaded machine up to
    # the load's drift: nothing follows a run without a fallback)
    left = r"run ~\d+\.\d s left(, up to ~\d+\.\d s( as the machine's load varies)?)?"
    assert all(re.search(rf"\(elapsed \d+\.\d s, this stage ~\d+\.\d s, {left}\)$", line) for line in text)


# -- export ---------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "name, expected",
    [
        ("../x", "x.rrd"),
        ("../../etc/passwd", "passwd.rrd"),
        ("..\\..\\x", "x.rrd"),
        ("/abs/run 1.rrd", "run_1.rrd"),
        (".hidden", "hidden.rrd"),
        ("agm-0.2", "agm-0.2.rrd"),
        ("x.RRD", "x.rrd"),
    ],
)
def test_export_names_are_file_names_inside_recordings(tmp_path, name, expected):
    assert sanitize_export_name(name) == expected
    path = export_path(tmp_path / "recordings", name)
    assert path == (tmp_path / "recordings").resolve() / expected


@pytest.mark.parametrize("name", ["", "..", "/", "../", " ", "...", "__"])
def test_export_names_with_nothing_usable_are_refused(tmp_path, name):
    with pytest.raises(ValueError, match="export name"):
        export_path(tmp_path, name)


def test_export_refuses_a_symlink_planted_under_the_name(tmp_path):
    rec = tmp_path / "recordings"
    rec.mkdir()
    (rec / "x.rrd").symlink_to(tmp_path / "outside.rrd")
    with pytest.raises(ValueError, match="outside"):
        export_path(rec, "x")


def test_exported_recording_holds_the_runs_final_estimate(tiny_record, tmp_path):
    import rerun as rr

    path = export_run(tiny_record, export_path(tmp_path / "recordings", "../tiny"))
    assert path == (tmp_path / "recordings" / "tiny.rrd").resolve()
    assert sorted(p.name for p in path.parent.iterdir()) == ["tiny.rrd"]
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        client = server.client()
        dataset = client.get_dataset("run")
        finals = dataset.reader(index=None).to_pandas()
    got = float(np.atleast_1d(finals["/final:log_mu_hat"].dropna().iloc[0])[0])
    want = tiny_record.final.estimate.log_mu_hat
    assert got == want or (math.isinf(got) and math.isinf(want))


def test_a_failed_export_leaves_no_file(tiny_record, tmp_path, monkeypatch):
    from pemviz.sinks import recording

    def boom(self, event):
        raise RuntimeError("disk full")

    monkeypatch.setattr(recording.RerunSink, "__call__", boom)
    rec = tmp_path / "recordings"
    with pytest.raises(RuntimeError, match="disk full"):
        export_run(tiny_record, export_path(rec, "x"))
    assert list(rec.iterdir()) == []


def test_the_live_note_says_why_no_q_detect_chart_is_drawn():
    """Why *Live* draws no q(detect) chart: none for braking (its stages are binned by the gap); on the crowd (several
    objects a step and no axis to bin them by) its stages drew from a proposal all the same; plain Monte Carlo drew
    from none."""
    from pemviz.app.charts import marginal_note

    def note(change=None, **settings):
        cfg = TINY.replace(**settings)
        problem = problem_for(cfg) if change is None else dataclasses.replace(problem_for(cfg), **change)
        record = PanelRun(1, cfg)
        record.problem = problem
        Experiment(cfg, [record], problem=problem).run()
        return marginal_note(record)

    assert note() == ""
    assert "its stages drew from a proposal, but its scene gives no axis to bin q(detect) by" in note(scenario="crowd")
    assert "no stage drawn by a proposal yet" in note(scenario="crowd", method="mc", n_per_stage=200)
    # a scene of several objects without their positions (a user's scene on the stack): it said it "reports neither a
    # gap nor the rows of several objects", of a scene that reports the rows of two
    bare = {"objects_xy": None, "noise_xy": None, "thresholds": None}
    assert "its stages drew from a proposal, but its scene gives no axis to bin q(detect) by" in note(
        bare, scenario="crowd"
    )
    assert "its scene gives no axis to bin q(detect) by" in note(bare, scenario="crowd", method="mc", n_per_stage=200)

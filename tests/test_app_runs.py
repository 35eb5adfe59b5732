"""The panel's bookkeeping without a browser: scene geometry, the least-robust list, run records,
config from the controls, export names and files, and the panel's run / stop / validation logic."""

from __future__ import annotations

import html
import math
import time
from pathlib import Path

import numpy as np
import pytest

from pemviz.app.runs import (
    QUICK,
    RunRecord,
    Trajectory,
    config_from_values,
    export_path,
    export_run,
    least_robust,
    sanitize_export_name,
    scene_positions,
)
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.engine import Experiment, RolloutsSampled, StageFinished, StageStarted
from pemviz.scenarios import RolloutBatch
from pemviz.scenarios.braking import BrakingParams, BrakingScenario

TINY = ExperimentConfig(n_stages=2, n_per_stage=20, n_final=20, ce_epochs=20, pretrain_rollouts=10, pretrain_epochs=20)


# -- scene geometry -------------------------------------------------------------------------------
def test_scene_positions_reproduce_the_highway_env_vehicles_positions():
    """Both cars' centres, rebuilt from the recorded (gap, speeds), equal highway-env's own positions."""
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
    traj = Trajectory(0, 0, 0.0, 0.0, False, obs[:, 0], obs[:, 1], obs[:, 2], detections)
    got_ego, got_lead = scene_positions(traj, params)
    np.testing.assert_allclose(got_ego, ego_x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got_lead, lead_x, rtol=0, atol=1e-9)
    assert got_ego[-1] > 20.0  # the ego really moved (not a trivially-zero comparison)


# -- the least-robust list ------------------------------------------------------------------------
def _sampled(stage: int, robustness: list[float]) -> RolloutsSampled:
    n, t = len(robustness), 4
    obs = np.zeros((n, t, 3))
    obs[:, :, 0] = np.arange(n)[:, None] + 5.0  # gap = 5 + rollout index, to check the rows travel along
    names = ("gap_m", "ego_speed_mps", "lead_speed_mps")
    batch = RolloutBatch(obs, np.ones((n, t), bool), np.zeros((n, t)), np.zeros((n, t)), names)
    r = np.array(robustness)
    return RolloutsSampled(stage, "ce", batch, r, {"classic": r}, r < 0, -np.arange(n, dtype=float))


def test_least_robust_keeps_the_n_smallest_over_all_stages_least_first():
    kept = least_robust([], _sampled(0, [3.0, -1.0, 2.0, 0.5]), n=3)
    kept = least_robust(kept, _sampled(1, [1.5, -2.0, 4.0]), n=3)
    assert [(t.stage, t.index, t.robustness) for t in kept] == [(1, 1, -2.0), (0, 1, -1.0), (0, 3, 0.5)]
    assert [t.crashed for t in kept] == [True, True, False]
    assert [t.log_weight for t in kept] == [-1.0, -1.0, -3.0]
    assert kept[2].gap_m[0] == 8.0  # rollout 3's own row
    assert kept[0].key == "s1r1"


# -- run records ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_record() -> RunRecord:
    record = RunRecord(1, TINY)
    progress = []

    def listen(event):
        record(event)
        if isinstance(event, (StageStarted, RolloutsSampled, StageFinished)) and event_stage(event) == 0:
            progress.append(record.progress())

    Experiment(TINY, [listen]).run()
    record.first_stage_progress = progress
    return record


def event_stage(event) -> int:
    return event.result.stage if isinstance(event, StageFinished) else event.stage


def test_run_record_follows_the_run_and_its_progress(tiny_record):
    r = tiny_record
    assert r.status == "finished" and r.final is not None
    assert [s.stage for s in r.stages] == [0, 1, 2, 3] and r.n_stage_events == 4
    # stage 0: started, rollouts sampled, finished -> (run %, stage %)
    assert r.first_stage_progress == [(0.0, 5.0), (0.0, 50.0), (25.0, 100.0)]
    assert r.progress() == (100.0, 100.0)
    gamma = r.stage_series("gamma")
    assert sorted(gamma) == [1, 2]  # only CE stages have a threshold
    assert gamma[1] == r.stages[1].gamma
    rate = r.stage_series("failure_rate")
    assert rate[3] == r.final.estimate.n_failures / r.final.estimate.n
    assert len(r.trajectories) == 20
    everything = np.concatenate([e.robustness for e in r.events if isinstance(e, RolloutsSampled)])
    assert [t.robustness for t in r.trajectories] == sorted(everything)[:20]


# -- config from the controls ---------------------------------------------------------------------
def test_config_from_values_casts_integral_floats_and_reports_the_configs_own_message():
    cfg = config_from_values({"n_stages": 3.0, "n_per_stage": 20, "smoothing": 0.2, "pem": "", "no_such_knob": 1})
    assert (cfg.n_stages, cfg.n_per_stage, cfg.smoothing, cfg.pem) == (3, 20, 0.2, None)
    assert isinstance(cfg.n_stages, int)
    for values, message in (
        ({"smoothing": 0.0}, "alpha must be in (0, 1]"),
        ({"quantile_level": 1.0}, "sigma must be in [0.5, 1)"),
        ({"n_per_stage": 1}, "N must be an integer >= 2"),
        ({"n_stages": 2.5}, "K must be an integer in [1, 1000]"),
    ):
        with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
            config_from_values(values)


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


# -- the panel without a browser ------------------------------------------------------------------
@pytest.fixture(scope="module")
def panel(tmp_path_factory):
    from pemviz.app.panel import PanelApp

    recordings = tmp_path_factory.mktemp("panel") / "rec"
    app = PanelApp("127.0.0.1", 0, recordings_dir=recordings, preset="quick")
    assert app.read_config() == ExperimentConfig(**QUICK) and app.preset.value == "quick"
    yield app
    app.close()


def test_panel_refuses_invalid_values_and_runs_valid_ones(panel):
    panel.controls["n_per_stage"].value = 1
    assert "N must be an integer >= 2" in html.unescape(panel.error_html.content)
    assert panel.start_run() == "n_per_stage (N) = 1 is invalid: N must be an integer >= 2"
    assert panel.current is None and not panel.running
    assert "Run refused" in panel.error_html.content
    panel.controls["n_per_stage"].value = 20
    assert panel.error_html.content == ""
    panel.controls["n_stages"].value = 2
    assert panel.start_run() is None
    assert panel.start_run() == "a run is going: press Stop first"
    assert panel.wait_for_run(60)
    assert panel.current.status == "finished" and "Final estimate" in panel.result_html.content


def test_panel_stop_cancels_within_2_s_and_keeps_at_most_3_runs(panel):
    panel.controls["n_stages"].value = 50
    ids = []
    for _ in range(4):
        assert panel.start_run() is None
        record = panel.current
        ids.append(record.run_id)
        t0 = time.monotonic()
        while len(record.stages) < 2 and time.monotonic() - t0 < 60:
            time.sleep(0.02)
        panel.stop_run()
        assert panel.wait_for_run(10)
        assert record.status == "cancelled" and panel.last_stop_latency_s < 2.0
    assert [r.run_id for r in panel.runs] == ids[-3:]  # the oldest was dropped
    assert len(panel.compare_plots) == 3

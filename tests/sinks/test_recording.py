"""The rerun recording of a run, read back through rerun's own API (a local catalog server + DataFusion).

Small runs (K = 3, N = 20, and a naive-50 run of 30 rollouts that crashes often) are recorded once per
module; the tests compare what the recording holds with the engine's events and with an independent
replay of the braking scenario.
"""

from __future__ import annotations

import io
import math
import re
import threading

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")

from pemviz import cli  # noqa: E402
from pemviz.config import ExperimentConfig  # noqa: E402
from pemviz.engine import experiment as engine  # noqa: E402
from pemviz.engine.events import FinalEstimate, RolloutsSampled, RunStarted, StageFinished  # noqa: E402
from pemviz.engine.experiment import Experiment  # noqa: E402
from pemviz.scenarios.braking.failures import severity  # noqa: E402
from pemviz.scenarios.braking.simulator import BrakingParams, BrakingScenario  # noqa: E402
from pemviz.scenarios.problems import problem_for  # noqa: E402
from pemviz.sinks.console import ConsoleSink  # noqa: E402
from pemviz.sinks.recording import RerunSink  # noqa: E402
from pemviz.sinks.rerun_views import (  # noqa: E402
    CRASH_RGBA,
    DETECTED_RGBA,
    MISSED_RGBA,
    PROPOSAL_FIG,
    SAFE_RGBA,
    TAG_CRASH_RGBA,
    TAG_RGBA,
    nice_ticks,
)

from conftest import verify_rrd  # noqa: E402

SMALL = dict(
    n_stages=3,
    n_per_stage=20,
    n_final=20,
    ce_epochs=30,
    pretrain_epochs=50,
    pretrain_rollouts=20,
    seed=5,
    plain_fallback=0,
)
"""A few seconds of the cross-entropy sampler, its stages alone (too small to back an interval: by default plain Monte
Carlo would follow, a stage without a proposal curve; ``test_a_run_followed_by_plain_monte_carlo_records_its_batches``
records one)."""
MU_RE = re.compile(r"(?:mu_hat = (\S+)|no failure seen) \(log mu_hat = (\S+) nats\)")
CURVE_RE = re.compile(r"/proposal/data/stage_\d\d:LineStrips2D:strips")


def packed(rgba) -> int:
    """rerun stores a colour as one uint32 0xRRGGBBAA."""
    r, g, b, a = rgba
    return (r << 24) | (g << 16) | (b << 8) | a


def record(path, cfg: ExperimentConfig, extra_listeners=(), cancel=None):
    """Run ``cfg`` with a console sink (to a string), the rerun sink (with the run's problem) and an event log."""
    events: list = []
    out = io.StringIO()
    problem = problem_for(cfg)
    sink = RerunSink.to_file(path, problem=problem)
    try:
        Experiment(
            cfg, [ConsoleSink(out, io.StringIO()), sink, events.append, *extra_listeners], cancel, problem=problem
        ).run()
    finally:
        sink.close()
    return events, out.getvalue()


def read(path_by_name: dict) -> dict:
    """{name: {index: pyarrow table}} for the static data and the ``step`` and ``stage`` timelines."""
    tables = {}
    with rr.server.Server(datasets={name: [str(p)] for name, p in path_by_name.items()}) as server:
        client = server.client()
        for name in path_by_name:
            ds = client.get_dataset(name)
            tables[name] = {
                "static": ds.reader(index=None).to_arrow_table(),
                "step": ds.reader(index="step").to_arrow_table(),
                "stage": ds.reader(index="stage").to_arrow_table(),
            }
    return tables


def column(table, name: str) -> list:
    assert name in table.column_names, f"{name} not in the recording"
    return table.column(name).to_pylist()


def static_value(tables, name: str):
    """The one static value (a list of instances) of a column."""
    values = [v for v in column(tables["static"], name) if v is not None]
    assert len(values) == 1, name
    return values[0]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("recording")
    adaptive = record(d / "adaptive.rrd", ExperimentConfig.of(**SMALL))
    naive = record(d / "naive.rrd", ExperimentConfig.of(method="naive50", n_per_stage=30, seed=2))
    tables = read({"adaptive": d / "adaptive.rrd", "naive": d / "naive.rrd"})
    return {
        "adaptive": (adaptive[0], adaptive[1], tables["adaptive"], d / "adaptive.rrd"),
        "naive": (naive[0], naive[1], tables["naive"], d / "naive.rrd"),
    }


def featured_rows(tables, stage: int) -> list[int]:
    """Batch rows of a stage's featured rollouts (their own entities under ``/rollouts/gap_m/stage_KK/``), ascending."""
    prefix = f"/rollouts/gap_m/stage_{stage:02d}/rollout_"
    numbers = {int(c[len(prefix) :].split(":")[0]) for c in tables["static"].column_names if c.startswith(prefix)}
    return sorted(numbers)


def of(events, kind):
    return [e for e in events if isinstance(e, kind)]


def stage_estimates(events) -> list:
    """The estimate of each finished stage, in order."""
    from pemviz.engine.events import StageFinished

    return [ev.result.estimate for ev in of(events, StageFinished)]


def test_recordings_verify_and_are_renamed_from_partial(runs):
    for _, _, _, path in runs.values():
        assert path.is_file() and not path.with_name(path.name + ".partial").exists()
        verify_rrd(path)


def test_one_proposal_curve_per_stage_in_0_1_equal_to_the_stage_results(runs):
    events, _, tables, _ = runs["adaptive"]
    results = [e.result for e in of(events, StageFinished)]
    grid = of(events, RunStarted)[0].curve_grid_m
    names = sorted(c for c in tables["static"].column_names if CURVE_RE.fullmatch(c))
    # pretraining (stage 0), the K = 3 CE stages and the final batch (drawn from stage 3's proposal)
    assert names == [f"/proposal/data/stage_{k:02d}:LineStrips2D:strips" for k in range(5)]
    np.testing.assert_array_equal(results[4].proposal_curve, results[3].proposal_curve)
    for res in results:
        (strip,) = static_value(tables, f"/proposal/data/stage_{res.stage:02d}:LineStrips2D:strips")
        xy = np.asarray(strip)
        assert xy.shape == (grid.size, 2)
        assert np.all((xy[:, 1] >= 0) & (xy[:, 1] <= 1))
        np.testing.assert_allclose(xy[:, 0], grid, atol=1e-6)
        np.testing.assert_allclose(xy[:, 1], res.proposal_curve, atol=1e-6)  # float32 storage
    (pem,) = static_value(tables, "/proposal/data/pem:LineStrips2D:strips")
    np.testing.assert_allclose(np.asarray(pem)[:, 1], of(events, RunStarted)[0].pem_curve, atol=1e-6)


def test_final_mu_hat_logged_equals_the_printed_one(runs):
    for events, printed, tables, _ in runs.values():
        m = MU_RE.search(printed)
        assert m, printed
        logged = static_value(tables, "/final:log_mu_hat")[0]
        assert logged == pytest.approx(float(m.group(2)), abs=5e-5)
        assert logged == of(events, FinalEstimate)[0].estimate.log_mu_hat


def test_every_rollout_gap_trace_has_T_points_equal_to_the_batch(runs):
    for events, _, tables, _ in runs.values():
        table = tables["step"]
        steps = column(table, "step")
        for ev in of(events, RolloutsSampled):
            rows = column(table, f"/rollouts/gap_m/stage_{ev.stage:02d}:Scalars:scalars")
            got = {s: v for s, v in zip(steps, rows, strict=False) if v is not None}
            assert sorted(got) == list(range(ev.batch.n_steps))  # T points per rollout
            trace = np.array([got[t] for t in range(ev.batch.n_steps)]).T  # [N, T]
            np.testing.assert_array_equal(trace, ev.batch.signal("gap_m"))
            rows = featured_rows(tables, ev.stage)  # the stage's featured rollouts, ascending
            gap = ev.batch.signal("gap_m")[rows]
            # marked where a detection still matters: inside 10 m, up to the first step below 2 m
            matters = (gap < 10.0) & (np.cumsum(gap < 2.0, axis=1) - (gap < 2.0) == 0)
            for key, seen in (("detected", True), ("missed", False)):
                marks = column(table, f"/rollouts/{key}/stage_{ev.stage:02d}:Scalars:scalars")
                marks = np.array([m for m in marks if m is not None]).T  # [featured, T]
                np.testing.assert_array_equal(np.isfinite(marks), (ev.batch.detected[rows, :, 0] == seen) & matters)
                np.testing.assert_array_equal(
                    marks[np.isfinite(marks)], ev.batch.signal("gap_m")[rows][np.isfinite(marks)]
                )


def test_crashes_are_red_and_the_least_robust_rollouts_tagged(runs):
    events, _, tables, _ = runs["naive"]
    (ev,) = of(events, RolloutsSampled)
    assert 0 < ev.failed.sum() < ev.failed.size  # the naive-50 run crashes in some rollouts, not all
    colours = static_value(tables, "/rollouts/gap_m/stage_01:SeriesLines:colors")
    names = static_value(tables, "/rollouts/gap_m/stage_01:SeriesLines:names")
    tagged = set(np.argsort(ev.robustness, kind="stable")[:3].tolist())
    for i, (c, name) in enumerate(zip(colours, names, strict=False)):
        if i in tagged:
            assert c == packed(TAG_CRASH_RGBA if ev.failed[i] else TAG_RGBA) and "least-robust" in name
        else:
            assert c == packed(CRASH_RGBA if ev.failed[i] else SAFE_RGBA) and "least-robust" not in name
        # a failure's words: contact (gap at or below 0.7 m, the camera-to-rear gap of a collision) or breach
        low = ev.batch.signal("gap_m")[i].min()
        said = ("contact at " in name) if low <= 0.7 else (f"breach {low:.2f} m, no contact" in name)
        assert said == bool(ev.failed[i]) and ("contact" in name or "breach" in name) == bool(ev.failed[i])
    summary = {
        k: static_value(tables, f"/rollouts/summary/stage_01:{k}")
        for k in ("failed", "least_robust", "log_weight", "robustness_classic", "robustness_agm")
    }
    assert summary["failed"] == ev.failed.tolist()
    assert [i for i, t in enumerate(summary["least_robust"]) if t] == sorted(tagged)
    np.testing.assert_array_equal(summary["log_weight"], ev.log_weight)
    np.testing.assert_array_equal(summary["robustness_agm"], ev.robustness_by_metric["agm"])


def test_stage_series_hold_each_stage_result(runs):
    events, _, tables, _ = runs["adaptive"]
    table = tables["stage"]
    stages = column(table, "stage")
    rate = dict(zip(stages, column(table, "/stages/failure_rate:Scalars:scalars"), strict=False))
    ess = dict(zip(stages, column(table, "/stages/ess:Scalars:scalars"), strict=False))
    results = [e.result for e in of(events, StageFinished)]
    assert sorted(rate) == [r.stage for r in results] == [0, 1, 2, 3, 4]
    for r in results:
        assert rate[r.stage] == [r.estimate.n_failures / r.estimate.n]
        assert ess[r.stage] == [pytest.approx(r.estimate.ess)]


def test_scene_boxes_follow_a_replay_of_the_braking_scenario(runs):
    """The ego and lead boxes of each scene lane sit where highway-env puts the cars for that rollout."""
    p = BrakingParams()
    for name in ("adaptive", "naive"):
        events, _, tables, _ = runs[name]
        steps = column(tables["step"], "step")
        for ev in of(events, RolloutsSampled):
            i = int(np.argmin(ev.robustness))
            path = f"/scene/stage_{ev.stage:02d}"
            ego = dict(zip(steps, column(tables["step"], f"{path}/ego:Boxes2D:centers"), strict=False))
            lead = dict(zip(steps, column(tables["step"], f"{path}/lead:Boxes2D:centers"), strict=False))
            half = dict(zip(steps, column(tables["step"], f"{path}/lead:Boxes2D:half_sizes"), strict=False))
            sim = BrakingScenario(p)
            truth = []
            for t in range(ev.batch.n_steps):
                truth.append((sim.ego.position[0], sim.lead.position[0]))
                sim.step(bool(ev.batch.detected[i, t, 0]))
            logged = [(ego[t][0][0], lead[t][0][0]) for t in range(ev.batch.n_steps)]
            np.testing.assert_allclose(logged, truth, atol=1e-4)  # float32 positions up to ~40 m
            assert half[0][0] == pytest.approx([p.lead_length_m / 2, p.vehicle_width_m / 2])


def test_properties_carry_the_pemviz_and_rerun_versions(runs):
    import pemviz
    from rerun.catalog import ContentFilter

    _, _, _, path = runs["adaptive"]
    with rr.server.Server(datasets={"run": [str(path)]}) as server:
        ds = server.client().get_dataset("run")
        table = ds.filter_contents(ContentFilter.nothing().include_properties()).reader(index=None).to_arrow_table()
    values = {c.split(":")[-1]: v for c in table.column_names for v in table.column(c).to_pylist() if v is not None}
    assert values["pemviz_version"] == [pemviz.__version__]
    assert values["rerun_sdk_version"] == [rr.__version__]


def test_figure_transform_maps_the_axis_ranges_onto_the_plot_box(runs):
    _, _, tables, _ = runs["adaptive"]
    t = np.asarray(static_value(tables, "/proposal/data:Transform3D:translation")[0])
    s = np.asarray(static_value(tables, "/proposal/data:Transform3D:scale")[0])
    # (0 m, probability 0) -> bottom left (0, height); (13 m, 1) -> top right (width, 0): rerun's y points down
    np.testing.assert_allclose(t + s * [0.0, 0.0, 0.0], [0.0, PROPOSAL_FIG.height, 0.0], atol=1e-4)
    np.testing.assert_allclose(t + s * [13.0, 1.0, 0.0], [PROPOSAL_FIG.width, 0.0, 0.0], atol=1e-4)


def test_nice_ticks_are_round_and_cover_the_range():
    np.testing.assert_allclose(nice_ticks(0.0, 13.0, 6), [0, 2, 4, 6, 8, 10, 12])  # 13 / 6 = 2.17 -> 2
    np.testing.assert_allclose(nice_ticks(0.0, 1.0, 5), [0, 0.2, 0.4, 0.6, 0.8, 1.0])
    np.testing.assert_allclose(nice_ticks(-0.3, 1.2, 5), [-0.2, 0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2])  # 0.3 -> 0.2
    np.testing.assert_allclose(nice_ticks(-63.0, 2.0, 5), [-60, -50, -40, -30, -20, -10, 0])  # 13 -> 10


def _stages_in(path) -> tuple[list[int], list[str], str]:
    tables = read({"run": path})["run"]
    rates = zip(
        column(tables["stage"], "stage"), column(tables["stage"], "/stages/failure_rate:Scalars:scalars"), strict=False
    )
    stages = [s for s, v in rates if v]
    curves = sorted(c.split("/")[3][:8] for c in tables["static"].column_names if CURVE_RE.fullmatch(c))
    text = static_value(tables, "/description:TextDocument:text")[0]
    gaps = [c for c in tables["step"].column_names if re.fullmatch(r"/rollouts/gap_m/stage_\d\d:Scalars:scalars", c)]
    assert len(gaps) == len(stages)
    return stages, curves, text


def test_ctrl_c_after_stage_3_of_pemviz_run_leaves_a_valid_recording_of_stages_0_to_3(tmp_path, monkeypatch):
    """KeyboardInterrupt from a listener after stage 3: ``pemviz run``'s ``finally`` closes the recording."""

    class InterruptedAfterStage3(engine.Experiment):
        def __init__(self, config, listeners=(), cancel=None, *, problem):
            def interrupt(event):
                if isinstance(event, StageFinished) and event.result.stage == 3:
                    raise KeyboardInterrupt

            config = config.replace(pretrain_rollouts=20, pretrain_epochs=50)
            super().__init__(config, [*listeners, interrupt], cancel, problem=problem)

    monkeypatch.setattr(engine, "Experiment", InterruptedAfterStage3)
    out = tmp_path / "cut.rrd"
    assert cli.main(["run", "--k", "6", "--n", "20", "--n-final", "20", "--ce-epochs", "30", "--save", str(out)]) == 130
    assert out.is_file() and not (tmp_path / "cut.rrd.partial").exists()
    verify_rrd(out)
    stages, curves, text = _stages_in(out)
    assert stages == [0, 1, 2, 3]
    assert curves == [f"stage_{k:02d}" for k in range(4)]
    assert "Interrupted** after 4 finished stages" in text


def test_cancel_token_after_stage_3_leaves_a_valid_recording_of_stages_0_to_3(tmp_path):
    cancel = threading.Event()

    def cancel_after_stage_3(event):
        if isinstance(event, StageFinished) and event.result.stage == 3:
            cancel.set()

    out = tmp_path / "cancelled.rrd"
    record(out, ExperimentConfig.of(**{**SMALL, "n_stages": 6}), [cancel_after_stage_3], cancel)
    verify_rrd(out)
    stages, curves, text = _stages_in(out)
    assert stages == [0, 1, 2, 3]
    assert curves == [f"stage_{k:02d}" for k in range(4)]
    assert "Run cancelled** (cancelled by the user) after 4 finished stages" in text


def test_scrubbing_the_stage_timeline_steps_the_proposal_curve_and_the_histograms(runs):
    events, _, tables, _ = runs["adaptive"]
    table = tables["stage"]
    stages = column(table, "stage")
    curves = dict(zip(stages, column(table, "/proposal/data/current:LineStrips2D:strips"), strict=False))
    results = {e.result.stage: e.result for e in of(events, StageFinished)}
    for k, res in results.items():
        (strip,) = curves[k]
        np.testing.assert_allclose(np.asarray(strip)[:, 1], res.proposal_curve, atol=1e-6)
    hist = dict(zip(stages, column(table, "/histograms/robustness:BarChart:values"), strict=False))
    for ev in of(events, RolloutsSampled):
        (tensor,) = hist[ev.stage]
        assert sum(tensor["buffer"]) == ev.robustness.size  # every rollout counted once


def test_the_estimate_view_and_series_carry_the_interval_verdict_and_stage_names(runs):
    events, _, tables, _ = runs["adaptive"]
    final = of(events, FinalEstimate)[0].estimate
    text = static_value(tables, "/estimate:TextDocument:text")[0]
    shown = final.interval_text() if final.interval_backed else final.bound_text()  # a bound where none is backed
    assert text.startswith("# Final estimate") and shown in text and final.verdict in text
    table = tables["stage"]
    lo = [v for v in column(table, "/stages/log10_mu_hat/ci_low:Scalars:scalars") if v]
    high = "/stages/log10_mu_hat/ci_high:Scalars:scalars"  # logged only where an interval is backed
    hi = [v for v in column(table, high) if v] if high in table.column_names else []
    mu = [v for v in column(table, "/stages/log10_mu_hat:Scalars:scalars") if v]
    assert len(lo) == len(mu) and all(a[0] <= m[0] for a, m in zip(lo, mu, strict=False))
    # an upper end only for the stages whose weights back an interval (the others show their lower bound alone)
    backed = [e for e in stage_estimates(events) if math.isfinite(e.log10_mu_hat) and e.interval_backed]
    assert len(hi) == len(backed) and all(
        b[0] == pytest.approx(e.log_ci[1] / math.log(10.0), rel=1e-6) for b, e in zip(hi, backed, strict=False)
    )
    description = static_value(tables, "/description:TextDocument:text")[0]
    for name in ("| 0 | pretraining |", "| 1 | CE stage 1/3 |", "| 4 | final batch |"):
        assert name in description


def test_the_gap_view_has_the_2_m_and_10_m_lines(runs):
    _, _, tables, _ = runs["naive"]
    names = static_value(tables, "/rollouts/gap_m/thresholds:SeriesLines:names")
    assert names == ["crash gap 2 m", "braking distance 10 m"]
    rows = [v for v in column(tables["step"], "/rollouts/gap_m/thresholds:Scalars:scalars") if v is not None]
    assert len(rows) == BrakingParams().n_steps and all(v == [2.0, 10.0] for v in rows)


def test_large_stages_keep_the_least_robust_failures_and_a_uniform_sample():
    from pemviz.sinks.rerun_views import ALL_ROLLOUTS_UP_TO, SAMPLED_ROLLOUTS

    n = 20 * ALL_ROLLOUTS_UP_TO
    rng = np.random.default_rng(0)
    r = rng.normal(size=n)
    failed = r < -2.5
    ev = RolloutsSampled(1, "ce", None, r, {"classic": r}, failed, np.zeros(n))
    sink = RerunSink(rr.RecordingStream("test"))
    keep = sink.kept_rollouts(ev)
    assert set(np.argsort(r)[:3]) <= set(keep) and set(np.flatnonzero(failed)[:SAMPLED_ROLLOUTS]) <= set(keep)
    assert {0, n - 1} <= set(keep) and len(keep) <= 2 * SAMPLED_ROLLOUTS + 3
    small = RolloutsSampled(1, "ce", None, r[:50], {}, failed[:50], np.zeros(50))
    assert sink.kept_rollouts(small).tolist() == list(range(50))


# -- the Explain tab, the featured rollouts and the marginal proposal, read back -------------------------------------


def highway_env_min_gap(detected: np.ndarray) -> float:
    """The smallest gap (metres) of the braking scenario on highway-env's vehicles with these detections: an
    independent replay (not the batched twin the explanation searches on)."""
    sim = BrakingScenario(BrakingParams())
    low = np.inf
    for seen in detected:
        low = min(low, sim.gap_m)
        sim.step(bool(seen))
    return low


def explained(tables) -> dict:
    """The most likely failure's properties (``/explain/failure``), name -> value."""
    prefix = "/explain/failure:"
    out = {}
    for c in tables["static"].column_names:
        if c.startswith(prefix):
            (value,) = [v for v in column(tables["static"], c) if v is not None]
            out[c[len(prefix) :]] = value[0] if len(value) == 1 else value
    return out


@pytest.mark.parametrize("name", ["naive", "adaptive"])
def test_the_most_likely_failure_is_read_back_with_a_minimal_miss_set_that_highway_env_confirms(runs, name):
    events, _, tables, _ = runs[name]
    # the failing rollout with the largest sum of log p over T - 1 steps, found here from the events
    best = max(
        (
            (float(ev.batch.log_p[i, :-1].sum()), ev.stage, int(i))
            for ev in of(events, RolloutsSampled)
            for i in np.flatnonzero(ev.failed)
        ),
        key=lambda x: x[0],
    )
    log_p, stage, i = best
    props = explained(tables)
    assert (props["stage"], props["rollout"]) == (stage, i)
    assert props["log_p"] == pytest.approx(log_p, abs=1e-9)
    (ev,) = [e for e in of(events, RolloutsSampled) if e.stage == stage]
    detected = ev.batch.detected[i, :, 0]
    assert highway_env_min_gap(detected) < 2.0  # it fails
    low = ev.batch.signal("gap_m")[i].min()
    assert props["outcome"] == (f"breach {low:.2f} m, no contact" if low > 0.7 else props["outcome"])
    assert props["outcome"].startswith("contact at ") == (low <= 0.7)
    misses = np.flatnonzero(~detected)
    np.testing.assert_array_equal(np.atleast_1d(props["misses"]), misses)
    # the minimal miss set: all misses; detecting at them avoids the failure, leaving any one out does not
    ms = np.atleast_1d(np.asarray(props["minimal_miss_set"], dtype=np.int64))
    assert ms.size > 0 and set(ms) <= set(misses)
    fixed = detected.copy()
    fixed[ms] = True
    assert highway_env_min_gap(fixed) >= 2.0
    assert props["minimal_set_min_gap_m"] == pytest.approx(highway_env_min_gap(fixed), abs=1e-6)
    for j in range(ms.size):
        partial = detected.copy()
        partial[np.delete(ms, j)] = True
        assert highway_env_min_gap(partial) < 2.0
    # the last saving step: one detection there avoids the failure, one at any later miss does not
    last = props["last_saving_step"]
    for t in misses[misses > max(last, -1)]:
        later = detected.copy()
        later[t] = True
        assert highway_env_min_gap(later) < 2.0
    if last >= 0:
        saved = detected.copy()
        saved[last] = True
        assert highway_env_min_gap(saved) >= 2.0
    # the summary names it, and the rollout is also an entity of its own with the same words
    text = static_value(tables, "/explain/summary:TextDocument:text")[0]
    assert f"rollout {i}" in text and props["outcome"] in text
    featured = static_value(tables, f"/rollouts/gap_m/stage_{stage:02d}/rollout_{i:03d}:outcome")
    assert featured == [props["outcome"]]


def test_p_and_q_along_the_most_likely_failure_are_its_detectors_probabilities_and_misses_are_marked(runs):
    events, _, tables, _ = runs["naive"]
    props = explained(tables)
    (ev,) = [e for e in of(events, RolloutsSampled) if e.stage == props["stage"]]
    i = props["rollout"]
    step = column(tables["step"], "step")
    series = {
        k: dict(zip(step, column(tables["step"], f"/explain/detect/{k}:Scalars:scalars"), strict=False))
        for k in ("pem", "sampler", "misses")
    }
    q = np.array([series["sampler"][t][0] for t in range(ev.batch.n_steps)])
    p = np.array([series["pem"][t][0] for t in range(ev.batch.n_steps)])
    d = ev.batch.detected[i, :, 0]
    # the naive-50 sampler detects with probability 1/2 everywhere; the PEM's p(detect) from its log p
    np.testing.assert_allclose(q, 0.5, atol=1e-12)
    np.testing.assert_allclose(np.where(d, p, 1 - p), np.exp(ev.batch.log_p[i]), rtol=1e-12)
    marked = sorted(t for t, v in series["misses"].items() if v is not None)
    assert marked == np.flatnonzero(~d).tolist()


def test_the_featured_rollouts_are_each_an_entity_with_stage_log_p_robustness_and_severity(runs):
    events, _, tables, _ = runs["adaptive"]
    for ev in of(events, RolloutsSampled):
        rows = featured_rows(tables, ev.stage)
        least = np.argsort(ev.robustness, kind="stable")[:3]
        failed = np.flatnonzero(ev.failed)
        likely = failed[np.argsort(-ev.batch.log_p[failed, :-1].sum(axis=1), kind="stable")[:3]]
        assert rows == sorted(set(least.tolist()) | set(likely.tolist()))
        for i in rows:
            path = f"/rollouts/gap_m/stage_{ev.stage:02d}/rollout_{i:03d}"
            value = {k: static_value(tables, f"{path}:{k}")[0] for k in ("stage", "log_p", "robustness", "min_gap_m")}
            assert value["stage"] == ev.stage and value["robustness"] == pytest.approx(ev.robustness[i])
            assert value["log_p"] == pytest.approx(ev.batch.log_p[i, :-1].sum(), abs=1e-9)
            assert value["min_gap_m"] == pytest.approx(ev.batch.signal("gap_m")[i].min())
            steps = column(tables["step"], "step")
            trace = [
                v
                for s, v in zip(steps, column(tables["step"], f"{path}:Scalars:scalars"), strict=False)
                if v is not None
            ]
            np.testing.assert_array_equal(np.array(trace)[:, 0], ev.batch.signal("gap_m")[i])


def test_the_marginal_proposal_shows_q_miss_inside_10_m_above_the_pems(runs):
    """Per gap bin the mean q(detect) over the visited states, computed here from the rollouts; the final batch's
    sampler misses inside 10 m far more often than the PEM does (the acceptance of the honest proposal view)."""
    events, _, tables, _ = runs["adaptive"]
    table = tables["stage"]
    stages = column(table, "stage")
    stats = {
        k: dict(zip(stages, column(table, f"/proposal_marginal/stats:{k}"), strict=False))
        for k in ("edges_m", "q_mean", "p_mean", "q_miss_window", "p_miss_window")
    }
    bars = dict(zip(stages, column(table, "/proposal_marginal/miss/d_q:BarChart:values"), strict=False))
    for ev in of(events, RolloutsSampled):
        edges = np.asarray(stats["edges_m"][ev.stage])
        q_mean = np.asarray(stats["q_mean"][ev.stage], dtype=float)
        gap, d, lq = ev.batch.signal("gap_m").ravel(), ev.batch.detected[..., 0].ravel(), ev.batch.log_q.ravel()
        q = np.where(d, np.exp(lq), 1 - np.exp(lq))
        for b in (5, 15, 19):  # 2.5-3 m, 7.5-8 m, 9.5-10 m
            inside = (gap >= edges[b]) & (gap < edges[b + 1])
            if inside.any():
                assert q_mean[b] == pytest.approx(q[inside].mean(), rel=1e-9)
        assert np.allclose(np.asarray(bars[ev.stage][0]["buffer"]), np.nan_to_num(1 - q_mean), atol=1e-9)
    final = max(stats["q_miss_window"])
    assert stats["q_miss_window"][final][0] > 3 * stats["p_miss_window"][final][0]


def test_the_naive_50_samplers_marginal_q_is_one_half_in_every_visited_bin(runs):
    events, _, tables, _ = runs["naive"]
    (q_mean,) = [v for v in column(tables["stage"], "/proposal_marginal/stats:q_mean") if v is not None]
    q_mean = np.asarray(q_mean, dtype=float)
    assert np.isfinite(q_mean).sum() > 10
    np.testing.assert_allclose(q_mean[np.isfinite(q_mean)], 0.5, atol=1e-12)


def assert_every_view_has_data(events: list, tables: dict) -> None:
    """What a user sees as the recording opens (on ``step``, for every tab): each view has rows on ``step`` or static
    ones (a figure of the Stages tab: its data or its note, not only its axes), for the layout the recording
    carries."""
    import rerun.blueprint as rrb
    from pemviz.sinks.rerun_blueprint import TIMELINE, default_blueprint

    bp = default_blueprint(5, of(events, RunStarted)[0].problem)
    tabs = [c for c in bp.root_container.contents if isinstance(c, rrb.Tabs)][0].contents

    def views(part):
        inner = getattr(part, "contents", None)
        if isinstance(inner, (list, tuple)) and hasattr(part, "kind"):
            return [v for child in inner for v in views(child)]
        return [part]

    for key, tab in zip(("stages", "explain", "rollouts"), tabs, strict=False):
        table, static = tables[TIMELINE[key]], tables["static"]
        filled = [c for c in table.column_names if c.startswith("/") and any(x is not None for x in column(table, c))]
        temporal_only = ("Scalars", "BarChart", "Series")  # a static style is no data
        filled += [c for c in static.column_names if c.startswith("/") and not any(k in c for k in temporal_only)]
        for v in views(tab):
            queries = [str(v.origin)] + [
                str(q).lstrip("+ ") for q in (v.contents if isinstance(v.contents, list) else [])
            ]
            roots = {"/" + q.replace("$origin", str(v.origin)).replace("/**", "").strip("/") for q in queries}
            if any(r.startswith("/stage_figures/") for r in roots):  # a figure: its data, not only its axes
                roots = {r + "/data" for r in roots}
            shown = [c for c in filled if any(c.startswith(r + "/") or c.startswith(r + ":") for r in roots)]
            assert shown, f"{v.name} ({key}) shows nothing on {TIMELINE[key]}"


def test_every_view_of_each_tab_has_data_on_the_timeline_the_recording_opens_with(runs):
    events, _, tables, _ = runs["adaptive"]
    assert_every_view_has_data(events, tables)


def test_the_share_of_failures_with_contact_per_stage(runs):
    events, _, tables, _ = runs["naive"]
    (ev,) = of(events, RolloutsSampled)
    stages = column(tables["stage"], "stage")
    share = dict(zip(stages, column(tables["stage"], "/stages/contact_share:Scalars:scalars"), strict=False))
    low = ev.batch.signal("gap_m")[ev.failed].min(axis=1)
    assert share[ev.stage] == [pytest.approx(np.mean(low <= 0.7))]


def test_the_braking_drawing_says_which_rollouts_made_contact_at_once_as_each_rollouts_outcome_does(runs):
    """``contacts`` (the drawing object's optional hook, :func:`pemviz.sinks.rerun_views.contact_share`) equals the
    ``contact`` of each rollout's outcome values, failing and safe rollouts alike, and the share is the same."""
    from pemviz.sinks.rerun_views import contact_share, outcome_values

    events, _, _, _ = runs["naive"]
    (ev,) = of(events, RolloutsSampled)
    drawing = of(events, RunStarted)[0].problem.drawing
    rows = np.arange(ev.batch.n)
    each = [bool(outcome_values(drawing, ev.batch, int(i))["contact"]) for i in rows]
    assert drawing.contacts(ev.batch, rows).tolist() == each and any(each)
    failing = np.flatnonzero(ev.failed)
    assert contact_share(drawing, ev.batch, ev.failed) == {"contact_share": float(np.mean([each[i] for i in failing]))}


def test_a_cut_in_recording_shows_every_object_detected_missed_or_unseen_and_where_it_was_measured(tmp_path):
    from pemviz.scenarios.cut_in.scenario import OBJECT_NAMES

    cfg = ExperimentConfig.of(
        scenario="cut-in",
        n_stages=2,
        n_per_stage=60,
        n_final=60,
        ce_epochs=30,
        pretrain_epochs=50,
        pretrain_rollouts=60,
        seed=2,
        plain_fallback=0,  # the stages' rollouts: no retry, no plain rollout for the test to hold
    )
    events, _ = record(tmp_path / "cut_in.rrd", cfg)
    failures = [e for e in events if isinstance(e, RolloutsSampled) and e.failed.any()]
    assert failures, "the run found no failure to explain"
    tables = read({"c": tmp_path / "cut_in.rrd"})["c"]
    assert_every_view_has_data(events, tables)  # the cut-in's layout as opened, too
    step = tables["step"]
    # no exact answer: the estimate stands beside the plain Monte Carlo reference, in words and as a series
    text = static_value(tables, "/estimate:TextDocument:text")[0]
    assert "reference 7.95e-05 [7.50e-05, 8.41e-05] (1,176 failures in 14,800,000 rollouts" in text
    reference = [v for v in column(tables["stage"], "/stages/log10_mu_hat/reference:Scalars:scalars") if v]
    assert reference and all(v[0] == pytest.approx(np.log10(1176 / 14.8e6), abs=1e-9) for v in reference)
    true = [p for p in column(step, "/explain/objects/true:Points2D:positions") if p]
    m = 5
    assert len(true) == 100 and all(len(p) == m for p in true)
    measured = [p for p in column(step, "/explain/objects/measured:Points2D:positions") if p is not None]
    colours = [c for c in column(step, "/explain/objects/true:Points2D:colors") if c]
    green, orange = packed(DETECTED_RGBA), packed(MISSED_RGBA)
    n_green = sum(c.count(green) for c in colours)
    assert n_green == sum(len(p) for p in measured) > 0  # one measurement per detected object and step
    assert sum(c.count(orange) for c in colours) > 0
    assert any(c.startswith("/explain/detect/object_4/") for c in step.column_names)
    assert "visible" in OBJECT_NAMES
    # the tracker's estimate: a box per tracked car and step, where the rollout's rows put it (the true position plus
    # the track's error along and across the road); the rollout found by its true positions
    true_xy = np.array(true, dtype=np.float64)  # [T, M, 2]: right, -ahead
    col = {name: OBJECT_NAMES.index(name) for name in ("loc_x", "loc_z", "tracked", "track_err_x_m", "track_err_y_m")}
    rows = next(
        e.batch.objects[i]
        for e in failures
        for i in np.flatnonzero(e.failed)
        if np.allclose(
            np.stack([e.batch.objects[i][:, :, col["loc_x"]], -e.batch.objects[i][:, :, col["loc_z"]]], -1),
            true_xy,
            atol=1e-4,
        )
    )
    has = rows[:, :, col["tracked"]] > 0.5
    want = np.stack(
        [
            rows[:, :, col["loc_x"]] + rows[:, :, col["track_err_y_m"]],
            -(rows[:, :, col["loc_z"]] + rows[:, :, col["track_err_x_m"]]),
        ],
        -1,
    )
    boxes = column(step, "/explain/objects/tracked:Boxes2D:centers")
    got = [np.array(b, dtype=np.float64).reshape(-1, 2) if b else np.zeros((0, 2)) for b in boxes]
    assert has.any() and len(got) == 100
    for t in range(100):
        np.testing.assert_allclose(got[t], want[t][has[t]], atol=1e-4)
    # each object's p(detect) of the PEM in its row band (j at 0, j + 0.8 at 1), recomputed here from the PEM at the
    # rollout's rows; q(detect) of the sampler in the same band, and 0 where the camera cannot see the car
    from scipy.special import expit

    target = problem_for(cfg).target
    p_want = expit(target.detect_logit(rows.reshape(-1, rows.shape[-1]))).reshape(rows.shape[:2])
    seen = rows[:, :, OBJECT_NAMES.index("visible")] > 0.5
    for j in range(m):
        pem = np.array(column(step, f"/explain/detect/object_{j}/pem:Scalars:scalars"), dtype=object)
        pem = np.array([v[0] for v in pem if v], dtype=np.float64)
        np.testing.assert_allclose(pem, j + 0.8 * p_want[:, j], atol=1e-9)
        q = np.array([v[0] for v in column(step, f"/explain/detect/object_{j}/sampler:Scalars:scalars") if v])
        assert q.shape == (100,) and np.all((q >= j) & (q <= j + 0.8))
        assert np.all(q[~seen[:, j]] == j)


def test_the_recording_lists_every_failure_of_the_estimate_by_share_and_its_groups(runs):
    """``final/failures``: one entry per failure of the final estimate, the largest share first, the shares adding up
    to 1 and their log-weights giving the run's log mu_hat; ``failures``: the groups in Markdown."""
    from scipy.special import logsumexp

    events, _, tables, _ = runs["adaptive"]
    final = next(e for e in events if isinstance(e, FinalEstimate))
    share = np.array(static_value(tables, "/final/failures:share"))
    log_w = np.array(static_value(tables, "/final/failures:log_weight"))
    assert share.size == final.estimate.n_failures > 0
    assert np.all(np.diff(share) <= 0) and math.isclose(share.sum(), 1.0, rel_tol=1e-12)
    n = final.estimate.n
    assert math.isclose(float(logsumexp(log_w)) - math.log(n), final.estimate.log_mu_hat, rel_tol=1e-12)
    text = static_value(tables, "/failures:TextDocument:text")[0]
    assert f"## Failures of the final estimate: {share.size:,}" in text and "last saving detection" in text
    # each failure's severity, aligned with the shares: its rollout's severity() in the stage's batch
    stage = static_value(tables, "/final/failures:stage")
    rollout = static_value(tables, "/final/failures:rollout")
    dist = np.array(static_value(tables, "/final/failures:min_distance"), dtype=np.float64)
    speed = np.array(static_value(tables, "/final/failures:impact_speed"), dtype=np.float64)
    batches = {e.stage: e.batch for e in events if isinstance(e, RolloutsSampled)}
    want = [severity(batches[k].signal("gap_m")[i]) for k, i in zip(stage, rollout, strict=False)]
    np.testing.assert_array_equal(dist, [w.min_gap_m for w in want])
    np.testing.assert_array_equal(speed, [w.contact_speed_mps for w in want])
    # p(severity | failure): the shares of p of no contact, 0-2, 2-5 and > 5 m/s, as bars adding up to 1
    (tensor,) = static_value(tables, "/final/severity_of_failures:BarChart:values")
    bars = np.asarray(tensor["buffer"], dtype=np.float64)
    by_hand = [
        share[np.isnan(speed)].sum(),
        share[speed < 2].sum(),
        share[(speed >= 2) & (speed < 5)].sum(),
        share[speed >= 5].sum(),
    ]
    np.testing.assert_allclose(bars, by_hand, rtol=1e-9, atol=1e-300)
    assert bars.sum() == pytest.approx(1.0, rel=1e-12)
    assert static_value(tables, "/final/severity_of_failures:bin") == ["no contact", "0-2 m/s", "2-5 m/s", "> 5 m/s"]
    assert static_value(tables, "/final/severity_of_failures:bin_failures") == [
        int(np.isnan(speed).sum()),
        *np.histogram(speed, [0, 2, 5, np.inf])[0].tolist(),
    ]


def test_a_run_followed_by_plain_monte_carlo_records_its_batches(tmp_path):
    """The default sampler too small to back an interval on the toy at p = 1e-3, and its retry at 4 N too: plain Monte
    Carlo follows, each of the retry's stages and of its batches a stage of the recording's timeline with its estimate,
    and the recording verifies."""
    cfg = ExperimentConfig.of(
        scenario="toy",
        scenario_params=(("braking", 32),),
        n_stages=1,
        n_per_stage=10,
        n_final=10,
        pretrain_rollouts=10,
        plain_fallback=500,
    )
    events, out = record(tmp_path / "fallback.rrd", cfg)
    verify_rrd(tmp_path / "fallback.rrd")
    finished = [e.result for e in of(events, StageFinished)]
    assert [r.kind for r in finished[:6]] == ["pretrain", "ce", "final"] * 2  # the stages, then their retry
    assert [r.estimate.n for r in finished[3:6]] == [10, 40, 10]
    plain = [r for r in finished if r.stage > 5]
    assert plain and all(r.kind == "final" and r.estimate.plain_mc for r in plain)
    tables = read({"fallback": tmp_path / "fallback.rrd"})["fallback"]
    stages = {s for s in column(tables["stage"], "stage") if s is not None}
    assert {r.stage for r in finished} <= stages
    assert "plain Monte Carlo after the stages, whose weights backed no interval" in out

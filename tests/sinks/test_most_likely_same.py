"""The console, the panel and the recording state the same most likely failure: the same stage, rollout number and
log p under the PEM (nats over T - 1 steps, :func:`pemviz.core.counterfactuals.failure_log_p`), to 1e-9, on a small
braking run, a small cut-in run and a braking run whose stages stream (their listeners see a sample of each stage, so
a rollout's number is not its row). The recording's value is read back through rerun's own reader."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")

from pemviz.app.rollouts_tab import RolloutsTab  # noqa: E402
from pemviz.app.runs import PanelRun  # noqa: E402
from pemviz.config import ExperimentConfig  # noqa: E402
from pemviz.core.counterfactuals import (  # noqa: E402
    LikelyFailure,
    failure_log_p,
    likeliest_failures,
    most_likely_failure,
)
from pemviz.engine.events import RolloutsSampled  # noqa: E402
from pemviz.engine.experiment import Experiment  # noqa: E402
from pemviz.scenarios.problems import problem_for  # noqa: E402
from pemviz.sinks.console import ConsoleSink  # noqa: E402
from pemviz.sinks.most_likely import MostLikelyFailure  # noqa: E402
from pemviz.sinks.recording import RerunSink  # noqa: E402

SMALL = dict(ce_epochs=30, pretrain_epochs=50, plain_fallback=0)  # the stages' failures, no plain rollouts after
CONFIGS = {
    "braking": ExperimentConfig.of(n_stages=3, n_per_stage=100, n_final=100, pretrain_rollouts=100, seed=1, **SMALL),
    "cut-in": ExperimentConfig.of(
        scenario="cut-in", n_stages=2, n_per_stage=60, n_final=60, pretrain_rollouts=60, seed=2, **SMALL
    ),
    "braking-streamed": ExperimentConfig.of(
        n_stages=2, n_per_stage=400, n_final=400, pretrain_rollouts=100, seed=1, chunk_rollouts=100, **SMALL
    ),
}


def read_explained(paths: dict) -> dict:
    """name -> the recording's ``/explain/failure`` properties (name -> value), read back through rerun."""
    out = {}
    with rr.server.Server(datasets={name: [str(p)] for name, p in paths.items()}) as server:
        client = server.client()
        for name in paths:
            table = client.get_dataset(name).reader(index=None).to_arrow_table()
            props = {}
            for c in table.column_names:
                if c.startswith("/explain/failure:"):
                    (value,) = [v for v in table.column(c).to_pylist() if v is not None]
                    props[c.split(":", 1)[1]] = value[0] if len(value) == 1 else value
            out[name] = props
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("most_likely")
    out = {}
    for name, cfg in CONFIGS.items():
        problem = problem_for(cfg)
        console = ConsoleSink(io.StringIO(), io.StringIO())  # as pemviz run: its why line is MostLikelyFailure's
        likely, panel, events = MostLikelyFailure(), PanelRun(1, cfg), []  # panel: what the session's listener feeds
        panel.problem = problem
        recording = RerunSink.to_file(d / f"{name}.rrd", problem=problem)
        try:
            Experiment(cfg, [console, likely, panel, recording, events.append], problem=problem).run()
        finally:
            recording.close()
        out[name] = dict(problem=problem, likely=likely, panel=panel, recording=recording, events=events)
    read = read_explained({name: d / f"{name}.rrd" for name in CONFIGS})
    for name in CONFIGS:
        out[name]["read"] = read[name]
    return out


def by_hand(events) -> tuple[int, int, float]:
    """(stage, rollout number, log p) of the failing rollout with the largest sum of log p over T - 1 steps, the
    earlier on ties, found here from the events."""
    best = None
    for ev in events:
        if not isinstance(ev, RolloutsSampled):
            continue
        for i in np.flatnonzero(ev.failed):
            log_p = float(ev.batch.log_p[i, :-1].sum())
            if best is None or log_p > best[2]:
                best = (ev.stage, int(ev.rollout_numbers[i]), log_p)
    assert best is not None, "the run found no failure"
    return best


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_console_panel_and_recording_state_the_same_most_likely_failure(runs, name):
    r = runs[name]
    stage, rollout, log_p = by_hand(r["events"])
    likely, panel, recording, read = r["likely"], r["panel"], r["recording"], r["read"]
    best = panel.most_likely_failure
    stated = {
        "console": (likely.stage, likely.rollout, likely.log_p),
        "panel": (panel.likely.stage, panel.likely.rollout, panel.likely.log_p),
        "panel list": (best.stage, best.index, best.log_p_total),
        "recording sink": (
            recording.most_likely.stage,
            int(recording.most_likely.rollout_numbers[0]),
            recording.most_likely_log_p,
        ),
        "recording read back": (read["stage"], read["rollout"], read["log_p"]),
    }
    for who, (s, n, lp) in stated.items():
        assert (s, n) == (stage, rollout), who
        assert math.isclose(lp, log_p, rel_tol=0, abs_tol=1e-9), (who, lp, log_p)
    label = RolloutsTab.rollout_label(best, True)
    assert f"stage {stage} rollout {rollout} " in label and f"log p {log_p:.1f}" in label


def test_a_streamed_stage_states_the_rollout_number_not_the_row_of_the_sample(runs):
    r = runs["braking-streamed"]
    streamed = [ev for ev in r["events"] if isinstance(ev, RolloutsSampled) and ev.n_total is not None]
    assert streamed and all(ev.batch.n < ev.n_total for ev in streamed)
    best = r["panel"].likely
    assert best.stage in {ev.stage for ev in streamed}
    assert best.row != best.rollout  # otherwise this run would not tell the row from the number


def test_the_console_line_states_the_same_stage_and_log_p(runs):
    """The cut-in's *why* line (what ``pemviz run`` prints) states the same failure's log p as its two parts, which
    add up to it: the log-probability of its detections (<= 0) and the log-density of its measurement errors."""
    r = runs["cut-in"]
    likely = r["likely"]
    parts = likely.parts(r["problem"])
    assert parts.errors is not None and parts.detections <= 0.0
    assert math.isclose(parts.total, likely.log_p, rel_tol=1e-9)
    line = likely.why(r["problem"])
    assert line is not None
    assert line.startswith(
        f"why: the most likely failure (stage {likely.stage}; over all 99 steps: "
        f"log-probability of its detections {parts.detections:.1f} nats, log-density of its "
        f"measurement errors {parts.errors:+.1f} "
        "nats): "
    )


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_the_recording_and_the_panel_state_the_parts_of_log_p_apart(runs, name):
    """The recording's ``explain/failure`` (read back) and the panel's most likely failure state the same two parts:
    the log-probability of the detections (<= 0) and, on the cut-in only, the log-density of the measurement errors;
    on the braking scenario (detections only) the log-probability is the log p itself and no density is named."""
    r = runs[name]
    read, best = r["read"], r["panel"].most_likely_failure
    parts = r["likely"].parts(r["problem"])
    assert read["log_prob_detections"] <= 0.0
    assert math.isclose(read["log_prob_detections"], parts.detections, rel_tol=0, abs_tol=1e-9)
    assert math.isclose(best.log_p_parts.detections, parts.detections, rel_tol=0, abs_tol=1e-9)
    if name == "cut-in":
        assert math.isclose(read["log_density_errors"], parts.errors, rel_tol=0, abs_tol=1e-9)
        assert math.isclose(read["log_prob_detections"] + read["log_density_errors"], read["log_p"], rel_tol=1e-9)
        assert best.log_p_words() == parts.words()
        assert "log-density of its measurement errors" in best.log_p_words()
    else:
        assert "log_density_errors" not in read and parts.errors is None and best.log_p_parts.errors is None
        assert math.isclose(read["log_prob_detections"], read["log_p"], rel_tol=0, abs_tol=1e-9)
        assert best.log_p_words() == f"log-probability of its detections {read['log_p']:.1f} nats"


def test_ties_keep_the_earlier_rollout_and_log_p_counts_t_minus_1_steps():
    from pemviz.core.rollouts import RolloutBatch

    log_p = np.array([[-1.0, -2.0, -50.0], [-2.0, -1.0, 0.0], [-0.5, -0.5, 0.0], [-3.0, 0.0, 0.0]])
    n, t = log_p.shape
    batch = RolloutBatch(np.zeros((n, t, 1)), np.ones((n, t, 1), bool), log_p, np.zeros((n, t)), ("gap_m",))
    failed = np.array([True, True, False, True])
    np.testing.assert_array_equal(failure_log_p(batch, failed), [-3.0, -3.0, -np.inf, -3.0])  # the last step: no
    np.testing.assert_array_equal(likeliest_failures(batch, failed, 2), [0, 1])
    np.testing.assert_array_equal(likeliest_failures(batch, ~np.ones(n, bool), 2), np.zeros(0))
    with pytest.raises(ValueError, match="failed needs shape"):
        failure_log_p(batch, failed[:2])
    first = most_likely_failure(RolloutsSampled(0, "ce", batch, np.zeros(n), {}, failed, np.zeros(n)))
    assert first == LikelyFailure(0, 0, 0, -3.0)
    assert most_likely_failure(RolloutsSampled(1, "ce", batch, np.zeros(n), {}, failed, np.zeros(n)), first) is first
    assert most_likely_failure(RolloutsSampled(1, "ce", batch, np.zeros(n), {}, ~np.ones(n, bool), np.zeros(n))) is None

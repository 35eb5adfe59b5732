"""A state run's recording shows, per stage, q(detect) against the PEM's p(detect) over the feature that moved the
proposal most (pemviz.sinks.rerun_features): a small crossing run through ``pemviz run --save`` (its recording
written by the second process, from pickled events) read back, against the same run's curves computed in this
process while each stage's sampler was the one that drew (pemviz.core.feature_view, checked against closed forms in
tests/core/test_feature_view.py)."""

from __future__ import annotations

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
pytest.importorskip("datafusion", reason="rerun-sdk[catalog] reads recordings back")

from pemviz.config import ExperimentConfig  # noqa: E402
from pemviz.core.feature_view import stage_feature_curve  # noqa: E402
from pemviz.engine.events import RolloutsSampled  # noqa: E402
from pemviz.engine.experiment import Experiment  # noqa: E402
from pemviz.scenarios.problems import problem_for  # noqa: E402
from pemviz.sinks.rerun_blueprint import FEATURE_VIEW_NAME, default_blueprint  # noqa: E402

from conftest import run_cli, verify_rrd  # noqa: E402

from .test_recording import column, read  # noqa: E402

SMALL_STATE = dict(
    scenario="crossing", method="state", n_per_stage=20, n_final=20, n_stages=2, seed=5, plain_fallback=0
)
"""The smallest crossing run of the state method: pretraining, 2 CE stages of 20 rollouts, a final batch of 20
(~3 s); seed 5 fails once in stage 2 and once in the final batch (a mixture with the PEM's own rollouts), so the
recording explains a failure drawn by the state proposal."""


def curves_in_process() -> dict:
    """Stage -> the feature curve of the proposal that drew it, computed as the stage's rollouts are heard."""
    cfg = ExperimentConfig.of(**SMALL_STATE)
    problem = problem_for(cfg)
    out: dict = {}

    def listen(ev) -> None:
        if isinstance(ev, RolloutsSampled):
            out[ev.stage] = stage_feature_curve(ev.batch, ev.sampler, problem.target, problem.features)

    Experiment(cfg, [listen], problem=problem).run()
    return out


def test_a_state_run_records_q_and_the_pem_over_the_feature_that_moved_q_most_at_every_stage(tmp_path):
    path = tmp_path / "state.rrd"
    r = run_cli(
        "run", "--scenario", "crossing", "--method", "state", "--n", "20", "--n-final", "20", "--k", "2",
        "--plain-fallback", "0", "--seed", "5", "--save", str(path),
    )  # fmt: skip  # the command as typed, its flags in pairs
    assert r.returncode == 0, r.stderr[-2000:]
    verify_rrd(path)
    tables = read({"s": path})["s"]
    stage = tables["stage"]
    stages = column(stage, "stage")
    expected = curves_in_process()
    assert expected[0] is None and all(expected[k] is not None for k in (1, 2, 3))  # the PEM draws the pretraining
    logged = {}
    for i, k in enumerate(stages):
        name = column(stage, "/feature/stats:feature")[i]
        if name is not None:
            logged[k] = i
    assert sorted(logged) == [1, 2, 3]
    for k, i in logged.items():
        c = expected[k]
        assert column(stage, "/feature/stats:feature")[i] == [c.name]
        np.testing.assert_array_equal(column(stage, "/feature/stats:x")[i], c.x)
        np.testing.assert_array_equal(column(stage, "/feature/stats:q_detect")[i], c.q_detect)
        np.testing.assert_array_equal(column(stage, "/feature/stats:p_detect")[i], c.p_detect)
        # the two series, named, over the feature; the figure titled with the feature's name
        assert column(stage, "/feature/data/q_detect:LineStrips2D:labels")[i] == ["q(detect)"]
        assert column(stage, "/feature/data/pem:LineStrips2D:labels")[i] == ["PEM p(detect)"]
        q_strip = column(stage, "/feature/data/q_detect:LineStrips2D:strips")[i][0]
        p_strip = column(stage, "/feature/data/pem:LineStrips2D:strips")[i][0]
        np.testing.assert_allclose(np.array(q_strip), np.column_stack([c.x, c.q_detect]), rtol=1e-6)  # float32
        np.testing.assert_allclose(np.array(p_strip), np.column_stack([c.x, c.p_detect]), rtol=1e-6)
        title = column(stage, "/feature/axes/title:Points2D:labels")[i]
        assert title[0] == c.name and title[1].startswith(f"stage {k}: {c.name} moves logit q by ")
    # the run's last curve moves q(detect) from the PEM's in some bin, and it shows on the timeline the recording opens
    last = expected[3]
    assert np.max(np.abs(last.q_detect - last.p_detect)) > 0.05
    step = tables["step"]
    assert any(v is not None for v in column(step, "/feature/data/q_detect:LineStrips2D:strips"))
    # the most likely failure's objects show the state proposal's q(detect), asked with the replayed features
    q = [v for v in column(step, "/explain/detect/object_0/sampler:Scalars:scalars") if v is not None]
    p = [v for v in column(step, "/explain/detect/object_0/pem:Scalars:scalars") if v is not None]
    assert len(q) == len(p) > 0 and q != p


def test_the_stages_tab_of_a_state_run_has_the_feature_view_and_others_do_not():
    from pemviz.scenarios.problems import problem_for as pf

    view = pf(ExperimentConfig.of(scenario="crossing")).view

    def names(bp) -> list[str]:
        found = []

        def walk(part) -> None:
            inner = getattr(part, "contents", None)
            if isinstance(inner, (list, tuple)):
                for child in inner:
                    walk(child)
            found.append(str(getattr(part, "name", "")))

        walk(bp.root_container)
        return found

    assert FEATURE_VIEW_NAME in names(default_blueprint(5, view, features=True))
    assert FEATURE_VIEW_NAME not in names(default_blueprint(5, view))

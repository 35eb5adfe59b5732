"""The rerun sink on hand-made events, logged into a stream that keeps what it is given: the stage names and colours
come from the run's plan, the threshold lines and the scene from the problem's view (none of the braking scenario's
for a toy)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rerun")

from pemviz.config import ExperimentConfig  # noqa: E402
from pemviz.engine.events import StageStarted  # noqa: E402
from pemviz.sinks.recording import RerunSink  # noqa: E402
from pemviz.sinks.rerun_views import DETECTED_RGBA, MISSED_RGBA  # noqa: E402

from .synthetic import BRAKING, TOY, batch, finished, run_started, sampled  # noqa: E402


class Stream:
    """Stands for a :class:`rerun.RecordingStream`: keeps every entity logged, with its archetypes."""

    def __init__(self) -> None:
        self.logged: dict[str, list] = {}
        self.blueprint = None

    def log(self, path, *archetypes, static=False) -> None:
        self.logged.setdefault(path, []).extend(archetypes)

    def send_columns(self, path, indexes, columns) -> None:
        self.logged.setdefault(path, []).append(columns)

    def send_blueprint(self, blueprint) -> None:
        self.blueprint = blueprint

    def __getattr__(self, name):  # set_time, flush, send_property, ...: nothing to keep
        return lambda *a, **k: None


def record(view):
    stream = Stream()
    sink = RerunSink(stream)
    sink(run_started(view))
    gaps = np.array([[12.0, 8.0, 4.0, 1.5, 1.0], [12.0, 9.0, 6.0, 4.0, 3.0]])  # the first crashes (gap < 2 m)
    for stage, kind in ((0, "pretrain"), (1, "ce")):
        sink(StageStarted(stage, kind, 2))
        sink(sampled(stage, kind, batch(gaps, ("gap_m", "ego_speed_mps") if view.drawing else ("gap_m",))))
        sink(finished(stage, kind, 2, 1, gamma=0.5))
    return sink, stream


def view_names(part) -> list[str]:
    """The names of the views in a blueprint (or a container of it), depth first."""
    part = getattr(part, "root_container", part)
    inner = getattr(part, "contents", None)
    if isinstance(inner, (list, tuple)) and hasattr(part, "kind"):  # a container (a view's contents are queries)
        return [name for child in inner for name in view_names(child)]
    return [str(part.name)]


def tabs(blueprint) -> dict[str, list]:
    """{tab name: [its views, depth first]} of the blueprint's tab container."""
    root = blueprint.root_container
    (container,) = [c for c in root.contents if str(c.kind).endswith("Tabs")]

    def views(part) -> list:
        inner = getattr(part, "contents", None)
        if isinstance(inner, (list, tuple)) and hasattr(part, "kind"):
            return [v for child in inner for v in views(child)]
        return [part]

    return {str(tab.name): views(tab) for tab in container.contents}


def origins(views) -> set[str]:
    """The first path segment of every view's origin or contents (``/stages/ess`` -> ``stages``)."""
    out = set()
    for v in views:
        paths = [str(v.origin)] + [str(q).lstrip("+ ") for q in (v.contents if isinstance(v.contents, list) else [])]
        out |= {p.strip("/").split("/")[0] for p in paths if p.strip("/")}
    return out


def threshold_names(stream: Stream) -> list[str]:
    (lines,) = [a for a in stream.logged["rollouts/gap_m/thresholds"] if type(a).__name__ == "SeriesLines"]
    return lines.names.as_arrow_array().to_pylist()


def test_a_braking_run_draws_the_crash_gap_the_braking_distance_and_a_scene_lane_per_stage():
    sink, stream = record(BRAKING)
    assert threshold_names(stream) == ["crash gap 2 m", "braking distance 10 m"]
    assert {"scene/stage_00/lane", "scene/stage_01/ego"} <= set(stream.logged)
    assert "| 1 | CE stage 1/2 | 0.5000 | 1/2 |" in sink.stage_rows[1]
    names = view_names(stream.blueprint)
    assert "Scene: each stage's least robust rollout (play on step)" in names
    assert "Scene of the most likely failure (play on step)" in names
    assert "share of the stage's failures with contact" in names
    assert any(n.startswith("d: gap_m (m), kept rollouts") for n in names)


def test_a_toy_run_draws_its_own_thresholds_and_no_scene():
    sink, stream = record(TOY)
    assert threshold_names(stream) == ["failure below 3 units", "braking within 5 units"]
    assert not [p for p in stream.logged if p.startswith("scene") or p.startswith("explain/scene")]
    assert not [p for p in stream.logged if p.startswith("explain/controller") or p.startswith("stages/contact")]
    names = view_names(stream.blueprint)
    assert not [n for n in names if "Scene" in n or "Controller" in n or "contact" in n]
    assert any(n.startswith("d: gap_m (units), kept rollouts") for n in names)
    assert "braking scenario" not in sink.intro_md
    assert "10 m" not in sink.intro_md and "2 m" not in sink.intro_md


def test_each_tab_shows_only_entities_of_its_timeline():
    """Stages: the per-stage entities (static figures, bars on ``stage`` and ``step``); Explain and Rollouts: the
    per-step ones (``step``)."""
    for view in (BRAKING, TOY):
        sink, stream = record(view)
        sink.close()  # an interrupted run: the most likely failure is explained at close
        by_tab = tabs(stream.blueprint)
        assert list(by_tab) == [
            "Stages (any timeline; on stage, scrub its bars)",
            "Explain: the most likely failure (timeline: step)",
            "Rollouts (timeline: step)",
        ]
        stages, explain, rollouts = by_tab.values()
        assert origins(stages) == {"proposal_marginal", "proposal", "stage_figures", "histograms"}
        assert origins(explain) == {"explain"}
        assert origins(rollouts) == ({"rollouts", "scene"} if view.drawing else {"rollouts"})
        # and the sink logged every origin a tab shows
        logged = {p.split("/")[0] for p in stream.logged}
        assert origins(stages) | origins(explain) | origins(rollouts) <= logged


def test_a_failure_the_replay_does_not_reproduce_is_explained_without_a_counterfactual():
    """The synthetic crash (gap 12 -> 1 m in 5 steps, every step detected) is no rollout of the braking scenario: the
    explanation gives its severity and says the replay does not reproduce it, and shows no minimal miss set."""
    sink, stream = record(BRAKING)
    sink.close()
    (doc,) = stream.logged["explain/summary"]
    text = doc.text.as_arrow_array().to_pylist()[0]
    assert "breach 1.00 m, no contact" in text and "The replay does not reproduce this rollout" in text
    assert "explain/gap_m/with_minimal_set" not in stream.logged
    assert "explain/controller/acceleration" not in stream.logged
    (props,) = stream.logged["explain/failure"]
    assert "minimal_miss_set" not in str(props.as_component_batches())


def test_stage_colours_run_from_blue_at_stage_0_to_orange_at_the_plans_last_stage():
    sink, _ = record(BRAKING)  # the plan's last stage is 3, the final batch
    assert sink._colour(0) == (40, 110, 230, 255) and sink._colour(3) == (255, 150, 30, 255)
    assert sink._colour(1) == (40 + 215 // 3, int(110 + 40 / 3), int(230 - 200 / 3), 255)


def test_the_detection_colours_are_green_and_orange():
    assert DETECTED_RGBA == (40, 170, 80, 255) and MISSED_RGBA == (245, 130, 30, 255)


def test_a_method_without_its_own_words_is_described_by_its_plan():
    """A method whose record has no words of its own (:attr:`pemviz.methods.Method.describe`): its description lists
    the planned stages (was a KeyError that stopped the run); a built-in one says its own."""
    from types import SimpleNamespace

    from pemviz.core.plan import RunPlan
    from pemviz.methods import Method, register_method, unregister_method
    from pemviz.sinks.rerun_views import method_markdown

    plan = RunPlan.of([(0, "pretrain", 50), (1, "ce", 80), (2, "final", 300)])
    register_method(Method("splitting-2030", "a method of one's own", "pemviz.estimators.builtin:mc"))
    try:
        config = ExperimentConfig.of(method="splitting-2030", n_per_stage=80)
        ev = SimpleNamespace(config=config, plan=plan, problem=SimpleNamespace(thresholds=None))
        text = method_markdown(ev)
    finally:
        unregister_method("splitting-2030")
    assert text.startswith("method **splitting-2030**:")
    assert "pretraining (50 rollouts)" in text and "(300 rollouts)" in text
    ev = SimpleNamespace(config=ExperimentConfig.of(method="mc", n_per_stage=80), plan=plan, problem=ev.problem)
    assert method_markdown(ev) == "plain **Monte Carlo** with the PEM: 80 rollouts."

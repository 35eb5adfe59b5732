"""The recording draws what a scenario's drawing object gives it (:class:`pemviz.sinks.drawing.RecordingDrawing`) and
names no scene itself: a made-up scenario's drawing object gets its own description, outcome words, lanes with its own
entities and its own explanation, in the colours of the roles it names; the built-in drawing objects implement the
protocol and survive pickling (the recording process gets them so)."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest

pytest.importorskip("rerun")

from pemviz.core.problem_view import ProblemView, SignalView, Thresholds  # noqa: E402
from pemviz.engine.events import StageStarted  # noqa: E402
from pemviz.scenarios.braking.drawing import BrakingDrawing  # noqa: E402
from pemviz.scenarios.cut_in.drawing import CutInDrawing  # noqa: E402
from pemviz.sinks.drawing import ROLES, RecordingDrawing  # noqa: E402
from pemviz.sinks.recording import RerunSink  # noqa: E402
from pemviz.sinks.rerun_explain import ROLE_RGBA  # noqa: E402

from .synthetic import batch, finished, run_started, sampled  # noqa: E402
from .test_recording_sink import Stream  # noqa: E402


@dataclasses.dataclass(frozen=True)
class Outcome:
    failed: bool
    contact: bool
    short: str
    rank: float


@dataclasses.dataclass(frozen=True)
class RobotDrawing:
    """A robot that must keep 2 units from a wall: the distance is the first signal."""

    dt_s: float = 0.1
    draws_scene: bool = True
    object_words: str = "the wall"

    def outcome(self, b, i) -> Outcome:
        d = b.signal("gap_m")[i]
        return Outcome(bool(d.min() < 2.0), bool(d.min() < 1.2), f"closest {d.min():.1f} units", -float(d.min()))

    def intro(self, formula, metric, method):
        return f"# A robot and a wall\n\nSpec `{formula}`, metric {metric}. {method}", " and the robot's corridor."

    def outcome_values(self, b, i):
        o = self.outcome(b, i)
        return {"outcome": o.short, "contact": o.contact, "closest_units": float(b.signal("gap_m")[i].min())}

    def scene_lane(self, b, i):
        d = b.signal("gap_m")[i]
        x = np.arange(d.size, dtype=np.float64)
        return (("robot", x, (0.5, 0.5), None), ("wall", x + d, (0.1, 1.0), d < 2.0)), None, float((x + d).max())

    def explanation(self, b, i):
        d = b.signal("gap_m")[i]
        return {
            "words": "hit the wall",
            "props": {"closest_units": float(d.min())},
            "lines": ["It hit the wall.", ""],
            "series": (("wall/distance", "distance (units)", "object_speed", d),),
            "markers": (("detect/touch", "touch", "failure", "down", np.array([3]), None, 5.0),),
        }


VIEW = ProblemView(
    "robot",
    "a robot near a wall",
    (SignalView("d", "gap_m", "units"),),
    Thresholds(2.0, 5.0, "units", "too close", "looking"),
    drawing=RobotDrawing(),
)


def values(any_values) -> dict:
    """{field: values} of a :class:`rerun.AnyValues`."""
    return {str(b.component_descriptor()): b.as_arrow_array().to_pylist() for b in any_values.as_component_batches()}


def record(view: ProblemView):
    stream = Stream()
    sink = RerunSink(stream)
    sink(run_started(view))
    gaps = np.array([[12.0, 8.0, 4.0, 1.5, 1.0], [12.0, 9.0, 6.0, 4.0, 3.0]])
    for stage, kind in ((0, "pretrain"), (1, "ce")):
        sink(StageStarted(stage, kind, 2))
        sink(sampled(stage, kind, batch(gaps, ("gap_m",))))
        sink(finished(stage, kind, 2, 1, gamma=0.5))
    sink.close()
    return sink, stream


def test_a_made_up_scenario_is_drawn_from_its_drawing_object():
    sink, stream = record(VIEW)
    assert sink.intro_md.startswith("# A robot and a wall") and sink.intro_md.endswith(" and the robot's corridor.\n")
    assert {"scene/stage_00/robot", "scene/stage_00/wall", "scene/stage_01/label"} <= set(stream.logged)
    assert not [p for p in stream.logged if p.endswith("/sight") or p.endswith("/ego") or p.endswith("/lead")]
    (summary,) = stream.logged["rollouts/summary/stage_01"]
    assert values(summary)["outcome"] == ["closest 1.0 units", "closest 3.0 units"]
    (featured,) = [a for a in stream.logged["rollouts/gap_m/stage_01/rollout_000"] if type(a).__name__ == "AnyValues"]
    assert values(featured)["closest_units"] == [1.0] and values(featured)["contact"] == [True]
    assert {"explain/wall/distance", "explain/detect/touch", "explain/scene/robot"} <= set(stream.logged)
    (doc,) = stream.logged["explain/summary"]
    text = doc.text.as_arrow_array().to_pylist()[0]
    assert ": hit the wall" in text and "It hit the wall." in text and "missed the wall at 0 of 5 steps" in text
    (props,) = stream.logged["explain/failure"]
    assert values(props)["closest_units"] == [1.0]
    assert "stages/contact_share" in stream.logged


def test_every_role_has_a_colour_and_the_built_in_drawings_implement_the_hooks():
    assert set(ROLE_RGBA) == set(ROLES)
    for drawing in (BrakingDrawing(), CutInDrawing()):
        assert isinstance(drawing, RecordingDrawing)
        assert pickle.loads(pickle.dumps(drawing)) == drawing
    assert BrakingDrawing().draws_scene and not CutInDrawing().draws_scene
    assert CutInDrawing().intro("G(d >= 2)", "classic", "mc") is None


def test_the_cut_ins_outcome_values_are_its_severity_and_every_failure_is_said_failed():
    from pemviz.config import ExperimentConfig
    from pemviz.core.detectors import ConstantDetector
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.cut_in.story import cut_in_severity
    from pemviz.scenarios.problems import problem_for

    problem = problem_for(ExperimentConfig.of(scenario="cut-in"))
    b = RolloutBatch.concatenate(
        [problem.simulate(12, ConstantDetector(p), problem.target, np.random.default_rng(3)) for p in (0.5, 0.02)]
    )  # the cut-in car seen half the time (safe), or almost never (failures)
    failed = problem.failed(b)
    assert 0 < failed.sum() < b.n  # both kinds
    names, object_names = tuple(b.observation_names), tuple(b.object_names)
    for i in range(b.n):
        told = problem.drawing.outcome_values(b, i)
        want = cut_in_severity(b.observations[i], names, b.objects[i], object_names, 0.1)
        assert told["outcome"] == want.short and told["contact"] == want.contact
        assert told["min_clearance_m"] == want.min_clearance_m
        assert told["outcome"].startswith("no failure") != bool(failed[i])
    assert CutInDrawing().outcome_values(batch(np.full((2, 5), 9.0)), 0) is None  # rows without its columns

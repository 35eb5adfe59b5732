"""The run's arguments are read once, at the top: followed from ``pemviz run``'s parsed arguments
(``scripts/arg_walk.py``: every pemviz function called with the command's ``Namespace``), a run writing every kind of
output (recording, rollout file, result document, report, JUnit) keeps them in ``commands/`` and climbs back into a
module they had left at most 5 times; the walk itself is checked on a hand-made sequence of stays."""

from __future__ import annotations

from conftest import REPO, load_script

walker = load_script(REPO / "scripts" / "arg_walk.py")


def test_the_walk_counts_visits_rooms_and_climbs_back():
    w = walker.Walk([("a.py", "f"), ("a.py", "g"), ("b.py", "h"), ("a.py", "i"), ("c.py", "j"), ("b.py", "k")])
    assert [m for m, _ in w.visits] == ["a.py", "b.py", "a.py", "c.py", "b.py"]
    assert (w.rooms, w.climbs_back) == (3, 2)
    assert w.summary() == "6 stays in 3 rooms (5 visits), climbing back 2 times"


def test_a_run_with_every_output_keeps_its_arguments_in_commands_and_climbs_back_at_most_5_times(tmp_path):
    argv = ["run", "--preset", "quick", "--k", "2", "--save", str(tmp_path / "r.rrd")]
    for flag, name in (("--save-rollouts", "r.parquet"), ("--json", "r.json"), ("--report", "r.html")):
        argv += [flag, str(tmp_path / name)]
    argv += ["--junit", str(tmp_path / "r.xml"), "--require", "p < 1e-9", "--max-sims", "3000"]
    w, status = walker.walk(argv)
    assert status in (0, 3) and (tmp_path / "r.json").is_file() and (tmp_path / "r.xml").is_file()  # 3: undecided
    modules = {m for m, _ in w.stays}
    assert ("commands/run.py", "main") in w.stays and "commands/run_outputs.py" in modules  # planned there, once
    assert all(m.startswith("commands/") for m in modules), w.visits
    assert w.climbs_back <= 5, w.visits


def test_the_run_s_config_goes_down_the_call_graph_once_and_names_its_method_only_in_the_config():
    """Followed through the config made from the arguments, each function once (``--config --distinct``), a quick
    run of one stage: 43 stays in 18 modules, climbing back 12 times (the quick preset's eight stages, ``python
    scripts/arg_walk.py --config --distinct``: 42 stays, 11 times; both 22 and 19 before the hooks took what they
    read, not the config); the method is looked up by its name only where the config resolves it."""
    w, status = walker.walk(["run", "--preset", "quick", "--k", "1", "--no-record"], config=True)
    w = walker.distinct(w)
    assert status == 0 and w.stays[0] == ("commands/run.py", "main")
    assert {m for m, _ in w.stays} >= {"engine/experiment.py", "estimators/fallback.py", "sinks/console.py"}
    assert w.climbs_back <= 12, w.visits
    assert w.lookups and {m for m, _ in w.lookups} == {"config.py"}, w.lookups

"""``pemviz run``: one experiment (adaptive sampler or a baseline), a console table and a rerun recording."""

from __future__ import annotations

import argparse
import importlib.util
import json
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pemviz import commands
from pemviz.commands import COMMANDS, UsageError, add_row, add_setting, interrupted, pem_argument, setting_error
from pemviz.commands.run_outputs import RunOutputs, plan_outputs
from pemviz.commands.run_recording import (
    add_recording_args,
    default_recording_path,
    probe_viewer,
    recording_target,
    serve,
)
from pemviz.config import ConfigError, ExperimentConfig, scene_defaults
from pemviz.engine.resources import check_run_memory
from pemviz.methods import BUILTIN_METHODS, DEFAULT_METHOD
from pemviz.presets import DEFAULT_PRESET, PRESETS, preset_help
from pemviz.settings import DEFAULT_SCENARIO, SCENARIOS, SETTINGS, rows_of

if TYPE_CHECKING:
    from pemviz.core.problems import Problem
    from pemviz.engine.events import Listener

# The parser needs only the light modules above: torch, rerun, the engine, the sinks and pyarrow are imported in
# main, where a run needs them (rerun only when it records), so that `pemviz --help` answers at once and
# `pemviz run --no-record` never loads rerun.


RUN_SETTINGS = tuple(name for name, s in SETTINGS.items() if s.flags and name != "method")
"""The settings ``pemviz run`` takes as flags besides ``--method``: every row of :data:`pemviz.settings.SETTINGS` that
has a flag, in the table's order (a method of one's own adds its own: :func:`add_method_settings`)."""


def add_method_settings(p: argparse.ArgumentParser) -> None:
    """A flag for each setting of each registered method's own settings (:attr:`pemviz.methods.Method.settings`; the
    method plugins loaded first), a plugin's help led by the method's name (a built-in method's rows name it); a flag
    ``pemviz run`` has already is left out (the setting is still the config's by its name). A plugin that cannot be
    loaded, or a settings class without rows, is left to :func:`config_from_args`, which says why in one line."""
    from pemviz.methods import MethodPluginError, load_method_plugins, records

    try:
        load_method_plugins()
    except MethodPluginError:
        pass  # the built-in methods' flags all the same
    taken = {flag for action in p._actions for flag in action.option_strings}
    for record in records():
        if record.settings is None:
            continue
        try:
            kind = record.settings_class()
            assert kind is not None  # its settings are given
            rows, defaults = rows_of(kind, record.name), kind()
        except (TypeError, ValueError, ImportError, AttributeError):
            continue
        for row in rows.values():
            if not taken & {*(row.flags or (row.flag,))}:
                lead = "" if record.name in BUILTIN_METHODS else f"method {record.name}'s "
                add_row(p, row, getattr(defaults, row.name), lead=lead)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz run`` and its flags (the settings and the outputs) to the sub-command parsers ``sub``."""
    p = sub.add_parser(
        "run",
        help=COMMANDS["run"][1],
        description="Run the PEM + adaptive importance sampling pipeline (or a baseline) and record it. "
        "With no recording flag the recording goes to "
        "recordings/<scenario>-<method>-<preset>-<metric>-<sim>-seed<seed>-<time>.rrd.",
        conflict_handler="resolve",  # lets --connect also take the viewer URL (rerun's --connect --url still works)
    )
    add_setting(p, "method")
    p.add_argument(
        "--preset",
        help=f"sampler settings, one of {', '.join(PRESETS)} (default {DEFAULT_PRESET}): {preset_help()}. A preset "
        "sets some of the values below; a flag given here overrides it.",
    )
    for name in RUN_SETTINGS:
        add_setting(p, name)
    add_method_settings(p)
    p.add_argument(
        "--save-rollouts",
        dest="save_rollouts",
        metavar="PATH.parquet",
        help="write the rollouts of every stage the estimate uses, each with its stage, sampler component and the "
        "log density it was weighed with, for `pemviz estimate` to reproduce the estimate "
        "(format: pemviz.io.rollout_format)",
    )
    p.add_argument(
        "--rollout-stages",
        dest="rollout_stages",
        default="used",
        choices=("used", "all"),
        help="--save-rollouts: the stages the estimate uses (default), or all of them",
    )
    p.add_argument(
        "--json",
        dest="json_path",
        metavar="PATH.json",
        help="write the result as one JSON document: estimate, interval, verdict, requirement outcome, "
        "settings, seed, version, the recording's path (format: pemviz.io.result; schema: the user "
        "guide's 'pemviz in CI')",
    )
    p.add_argument(
        "--junit",
        dest="junit_path",
        metavar="PATH.xml",
        help="with --require: write the requirement as a JUnit XML test case (passed, failure when "
        "violated, error when undecided) for CI dashboards",
    )
    p.add_argument(
        "--report",
        dest="report_path",
        metavar="PATH.html",
        help="write a safety-case report: one self-contained HTML page (and PATH.md, its Markdown twin) "
        "with the estimate, verdict, severity, scenario, PEM, settings and the sha256 of the inputs",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace existing --save / --save-rollouts / --json / --junit / --report files (only files "
        "pemviz wrote)",
    )
    add_recording_args(p)
    p.set_defaults(func=main)


def config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    """Build and validate the config; raises ConfigError with a one-line message. Without ``--method`` and
    ``--preset`` a scenario runs its own defaults (:func:`pemviz.config.scene_defaults`; flags still override); the
    scenario registry and its plugins are loaded first (:func:`pemviz.scenarios.registry.load_plugins`).

    Raises:
        ConfigError: a setting, preset or parameter refused; ScenarioPluginError, MethodPluginError: a plugin that
            cannot be loaded."""
    if args.scenario is not None and args.scenario not in SCENARIOS:  # another registered scenario: load the registry
        from pemviz.scenarios.registry import load_plugins

        load_plugins()
    if args.method is not None and args.method not in BUILTIN_METHODS:  # a method of one's own: load the method plugins
        from pemviz.methods import load_method_plugins

        load_method_plugins()
    preset = DEFAULT_PRESET if args.preset is None else args.preset
    if preset not in PRESETS:
        raise ConfigError(f"--preset {preset!r} is invalid: use one of {', '.join(PRESETS)}")
    fields = dict(PRESETS[preset])
    scene = args.scenario or DEFAULT_SCENARIO
    params = None if args.scenario_params is None else scenario_params(scene, args.scenario_params)
    if args.method is None and args.preset is None:
        fields.update(scene_defaults(scene, params or ()))
    for name in ("method", *RUN_SETTINGS):
        value = getattr(args, name)
        if value is not None:
            fields[name] = value
    fields.update(method_settings_of(args, fields.get("method", DEFAULT_METHOD)))
    if params is not None:  # --param NAME=VALUE: parsed by the scenario's field types
        fields["scenario_params"] = params
    return ExperimentConfig.of(**fields)


def method_settings_of(args: argparse.Namespace, method: str) -> dict[str, Any]:
    """The settings of ``method``'s own given as flags (:func:`add_method_settings`), by name.

    Raises:
        ConfigError: a flag of another method's settings."""
    from pemviz.methods import records

    given: dict[str, Any] = {}
    for record in records():
        kind = record.settings_class()
        for row in () if kind is None else rows_of(kind, record.name).values():
            value = getattr(args, row.name, None)
            if value is not None and record.name != method:
                raise ConfigError(
                    f"{row.flag} is a setting of method {record.name}: give it with --method {record.name}", row.name
                )
            if value is not None:
                given[row.name] = value
    return given


def scenario_params(
    scenario: str, texts: list[str]
) -> tuple[tuple[str, float | int | bool | str], ...] | tuple[str, ...]:
    """The ``(name, value)`` pairs of ``--param NAME=VALUE`` flags (:mod:`pemviz.scenarios.parameters`): each value
    parsed by its field's type and the scenario's dataclass built from them (its range check).

    Raises:
        ConfigError: an unknown scenario, a text that is not NAME=VALUE, a name that is not one of the scenario's
            parameters (the message lists them), a value not of its type or outside the dataclass's range, a name
            given twice; one line."""
    from pemviz.scenarios.parameters import ParameterError, parse_assignments
    from pemviz.settings import SETTINGS

    if not SETTINGS["scenario"].accepts(scenario):  # the config refuses the scenario first
        return tuple(texts)
    try:
        return parse_assignments(scenario, texts)
    except ParameterError as exc:
        raise ConfigError(str(exc), "scenario_params") from None


def rollout_files(parquet: Path) -> list[tuple[str, Path]]:
    """The files ``--save-rollouts`` wrote, each with what it is, as the run names them: ``rollouts`` (the Parquet
    table), ``rollouts' sidecar`` (its JSON) and, if the sidecar names one, ``rollouts' proposal``."""
    from pemviz.io.rollout_format import sidecar_path

    sidecar = sidecar_path(parquet)
    files = [("rollouts", parquet), ("rollouts' sidecar", sidecar)]
    try:
        proposal = json.loads(sidecar.read_text()).get("proposal")
    except (OSError, ValueError, AttributeError):
        proposal = None
    if isinstance(proposal, str) and proposal.endswith(".pt"):
        files.append(("rollouts' proposal", parquet.parent / proposal))
    return files


def input_files(cfg: ExperimentConfig, target: object) -> list[dict[str, str]]:
    """The files a run reads, each ``{"what", "path", "sha256"}``: the detection PEM where the problem's ``target``
    holds one (the braking scenario's, a scene on :func:`pemviz.stack.detector.camera_detector`), and the noise PEM
    where it holds that too (the cut-in, the crossing); none for a scene whose detector is its own (the toys, a
    user's camera model)."""
    from pemviz.io.data import sha256_file
    from pemviz.pem.noise import NoiseModel
    from pemviz.pem.recipes import DEFAULT_PEM_NAME
    from pemviz.pem.store import _pem_file, noise_pem_path

    files = []
    if getattr(target, "pem", None) is not None or getattr(target, "detect", None) is not None:
        files.append(("detection PEM", _pem_file(cfg.perception.pem or DEFAULT_PEM_NAME)))
    if isinstance(getattr(target, "noise", None), NoiseModel):
        files.append(("noise PEM", noise_pem_path()))
    return [{"what": what, "path": str(path), "sha256": sha256_file(path)} for what, path in files]


def result_lines(
    cfg: ExperimentConfig, problem: Problem, final, why: str | None = None, failures: dict | None = None, severity=None
) -> tuple[list[str], dict]:
    """The console's lines after the table and the result document of a finished run (``recording`` None:
    :func:`write_results` sets it), built while the recording process writes the file.

    Args:
        cfg: the run's config.
        problem: its :class:`pemviz.core.problems.Problem`.
        final: its :class:`pemviz.engine.events.FinalEstimate`.
        why: the errors that decided the most likely failure (a line), or None.
        failures: the final estimate's failures in groups (:func:`pemviz.sinks.population.grouping_document`), or
            None.
        severity: their :class:`pemviz.core.severity.FailureSeverity` (None: none).

    Returns:
        ``(lines, document)``: :func:`pemviz.sinks.console.final_lines`'s lines (and ``why``) and
            :func:`pemviz.io.result.result_document` of the run."""
    from pemviz.io.result import result_document
    from pemviz.sinks.console import final_lines

    lines = final_lines(final, cfg, problem.exact_log_p, problem.reference, severity, problem.view.committor) + (
        [why] if why is not None else []
    )
    doc = result_document(
        cfg,
        final,
        exact_log_p=problem.exact_log_p,
        reference=problem.reference,
        recording=None,
        command=shlex.join(["pemviz", *sys.argv[1:]]),
        problem=problem,
        console=lines,
        inputs=input_files(cfg, problem.target),
        failures=failures,
    )
    return lines, doc


def write_results(
    lines: list[str], doc: dict, recording: str | None, outputs: RunOutputs, saved: Path | None = None
) -> None:
    """Write ``--json``, ``--junit`` and ``--report`` (atomically) and say where; with a ``saved`` recording its
    result document beside it (:func:`pemviz.io.result.result_beside`). ``lines`` and ``doc`` are
    :func:`result_lines`'; ``recording`` where the recording went (None: nowhere); ``outputs`` the run's files
    (:func:`plan_outputs`).

    Raises:
        OSError, pemviz.core.files.OutputExists: a file that could not be written (nothing partial is left)."""
    from pemviz.io.result import result_beside, write_junit, write_result_json

    json_path, junit_path, report_path = outputs.result_files
    overwrite = outputs.overwrite
    doc["recording"] = recording
    if json_path is not None:
        print(f"result: {write_result_json(json_path, doc, overwrite=overwrite)}", file=sys.stderr)
    if saved is not None:
        print(f"result: {write_result_json(result_beside(saved), doc, overwrite=overwrite)}", file=sys.stderr)
    if junit_path is not None:
        console = "\n".join(line for line in lines[1:] if line.startswith(("mu_hat", "no failure", "stop:")))
        print(f"junit: {write_junit(junit_path, doc, console, overwrite=overwrite)}", file=sys.stderr)
    if report_path is not None:
        from pemviz.sinks.report import write_report

        page, twin = write_report(report_path, doc, overwrite=overwrite)
        print(f"report: {page} (and {twin})", file=sys.stderr)


def main(args: argparse.Namespace) -> int:
    """``pemviz run``: build the config from the flags, check every output, run the experiment and record it.

    Returns:
        The exit status of the run (:func:`_run_experiment`).

    Raises:
        UsageError: a bad setting, PEM or output path, or ``--executor ray`` without Ray."""
    if commands.AS_PROGRAM:  # scipy.special, which the PEM's modules import, without numpy's unused submodules
        from pemviz.sinks.process import import_scipy_special_lean

        import_scipy_special_lean()
    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        raise setting_error(exc) from None
    pem_argument(cfg.perception.pem)
    if cfg.execution.executor == "ray":
        if importlib.util.find_spec("ray") is None:
            raise UsageError("--executor ray: Ray is not installed (pip install ray)")
        from pemviz.engine.executors import probe_ray_address

        probe_ray_address(cfg.execution.ray_address)  # before any work: a wrong address is one line, not a silent wait
    target = recording_target(args)
    default = (
        default_recording_path(cfg, args.preset or DEFAULT_PRESET) if target == "save" and args.save is None else None
    )
    outputs = plan_outputs(args, cfg, target, default)  # every file the run writes, checked once, before any work
    rollout_sink = None
    if outputs.rollouts is not None:
        from pemviz.sinks.rollouts import RolloutSink

        try:
            rollout_sink = RolloutSink(
                outputs.rollouts, pem=cfg.perception.pem, overwrite=outputs.overwrite, stages=args.rollout_stages
            )
        except ValueError as exc:
            raise UsageError(str(exc)) from None
    if (
        commands.AS_PROGRAM and target in ("stdout", "connect", "serve") and cfg.execution.executor != "ray"
    ):  # "save": the child's
        from pemviz.sinks.process import settle_pyarrow_without_pandas

        settle_pyarrow_without_pandas()
    save_path = outputs.recording
    if target == "connect":
        args.url = probe_viewer(args.url)
    early = None
    if target == "save" and commands.AS_PROGRAM and cfg.execution.executor != "ray":
        from pemviz.sinks.recording_process import RecordingProcess  # rerun imported beside the run, not before it

        assert save_path is not None  # plan_outputs names the file of a recording saved
        save_path.parent.mkdir(parents=True, exist_ok=True)
        early = RecordingProcess(save_path, overwrite=outputs.overwrite)
    try:
        return _run_experiment(args, cfg, target, outputs, early, rollout_sink)
    except BaseException:
        if early is not None:
            early.close(commit=False)  # idempotent: closed already where the run got that far
        raise


def keep_interrupted(rollout_sink: Any) -> str:
    """What an interrupted run's rollout file keeps (:meth:`pemviz.sinks.rollouts.RolloutSink.keep_finished`: its last
    finished stage, whose estimate ``pemviz estimate`` gives back), in words; empty where it keeps nothing (no
    rollout file asked for, no saved stage finished, or the file could not be committed: then none is left)."""
    if rollout_sink is None:
        return ""
    try:
        kept = rollout_sink.keep_finished()
    except Exception:  # a file cut short is never left: the sink's close drops it
        return ""
    if kept is None:
        return ""
    path, stage, est = kept
    shown = "no failure" if est.n_failures == 0 else f"mu_hat = {est.mu_hat:.4e}"
    return (
        f"rollouts {path} kept: stage {stage}, the last finished, {est.n:,} rollouts ({shown}, its row's "
        "estimate; pemviz estimate gives it back)"
    )


def _run_experiment(args, cfg: ExperimentConfig, target, outputs: RunOutputs, early, rollout_sink) -> int:
    """The run itself, its listeners and its files (:func:`main`), written where ``outputs`` says
    (:func:`pemviz.commands.run_outputs.plan_outputs`); ``early``: the recording process started before the problem was
    built, or None."""
    save_path, asks_results = outputs.recording, outputs.asks_results
    from pemviz.engine.cost import N_STEPS
    from pemviz.engine.experiment import Experiment, scene_pilot, stream_above
    from pemviz.engine.resources import tasks_now, torch_threads
    from pemviz.estimators import check_runnable
    from pemviz.scenarios.registry import problem_for  # any registered scenario: the built-in ones and plugins
    from pemviz.sinks.console import ConsoleSink
    from pemviz.sinks.most_likely import MostLikelyFailure
    from pemviz.sinks.population import FailureGroups, grouping_document

    opened = tasks_now()  # the load is read from here to the run's start: over the problem's build
    problem = problem_for(cfg)  # loads the PEM: a bad --pem fails here, before any output exists
    check_run_memory(cfg, problem.n_steps or N_STEPS, stream_above=stream_above(cfg))
    try:
        check_runnable(cfg, problem)  # a sampler that cannot run on this scenario: before any output or rollout
    except ValueError as exc:
        raise UsageError(f"--preset / --scenario: {exc}") from None
    experiment = Experiment(cfg, problem=problem)
    wanted = target != "no-record" or asks_results  # files that show the groups
    groups = FailureGroups(problem.drawing, problem, keys=wanted)  # the failures' severity (console), groups
    console = ConsoleSink(out=sys.stderr) if target == "stdout" else ConsoleSink()
    console.clock.load_since = opened
    console.clock.pilot = scene_pilot(problem)  # a pilot of the scene's rollouts prices the run
    # prints the failures' severity, which groups (heard first) reads at the final estimate
    console.failures = groups
    listeners: list[Listener] = [groups, console]
    recorder = None
    if early is not None:
        recorder = early
    elif target != "no-record":
        from pemviz.sinks.recording import RerunSink  # rerun, and pandas through pyarrow: only for a recording

        if target == "save":
            assert save_path is not None  # plan_outputs names the file of a recording saved
            save_path.parent.mkdir(parents=True, exist_ok=True)
            recorder = RerunSink.to_file(save_path, overwrite=outputs.overwrite)
        elif target == "stdout":
            recorder = RerunSink.to_stdout()
        elif target == "connect":
            recorder = RerunSink.to_grpc(args.url)
            print(f"recording: streaming to {args.url}", file=sys.stderr)
        else:
            recorder = serve(args)
        recorder.problem = problem  # the failures' severity (final/failures, final/severity_of_failures)
    if recorder is not None:
        recorder.share_failure_groups(groups)  # grouped once for the console, the recording and the result files
        listeners.insert(0 if recorder is early else len(listeners), recorder)  # the child hears the end first
    if rollout_sink is not None:
        rollout_sink.problem = problem  # its sidecar: the scenario's formula, signals and step
        listeners.append(rollout_sink)
    experiment.listeners[:0] = listeners
    odd_map = None
    if getattr(problem, "odd", None) is not None:  # over an operating design domain: the map after the estimate
        from pemviz.sinks.odd_map import OddMapSink

        odd_map = OddMapSink(out=sys.stderr if target == "stdout" else None)
        experiment.listeners.append(odd_map)
    likely = (
        MostLikelyFailure()
        if not getattr(problem.drawing, "draws_scene", False) and problem.branch is not None
        else None
    )
    if likely is not None:  # a drawing that explains no failure itself: say which errors decided
        experiment.listeners.append(likely)
    try:
        with torch_threads(1, blas=1):
            done = experiment.run()
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: keep the finished stages, say what was saved
        where = recorder.close() if recorder is not None else None
        stages = f"{len(experiment.stages)} stage(s) finished"
        said = [f"recording {where} (marked interrupted)"] if where else []
        kept_stage = keep_interrupted(rollout_sink)
        said += [kept_stage] if kept_stage else []
        said += [lost] if (lost := outputs.unwritten(rollouts=not kept_stage)) else []
        raise interrupted(exc, "; ".join([stages, *(said or ["nothing written"])])) from None
    except BaseException:
        if recorder is not None:
            recorder.close(commit=False)
        raise
    finally:
        if rollout_sink is not None:
            rollout_sink.close()  # rollouts of a run that did not finish are not kept
    kept = rollout_files(rollout_sink.written) if rollout_sink is not None and rollout_sink.written is not None else []
    for what, path in kept:
        print(f"{what}: {path}", file=sys.stderr)
    where = None
    try:
        why = likely.why(problem) if likely is not None else None  # the errors that decided the most likely failure
        if why is not None:
            print(why)
        if target == "serve":
            try:  # entered before the line is printed: a Ctrl-C sent as soon as it is read still ends the serving
                print("run finished; still serving the recording (Ctrl-C to stop)", file=sys.stderr, flush=True)
                __import__("rerun").script_teardown(args)  # waits for Ctrl-C
            except KeyboardInterrupt:
                pass
        final = getattr(done, "final", None)
        results = None  # the result files' lines and document, made while the recording process writes the file
        if final is not None and (target == "save" or asks_results):
            try:
                failures = grouping_document(groups.grouping) if groups.grouping is not None else None
                results = result_lines(cfg, problem, final, why, failures, getattr(groups.grouping, "severity", None))
                if final.odd_map is not None and final.odd_map.bins:
                    results[1]["odd_map"] = final.odd_map.document()
            except BaseException:  # a run that fails here writes nothing, as one that fails in a stage
                if recorder is not None:
                    recorder.close(commit=False)
                raise
        where = None
        if recorder is not None:
            where = recorder.close()
            if where is not None:
                print(f"recording: {where}", file=sys.stderr)
        saved = Path(where) if where is not None and target == "save" else None
        if results is not None and (saved is not None or asks_results):
            write_results(*results, str(where) if where is not None else None, outputs, saved)
        if cfg.stop.require is not None and final is not None and final.decision is not None:
            from pemviz.core.requirement import EXIT_CODES

            return EXIT_CODES[final.decision.outcome]
        return 0
    except KeyboardInterrupt as exc:  # after the run: say what it had written (rollouts, recording), not "nothing"
        written = [*(str(path) for _, path in kept), *([str(where)] if where is not None else [])]
        files = f"{', '.join(written)} written" if written else "no file written"
        raise interrupted(exc, f"the run finished; {files}; its result files not written") from None

"""``pemviz run``: one experiment (adaptive sampler or a baseline), a console table and a rerun recording."""

from __future__ import annotations

import argparse
import sys
from datetime import datetime
from pathlib import Path

from pemviz.config import DEFAULT_PRESET, EXECUTORS, METHODS, METRICS, PRESETS, SIMULATORS, ConfigError, ExperimentConfig


def register(sub: argparse._SubParsersAction) -> None:
    d = ExperimentConfig()
    p = sub.add_parser(
        "run",
        help="estimate the crash probability of the braking scenario",
        description="Run the PEM + adaptive importance sampling pipeline (or a baseline) and record it.",
    )
    p.add_argument("--method", default=d.method, help=f"one of {', '.join(METHODS)} (default {d.method})")
    p.add_argument(
        "--preset", default=DEFAULT_PRESET,
        help=f"sampler settings, one of {', '.join(PRESETS)} (default {DEFAULT_PRESET}: the recommended sampler, "
        "right against exact answers; paper: the published settings, biased low at this budget)",
    )
    p.add_argument("--k", "--stages", dest="n_stages", type=int, default=None, help=f"stages K (default {d.n_stages})")
    p.add_argument(
        "--n", dest="n_per_stage", type=int, default=None,
        help=f"rollouts per stage N, or the baseline's rollouts (default {d.n_per_stage})",
    )  # fmt: skip
    p.add_argument("--n-final", dest="n_final", type=int, default=None, help=f"final rollouts N_e (default {d.n_final})")
    p.add_argument("--sigma", dest="quantile_level", type=float, default=None, help="quantile level sigma in [0.5, 1)")
    p.add_argument("--alpha", dest="smoothing", type=float, default=None, help="smoothing alpha in (0, 1]")
    p.add_argument("--metric", default=None, help=f"robustness metric: {', '.join(METRICS)}")
    p.add_argument("--seed", type=int, default=None, help=f"random seed (default {d.seed})")
    p.add_argument("--ce-epochs", dest="ce_epochs", type=int, default=None, help="Adam epochs per stage")
    p.add_argument("--pem", default=None, help="a shipped PEM name (ml-nn, gbt) or a weights file (default: pemviz.pem.DEFAULT_PEM_NAME)")
    p.add_argument(
        "--sim", default=None,
        help=f"scenario back-end: {'|'.join(SIMULATORS)} (default {d.sim}; same rollouts for a seed)",
    )  # fmt: skip
    p.add_argument(
        "--executor", default=None,
        help=f"where rollouts run: {'|'.join(EXECUTORS)} (default {d.executor}; ray: Ray tasks, same estimate)",
    )  # fmt: skip
    p.add_argument("--ray-address", dest="ray_address", default=None, help="Ray cluster (default: start a local one)")
    p.add_argument(
        "--save-rollouts", dest="save_rollouts", default=None, metavar="PATH.parquet",
        help="write the final batch's rollouts (with log_p, log_q) for `pemviz estimate` (format: pemviz.rollout_io)",
    )  # fmt: skip
    rec = p.add_argument_group("recording (rerun)")
    rec.add_argument("--save", default=None, help="write the recording to this .rrd (default recordings/<name>.rrd)")
    rec.add_argument("--serve", action="store_true", help="serve the recording over gRPC for a rerun viewer")
    rec.add_argument("--connect", nargs="?", const="", default=None, metavar="URL", help="stream to a running viewer")
    rec.add_argument("--no-record", action="store_true", help="write no recording")
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing --save / --save-rollouts files (only files pemviz wrote)")
    p.set_defaults(func=main)


def config_from_args(args: argparse.Namespace) -> ExperimentConfig:
    """Build and validate the config; raises ConfigError with a one-line message."""
    if args.preset not in PRESETS:
        raise ConfigError(f"preset = {args.preset!r} is invalid: use one of {', '.join(PRESETS)}")
    fields = dict(PRESETS[args.preset])
    for name in ("method", "n_stages", "n_per_stage", "n_final", "quantile_level", "smoothing", "metric", "seed",
                 "ce_epochs", "pem", "sim", "executor", "ray_address"):  # fmt: skip
        value = getattr(args, name)
        if value is not None:
            fields[name] = value
    return ExperimentConfig(**fields)


FLAGS = {"n_stages": "--k", "n_per_stage": "--n", "n_final": "--n-final", "quantile_level": "--sigma",
         "smoothing": "--alpha", "ce_epochs": "--ce-epochs", "ray_address": "--ray-address"}
"""Config fields whose flag is not ``--`` + the field name."""


def check_save_path(path: Path, overwrite: bool = False) -> Path:
    """Refuse a recording path that cannot be written, before any work starts (nothing is created)."""
    from pemviz.commands import UsageError
    from pemviz.files import check_output_path

    try:
        return check_output_path(path, ".rrd", "--save", overwrite=overwrite)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def free_default_path(folder: Path, stem: str, suffix: str = ".rrd") -> Path:
    """``folder/stem.rrd``, or ``stem-2.rrd``, ``stem-3.rrd`` ... when taken: default names never replace a file."""
    path, k = folder / f"{stem}{suffix}", 2
    while path.exists():
        path, k = folder / f"{stem}-{k}{suffix}", k + 1
    return path


def default_recording_path(cfg: ExperimentConfig) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return free_default_path(Path("recordings"), f"{cfg.method}-{cfg.metric}-seed{cfg.seed}-{stamp}")


def main(args: argparse.Namespace) -> int:
    from pemviz.commands import UsageError

    try:
        cfg = config_from_args(args)
    except ConfigError as exc:
        flag = FLAGS.get(exc.field or "", f"--{(exc.field or '').replace('_', '-')}")
        raise UsageError(f"{flag}: {exc}" if exc.field else str(exc)) from None
    if args.pem is not None:
        from pemviz.pem import shipped_pems

        if args.pem not in shipped_pems() and not Path(args.pem).is_file():
            raise UsageError(f"--pem {args.pem}: neither a shipped PEM ({', '.join(shipped_pems())}) nor a file")
    if cfg.executor == "ray":
        import importlib.util

        if importlib.util.find_spec("ray") is None:
            raise UsageError("--executor ray: Ray is not installed (pip install ray)")
        from pemviz.executors import probe_ray_address

        probe_ray_address(cfg.ray_address)  # before any work: a wrong address is one line, not a silent wait
    rollout_sink = None
    if args.save_rollouts is not None:
        from pemviz.rollout_io import RolloutSink

        from pemviz.engine import STREAM_ABOVE

        n_final = cfg.n_final if cfg.method == "adaptive" else cfg.n_per_stage
        if n_final > STREAM_ABOVE:  # such batches are streamed in chunks, never held whole
            raise UsageError(f"--save-rollouts: at most {STREAM_ABOVE} final rollouts can be saved, got {n_final}")
        try:
            rollout_sink = RolloutSink(args.save_rollouts, pem=cfg.pem, overwrite=args.overwrite)
        except ValueError as exc:
            raise UsageError(str(exc)) from None

    save_path = None
    if not args.no_record and not args.serve and args.connect is None:
        if args.save is None:  # recordings/ is made once every check has passed
            from pemviz.files import check_output_folder

            save_path = default_recording_path(cfg)
            try:
                check_output_folder(save_path.parent, (save_path.name,), "recording folder")
            except ValueError as exc:
                raise UsageError(str(exc)) from None
        else:
            save_path = check_save_path(Path(args.save), args.overwrite)

    from pemviz.commands import interrupted
    from pemviz.engine import STREAM_ABOVE, Experiment
    from pemviz.resources import check_run_memory
    from pemviz.scenarios.braking import BrakingParams
    from pemviz.sinks.console import ConsoleSink

    check_run_memory(cfg, BrakingParams().n_steps, stream_above=STREAM_ABOVE if cfg.executor == "serial" else None)
    experiment = Experiment(cfg)  # loads the PEM: a bad --pem fails here, before any output exists
    listeners = [ConsoleSink()]
    recorder = None
    if save_path is not None or args.serve or args.connect is not None:
        from pemviz.sinks.recording import RerunSink

        if save_path is not None:
            save_path.parent.mkdir(exist_ok=True)
            recorder = RerunSink.to_file(save_path, overwrite=args.overwrite)
        else:
            recorder = RerunSink.to_grpc(args.connect or None, serve=args.serve)
        listeners.append(recorder)
    if rollout_sink is not None:
        listeners.append(rollout_sink)
    experiment.listeners[:0] = listeners
    try:
        experiment.run()
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: keep the finished stages, say what was saved
        where = recorder.close() if recorder is not None else None
        done = f"{len(experiment.stages)} stage(s) finished"
        raise interrupted(exc, f"{done}; recording {where} (marked interrupted)" if where else
                          f"{done}; nothing written") from None
    except BaseException:
        if recorder is not None:
            recorder.close(commit=False)
        raise
    if rollout_sink is not None and rollout_sink.written is not None:
        print(f"rollouts: {rollout_sink.written}", file=sys.stderr)
    elif rollout_sink is not None and rollout_sink.skipped:
        print(f"--save-rollouts: nothing written: {rollout_sink.skipped}", file=sys.stderr)
    if recorder is not None:
        where = recorder.close()
        if where is not None:
            print(f"recording: {where}", file=sys.stderr)
    return 0

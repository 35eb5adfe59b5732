"""``pemviz pem train | eval``: (re)train the shipped PEM weights (detection and noise); cross-validate the PEM models
(Table I) and the noise PEMs against the homoscedastic baseline."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from pemviz.commands import UsageError, add_command, output_folder
from pemviz.io.data import DataError, load_salient_data, sha256_file
from pemviz.io.files import check_output_folder, check_output_path, write_text_atomic
from pemviz.pem import fit_norm_stats, save_pem
from pemviz.pem.encoding import bce_from_logits
from pemviz.pem.noise import nll, noise_training_data
from pemviz.pem.recipes import NOISE_RECIPES, PEM_RECIPES
from pemviz.pem.store import load_reference_pem, noise_pem_path, pem_path, save_noise_pem
from pemviz.studies import noise_eval
from pemviz.studies.pem_eval import MODEL_NAMES, EvalConfig, evaluate_pems, format_csv, format_markdown, summary_lines
from pemviz.studies.pem_eval_recording import write_recording

NOISE_CSV = "pem-noise-eval.csv"


DESCRIPTION = """
Train the PEM on the KITTI salient files or cross-validate the models (both need the files: pemviz data fetch).
"""
"""``pemviz pem --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz pem`` and its actions ``train`` and ``eval`` to the sub-command parsers ``sub``."""
    p = add_command(sub, "pem", DESCRIPTION)
    actions = p.add_subparsers(dest="pem_command", required=True)
    _add_train(actions)
    _add_eval(actions)


def _add_train(actions: argparse._SubParsersAction) -> None:
    """``pemviz pem train``'s flags."""
    t = actions.add_parser(
        "train",
        help="train a PEM on the full salient file and write its weights",
        description="Train a named PEM on salient_inputs_no_miscUnknown.txt and write pemviz/assets/pem_<model>.pt "
        "(a noise PEM: pemviz/assets/noise_<model>.pt; or --out).",
    )
    t.add_argument(
        "--model",
        default="ml-nn",
        help=f"one of {', '.join([*PEM_RECIPES, *NOISE_RECIPES])} (default ml-nn: the paper's; gbt: the best "
        "cross-validated; hetero-t: the noise PEM of range and lateral errors)",
    )
    t.add_argument(
        "--epochs", type=int, help="epochs for ml-nn and hetero-t, trees for gbt (default: the model's, 300, 300, 100)"
    )
    t.add_argument("--seed", type=int, help="seed (default: the model's shipped seed)")
    t.add_argument(
        "--ensemble",
        type=int,
        metavar="M",
        help="train M bootstrap refits of a detection PEM instead (its epistemic uncertainty, for pemviz "
        "run --pem-uncertainty) and write pemviz/assets/ensemble_<model>.pt (or --out; beside a PEM file "
        "X.pt, pemviz looks for X.ensemble.pt)",
    )
    t.add_argument("--out", metavar="PATH", help="weights file (default: the shipped pemviz/assets/pem_<model>.pt)")
    t.add_argument("--data-dir", metavar="DIR", help="folder with the salient files (default: searched)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(func=train_main)


def _add_eval(actions: argparse._SubParsersAction) -> None:
    """``pemviz pem eval``'s flags."""
    e = actions.add_parser(
        "eval",
        help="5-fold cross-validation of the PEM models (paper Table I) and the noise PEMs, with calibration",
        description="Cross-validate ML-NN, LR, Guess-mu, B-NN and pemviz's gradient-boosted trees on the paper's "
        "5 stratified folds, and the noise PEMs (range and lateral errors of detected obstacles, metres) against "
        "the homoscedastic baseline on the same folds; write a Markdown table of both, a CSV table of each and a "
        "rerun recording (ROC curves, reliability diagrams, p(detect | gap) beside the authors' PEM). Needs the "
        "KITTI salient files (see pemviz data fetch).",
    )
    e.add_argument(
        "--models",
        help=f"comma-separated subset of {','.join(MODEL_NAMES)} (detection) and "
        f"{','.join(noise_eval.NOISE_MODEL_NAMES)} (noise); default all",
    )
    e.add_argument("--folds", help="comma-separated fold numbers 0..4 (default all)")
    e.add_argument(
        "--quick",
        action="store_true",
        help="CI size: fold 0 only, 20 ML-NN epochs, 60 trees, 200 B-NN steps, 100 B-NN samples, 15 noise epochs",
    )
    e.add_argument("--epochs", type=int, help="ML-NN epochs per fold (default 300)")
    e.add_argument("--noise-epochs", type=int, help="noise PEM epochs per fold (default 100)")
    e.add_argument("--trees", type=int, help="boosted trees per fold (default 300)")
    e.add_argument("--bnn-steps", type=int, help="B-NN SVI steps per fold (default 2000)")
    e.add_argument("--bnn-samples", type=int, help="B-NN posterior samples (default 800)")
    e.add_argument("--seed", type=int, default=0, help="seed of every model (default 0)")
    e.add_argument(
        "--ensemble",
        type=int,
        metavar="M",
        help="also cross-validate M bootstrap members of the ML-NN (as pemviz pem train --ensemble M builds "
        "them) beside the nominal one, on the same folds (pem-eval-ensemble.md)",
    )
    e.add_argument("--jobs", type=int, default=1, help="worker processes for --ensemble (default 1)")
    e.add_argument(
        "--out",
        default="recordings",
        metavar="DIR",
        help=f"folder for pem-eval.md, pem-eval.csv, {NOISE_CSV} and pem-eval.rrd, created if needed "
        "(default recordings)",
    )
    e.add_argument("--save", metavar="PATH", help="recording path (default <out>/pem-eval.rrd)")
    e.add_argument("--no-record", action="store_true", help="write no rerun recording")
    e.add_argument("--data-dir", metavar="DIR", help="folder with the salient files (default: searched)")
    e.set_defaults(func=eval_main)


def _check_out_path(out: Path) -> None:
    """``--out`` of ``pem train``: a ``.pt`` file that can be written (checked before training; it is replaced)."""
    try:
        check_output_path(out, ".pt", "--out", overwrite=True)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def train_main(args: argparse.Namespace) -> int:
    """``pemviz pem train``: train a detection PEM, a noise PEM or an ensemble of detection PEMs on the salient data and
    write it.

    Returns:
        The exit status: 0, or 1 after one error line when the salient data cannot be read.

    Raises:
        UsageError: an unknown model, ``--epochs`` < 1, a bad ``--ensemble`` or output path."""
    if args.model not in PEM_RECIPES and args.model not in NOISE_RECIPES:
        raise UsageError(f"--model {args.model!r}: use one of {', '.join([*PEM_RECIPES, *NOISE_RECIPES])}")
    if args.epochs is not None and args.epochs < 1:
        raise UsageError(f"--epochs {args.epochs}: must be >= 1")
    noise = args.model in NOISE_RECIPES
    recipe = NOISE_RECIPES[args.model] if noise else PEM_RECIPES[args.model]
    ensemble = getattr(args, "ensemble", None)
    if ensemble is not None and (noise or not hasattr(recipe, "hidden") or ensemble < 2):
        raise UsageError(
            f"--ensemble {ensemble}: give M >= 2 with a network detection PEM "
            f"({', '.join(n for n, r in PEM_RECIPES.items() if hasattr(r, 'hidden'))})"
        )
    if ensemble is not None:
        from pemviz.pem.ensemble import ensemble_path

        out = Path(args.out) if args.out else ensemble_path(recipe.name)
    else:
        out = Path(args.out) if args.out else (noise_pem_path if noise else pem_path)(recipe.name)
    _check_out_path(out)
    try:
        data = load_salient_data(args.data_dir)
    except (DataError, FileNotFoundError) as exc:
        print(f"pemviz pem train: error: {exc}", file=sys.stderr)
        return 1
    seed = recipe.seed if args.seed is None else args.seed
    epochs = recipe.epochs if args.epochs is None else args.epochs
    metadata = {
        "command": f"pemviz pem train --model {recipe.name} --seed {seed} --epochs {epochs}",
        "data_file": data.inputs_path.name,
        "data_sha256": sha256_file(data.inputs_path),
        "labels_sha256": sha256_file(data.labels_path),
    }
    if ensemble is not None:
        metadata["command"] = (
            f"pemviz pem train --model {recipe.name} --ensemble {ensemble} --seed {seed} --epochs {epochs}"
        )
        _train_ensemble(
            recipe, data, ensemble, seed=seed, epochs=epochs, out=out, progress=not args.no_progress, metadata=metadata
        )
    else:
        train = _train_noise if noise else _train_detection
        train(recipe, data, seed=seed, epochs=epochs, out=out, progress=not args.no_progress, metadata=metadata)
    print(f"wrote {out}")
    return 0


def _train_detection(recipe, data, *, seed: int, epochs: int, out: Path, progress: bool, metadata: dict) -> None:
    """``pem train --model ml-nn | gbt``: a detection PEM on the full file, its BCE and p(detect | gap), saved."""
    print(f"training {recipe.name} ({recipe.description}) on {data.inputs_path} ({len(data)} rows), seed {seed}")
    pem = recipe.train(data.inputs, data.labels, seed=seed, epochs=epochs, progress=progress, metadata=metadata)
    bce = bce_from_logits(pem.logit(data.inputs), data.labels)
    gaps = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 12.293, 13.0])
    p = pem.prob_at_gap(gaps)
    print(f"BCE on the full training file: {bce:.4f} nats (Guess-mu: 0.2595)")
    print("p(detect | gap): " + ", ".join(f"{g:g} m {q:.4f}" for g, q in zip(gaps, p, strict=False)))
    try:
        ref = load_reference_pem()
    except FileNotFoundError:
        pass
    else:
        grid = np.linspace(2.0, 13.0, 111)
        diff = np.abs(pem.prob_at_gap(grid) - ref.prob_at_gap(grid)).max()
        print(f"max |p_pemviz - p_authors| over gaps 2..13 m: {diff:.4f}")
    save_pem(pem, out)


def _train_ensemble(recipe, data, m: int, *, seed: int, epochs: int, out: Path, progress: bool, metadata: dict) -> None:
    """``pem train --ensemble M``: M bootstrap refits of a detection PEM (:mod:`pemviz.pem.ensemble`), each one's BCE
    on the full file and p(detect | 4 m), saved as one ensemble file."""
    from pemviz.pem.ensemble import save_ensemble, train_ensemble

    print(f"training {m} bootstrap refits of {recipe.name} on {data.inputs_path} ({len(data)} rows), seed {seed}")
    members = train_ensemble(
        recipe, data.inputs, data.labels, m, seed=seed, epochs=epochs, progress=progress, metadata=metadata
    )
    for k, pem in enumerate(members):
        bce = bce_from_logits(pem.logit(data.inputs), data.labels)
        print(
            f"member {k}: BCE on the full file {bce:.4f} nats, "
            f"p(detect | 4 m) {pem.prob_at_gap(np.array([4.0]))[0]:.4f}"
        )
    save_ensemble(members, out, recipe.name, metadata)


def _train_noise(recipe, data, *, seed: int, epochs: int, out: Path, progress: bool, metadata: dict) -> None:
    """``pem train --model hetero-t``: the noise PEM on the detected obstacles' metric errors of the full file
    (z-scored with the full file's statistics, as the detection PEMs), saved."""
    noise = noise_training_data(data.inputs, data.label_table, seed=seed)
    print(
        f"training {recipe.name} ({recipe.description}) on {noise.rows.size} detected obstacles of "
        f"{data.labels_path} ({len(data)} rows), seed {seed}"
    )
    model = recipe.train(
        noise.inputs,
        noise.errors,
        seed=seed,
        epochs=epochs,
        norm=fit_norm_stats(data.inputs),
        progress=progress,
        metadata=metadata,
    )
    print(
        f"NLL on the full training set: {nll(model, noise.inputs, noise.errors):.4f} nats per obstacle; "
        f"degrees of freedom (range, lateral) {model.df[0]:.2f}, {model.df[1]:.2f}"
    )
    save_noise_pem(model, out)


def _int_list(text: str | None, option: str) -> tuple[int, ...] | None:
    if text is None:
        return None
    try:
        return tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise UsageError(f"{option} {text!r}: give comma-separated integers") from None


def eval_config_from_args(args: argparse.Namespace) -> tuple[EvalConfig | None, noise_eval.NoiseEvalConfig | None]:
    """The detection PEMs' :class:`pemviz.studies.pem_eval.EvalConfig` and the noise PEMs'
    :class:`pemviz.studies.noise_eval.NoiseEvalConfig` of the command line (None where ``--models`` names none of
    that kind); UsageError on bad values."""
    fields: dict = {"seed": args.seed}
    noise_fields: dict = {"seed": args.seed}
    if args.quick:
        fields.update(folds=(0,), mlnn_epochs=20, gbt_trees=60, bnn_steps=200, bnn_samples=100)
        noise_fields.update(folds=(0,), epochs=15)
    detect_models: tuple[str, ...] = MODEL_NAMES
    noise_models: tuple[str, ...] = noise_eval.NOISE_MODEL_NAMES
    if args.models is not None:
        names = tuple(m.strip() for m in args.models.split(",") if m.strip())
        detect_models = tuple(m for m in names if m not in noise_eval.NOISE_MODEL_NAMES)
        noise_models = tuple(m for m in names if m in noise_eval.NOISE_MODEL_NAMES)
        if not names:
            raise UsageError(f"--models {args.models!r}: name at least one model")
    fields["models"] = detect_models
    noise_fields["models"] = noise_models
    folds = _int_list(args.folds, "--folds")
    if folds is not None:
        fields["folds"] = noise_fields["folds"] = folds
    for option, name in (
        ("epochs", "mlnn_epochs"),
        ("trees", "gbt_trees"),
        ("bnn_steps", "bnn_steps"),
        ("bnn_samples", "bnn_samples"),
    ):
        value = getattr(args, option)
        if value is not None:
            fields[name] = value
    if args.noise_epochs is not None:
        noise_fields["epochs"] = args.noise_epochs
    try:
        # the noise config is checked even when unused, so that a bad --noise-epochs is never silently ignored
        noise = noise_eval.NoiseEvalConfig(**{**noise_fields, "models": noise_models or noise_eval.NOISE_MODEL_NAMES})
        detect = EvalConfig(**fields) if detect_models else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return detect, (noise if noise_models else None)


def eval_main(args: argparse.Namespace) -> int:
    """``pemviz pem eval``: cross-validate the PEM models and write the reports (Markdown, CSV, recording).

    Returns:
        The exit status: 0, or 1 after one error line when the salient data cannot be read.

    Raises:
        UsageError: a bad model list, fold list, ``--ensemble``, ``--jobs`` or output path."""
    config, noise_config = eval_config_from_args(args)
    if getattr(args, "ensemble", None) is not None and (args.ensemble < 2 or args.jobs < 1):
        raise UsageError(f"--ensemble {args.ensemble} --jobs {args.jobs}: give M >= 2 members and at least 1 job")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: exists and is not a folder")
    rrd = None if args.no_record or config is None else (Path(args.save) if args.save else out / "pem-eval.rrd")

    out = output_folder(out)  # created like validate's and tables' --out
    try:  # every output checked before the cross-validation (the reports are regenerated in place)
        check_output_folder(out, ("pem-eval.md", "pem-eval.csv", NOISE_CSV, "pem-eval-ensemble.md"))
        if rrd is not None:
            check_output_path(rrd, ".rrd", "--save", overwrite=True)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        data = load_salient_data(args.data_dir)
    except (DataError, FileNotFoundError) as exc:
        print(f"pemviz pem eval: error: {exc}", file=sys.stderr)
        return 1
    markdown, wrote = [], []
    if config is not None:
        result = _eval_detection(data, config)
        markdown.append(format_markdown(result))
        wrote.append(write_text_atomic(out / "pem-eval.csv", format_csv(result)))
        if rrd is not None:
            wrote.append(write_recording(result, rrd))
    if getattr(args, "ensemble", None) is not None:
        wrote.append(_eval_ensemble(data, args, config, result if config is not None else None, out))
    if noise_config is not None:
        noise = _eval_noise(data, noise_config)
        markdown.append(noise_eval.format_markdown(noise))
        wrote.append(write_text_atomic(out / NOISE_CSV, noise_eval.format_csv(noise)))
    wrote.insert(0, write_text_atomic(out / "pem-eval.md", "\n".join(markdown)))
    print(f"wrote {', '.join(str(w) for w in wrote)}")
    return 0


def _cross_validate(heading: str, fold_line: Callable[[str, Any], str], run: Callable, summary: Callable, best: str):
    """Print ``heading``, run ``run(on_fold)`` printing a line per fold, then the ``summary`` lines and the best model
    (``best``: what it is best by); the result."""
    print(heading, flush=True)
    result = run(lambda name, fs: print(f"  {fold_line(name, fs)}", flush=True))
    print("\n".join(summary(result)))
    print(f"{best}: {result.best()}; wall time {result.wall_s:.0f} s", flush=True)
    return result


def _eval_detection(data, config: EvalConfig):  # -> pemviz.studies.pem_eval.EvalResult
    """Table I: the detection PEMs' cross-validation, with its console lines."""
    return _cross_validate(
        f"cross-validating {', '.join(config.models)} on folds {list(config.fold_ids)} of {config.n_splits} "
        f"({len(data)} rows from {data.inputs_path.parent})",
        lambda name, fs: f"{name:9s} fold {fs.fold}: BCE {fs.bce:.4f}  AUC {fs.auc:.4f}  AP {fs.ap:.4f}  "
        f"ECE {fs.ece:.4f}  ({fs.fit_s:.1f} s)",
        lambda on_fold: evaluate_pems(
            data.inputs, data.labels, config, on_fold=on_fold, data_source=data.inputs_path.name
        ),
        summary_lines,
        "best by mean BCE",
    )


def _eval_ensemble(data, args: argparse.Namespace, config, result, out: Path) -> Path:
    """``--ensemble M``: the bootstrap members' cross-validation beside the nominal ML-NN's (when it ran), printed and
    written to ``pem-eval-ensemble.md``."""
    from pemviz.studies.ensemble_eval import evaluate_ensemble, format_ensemble_markdown

    config = config or EvalConfig(models=("ml-nn",), seed=args.seed)
    print(
        f"cross-validating {args.ensemble} bootstrap members of ml-nn on folds {list(config.fold_ids)} "
        f"({args.jobs} worker(s))",
        flush=True,
    )

    def on_fit(k: int, fold: int, bce: float, auc: float) -> None:
        print(f"  member {k:2d} fold {fold}: BCE {bce:.4f}  AUC {auc:.4f}", flush=True)

    ev = evaluate_ensemble(data.inputs, data.labels, args.ensemble, config, jobs=args.jobs, on_fit=on_fit)
    nominal = None
    if result is not None and "ml-nn" in config.models:
        nominal = result.model("ml-nn")
    text = format_ensemble_markdown(ev, nominal)
    print(text)
    return write_text_atomic(out / "pem-eval-ensemble.md", text)


def _eval_noise(data, config: noise_eval.NoiseEvalConfig) -> noise_eval.NoiseEvalResult:
    """The noise PEMs' cross-validation against the homoscedastic baseline, with its console lines."""
    return _cross_validate(
        f"cross-validating the noise PEMs {', '.join(config.models)} on folds {list(config.fold_ids)} of "
        f"{config.n_splits} (detected obstacles of {data.labels_path.name})",
        lambda name, fs: f"{name:14s} fold {fs.fold}: NLL {fs.nll:.4f}  coverage 95 % {fs.coverage[-1, 0]:.3f} / "
        f"{fs.coverage[-1, 1]:.3f}  ({fs.fit_s:.1f} s)",
        lambda on_fold: noise_eval.evaluate_noise_pems(
            data.inputs, data.label_table, config, on_fold=on_fold, data_source=data.labels_path.name
        ),
        noise_eval.summary_lines,
        "best noise PEM by mean NLL",
    )

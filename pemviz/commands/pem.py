"""``pemviz pem train | eval``: (re)train the shipped PEM weights; cross-validate the PEM models (Table I)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    from pemviz.pem import PEM_RECIPES

    p = sub.add_parser(
        "pem",
        help="train or evaluate the perception error model (PEM)",
        description="Train the PEM on the KITTI salient files (spec section 2) or cross-validate the models.",
    )
    actions = p.add_subparsers(dest="pem_command", required=True)
    t = actions.add_parser(
        "train",
        help="train a PEM on the full salient file and write its weights",
        description="Train a named PEM on salient_inputs_no_miscUnknown.txt and write assets/pem_<model>.pt "
        "(or --out).",
    )
    t.add_argument("--model", default="ml-nn", help=f"one of {', '.join(PEM_RECIPES)} (default ml-nn)")
    t.add_argument("--epochs", type=int, default=None, help="epochs (default: the model's, 300 for ml-nn)")
    t.add_argument("--seed", type=int, default=None, help="seed (default: the model's shipped seed)")
    t.add_argument("--out", default=None, metavar="PATH", help="weights file (default assets/pem_<model>.pt)")
    t.add_argument("--data-dir", default=None, metavar="DIR", help="folder with the salient files (default: searched)")
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(func=train_main)


def _check_out_path(out: Path) -> None:
    from pemviz.cli import UsageError

    if out.suffix != ".pt":
        raise UsageError(f"--out {out}: the weights file must end in .pt")
    if out.is_dir():
        raise UsageError(f"--out {out}: is a directory")
    if not out.parent.is_dir():
        raise UsageError(f"--out {out}: folder {out.parent} does not exist")


def train_main(args: argparse.Namespace) -> int:
    from pemviz.cli import UsageError
    from pemviz.data import DataError, load_salient_data, sha256_file
    from pemviz.pem import PEM_RECIPES, bce_from_logits, load_reference_pem, pem_path, save_pem

    if args.model not in PEM_RECIPES:
        raise UsageError(f"--model {args.model!r}: use one of {', '.join(PEM_RECIPES)}")
    if args.epochs is not None and args.epochs < 1:
        raise UsageError(f"--epochs {args.epochs}: must be >= 1")
    recipe = PEM_RECIPES[args.model]
    out = Path(args.out) if args.out else pem_path(recipe.name)
    _check_out_path(out)
    try:
        data = load_salient_data(args.data_dir)
    except (DataError, FileNotFoundError) as exc:
        print(f"pemviz pem train: error: {exc}", file=sys.stderr)
        return 1
    seed = recipe.seed if args.seed is None else args.seed
    print(f"training {recipe.name} ({recipe.description}) on {data.inputs_path} ({len(data)} rows), seed {seed}")
    epochs = recipe.epochs if args.epochs is None else args.epochs
    metadata = {
        "command": f"pemviz pem train --model {recipe.name} --seed {seed} --epochs {epochs}",
        "data_file": data.inputs_path.name,
        "data_sha256": sha256_file(data.inputs_path),
        "labels_sha256": sha256_file(data.labels_path),
    }
    pem = recipe.train(data.inputs, data.labels, seed=seed, epochs=epochs, progress=not args.no_progress,
                       metadata=metadata)
    bce = bce_from_logits(pem.logit(data.inputs), data.labels)
    gaps = np.array([2.0, 4.0, 6.0, 8.0, 10.0, 12.293, 13.0])
    p = pem.prob_at_gap(gaps)
    print(f"BCE on the full training file: {bce:.4f} nats (Guess-mu: 0.2595)")
    print("p(detect | gap): " + ", ".join(f"{g:g} m {q:.4f}" for g, q in zip(gaps, p)))
    try:
        ref = load_reference_pem()
    except FileNotFoundError:
        pass
    else:
        grid = np.linspace(2.0, 13.0, 111)
        diff = np.abs(pem.prob_at_gap(grid) - ref.prob_at_gap(grid)).max()
        print(f"max |p_pemviz - p_authors| over gaps 2..13 m: {diff:.4f}")
    save_pem(pem, out)
    print(f"wrote {out}")
    return 0

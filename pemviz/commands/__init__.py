"""Sub-commands of the ``pemviz`` command line; each module exposes ``register(subparsers)``.

This module holds what the commands share (and :mod:`pemviz.cli` uses): :class:`UsageError`, :class:`Terminated`,
the output folder check, and the argument helpers of ``validate`` and ``tables``; it imports no command.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any, Iterable

from pemviz.config import ConfigError, ExperimentConfig
from pemviz.io.files import check_output_path


COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("pemviz.commands.run", "estimate the crash probability of the braking scenario"),
    "data": ("pemviz.commands.data", "fetch or locate the KITTI salient-variable files"),
    "pem": ("pemviz.commands.pem", "train or evaluate the perception error model (PEM)"),
    "serve": ("pemviz.commands.serve", "open the interactive panel in the browser (viser)"),
    "estimate": ("pemviz.commands.estimate", "estimate the failure probability from logged rollouts (Parquet)"),
    "validate": ("pemviz.commands.validate", "judge the sampler and the baselines against exact failure probabilities"),
    "tables": ("pemviz.commands.tables", "reproduce the paper's Tables II and III with repetitions and the exact answer"),
}
"""Each command: (its module, its one-line help). ``pemviz --help`` lists them without importing any command module."""


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2, nothing written."""


def output_folder(path: str | Path, flag: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) if needed and check that files can be written there.

    Every command's ``--out DIR`` goes through here, so they all behave alike: a missing folder is created, an
    existing one is reused (``validate`` and ``tables`` resume from it).

    Raises:
        UsageError: ``path`` is a file, or the folder cannot be created or written.
    """
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{flag} {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".pemviz-probe-"):
            pass
    except OSError as exc:
        raise UsageError(f"{flag} {out}: cannot write there ({exc.strerror or exc})") from None
    return out


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, CI, containers), raised where Python runs, handled like Ctrl-C: the command
    finishes what can be finished (a recording marked interrupted), says so in one line, exit status 143."""


def interrupted(exc: KeyboardInterrupt, done: str) -> KeyboardInterrupt:
    """The same interrupt (Ctrl-C or :class:`Terminated`) carrying what the command finished, for the one line
    the command line prints."""
    return type(exc)(done)


def split_choices(text: str, allowed: Iterable[str], flag: str) -> tuple[str, ...]:
    """The comma-separated names of ``--FLAG text``, each one of ``allowed``, in the order given.

    Raises:
        UsageError: an empty list or a name outside ``allowed``.
    """
    items = tuple(x.strip() for x in text.split(",") if x.strip())
    allowed = tuple(allowed)
    if not items or any(x not in allowed for x in items):
        raise UsageError(f"--{flag} {text!r}: use a comma-separated list of {', '.join(allowed)}")
    return items


def add_sampler_arguments(p: argparse.ArgumentParser) -> None:
    """The sampler sizes shared by ``validate`` and ``tables``: --k, --n, --n-final, --ce-epochs, ..."""
    d = ExperimentConfig()
    p.add_argument("--k", "--stages", dest="n_stages", type=int, default=None, help=f"stages K (default {d.n_stages})")
    p.add_argument("--n", dest="n_per_stage", type=int, default=None, help=f"rollouts per stage N (default {d.n_per_stage})")
    p.add_argument("--n-final", dest="n_final", type=int, default=None, help=f"final rollouts N_e (default {d.n_final})")
    p.add_argument("--ce-epochs", dest="ce_epochs", type=int, default=None, help=f"epochs per stage (default {d.ce_epochs})")
    p.add_argument("--pretrain-epochs", dest="pretrain_epochs", type=int, default=None,
                   help=f"pretraining epochs (default {d.pretrain_epochs})")
    p.add_argument("--pem", default=None, help="PEM weights (default: the shipped one)")


def base_fields(args: argparse.Namespace) -> dict[str, Any]:
    """Config fields given on the command line (validated by building a config)."""
    fields = {k: getattr(args, k) for k in ("n_stages", "n_per_stage", "n_final", "ce_epochs", "pretrain_epochs", "pem")
              if getattr(args, k, None) is not None}  # fmt: skip
    try:
        ExperimentConfig(**fields)
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    return fields


def check_save_path(path: Path, overwrite: bool = False) -> Path:
    """Refuse a recording path that cannot be written, before any work starts (nothing is created)."""
    try:
        return check_output_path(path, ".rrd", "--save", overwrite=overwrite)
    except ValueError as exc:
        raise UsageError(str(exc)) from None

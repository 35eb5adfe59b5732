"""An ensemble of plausible PEMs: bootstrap refits that express the shipped PEM's epistemic uncertainty.

A crash needs many misses in a row, so p moves by orders of magnitude with small shifts of the PEM at short range.
The ensemble is M refits of the same recipe, each on a bootstrap resample of the training rows (Efron & Tibshirani,
"An Introduction to the Bootstrap", 1993; Lakshminarayanan, Pritzel & Blundell, "Simple and scalable predictive
uncertainty estimation using deep ensembles", NeurIPS 2017), z-scored with the full file's statistics; rollouts
drawn once are re-weighted under each member (:mod:`pemviz.core.reweight`). The file is a ``torch.save`` dict
(``format`` ``pemviz-pem-ensemble``, ``version`` 1, ``nominal``, ``metadata``, ``members``: PEM payloads as
:func:`pemviz.pem.store.save_pem` writes them), readable with ``weights_only=True``."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pemviz.pem.encoding import fit_norm_stats
from pemviz.pem.network import PEM, PemFormatError
from pemviz.pem.store import AnyPEM, _load_payload, _pem_from_payload, _pem_payload, _save, assets_dir

ENSEMBLE_TAG = "pemviz-pem-ensemble"
ENSEMBLE_VERSION = 1
DEFAULT_MEMBERS = 20
"""Members of the shipped ensemble (``pemviz pem train --model ml-nn --ensemble 20``)."""


def ensemble_path(name: str) -> Path:
    """Where the shipped ensemble of the PEM called ``name`` lives: ``<assets>/ensemble_<name>.pt``."""
    return assets_dir() / f"ensemble_{name}.pt"


def ensemble_for(pem: str | os.PathLike[str] | None) -> Path:
    """Where the ensemble of a PEM is looked for: ``<assets>/ensemble_<name>.pt`` for a shipped PEM's name (None: the
    default), ``<folder>/<stem>.ensemble.pt`` beside a PEM file."""
    from pemviz.pem.recipes import DEFAULT_PEM_NAME

    ref = DEFAULT_PEM_NAME if pem is None else pem
    p = Path(ref)
    if isinstance(ref, str) and p.suffix != ".pt" and len(p.parts) == 1:
        return ensemble_path(ref)
    return p.with_suffix(".ensemble.pt")


def bootstrap_rows(n: int, seed: int, member: int) -> np.ndarray:
    """The training rows of member ``member``: n draws with replacement from 0..n-1, int64 [n], from numpy's PCG64
    seeded with (seed, member) (the same rows on every machine)."""
    return np.random.default_rng([int(seed), int(member)]).integers(0, n, size=n)


def train_ensemble(
    recipe: Any,
    inputs: np.ndarray,
    labels: np.ndarray,
    m: int,
    *,
    seed: int = 0,
    epochs: int | None = None,
    progress: bool = False,
    metadata: Mapping[str, Any] | None = None,
) -> list[PEM]:
    """M bootstrap refits of a detection recipe (:class:`pemviz.pem.training.PemRecipe`): member k trains on
    :func:`bootstrap_rows` ``(n, seed, k)``, weights seeded ``seed + 1 + k``, with the full ``inputs``' z-score
    statistics.

    Args:
        recipe: the detection recipe refitted.
        inputs: the training file's raw salient inputs [N, 11].
        labels: its detections [N] in {0, 1}.
        m: members, at least 2.
        seed: the bootstrap's seed.
        epochs: each member's epochs (None: the recipe's).
        progress: print each member's training progress.
        metadata: provenance stored with each member.
    Raises:
        ValueError: m < 2, or what :func:`pemviz.pem.training.train_pem` raises."""
    if m < 2:
        raise ValueError(f"an ensemble needs at least 2 members, got {m}")
    inputs, labels = np.asarray(inputs), np.asarray(labels)
    norm = fit_norm_stats(inputs)
    members = []
    for k in range(m):
        rows = bootstrap_rows(len(labels), seed, k)
        meta = {**dict(metadata or {}), "member": k, "bootstrap_seed": [int(seed), k], "init_seed": int(seed) + 1 + k}
        members.append(
            recipe.train(
                inputs[rows],
                labels[rows],
                seed=int(seed) + 1 + k,
                epochs=epochs,
                norm=norm,
                progress=progress,
                metadata=meta,
            )
        )
    return members


def save_ensemble(
    members: Sequence[PEM], path: str | os.PathLike[str], nominal: str, metadata: Mapping[str, Any] | None = None
) -> Path:
    """Write an ensemble file atomically (see the module docstring).

    Raises:
        OSError: the folder is not writable (nothing is left behind)."""
    payload = {
        "format": ENSEMBLE_TAG,
        "version": ENSEMBLE_VERSION,
        "nominal": str(nominal),
        "metadata": dict(metadata or {}),
        "members": [_pem_payload(p) for p in members],
    }
    return _save(payload, path)


def load_ensemble(path: str | os.PathLike[str]) -> list[AnyPEM]:
    """The members of an ensemble file.

    Raises:
        FileNotFoundError: no such file; PemFormatError: not an ensemble file, or damaged."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(
            f"{p}: no PEM ensemble there (build one with pemviz pem train --ensemble 20, or "
            "pemviz.pem.ensemble.save_ensemble for a PEM of your own)"
        )
    payload = _load_payload(p, ENSEMBLE_TAG, ENSEMBLE_VERSION, "PEM ensemble")
    members = payload.get("members")
    if not isinstance(members, list) or len(members) < 2:
        raise PemFormatError(f"{p}: a PEM ensemble needs at least 2 members")
    return [_pem_from_payload(member, p) for member in members]

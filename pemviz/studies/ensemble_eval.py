"""The bootstrap members of a PEM ensemble (:mod:`pemviz.pem.ensemble`) cross-validated beside the nominal ML-NN, on
the folds and with the scores of :mod:`pemviz.studies.pem_eval` (``pemviz pem eval --ensemble M``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pemviz.pem import fit_norm_stats
from pemviz.pem.recipes import PEM_RECIPES
from pemviz.studies.pem_eval import EvalConfig, ModelEvaluation, score, stratified_folds


@dataclass(frozen=True)
class EnsembleEvaluation:
    """The bootstrap members of a PEM ensemble (:mod:`pemviz.pem.ensemble`) cross-validated as the models above are:
    in each fold, member k is the ML-NN recipe refitted on a bootstrap resample of the training fold (rows
    :func:`pemviz.pem.ensemble.bootstrap_rows` ``(n_train, seed, k)``, initial weights ``seed + 1 + k``, as the shipped
    ensemble is built), scored on the held-out fold.

    Attributes:
        seed: the recipe's seed; folds: the folds run; bce, auc: float64 [M, F] (nats; ROC-AUC); wall_s: seconds."""

    seed: int
    folds: tuple[int, ...]
    bce: np.ndarray
    auc: np.ndarray
    wall_s: float


def _member_fold(job: tuple) -> tuple[int, int, float, float]:
    """One (member, fold) fit and its held-out scores (a worker's job: module level, so that it pickles)."""
    from pemviz.pem.ensemble import bootstrap_rows

    k, fold, raw_train, y_train, raw_test, y_test, norm, seed, epochs, n_bins = job
    rows = bootstrap_rows(len(y_train), seed, k)
    model = PEM_RECIPES["ml-nn"].train(raw_train[rows], y_train[rows], seed=seed + 1 + k, epochs=epochs, norm=norm)
    bce, auc, _, _ = score(np.asarray(model.logit(raw_test), dtype=np.float64), y_test, n_bins)
    return k, fold, bce, auc


def evaluate_ensemble(
    inputs: np.ndarray,
    labels: np.ndarray,
    members: int,
    config: EvalConfig | None = None,
    *,
    jobs: int = 1,
    on_fit: Callable[[int, int, float, float], None] | None = None,
) -> EnsembleEvaluation:
    """Cross-validate ``members`` bootstrap members of the ML-NN recipe (its shipped seed) on ``config``'s folds, with
    ``jobs`` worker processes; ``on_fit(member, fold, bce, auc)`` after each fit.

    Raises:
        ValueError: members < 2 or jobs < 1."""
    if members < 2 or jobs < 1:
        raise ValueError(f"need members >= 2 and jobs >= 1, got {members}, {jobs}")
    config = EvalConfig() if config is None else config
    start = time.perf_counter()
    raw = np.asarray(inputs, dtype=np.float64)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    norm = fit_norm_stats(raw)
    splits = stratified_folds(y, config.n_splits)
    seed = PEM_RECIPES["ml-nn"].seed
    work = [
        (
            k,
            f,
            raw[splits[f][0]],
            y[splits[f][0]],
            raw[splits[f][1]],
            y[splits[f][1]],
            norm,
            seed,
            config.mlnn_epochs,
            config.n_bins,
        )
        for f in config.fold_ids
        for k in range(members)
    ]
    folds = list(config.fold_ids)
    bce, auc = np.full((members, len(folds)), np.nan), np.full((members, len(folds)), np.nan)

    def keep(result: tuple[int, int, float, float]) -> None:
        k, f, b, a = result
        bce[k, folds.index(f)], auc[k, folds.index(f)] = b, a
        if on_fit is not None:
            on_fit(k, f, b, a)

    if jobs == 1:
        for job in work:
            keep(_member_fold(job))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            for fut in as_completed([pool.submit(_member_fold, job) for job in work]):
                keep(fut.result())
    return EnsembleEvaluation(seed, tuple(folds), bce, auc, time.perf_counter() - start)


def format_ensemble_markdown(ev: EnsembleEvaluation, nominal: ModelEvaluation | None = None) -> str:
    """The members' cross-validation as Markdown: each member's mean BCE and ROC-AUC over the folds, their range, and
    the nominal ML-NN's row of the same folds beside them."""
    m = ev.bce.shape[0]
    lines = [
        f"Bootstrap ensemble of the ML-NN: {m} members (recipe seed {ev.seed}), folds {list(ev.folds)}; wall time "
        f"{ev.wall_s:.0f} s.",
        "",
        "| model | BCE (nats) | ROC-AUC |",
        "|---|---|---|",
    ]
    if nominal is not None:
        lines.append(f"| ml-nn (nominal) | {nominal.mean('bce'):.4f} | {nominal.mean('auc'):.4f} |")
    mb, ma = ev.bce.mean(axis=1), ev.auc.mean(axis=1)
    lines.append(
        f"| members: mean [min, max] | {mb.mean():.4f} [{mb.min():.4f}, {mb.max():.4f}] | {ma.mean():.4f} "
        f"[{ma.min():.4f}, {ma.max():.4f}] |"
    )
    lines += [f"| member {k} | {mb[k]:.4f} | {ma[k]:.4f} |" for k in range(m)]
    return "\n".join(lines) + "\n"

"""PEM quality: 5-fold cross-validation of the PEM models (Innes & Ramamoorthy 2022, Table I; the authors'
``eval_kfold_class_models.py``) with calibration: ``StratifiedKFold(n_splits=5)`` on the detected label, no shuffle,
z-scores from the full file; per fold BCE (nats), ROC-AUC, average precision and expected calibration error (15 bins).
Models: :data:`MODEL_NAMES`."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Generic, Protocol, TypeVar

import numpy as np
from scipy.special import expit

from pemviz.pem import braking_salient_inputs, encode_salient, fit_norm_stats
from pemviz.pem.bayes import train_bnn_pem
from pemviz.pem.encoding import NormStats, bce_from_logits
from pemviz.pem.recipes import PEM_RECIPES
from pemviz.pem.store import load_reference_pem

MODEL_NAMES = ("ml-nn", "lr", "guess-mu", "b-nn", "gbt")
"""Every model :func:`evaluate_pems` knows, in table order."""

MODEL_DESCRIPTIONS = {
    "ml-nn": "paper ML-NN: 14-20-20-1, BatchNorm, Adam 1e-3, batch 1024",
    "lr": "logistic regression on the 14 features (scikit-learn)",
    "guess-mu": "training-fold detection rate for every row",
    "b-nn": "Bayesian NN (pyro): N(0,1) priors, low-rank MVN guide, predictive mean",
    "gbt": "pemviz: gradient-boosted trees on the 14 features (scikit-learn)",
}

PAPER_TABLE_I = {"b-nn": (0.238, 0.726), "lr": (0.244, 0.688), "ml-nn": (0.226, 0.777), "guess-mu": (0.260, 0.5)}
"""(BCE, ROC-AUC) of the paper's Table I."""

GAP_GRID_M = np.round(np.arange(0.0, 50.0 + 1e-9, 0.25), 6)
"""Gaps (metres) at which each model's p(detect | braking scenario's lead) is tabulated."""


class Predictor(Protocol):
    """A fitted PEM model as the evaluation scores it: ``logit(raw_inputs)`` the logit of p(detect) of each row of raw
    inputs ``[N, 11]`` -> ``[N]``; ``logit_at_gap(gap_m)`` the logit of p(detect | the braking scenario's lead at gaps
    ``gap_m``, metres), the gaps' shape."""

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray: ...

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray: ...


class CrossValidation:
    """What the studies' settings share: the ``models`` (each known, none twice), ``n_splits`` stratified folds
    (:func:`stratified_folds`) and the ``folds`` tested (None: all)."""

    models: tuple[str, ...]
    n_splits: int
    folds: tuple[int, ...] | None

    @property
    def fold_ids(self) -> tuple[int, ...]:
        return tuple(range(self.n_splits)) if self.folds is None else tuple(self.folds)


def check_study(config: CrossValidation, known: tuple[str, ...], sizes: tuple[str, ...]) -> None:
    """Check a study's settings: its models among ``known``, at least 2 folds, and each field of ``sizes`` >= 1.

    Raises:
        ValueError: an unknown or repeated model, n_splits < 2, a fold outside 0..n_splits-1, or a size < 1."""
    models = config.models
    if not models or any(m not in known for m in models) or len(set(models)) != len(models):
        raise ValueError(f"models {list(models)}: use distinct ones of {', '.join(known)}")
    if config.n_splits < 2:
        raise ValueError(f"n_splits = {config.n_splits}: need at least 2 folds")
    if config.folds is not None and (not config.folds or any(not 0 <= f < config.n_splits for f in config.folds)):
        raise ValueError(f"folds {config.folds}: each must be in 0..{config.n_splits - 1}")
    for name in sizes:
        if getattr(config, name) < 1:
            raise ValueError(f"{name} = {getattr(config, name)}: must be >= 1")


@dataclass(frozen=True)
class EvalConfig(CrossValidation):
    """Settings of :func:`evaluate_pems`: ``folds`` (None = all; CI runs one), ``mlnn_epochs``, ``gbt_trees``,
    ``bnn_steps``, ``bnn_samples`` (smaller for a quick run; the defaults are the full protocol), ``seed`` for every
    model.

    Raises:
        ValueError: an unknown model, n_splits < 2, a fold outside 0..n_splits-1, or a size < 1."""

    models: tuple[str, ...] = MODEL_NAMES
    n_splits: int = 5
    folds: tuple[int, ...] | None = None
    mlnn_epochs: int = 300
    gbt_trees: int = 300
    bnn_steps: int = 2000
    bnn_samples: int = 800
    n_bins: int = 15
    seed: int = 0

    def __post_init__(self) -> None:
        check_study(self, MODEL_NAMES, ("mlnn_epochs", "gbt_trees", "bnn_steps", "bnn_samples", "n_bins"))


@dataclass(frozen=True)
class FoldScore:
    """One model on one test fold: BCE (nats), ROC-AUC, average precision, ECE; fit time in seconds."""

    fold: int
    n_test: int
    bce: float
    auc: float
    ap: float
    ece: float
    fit_s: float


@dataclass(frozen=True)
class ModelEvaluation:
    """A model's cross-validation: per-fold scores, out-of-fold logits and its p(detect | gap) curves.

    ``test_rows`` int ``[M]`` (rows of the data file, fold after fold), ``test_fold`` ``[M]``, ``logits``
    float64 ``[M]`` (each row scored by the model that did not train on it), ``gap_prob`` float64
    ``[F, G]`` (each fold's model on :data:`GAP_GRID_M`)."""

    name: str
    description: str
    folds: tuple[FoldScore, ...]
    test_rows: np.ndarray
    test_fold: np.ndarray
    logits: np.ndarray
    gap_prob: np.ndarray

    def mean(self, metric: str) -> float:
        return float(np.mean([getattr(f, metric) for f in self.folds]))

    def std(self, metric: str) -> float:
        values = [getattr(f, metric) for f in self.folds]
        return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0


class _Scored(Protocol):
    @property
    def name(self) -> str: ...

    def mean(self, metric: str) -> Any: ...


_Model = TypeVar("_Model", bound=_Scored)


class Evaluated(Generic[_Model]):
    """What the results of a cross-validation share: its models by name, and the best one, the lowest mean of the
    metric ``best_by`` over the folds."""

    models: tuple[_Model, ...]
    best_by: ClassVar[str]
    what: ClassVar[str] = "model"

    def model(self, name: str) -> _Model:
        for m in self.models:
            if m.name == name:
                return m
        raise KeyError(f"{self.what} {name!r} was not evaluated; evaluated: {[m.name for m in self.models]}")

    def best(self) -> str:
        """The model with the lowest mean ``best_by`` (BCE for the detection PEMs, NLL for the noise PEMs)."""
        return min(self.models, key=lambda m: m.mean(self.best_by)).name


@dataclass(frozen=True)
class EvalResult(Evaluated[ModelEvaluation]):
    """Everything :func:`evaluate_pems` measured (``labels``: the full file's, ``[N]``)."""

    config: EvalConfig
    models: tuple[ModelEvaluation, ...]
    labels: np.ndarray
    gaps_m: np.ndarray
    authors_gap_prob: np.ndarray | None
    wall_s: float
    data_source: str = ""

    best_by: ClassVar[str] = "bce"


# ------------------------------------------------------------------------------------------- metrics


def stratified_folds(labels: np.ndarray, n_splits: int = 5) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(train_rows, test_rows)`` of ``StratifiedKFold(n_splits)`` on the labels, file order, no shuffle."""
    from sklearn.model_selection import StratifiedKFold

    y = np.asarray(labels).reshape(-1)
    return list(StratifiedKFold(n_splits=n_splits, shuffle=False).split(np.zeros((y.shape[0], 1)), y))


def reliability_curve(
    prob: np.ndarray, labels: np.ndarray, n_bins: int = 15
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal-width reliability bins on [0, 1]: ``(mean predicted p, observed detection rate, count)``,
    each ``[n_bins]`` (NaN where a bin is empty). Bin ``k`` holds ``k/n <= p < (k+1)/n`` (p = 1 in the last)."""
    p = np.asarray(prob, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    bins = np.minimum((p * n_bins).astype(np.int64), n_bins - 1)
    count = np.bincount(bins, minlength=n_bins).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_p = np.bincount(bins, weights=p, minlength=n_bins) / count
        rate = np.bincount(bins, weights=y, minlength=n_bins) / count
    return mean_p, rate, count


def expected_calibration_error(prob: np.ndarray, labels: np.ndarray, n_bins: int = 15) -> float:
    """ECE = sum over equal-width bins of (bin share) * |mean predicted p - observed rate| (Guo et al. 2017)."""
    mean_p, rate, count = reliability_curve(prob, labels, n_bins)
    filled = count > 0
    return float(np.sum(count[filled] / count.sum() * np.abs(mean_p[filled] - rate[filled])))


def score(logits: np.ndarray, labels: np.ndarray, n_bins: int = 15) -> tuple[float, float, float, float]:
    """``(BCE nats, ROC-AUC, average precision, ECE)`` of logits against labels in {0, 1}."""
    from sklearn.metrics import average_precision_score, roc_auc_score

    logit = np.asarray(logits, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    prob = expit(logit)
    return (
        bce_from_logits(logit, y),
        float(roc_auc_score(y, logit)),
        float(average_precision_score(y, logit)),
        expected_calibration_error(prob, y, n_bins),
    )


# -------------------------------------------------------------------------------------------- models


@dataclass(frozen=True)
class LinearPredictor:
    """``logit = features @ coef + intercept`` (the fitted logistic regression), float64."""

    norm: NormStats
    coef: np.ndarray
    intercept: float

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        return encode_salient(raw_inputs, self.norm) @ self.coef + self.intercept

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        gap = np.asarray(gap_m, dtype=np.float64)
        return self.logit(braking_salient_inputs(gap)).reshape(gap.shape)


@dataclass(frozen=True)
class ConstantPredictor:
    """The same logit for every row (Guess-mu)."""

    value: float

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        return np.full(np.asarray(raw_inputs).shape[0], self.value)

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        return np.full(np.asarray(gap_m, dtype=np.float64).shape, self.value)


def fit_model(name: str, inputs: np.ndarray, labels: np.ndarray, norm: NormStats, config: EvalConfig) -> Predictor:
    """Train model ``name`` on raw inputs ``[N, 11]`` and labels ``[N]`` (one training split)."""
    y = np.asarray(labels, dtype=np.float64)
    if name == "ml-nn":
        return PEM_RECIPES["ml-nn"].train(inputs, y, seed=config.seed, epochs=config.mlnn_epochs, norm=norm)
    if name == "gbt":
        return PEM_RECIPES["gbt"].train(inputs, y, seed=config.seed, epochs=config.gbt_trees, norm=norm)
    if name == "lr":
        from sklearn.linear_model import LogisticRegression
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1):
            lr = LogisticRegression(max_iter=10000).fit(encode_salient(inputs, norm), y.astype(np.int64))
        return LinearPredictor(norm=norm, coef=lr.coef_[0].astype(np.float64), intercept=float(lr.intercept_[0]))
    if name == "guess-mu":
        mu = float(y.mean())
        return ConstantPredictor(math.log(mu) - math.log1p(-mu))
    if name == "b-nn":
        return train_bnn_pem(
            inputs, y, norm=norm, steps=config.bnn_steps, n_samples=config.bnn_samples, seed=config.seed
        )
    raise ValueError(f"unknown model {name!r}; known: {', '.join(MODEL_NAMES)}")


def evaluate_pems(
    inputs: np.ndarray,
    labels: np.ndarray,
    config: EvalConfig | None = None,
    *,
    on_fold: Callable[[str, FoldScore], None] | None = None,
    data_source: str = "",
) -> EvalResult:
    """Cross-validate the configured models (default :class:`EvalConfig`) on raw salient inputs ``[N, 11]`` and
    labels ``[N]``, z-scored on all N rows, folds from :func:`stratified_folds`; ``on_fold(model, score)`` after
    each fit; the authors' PEM curve is added when ``../shared/reference/carla-stuff-pem`` is present.

    Raises:
        ValueError: mismatched lengths or labels not in {0, 1}."""
    config = EvalConfig() if config is None else config
    start = time.perf_counter()
    raw = np.asarray(inputs, dtype=np.float64)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if raw.shape[0] != y.shape[0]:
        raise ValueError(f"inputs have {raw.shape[0]} rows but labels {y.shape[0]}")
    if not np.all((y == 0.0) | (y == 1.0)):
        raise ValueError("labels must be 0 or 1")
    norm = fit_norm_stats(raw)
    splits = stratified_folds(y, config.n_splits)
    results = []
    for name in config.models:
        scores, rows, fold_of, logits, curves = [], [], [], [], []
        for k in config.fold_ids:
            train, test = splits[k]
            t0 = time.perf_counter()
            model = fit_model(name, raw[train], y[train], norm, config)
            fit_s = time.perf_counter() - t0
            logit = np.asarray(model.logit(raw[test]), dtype=np.float64)
            bce, auc, ap, ece = score(logit, y[test], config.n_bins)
            fs = FoldScore(fold=k, n_test=int(test.shape[0]), bce=bce, auc=auc, ap=ap, ece=ece, fit_s=fit_s)
            scores.append(fs)
            rows.append(test)
            fold_of.append(np.full(test.shape[0], k))
            logits.append(logit)
            curves.append(expit(np.asarray(model.logit_at_gap(GAP_GRID_M))))
            if on_fold is not None:
                on_fold(name, fs)
        results.append(
            ModelEvaluation(
                name=name,
                description=MODEL_DESCRIPTIONS[name],
                folds=tuple(scores),
                test_rows=np.concatenate(rows),
                test_fold=np.concatenate(fold_of),
                logits=np.concatenate(logits),
                gap_prob=np.stack(curves),
            )
        )
    try:
        authors = load_reference_pem().prob_at_gap(GAP_GRID_M)
    except FileNotFoundError:
        authors = None
    return EvalResult(
        config=config,
        models=tuple(results),
        labels=y,
        gaps_m=GAP_GRID_M.copy(),
        authors_gap_prob=authors,
        wall_s=time.perf_counter() - start,
        data_source=data_source,
    )


# ----------------------------------------------------------------------------------------- formatting


def format_markdown(result: EvalResult) -> str:
    """The table as Markdown: mean +- std over folds, the paper's numbers, per-fold BCE and AUC."""
    folds = result.config.fold_ids
    lines = [
        f"PEM cross-validation: {len(folds)} of {result.config.n_splits} stratified folds (file order, no shuffle), "
        f"{result.labels.shape[0]} rows{f' from {result.data_source}' if result.data_source else ''}; "
        f"ECE with {result.config.n_bins} equal-width bins; wall time {result.wall_s:.0f} s.",
        "",
        "| model | BCE (nats) | ROC-AUC | AP | ECE | paper BCE | paper AUC | per-fold BCE | per-fold AUC "
        "| fit s/fold |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    best = result.best()
    for m in result.models:
        paper = PAPER_TABLE_I.get(m.name)
        name = f"**{m.name}**" if m.name == best else m.name
        lines.append(
            f"| {name} | {m.mean('bce'):.4f} ± {m.std('bce'):.4f} | {m.mean('auc'):.4f} ± {m.std('auc'):.4f} | "
            f"{m.mean('ap'):.4f} | {m.mean('ece'):.4f} | {f'{paper[0]:.3f}' if paper else '-'} | "
            f"{f'{paper[1]:.3f}' if paper else '-'} | "
            f"{' '.join(f'{f.bce:.4f}' for f in m.folds)} | {' '.join(f'{f.auc:.4f}' for f in m.folds)} | "
            f"{m.mean('fit_s'):.1f} |"
        )
    lines += [
        "",
        "Bold: lowest mean BCE. Models: " + "; ".join(f"`{m.name}` {m.description}" for m in result.models) + ".",
    ]
    return "\n".join(lines) + "\n"


def format_csv(result: EvalResult) -> str:
    """Long CSV: one row per model and fold, then one ``mean`` row per model."""
    out = ["model,fold,n_test,bce,roc_auc,average_precision,ece,fit_s"]
    for m in result.models:
        for f in m.folds:
            out.append(f"{m.name},{f.fold},{f.n_test},{f.bce:.6f},{f.auc:.6f},{f.ap:.6f},{f.ece:.6f},{f.fit_s:.3f}")
        out.append(
            f"{m.name},mean,{sum(f.n_test for f in m.folds)},{m.mean('bce'):.6f},{m.mean('auc'):.6f},"
            f"{m.mean('ap'):.6f},{m.mean('ece'):.6f},{m.mean('fit_s'):.3f}"
        )
    return "\n".join(out) + "\n"


def summary_lines(result: EvalResult) -> Sequence[str]:
    """One console line per model: mean BCE, AUC, AP, ECE and the paper's numbers."""
    out = []
    for m in result.models:
        paper = PAPER_TABLE_I.get(m.name)
        ref = f"   (paper {paper[0]:.3f} / {paper[1]:.3f})" if paper else ""
        out.append(
            f"{m.name:9s} BCE {m.mean('bce'):.4f}  AUC {m.mean('auc'):.4f}  AP {m.mean('ap'):.4f}  "
            f"ECE {m.mean('ece'):.4f}{ref}"
        )
    return out

"""Noise PEM quality: 5-fold cross-validation of the noise PEMs against the homoscedastic baseline, on the detection
PEMs' folds restricted to the noise data set. Scores on the held-out fold: NLL (nats per obstacle and per dimension),
coverage of the central intervals, ICE (the mean |coverage - level| from the PIT) and coverage by range band; models
:data:`NOISE_MODEL_NAMES`."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar, Literal, overload

import numpy as np

from pemviz.pem import encode_salient, fit_norm_stats
from pemviz.pem.encoding import NormStats
from pemviz.pem.noise import NOISE_DIMS, NoiseModel, fit_homoscedastic, noise_training_data
from pemviz.pem.recipes import NOISE_RECIPES
from pemviz.studies.pem_eval import CrossValidation, Evaluated, check_study, stratified_folds

NOISE_MODEL_NAMES = ("homo-normal", "homo-t", "hetero-normal", "hetero-laplace", "hetero-t")
"""Every noise model :func:`evaluate_noise_pems` knows, in table order."""
NOISE_MODEL_DESCRIPTIONS = {
    "homo-normal": "baseline: linear mean on the 14 features, one Normal scale per dimension (scikit-learn)",
    "homo-t": "one Student-t per dimension: constant location, scale, df (scipy.stats.t.fit)",
    "hetero-normal": "NoisePEM: 14-32-32-4 network -> Normal location and log scale",
    "hetero-laplace": "NoisePEM: 14-32-32-4 network -> Laplace location and log scale",
    "hetero-t": "NoisePEM: 14-32-32-4 network -> Student-t location and log scale, learned df (shipped)",
}
_HETERO_FAMILY = {"hetero-normal": "normal", "hetero-laplace": "laplace", "hetero-t": "student-t"}
COVERAGE_LEVELS = (0.5, 0.8, 0.9, 0.95)
"""Central predictive intervals whose empirical coverage the table reports."""
ICE_LEVELS = tuple(round(0.05 * k, 2) for k in range(1, 20))
"""Levels of the interval calibration error: 0.05, 0.10, ..., 0.95."""
RANGE_BANDS_M = (1.0, 10.0, 20.0, 40.0, np.inf)
"""Range bands (metres, loc_z) of the per-band coverage of the 90 % interval."""


@dataclass(frozen=True)
class NoiseEvalConfig(CrossValidation):
    """Settings of :func:`evaluate_noise_pems`: ``models``, ``n_splits``, ``folds`` (None = all), ``epochs`` of the
    heteroscedastic networks (default: the shipped recipe's), ``seed`` (networks and dequantisation).

    Raises:
        ValueError: an unknown or repeated model, n_splits < 2, a fold outside 0..n_splits-1, or epochs < 1."""

    models: tuple[str, ...] = NOISE_MODEL_NAMES
    n_splits: int = 5
    folds: tuple[int, ...] | None = None
    epochs: int = NOISE_RECIPES["hetero-t"].epochs
    seed: int = 0

    def __post_init__(self) -> None:
        check_study(self, NOISE_MODEL_NAMES, ("epochs",))


@dataclass(frozen=True)
class NoiseFoldScore:
    """One noise model on one test fold: ``nll`` (nats per obstacle), ``nll_dims`` ``[2]``, ``coverage``
    ``[len(COVERAGE_LEVELS), 2]``, ``ice`` ``[2]`` (per dimension: range, lateral), fit time in seconds."""

    fold: int
    n_train: int
    n_test: int
    nll: float
    nll_dims: np.ndarray
    coverage: np.ndarray
    ice: np.ndarray
    fit_s: float


@dataclass(frozen=True)
class NoiseModelEvaluation:
    """A noise model's cross-validation: per-fold scores and, out of fold, each test row's ``pit`` ``[M, 2]`` and
    ``range_m`` ``[M]`` (loc_z, metres)."""

    name: str
    description: str
    folds: tuple[NoiseFoldScore, ...]
    pit: np.ndarray
    range_m: np.ndarray

    @overload
    def mean(self, metric: Literal["nll_dims", "coverage", "ice"]) -> np.ndarray: ...
    @overload
    def mean(self, metric: str) -> np.ndarray | float: ...
    def mean(self, metric: str) -> np.ndarray | float:
        """The mean over folds of a :class:`NoiseFoldScore` field (an array for array fields)."""
        values = np.mean([np.asarray(getattr(f, metric), dtype=np.float64) for f in self.folds], axis=0)
        return float(values) if np.ndim(values) == 0 else values

    def band_coverage(self, level: float = 0.9) -> np.ndarray:
        """Out-of-fold coverage of the central ``level`` interval per :data:`RANGE_BANDS_M` band, ``[bands, 2]``."""
        inside = np.abs(self.pit - 0.5) <= level / 2
        band = np.digitize(self.range_m, RANGE_BANDS_M[1:-1])
        return np.array([inside[band == b].mean(axis=0) for b in range(len(RANGE_BANDS_M) - 1)])


@dataclass(frozen=True)
class NoiseEvalResult(Evaluated[NoiseModelEvaluation]):
    """Everything :func:`evaluate_noise_pems` measured; ``n_rows``: the noise data set's size."""

    config: NoiseEvalConfig
    models: tuple[NoiseModelEvaluation, ...]
    n_rows: int
    wall_s: float
    data_source: str = ""

    best_by: ClassVar[str] = "nll"
    what: ClassVar[str] = "noise model"


def score_noise(
    model: NoiseModel, features: np.ndarray, errors: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(NLL nats per obstacle, NLL per dimension [2], coverage [levels, 2], ICE [2], PIT [M, 2])`` of errors
    ``[M, 2]`` (metres) under a noise model at encoded features ``[M, 14]``."""
    log_p = model.log_prob_dims(features, errors)
    pit = model.cdf(features, errors)
    distance = np.abs(pit - 0.5)
    coverage = np.array([np.mean(distance <= level / 2, axis=0) for level in COVERAGE_LEVELS])
    ice = np.mean([np.abs(np.mean(distance <= level / 2, axis=0) - level) for level in ICE_LEVELS], axis=0)
    return float(-log_p.sum(axis=1).mean()), -log_p.mean(axis=0), coverage, ice, pit


def fit_noise_model(
    name: str, inputs: np.ndarray, errors: np.ndarray, norm: NormStats, config: NoiseEvalConfig
) -> NoiseModel:
    """Train noise model ``name`` on raw inputs ``[M, 11]`` and errors ``[M, 2]`` (one training split)."""
    if name == "homo-normal":
        return fit_homoscedastic(inputs, errors, family="normal", linear_mean=True, name=name, norm=norm)
    if name == "homo-t":
        return fit_homoscedastic(inputs, errors, family="student-t", linear_mean=False, name=name, norm=norm)
    if name in _HETERO_FAMILY:
        recipe = dataclasses.replace(NOISE_RECIPES["hetero-t"], name=name, family=_HETERO_FAMILY[name])
        return recipe.train(inputs, errors, seed=config.seed, epochs=config.epochs, norm=norm)
    raise ValueError(f"unknown noise model {name!r}; known: {', '.join(NOISE_MODEL_NAMES)}")


def evaluate_noise_pems(
    inputs: np.ndarray,
    label_table: np.ndarray,
    config: NoiseEvalConfig | None = None,
    *,
    on_fold: Callable[[str, NoiseFoldScore], None] | None = None,
    data_source: str = "",
) -> NoiseEvalResult:
    """Cross-validate the configured noise models on raw salient inputs ``[N, 11]`` and the label table ``[N, 9]``
    (:func:`pemviz.io.data.load_salient_label_table`); ``on_fold(model, score)`` after each fit.

    Raises:
        ValueError: shapes other than ``[N, 11]`` and ``[N, 9]``, or labels not in {0, 1}."""
    config = NoiseEvalConfig() if config is None else config
    start = time.perf_counter()
    raw = np.asarray(inputs, dtype=np.float64)
    data = noise_training_data(raw, label_table, seed=config.seed)
    norm = fit_norm_stats(raw)
    x_all = encode_salient(data.inputs, norm)
    splits = stratified_folds(np.asarray(label_table, dtype=np.float64)[:, 0], config.n_splits)
    results = []
    for name in config.models:
        scores, pits, ranges = [], [], []
        for k in config.fold_ids:
            train, test = (np.flatnonzero(np.isin(data.rows, part)) for part in splits[k])
            t0 = time.perf_counter()
            model = fit_noise_model(name, data.inputs[train], data.errors[train], norm, config)
            fit_s = time.perf_counter() - t0
            nll, nll_dims, coverage, ice, pit = score_noise(model, x_all[test], data.errors[test])
            fs = NoiseFoldScore(
                fold=k,
                n_train=int(train.size),
                n_test=int(test.size),
                nll=nll,
                nll_dims=nll_dims,
                coverage=coverage,
                ice=ice,
                fit_s=fit_s,
            )
            scores.append(fs)
            pits.append(pit)
            ranges.append(data.inputs[test, 9])
            if on_fold is not None:
                on_fold(name, fs)
        results.append(
            NoiseModelEvaluation(
                name=name,
                description=NOISE_MODEL_DESCRIPTIONS[name],
                folds=tuple(scores),
                pit=np.concatenate(pits),
                range_m=np.concatenate(ranges),
            )
        )
    return NoiseEvalResult(
        config=config,
        models=tuple(results),
        n_rows=int(data.rows.size),
        wall_s=time.perf_counter() - start,
        data_source=data_source,
    )


# ----------------------------------------------------------------------------------------- formatting


def _levels(values: np.ndarray) -> str:
    """Coverage at the :data:`COVERAGE_LEVELS` as ``0.49 / 0.80 / 0.90 / 0.95``."""
    return " / ".join(f"{v:.3f}" for v in values)


def format_markdown(result: NoiseEvalResult) -> str:
    """The noise PEMs' table as Markdown: mean over folds of the NLL (total and per dimension), the coverage of the
    central 50 / 80 / 90 / 95 % intervals and the ICE per dimension, per-fold NLL; then the 90 % coverage by range."""
    folds = result.config.fold_ids
    best = result.best()
    head = (
        f"Noise PEM cross-validation: {len(folds)} of {result.config.n_splits} stratified folds of Table I "
        f"(file order, no shuffle), {result.n_rows} detected obstacles at a range >= 1 m"
        f"{f' from {result.data_source}' if result.data_source else ''}; errors in metres (range dZ, lateral dX) "
        f"from the dequantised box errors; NLL in nats per obstacle; wall time {result.wall_s:.0f} s."
    )
    levels = "/".join(f"{round(100 * v)}" for v in COVERAGE_LEVELS)
    lines = [
        head,
        "",
        f"| model | NLL | NLL range | NLL lateral | coverage {levels} % range | coverage {levels} % lateral "
        "| ICE range | ICE lateral | per-fold NLL | fit s/fold |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for m in result.models:
        name = f"**{m.name}**" if m.name == best else m.name
        nll_dims, coverage, ice = m.mean("nll_dims"), m.mean("coverage"), m.mean("ice")
        per_fold = ", ".join(f"{f.nll:.4f}" for f in m.folds)
        lines.append(
            f"| {name} | {m.mean('nll'):.4f} | {nll_dims[0]:.4f} | {nll_dims[1]:.4f} | {_levels(coverage[:, 0])} "
            f"| {_levels(coverage[:, 1])} | {ice[0]:.4f} | {ice[1]:.4f} | {per_fold} | {m.mean('fit_s'):.1f} |"
        )
    edges = RANGE_BANDS_M
    bands = [f"{a:g}-{b:g} m" if np.isfinite(b) else f">= {a:g} m" for a, b in zip(edges[:-1], edges[1:], strict=True)]
    lines += [
        "",
        "Out-of-fold coverage of the central 90 % interval by range (loc_z), range / lateral:",
        "",
        "| model | " + " | ".join(bands) + " |",
        "|---|" + "---|" * len(bands),
    ]
    for m in result.models:
        cov = m.band_coverage(0.9)
        lines.append(f"| {m.name} | " + " | ".join(f"{c[0]:.3f} / {c[1]:.3f}" for c in cov) + " |")
    counts = np.bincount(np.digitize(result.models[0].range_m, RANGE_BANDS_M[1:-1]), minlength=len(bands))
    lines += ["| obstacles | " + " | ".join(str(int(c)) for c in counts) + " |", ""]
    lines += [f"- **{m.name}**: {m.description}" for m in result.models]
    return "\n".join(lines) + "\n"


def format_csv(result: NoiseEvalResult) -> str:
    """One row per model and fold: NLL (total, per dimension), coverage per level and dimension, ICE, fit seconds."""
    cov_cols = [f"coverage{round(100 * v)}_{d}" for v in COVERAGE_LEVELS for d in NOISE_DIMS]
    header = [
        "model",
        "fold",
        "n_train",
        "n_test",
        "nll",
        *(f"nll_{d}" for d in NOISE_DIMS),
        *cov_cols,
        *(f"ice_{d}" for d in NOISE_DIMS),
        "fit_s",
    ]
    rows = [",".join(header)]
    for m in result.models:
        for f in m.folds:
            values = [f.nll, *f.nll_dims, *f.coverage.reshape(-1), *f.ice]
            rows.append(
                ",".join(
                    [
                        m.name,
                        str(f.fold),
                        str(f.n_train),
                        str(f.n_test),
                        *(f"{v:.6f}" for v in values),
                        f"{f.fit_s:.2f}",
                    ]
                )
            )
    return "\n".join(rows) + "\n"


def summary_lines(result: NoiseEvalResult) -> Sequence[str]:
    """One console line per noise model: mean NLL, coverage of the 50 / 95 % intervals and ICE per dimension."""
    out = []
    i50, i95 = COVERAGE_LEVELS.index(0.5), COVERAGE_LEVELS.index(0.95)
    for m in result.models:
        cov, ice = m.mean("coverage"), m.mean("ice")
        out.append(
            f"{m.name:14s} NLL {m.mean('nll'):.4f}  coverage 50 % {cov[i50, 0]:.3f}/{cov[i50, 1]:.3f}  "
            f"95 % {cov[i95, 0]:.3f}/{cov[i95, 1]:.3f}  ICE {ice[0]:.4f}/{ice[1]:.4f}  "
            "(range/lateral)"
        )
    return out

"""The noise PEM: p(range error, lateral error | salient variables) of a detected obstacle.

A detected obstacle's measurement error ``e = (dZ, dX)`` (metres; measured minus true,
:func:`pemviz.pem.camera.box_errors_to_metric`) is drawn from a location-scale family with independent dimensions:

    p(e | x) = prod_{d in (range, lateral)} (1 / s_d(x)) g((e_d - m_d(x)) / s_d(x)),

``g`` a standard normal, Laplace or Student-t density, ``x`` the 14-dim encoding
(:func:`pemviz.pem.encode_salient`). :class:`NoisePEM` is heteroscedastic, ``(m(x), log s(x))`` from a small ReLU
network trained by maximum likelihood and evaluated in float64 numpy; :class:`HomoscedasticNoise` is the baseline.
``log_prob`` is in nats; the family is chosen in ``pemviz.studies.noise_eval``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from pemviz.pem.camera import MIN_RANGE_M, box_errors_to_metric
from pemviz.pem.encoding import (
    N_FEATURES,
    ONE_HOT_GROUPS,
    NormStats,
    SalientCodes,
    check_features,
    encode_salient,
    fit_norm_stats,
)
from pemviz.pem.network import GridMLP, OneHotColumns, PemFormatError, as_arrays, fold_state_dict
from pemviz.pem.training import NetworkRecipe, fit_network

NOISE_DIMS = ("range", "lateral")
"""The error dimensions, in column order: range error dZ (along camera z) and lateral error dX (along x), metres."""
FAMILIES = ("normal", "laplace", "student-t")
"""Location-scale families of the noise PEM (``scipy.stats`` ``norm``, ``laplace``, ``t``)."""
DF_MIN = 1.0
"""Lower bound of the Student-t degrees of freedom (``nu = DF_MIN + softplus(raw)``): above it the mean exists."""


def _check_errors(errors: np.ndarray, rows: int) -> np.ndarray:
    e = np.asarray(errors, dtype=np.float64)
    if e.shape != (rows, len(NOISE_DIMS)):
        raise ValueError(f"errors must have shape [R, 2] = [{rows}, 2] (range, lateral; metres), got {e.shape}")
    return e


def _check_family(family: str, df: np.ndarray | None) -> np.ndarray | None:
    if family not in FAMILIES:
        raise ValueError(f"noise family {family!r}: use one of {', '.join(FAMILIES)}")
    if family != "student-t":
        return None
    nu = np.asarray(df, dtype=np.float64).reshape(-1) if df is not None else np.zeros(0)
    if nu.shape != (len(NOISE_DIMS),) or not np.all(np.isfinite(nu) & (nu > 0)):
        raise ValueError(f"a Student-t noise PEM needs 2 finite degrees of freedom > 0, got {df}")
    return nu


@dataclass(frozen=True, eq=False, kw_only=True)
class NoiseModel:
    """What every noise PEM shares: the family, its degrees of freedom, and the density, CDF and sampler on the
    parameters of :meth:`noise_params` (defined by each kind).

    Attributes: ``name``; ``norm`` (the z-score statistics of the 14-dim encoding); ``family`` (one of
    :data:`FAMILIES`); ``df`` float64 ``[2]`` (Student-t only, else None); ``metadata`` (plain values)."""

    kind: ClassVar[str] = ""

    name: str
    norm: NormStats
    family: str
    df: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "df", _check_family(self.family, self.df))

    def noise_params(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(loc [R, 2], log_scale [R, 2])``, float64 (metres; log metres) of encoded features ``[R, 14]``.

        Raises:
            ValueError: features not of shape ``[R, 14]``."""
        raise NotImplementedError

    def noise_params_codes(self, codes: SalientCodes) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`noise_params` of ``codes.features()`` (:func:`pemviz.pem.encoding.salient_codes`), bit for bit."""
        return self.noise_params(codes.features())

    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        """The 14 encoded features float64 ``[R, 14]`` of raw salient inputs ``[R, 11]`` (:func:`encode_salient`)."""
        return encode_salient(raw_inputs, self.norm)

    def distribution(self, features: np.ndarray) -> Any:
        """The predictive distribution as a frozen ``scipy.stats`` distribution of shape ``[R, 2]``."""
        from scipy import stats  # ~0.5 s to import: not on a braking run's path

        loc, log_scale = self.noise_params(features)
        scale = np.exp(log_scale)
        if self.family == "normal":
            return stats.norm(loc, scale)
        if self.family == "laplace":
            return stats.laplace(loc, scale)
        return stats.t(self.df, loc, scale)

    def log_prob_dims(self, features: np.ndarray, errors: np.ndarray) -> np.ndarray:
        """log density of each error dimension, float64 ``[R, 2]`` (nats; errors ``[R, 2]`` in metres).

        Raises:
            ValueError: features not ``[R, 14]`` or errors not ``[R, 2]``."""
        x = check_features(features, "noise PEM", "R")
        return self.distribution(x).logpdf(_check_errors(errors, x.shape[0]))

    def log_prob(self, features: np.ndarray, errors: np.ndarray) -> np.ndarray:
        """log p(errors | features), float64 ``[R]`` (nats; the sum over the two independent dimensions).

        Raises:
            ValueError: features not ``[R, 14]`` or errors not ``[R, 2]``."""
        return self.log_prob_dims(features, errors).sum(axis=1)

    def cdf(self, features: np.ndarray, errors: np.ndarray) -> np.ndarray:
        """Predictive CDF of each error dimension at the errors (the probability integral transform, PIT),
        ``[R, 2]``."""
        x = check_features(features, "noise PEM", "R")
        return self.distribution(x).cdf(_check_errors(errors, x.shape[0]))

    def interval(self, features: np.ndarray, level: float) -> tuple[np.ndarray, np.ndarray]:
        """The central predictive interval of probability ``level`` in (0, 1): ``(low [R, 2], high [R, 2])``, metres.

        Raises:
            ValueError: ``level`` outside (0, 1)."""
        if not 0.0 < level < 1.0:
            raise ValueError(f"interval level must be in (0, 1), got {level}")
        return self.distribution(check_features(features, "noise PEM", "R")).interval(level)

    def sample(self, features: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One error per row, float64 ``[R, 2]`` (metres), drawn with ``rng`` (reproducible for a seeded generator)."""
        dist = self.distribution(check_features(features, "noise PEM", "R"))
        return np.asarray(dist.rvs(random_state=rng), dtype=np.float64).reshape(-1, len(NOISE_DIMS))


@dataclass(frozen=True, eq=False, kw_only=True)
class NoisePEM(NoiseModel):
    """The heteroscedastic noise PEM: an :class:`MLNN` (ReLU, no BatchNorm) with 4 outputs ``(m_range, m_lateral,
    log s_range, log s_lateral)`` in units of ``target_scale`` (float64 ``[2]``, metres); ``state_dict`` holds the
    weights as trained (float32 numpy arrays) and :meth:`noise_params` evaluates them in float64 numpy with the
    target scale folded in.

    Raises:
        ValueError: a target scale not 2 finite values > 0, or a bad family; PemFormatError: weights that do not fit
            ``hidden``."""

    kind: ClassVar[str] = "mlp"

    state_dict: Mapping[str, np.ndarray]
    hidden: tuple[int, ...]
    target_scale: np.ndarray

    def __post_init__(self) -> None:
        super().__post_init__()
        scale = np.asarray(self.target_scale, dtype=np.float64).reshape(-1)
        if scale.shape != (2,) or not np.all(np.isfinite(scale) & (scale > 0)):
            raise ValueError(f"target_scale must be 2 finite values > 0, got {self.target_scale}")
        object.__setattr__(self, "target_scale", scale)
        object.__setattr__(self, "state_dict", as_arrays(self.state_dict))
        try:
            layers = list(fold_state_dict(self.state_dict, self.hidden, batch_norm=False, out_dim=4))
        except ValueError as exc:
            raise PemFormatError(f"noise PEM {self.name!r}: weights do not fit hidden={self.hidden}: {exc}") from None
        w, b = layers[-1]  # outputs in target units: loc * scale, log_scale + log(scale)
        gain = np.concatenate([scale, np.ones(2)])
        layers[-1] = (w * gain[:, None], b * gain + np.concatenate([np.zeros(2), np.log(scale)]))
        self._grid: GridMLP  # derived from the fields, set on the frozen instance (not fields)
        self._one_hot: OneHotColumns
        object.__setattr__(self, "_layers", tuple(layers))
        object.__setattr__(self, "_grid", GridMLP.of(layers))
        object.__setattr__(self, "_one_hot", self._grid.one_hot(ONE_HOT_GROUPS))

    def noise_params(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = self._grid(check_features(features, "noise PEM", "R"))
        return out[:, :2], out[:, 2:]

    def noise_params_codes(self, codes: SalientCodes) -> tuple[np.ndarray, np.ndarray]:
        out = self._grid.of_codes(codes, self._one_hot)
        return out[:, :2], out[:, 2:]


@dataclass(frozen=True, eq=False, kw_only=True)
class HomoscedasticNoise(NoiseModel):
    """The homoscedastic baseline: ``loc = features @ coef + intercept`` (``coef`` float64 ``[14, 2]``, zero for a
    constant mean; ``intercept`` ``[2]``, metres) and one ``log_scale`` ``[2]`` for every row."""

    kind: ClassVar[str] = "linear"

    coef: np.ndarray
    intercept: np.ndarray
    log_scale: np.ndarray

    def __post_init__(self) -> None:
        super().__post_init__()
        for name, shape in (("coef", (N_FEATURES, 2)), ("intercept", (2,)), ("log_scale", (2,))):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape or not np.all(np.isfinite(value)):
                raise ValueError(f"homoscedastic noise {name} must be finite of shape {shape}, got {value.shape}")
            object.__setattr__(self, name, value)
        self._grid: GridMLP  # derived from the fields, set on the frozen instance (not a field)
        object.__setattr__(self, "_grid", GridMLP.of(((self.coef.T, self.intercept),)))

    def noise_params(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = check_features(features, "noise PEM", "R")
        return self._grid(x), np.broadcast_to(self.log_scale, (x.shape[0], 2)).copy()


# ------------------------------------------------------------------------------------------------ data


@dataclass(frozen=True)
class NoiseData:
    """The noise PEM's training set: ``rows`` int ``[M]`` (0-based rows of the salient files), their raw salient
    inputs ``[M, 11]`` and metric errors ``[M, 2]`` (range, lateral; metres)."""

    rows: np.ndarray
    inputs: np.ndarray
    errors: np.ndarray


def noise_training_data(inputs: np.ndarray, label_table: np.ndarray, *, seed: int = 0) -> NoiseData:
    """Metric measurement errors of the detected obstacles of the KITTI salient files with a range of at least
    :data:`MIN_RANGE_M`. The file rounds boxes and errors to whole pixels, so each pixel error is dequantised by
    uniform noise on [-1/2, 1/2) pixel (Uria, Murray & Larochelle 2013; Theis, van den Oord & Bethge 2016, Sec. 3.1;
    ``numpy.random.default_rng(seed)``) before :func:`pemviz.pem.camera.box_errors_to_metric`.

    Args:
        inputs: raw salient inputs ``[N, 11]`` (:data:`pemviz.pem.encoding.INPUT_COLUMNS`).
        label_table: the label file ``[N, 9]`` (:func:`pemviz.io.data.load_salient_label_table`).
        seed: seed of the dequantisation noise.
    Raises:
        ValueError: shapes other than ``[N, 11]`` and ``[N, 9]``, or no row left."""
    raw = np.asarray(inputs, dtype=np.float64)
    labels = np.asarray(label_table, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != 11 or labels.shape != (raw.shape[0], 9):
        raise ValueError(f"need inputs [N, 11] and a label table [N, 9], got {raw.shape} and {labels.shape}")
    rows = np.flatnonzero((labels[:, 0] == 1.0) & (raw[:, 9] >= MIN_RANGE_M))
    if rows.size == 0:
        raise ValueError(f"no detected obstacle at a range >= {MIN_RANGE_M} m")
    lab = labels[rows]
    jitter = np.random.default_rng(seed).uniform(-0.5, 0.5, size=(rows.size, 2))
    err_cx, err_h = lab[:, 5] + jitter[:, 0], lab[:, 8] + jitter[:, 1]
    true_h = lab[:, 4] - lab[:, 8]
    errors = box_errors_to_metric(raw[rows, 9], true_h + err_h, err_cx, err_h)
    return NoiseData(rows=rows, inputs=raw[rows], errors=errors)


# -------------------------------------------------------------------------------------------- training


@dataclass(frozen=True)
class NoiseRecipe(NetworkRecipe[NoisePEM]):
    """A heteroscedastic noise PEM: the family, architecture and optimiser settings of :func:`train_noise_pem`."""

    family: str = "student-t"
    hidden: tuple[int, ...] = (32, 32)
    epochs: int = 100
    batch_size: int = 512
    lr: float = 3e-3

    def _fit(self, inputs: np.ndarray, errors: np.ndarray, /, **common: Any) -> NoisePEM:
        return train_noise_pem(self, inputs, errors, **common)


def train_noise_pem(
    recipe: NoiseRecipe,
    inputs: np.ndarray,
    errors: np.ndarray,
    *,
    norm: NormStats | None = None,
    progress: bool = False,
    metadata: Mapping[str, Any] | None = None,
) -> NoisePEM:
    """Fit the heteroscedastic noise PEM by maximum likelihood (:class:`NoiseNLL`; the ML-NN's training loop,
    :func:`pemviz.pem.training.fit_network`), the targets divided by their std per dimension (folded back by
    :class:`NoisePEM`). The same seed gives the same weights on the same torch build.

    Args:
        recipe: the name, family (one of :data:`FAMILIES`), network and optimiser settings.
        inputs: raw salient inputs ``[M, 11]`` of detected obstacles.
        errors: their metric errors ``[M, 2]`` (metres).
        norm: z-score statistics of the encoding (default: fitted on ``inputs``).
        progress: print the training's progress.
        metadata: extra provenance stored with the model.
    Raises:
        ValueError: shapes other than ``[M, 11]`` / ``[M, 2]``, non-finite errors, an unknown family, fewer than 2
            rows, epochs < 1 or batch_size < 1."""
    import torch

    from pemviz.pem.modules import NoiseNLL

    raw = np.asarray(inputs, dtype=np.float64)
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = encode_salient(raw, norm)
    err = _check_errors(errors, x.shape[0])
    if not np.all(np.isfinite(err)) or x.shape[0] < 2:
        raise ValueError(f"need >= 2 rows of finite errors, got {x.shape[0]} rows")
    if recipe.epochs < 1 or recipe.batch_size < 1:
        raise ValueError(f"need epochs >= 1 and batch_size >= 1, got {recipe.epochs}, {recipe.batch_size}")
    loss_fn = NoiseNLL(recipe.family)
    target_scale = err.std(axis=0)
    x_t, t = (torch.as_tensor(a, dtype=torch.float32) for a in (x, err / target_scale))
    module, last_loss, meta = fit_network(x_t, t, recipe, loss_fn, progress=progress, out_dim=4)
    df = loss_fn.df().detach().to(torch.float64).numpy() if recipe.family == "student-t" else None
    meta["n_train"] = int(x.shape[0])
    # the loss is on errors / target_scale: add log(target_scale) to read it in nats of metres
    meta["final_epoch_train_nll"] = float(last_loss + np.log(target_scale).sum())
    meta.update(torch_version=str(torch.__version__), **dict(metadata or {}))
    return NoisePEM(
        name=recipe.name,
        norm=norm,
        family=recipe.family,
        df=df,
        state_dict=module.state_dict(),
        hidden=tuple(int(h) for h in recipe.hidden),
        target_scale=target_scale,
        metadata=meta,
    )


def fit_homoscedastic(
    inputs: np.ndarray,
    errors: np.ndarray,
    *,
    family: str = "normal",
    linear_mean: bool = True,
    name: str = "homo-normal",
    norm: NormStats | None = None,
) -> HomoscedasticNoise:
    """The homoscedastic baseline, fitted by maximum likelihood per dimension.

    - ``normal``: least-squares linear mean on the 14 features (scikit-learn ``LinearRegression``; a constant when
      ``linear_mean`` is False) and the residuals' root mean square as the scale (the Gaussian MLE).
    - ``laplace``, ``student-t``: a constant location and scale (and degrees of freedom) by ``scipy.stats``
      ``laplace.fit`` / ``t.fit`` (``linear_mean`` must be False).

    Raises:
        ValueError: shapes other than ``[M, 11]`` / ``[M, 2]``, an unknown family, or a linear mean with a family
            other than normal."""
    raw = np.asarray(inputs, dtype=np.float64)
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = encode_salient(raw, norm)
    err = _check_errors(errors, x.shape[0])
    _check_family(family, np.full(2, 2.0))
    coef = np.zeros((N_FEATURES, 2))
    if family == "normal":
        if linear_mean:
            from sklearn.linear_model import LinearRegression

            fit = LinearRegression().fit(x, err)
            coef, intercept = fit.coef_.T.copy(), fit.intercept_.copy()
        else:
            intercept = err.mean(axis=0)
        residual = err - (x @ coef + intercept)
        return HomoscedasticNoise(
            name=name,
            norm=norm,
            family=family,
            coef=coef,
            intercept=intercept,
            log_scale=0.5 * np.log(np.mean(residual**2, axis=0)),
        )
    if linear_mean:
        raise ValueError(f"a linear mean is fitted for the normal family only, not {family!r}")
    from scipy import stats  # ~0.5 s to import: only when fitting

    if family == "laplace":
        params = [stats.laplace.fit(err[:, d]) for d in range(2)]
        loc, scale, df = np.array([p[0] for p in params]), np.array([p[1] for p in params]), None
    else:
        params = [stats.t.fit(err[:, d]) for d in range(2)]
        df, loc, scale = (np.array([p[i] for p in params]) for i in range(3))
    return HomoscedasticNoise(
        name=name, norm=norm, family=family, df=df, coef=coef, intercept=loc, log_scale=np.log(scale)
    )


def nll(model: NoiseModel, inputs: np.ndarray, errors: np.ndarray) -> float:
    """Mean negative log-likelihood of errors ``[M, 2]`` (metres) at raw salient inputs ``[M, 11]``, nats per
    obstacle."""
    return float(-np.mean(model.log_prob(model.features(inputs), errors)))


__all__ = [
    "DF_MIN",
    "FAMILIES",
    "NOISE_DIMS",
    "HomoscedasticNoise",
    "NoiseData",
    "NoiseModel",
    "NoisePEM",
    "fit_homoscedastic",
    "noise_training_data",
    "nll",
    "train_noise_pem",
]

"""The paper's ML-NN PEM (and wider variants) and its evaluation that no CPU or batch rounds differently.

Innes & Ramamoorthy 2022, Sec. IV-A: Linear(14,20)-BatchNorm-ReLU-Linear(20,20)-BatchNorm-ReLU-Linear(20,1) -> logit
(the authors' ``PEMClass_Deterministic``); training is :mod:`pemviz.pem.training`. A :class:`PEM` evaluates in numpy
with each BatchNorm folded into the linear layer before it, in order-free arithmetic (:class:`GridMLP`: a row's
logit depends on that row alone); along the braking scenario's gap the network is exactly piecewise linear, so
:meth:`PEM.logit_at_gap` is one ``searchsorted`` and one multiply-add. Loading and evaluating a PEM does not import
torch (:func:`fold_state_dict`)."""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
from scipy.special import expit

from pemviz.pem.encoding import (
    BRAKING_CAMERA_TO_LEAD_CENTRE_M,
    BRAKING_Z_FEATURE,
    N_FEATURES,
    ONE_HOT_GROUPS,
    NormStats,
    SalientCodes,
    braking_features_at_z,
    check_features,
    encode_salient,
)

if TYPE_CHECKING:  # annotations only: it imports torch
    from pemviz.pem.modules import MLNN


class PemFormatError(ValueError):
    """A PEM weights file is not in pemviz's format (or is damaged)."""


BATCH_NORM_EPS = 1e-5
"""The ``eps`` of :class:`MLNN`'s BatchNorm layers (``torch.nn.BatchNorm1d``'s default): ``var + eps`` is under the
square root of the fold (:func:`fold_state_dict`)."""


def mlnn_shapes(
    hidden: Sequence[int], *, batch_norm: bool = True, in_dim: int = N_FEATURES, out_dim: int = 1
) -> dict[str, tuple[int, ...]]:
    """The state-dict keys of an :class:`MLNN` without dropout, in its order, with their shapes: per hidden layer of
    width ``h`` a Linear (``ff_nn.{i}.weight [h, prev]``, ``.bias [h]``), with ``batch_norm`` a BatchNorm1d
    (``ff_nn.{i+1}.weight``, ``.bias``, ``.running_mean``, ``.running_var`` ``[h]``, ``.num_batches_tracked []``) and a
    ReLU (no weights); then the output Linear ``[out_dim, prev]``, ``[out_dim]``."""
    shapes: dict[str, tuple[int, ...]] = {}
    index, prev = 0, int(in_dim)
    for width in (int(h) for h in hidden):
        shapes[f"ff_nn.{index}.weight"], shapes[f"ff_nn.{index}.bias"] = (width, prev), (width,)
        index += 1
        if batch_norm:
            for name in ("weight", "bias", "running_mean", "running_var"):
                shapes[f"ff_nn.{index}.{name}"] = (width,)
            shapes[f"ff_nn.{index}.num_batches_tracked"] = ()
            index += 1
        index += 1  # the ReLU
        prev = width
    shapes[f"ff_nn.{index}.weight"], shapes[f"ff_nn.{index}.bias"] = (int(out_dim), prev), (int(out_dim),)
    return shapes


def as_arrays(state: Mapping[str, Any]) -> dict[str, Any]:
    """A state dict with its torch tensors (if any; torch is not imported for this) and numpy arrays copied into
    numpy arrays of the same dtype and shape; other values as they are (:func:`fold_state_dict` refuses them)."""
    torch_module = sys.modules.get("torch")
    out: dict[str, Any] = {}
    for key, value in state.items():
        if torch_module is not None and isinstance(value, torch_module.Tensor):
            value = value.detach().cpu().numpy()
        out[key] = np.array(value, copy=True) if isinstance(value, np.ndarray) else value
    return out


def state_problem(state: Mapping[str, Any], shapes: Mapping[str, tuple[int, ...]]) -> str | None:
    """Why ``state`` does not load into a module whose state-dict shapes are ``shapes`` (as torch's strict
    ``load_state_dict`` would refuse it: missing or unexpected keys, a value that is not an array, another shape; a
    0-d entry may come as shape ``[1]``), or None when it does."""
    problems = []
    missing = [k for k in shapes if k not in state]
    unexpected = [k for k in state if k not in shapes]
    if missing:
        problems.append(f"missing keys {missing}")
    if unexpected:
        problems.append(f"unexpected keys {unexpected}")
    for key, shape in shapes.items():
        if key not in state:
            continue
        value = state[key]
        if not isinstance(value, np.ndarray):
            problems.append(f"{key} is a {type(value).__name__}, not an array")
        elif value.shape != shape and not (shape == () and value.shape == (1,)):
            problems.append(f"{key} has shape {list(value.shape)}, needs {list(shape)}")
    return "; ".join(problems) or None


def fold_state_dict(
    state: Mapping[str, np.ndarray],
    hidden: Sequence[int],
    *,
    batch_norm: bool = True,
    in_dim: int = N_FEATURES,
    out_dim: int = 1,
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The layers of the :class:`MLNN` with this state, folded in numpy, bit for bit as in torch: affine layers ``(W
    float64 [out, in], b float64 [out])``, each BatchNorm (eval mode, ``eps`` :data:`BATCH_NORM_EPS`) folded into
    the Linear before it, a ReLU after every layer but the last; the weights first rounded to float32 as torch's
    parameters hold them.

    Args:
        state: numpy arrays under :func:`mlnn_shapes`'s keys (e.g. :func:`as_arrays` of a module's
            ``state_dict()``).
        hidden: the hidden layers' widths.
        batch_norm: a BatchNorm after each hidden Linear.
        in_dim: the input features (the 14 of the encoding).
        out_dim: the outputs.
    Raises:
        ValueError: the state does not fit the architecture (:func:`state_problem`'s reason)."""
    shapes = mlnn_shapes(hidden, batch_norm=batch_norm, in_dim=in_dim, out_dim=out_dim)
    problem = state_problem(state, shapes)
    if problem is not None:
        raise ValueError(problem)

    def f64(key: str) -> np.ndarray:
        return np.asarray(state[key]).astype(np.float32).astype(np.float64)

    linears = [k[: -len(".weight")] for k in shapes if k.endswith(".weight") and len(shapes[k]) == 2]
    folded: list[tuple[np.ndarray, np.ndarray]] = []
    for prefix in linears:
        w, b = f64(f"{prefix}.weight"), f64(f"{prefix}.bias")
        bn = f"ff_nn.{int(prefix.rsplit('.', 1)[1]) + 1}"
        if f"{bn}.running_var" in shapes:
            scale = f64(f"{bn}.weight") / np.sqrt(f64(f"{bn}.running_var") + BATCH_NORM_EPS)
            b = scale * (b - f64(f"{bn}.running_mean")) + f64(f"{bn}.bias")
            w = scale[:, None] * w
        folded.append((np.ascontiguousarray(w), np.ascontiguousarray(b)))
    return tuple(folded)


MLP_BLOCK = 2048
"""Rows :class:`GridMLP` takes through all its layers at a time: a block's activations (2,048 x 32 float64, 512 KB)
stay in the CPU's cache between the layers. Speed only: a row's result is the same in any block."""


@dataclass(frozen=True, eq=False)
class GridMLP:
    """Folded affine layers (:func:`fold_state_dict`, ReLU between) evaluated in order-free arithmetic: a row's
    outputs depend on that row alone, never on the batch, the BLAS kernel or the CPU. Each layer's input row and
    weights are rounded to :func:`pemviz.core.exact.grid_bits` (K) bits of their largest magnitude (block floating
    point; Wilkinson 1963), so the integer products are exact in any order (:mod:`pemviz.core.exact`): float32's
    precision, which the networks were trained in. Build with :meth:`of`; call with float64 ``[N, K]`` for ``[N,
    out]``."""

    weights: tuple[np.ndarray, ...]
    """Per layer: integer-valued float64 ``[out, in]``, the weights over their layer's power of two."""
    scales: tuple[float, ...]
    """Per layer: that power of two."""
    biases: tuple[np.ndarray, ...]
    """Per layer: float64 ``[out, 1]``."""
    bits: tuple[int, ...]
    """Per layer: the significant bits of an input row."""

    @classmethod
    def of(cls, layers: Sequence[tuple[np.ndarray, np.ndarray]]) -> GridMLP:
        """The grid form of affine layers ``(W float64 [out, in], b float64 [out])``."""
        from pemviz.core import exact

        weights, scales, biases, bits = [], [], [], []
        for w, b in layers:
            k = exact.grid_bits(w.shape[1])
            wi, e = exact.on_grid(np.asarray(w, dtype=np.float64), k, None)
            weights.append(np.ascontiguousarray(wi))
            scales.append(math.ldexp(1.0, int(np.asarray(e).reshape(-1)[0])))
            biases.append(np.asarray(b, dtype=np.float64).reshape(-1, 1).copy())
            bits.append(k)
        return cls(tuple(weights), tuple(scales), tuple(biases), tuple(bits))

    @property
    def n_out(self) -> int:
        return int(self.weights[-1].shape[0])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Outputs float64 ``[N, out]`` of inputs float64 ``[N, in]`` (:data:`MLP_BLOCK` rows at a time)."""
        x = np.asarray(x, dtype=np.float64)
        out = np.empty((x.shape[0], self.n_out))
        for a in range(0, x.shape[0], MLP_BLOCK):
            xt = x[a : a + MLP_BLOCK].T.copy()  # a copy, even of one row: forward_t overwrites it
            out[a : a + MLP_BLOCK] = self.forward_t(xt, np.abs(xt).max(axis=0)).T
        return out

    def of_codes(self, codes: SalientCodes, columns: OneHotColumns) -> np.ndarray:
        """Outputs float64 ``[N, out]`` of the encoding held as :class:`~pemviz.pem.encoding.SalientCodes` (``columns``
        = :meth:`one_hot` of :data:`~pemviz.pem.encoding.ONE_HOT_GROUPS`): bit for bit ``self(codes.features())``,
        without building or multiplying the one-hot columns."""
        out = np.empty((codes.code.shape[0], self.n_out))
        for a in range(0, codes.code.shape[0], MLP_BLOCK):
            zt = codes.pose_t[:, a : a + MLP_BLOCK].copy()  # forward_t overwrites it
            largest = np.maximum(np.abs(zt).max(axis=0), 1.0)  # the ones of the one-hot columns count
            out[a : a + MLP_BLOCK] = self.forward_t(zt, largest, (columns, codes.code[a : a + MLP_BLOCK])).T
        return out

    def forward_t(
        self, xt: np.ndarray, largest: np.ndarray, first: tuple[OneHotColumns, np.ndarray] | None = None
    ) -> np.ndarray:
        """Outputs float64 ``[out, n]`` of one block of inputs laid out feature by feature, ``xt`` float64 ``[in, n]``
        (overwritten), ``largest`` float64 ``[n]`` the largest magnitude of each input row.

        ``first``: (:class:`OneHotColumns` of this network, code int [n]): the input rows also hold one-hot columns
        (exactly one 1 per group; ``code`` says which), and ``xt`` holds the other columns only, ``[in - C, n]``;
        ``largest`` counts the ones. The result is bit for bit that of the whole input rows."""
        h = xt
        for i, (wi, scale, b, bits) in enumerate(zip(self.weights, self.scales, self.biases, self.bits, strict=False)):
            if i:
                largest = h.max(axis=0)  # after a ReLU: >= 0
            shift = np.minimum(bits - np.frexp(largest)[1], 1000)  # each row's largest on 2^(bits - 1) .. 2^bits
            h *= np.ldexp(1.0, shift)  # powers of two: exact
            np.rint(h, out=h)
            if i == 0 and first is not None:
                r = first[0].other @ h  # integers below 2^53: exact in any order
                if shift.min() >= 0:  # each one on the row's grid is 2^shift: its terms scaled back are the table's
                    r *= np.ldexp(scale, -shift)  # exact (a power of two), and so is the sum of the exact terms
                    r += np.take(first[0].scaled, first[1], axis=1)
                else:  # a row of inputs beyond 2^bits: its ones round on its grid
                    r += np.take(first[0].table, first[1], axis=1) * np.rint(np.ldexp(1.0, shift))  # exact integers
                    r *= np.ldexp(scale, -shift)
            else:
                r = wi @ h
                r *= np.ldexp(scale, -shift)  # exact (a power of two)
            r += b
            if i < len(self.weights) - 1:
                np.maximum(r, 0.0, out=r)
            h = r
        return h

    def one_hot(self, groups: Sequence[Sequence[int]]) -> OneHotColumns:
        """The first layer split for inputs whose columns ``groups`` are one-hot (e.g. a class's and an occlusion's
        columns): :class:`OneHotColumns`, for :meth:`forward_t`."""
        w = self.weights[0]
        table = np.zeros((w.shape[0], 1))
        for columns in groups:  # integers below 2^53: exact
            table = (table[:, :, None] + w[:, None, list(columns)]).reshape(w.shape[0], -1)
        hot = {c for columns in groups for c in columns}
        other = [c for c in range(w.shape[1]) if c not in hot]
        return OneHotColumns(table, np.ascontiguousarray(w[:, other]), table * self.scales[0])


@dataclass(frozen=True, eq=False)
class OneHotColumns:
    """A :class:`GridMLP`'s first layer for inputs with one-hot column groups: ``table`` float64 ``[out, C]`` the
    integer weight sums of each combination (one column per group, the first group's index varying slowest),
    ``other`` float64 ``[out, in - hot]`` the integer weights of the remaining columns, in order; ``scaled`` the table
    times the layer's power of two (exact)."""

    table: np.ndarray
    other: np.ndarray
    scaled: np.ndarray


def _piecewise_linear_pieces(
    layers: tuple[tuple[np.ndarray, np.ndarray], ...], slope0: np.ndarray, offset0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact pieces of a ReLU network of one scalar input ``g`` (first pre-activation ``slope0 * g + offset0`` [H1],
    later layers ``layers[1:]``), by splitting intervals of ``g`` where a unit crosses zero: ``knots`` [K] and the
    output's ``slopes``, ``intercepts`` [K + 1] on each interval."""
    intervals = [(-math.inf, math.inf, slope0, offset0)]
    for w, b in layers[1:]:
        split: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        for lo, hi, a, c in intervals:
            with np.errstate(divide="ignore", invalid="ignore"):
                roots = -c / a
            inside = np.unique(roots[np.isfinite(roots) & (roots > lo) & (roots < hi)])
            edges = [lo, *inside.tolist(), hi]
            for left, right in zip(edges[:-1], edges[1:], strict=False):
                if math.isinf(left) and math.isinf(right):
                    probe = 0.0
                elif math.isinf(left):
                    probe = right - 1.0
                elif math.isinf(right):
                    probe = left + 1.0
                else:
                    probe = 0.5 * (left + right)
                active = (a * probe + c) > 0
                split.append((left, right, w @ (a * active), w @ (c * active) + b))
        intervals = split
    knots = np.array([iv[1] for iv in intervals[:-1]], dtype=np.float64)
    slopes = np.array([iv[2][0] for iv in intervals], dtype=np.float64)
    intercepts = np.array([iv[3][0] for iv in intervals], dtype=np.float64)
    return knots, slopes, intercepts


@dataclass(frozen=True, eq=False)
class PEM:
    """A trained PEM: network weights, z-score statistics, name and provenance (build with
    :func:`pemviz.pem.training.train_pem`, :func:`load_pem`, :func:`load_reference_pem` or :meth:`from_module`).
    ``state_dict`` (the :class:`MLNN` weights, float32 numpy arrays), ``hidden``, ``batch_norm``, ``temperature``
    (logits are divided by it) and ``metadata`` are stored by :func:`save_pem`.

    Raises:
        ValueError: a temperature not finite and > 0; PemFormatError: weights that do not fit ``hidden`` and
            ``batch_norm``."""

    kind: ClassVar[str] = "mlp"

    name: str
    norm: NormStats
    state_dict: Mapping[str, np.ndarray]
    hidden: tuple[int, ...] = (20, 20)
    batch_norm: bool = True
    temperature: float = 1.0
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.temperature) and self.temperature > 0):
            raise ValueError(f"PEM temperature must be finite and > 0, got {self.temperature}")
        object.__setattr__(self, "state_dict", as_arrays(self.state_dict))
        try:
            layers = fold_state_dict(self.state_dict, self.hidden, batch_norm=self.batch_norm)
        except ValueError as exc:
            raise PemFormatError(
                f"PEM {self.name!r}: weights do not fit hidden={self.hidden}, " f"batch_norm={self.batch_norm}: {exc}"
            ) from None
        # derived from the fields, set on the frozen instance (not fields)
        self._grid: GridMLP
        self._one_hot: OneHotColumns
        self._gap_knots: np.ndarray
        self._gap_slopes: np.ndarray
        self._gap_intercepts: np.ndarray
        object.__setattr__(self, "_layers", layers)
        object.__setattr__(self, "_grid", GridMLP.of(layers))
        object.__setattr__(self, "_one_hot", self._grid.one_hot(ONE_HOT_GROUPS))
        # Braking fast path: only loc_z varies with the gap, so the network is an exactly piecewise-linear
        # function of the gap (ReLU network of one variable); precompute its pieces once.
        const = braking_features_at_z(np.zeros(1), self.norm)[0]
        w1, b1 = layers[0]
        inv_std = 1.0 / float(self.norm.std[2])
        shift = BRAKING_CAMERA_TO_LEAD_CENTRE_M - float(self.norm.mean[2])
        slope0 = w1[:, BRAKING_Z_FEATURE] * inv_std  # d(pre-activation)/d(gap)
        offset0 = w1 @ const + b1 + slope0 * shift
        knots, slopes, intercepts = _piecewise_linear_pieces(layers, slope0, offset0)
        object.__setattr__(self, "_gap_knots", knots)
        object.__setattr__(self, "_gap_slopes", slopes / self.temperature)
        object.__setattr__(self, "_gap_intercepts", intercepts / self.temperature)

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_module(
        cls,
        module: MLNN,
        norm: NormStats,
        *,
        name: str,
        hidden: Sequence[int] = (20, 20),
        batch_norm: bool = True,
        temperature: float = 1.0,
        metadata: Mapping[str, Any] | None = None,
    ) -> PEM:
        """Wrap a trained :class:`MLNN` (its weights are copied into numpy arrays)."""
        return cls(
            name=name,
            norm=norm,
            state_dict=module.state_dict(),
            hidden=tuple(int(h) for h in hidden),
            batch_norm=batch_norm,
            temperature=float(temperature),
            metadata=dict(metadata or {}),
        )

    def to_module(self) -> MLNN:
        """A fresh torch :class:`MLNN` in eval mode with these weights (float32, as trained; no temperature). Imports
        torch."""
        import torch

        from pemviz.pem.modules import MLNN

        module = MLNN(N_FEATURES, self.hidden, batch_norm=self.batch_norm)
        try:
            module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in self.state_dict.items()})
        except RuntimeError as exc:
            raise PemFormatError(
                f"PEM {self.name!r}: weights do not fit hidden={self.hidden}, " f"batch_norm={self.batch_norm}: {exc}"
            ) from None
        return module.eval()

    # -- evaluation -----------------------------------------------------------------------------
    def _mlp(self, x: np.ndarray) -> np.ndarray:
        """Logits float64 ``[N]`` of encoded features ``[N, 14]`` (folded layers, ReLU between)."""
        out = self._grid(x)[:, 0]
        return out / self.temperature if self.temperature != 1.0 else out

    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        """The network input float64 ``[N, 14]`` for raw salient inputs ``[N, 11]`` (:func:`encode_salient`)."""
        return encode_salient(raw_inputs, self.norm)

    def logit_features(self, features: np.ndarray) -> np.ndarray:
        """Logit of p(detect), float64 ``[N]``, from encoded features ``[N, 14]``."""
        x = check_features(features)
        return self._mlp(x)

    def logit_codes(self, codes: SalientCodes) -> np.ndarray:
        """:meth:`logit_features` of ``codes.features()``, bit for bit, float64 ``[N]``, computed from the compact
        encoding (:func:`~pemviz.pem.encoding.salient_codes`)."""
        out = self._grid.of_codes(codes, self._one_hot)[:, 0]
        return out / self.temperature if self.temperature != 1.0 else out

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        """Logit of p(detect) for raw salient inputs.

        Args:
            raw_inputs: float ``[N, 11]``, KITTI column layout (:data:`pemviz.pem.encoding.INPUT_COLUMNS`).
        Returns:
            float64 ``[N]``, nats (log-odds); ``log p = -softplus(-logit)``, ``log(1-p) = -softplus(logit)``.
        Raises:
            ValueError: see :func:`encode_salient`."""
        return self._mlp(encode_salient(raw_inputs, self.norm))

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """Logit of p(detect) of the lead car at a gap (the braking scenario's lead car): the network's float64
        products on ``braking_salient_inputs(gap_m)`` to 1e-9 (tested), from its piecewise-linear pieces
        (:func:`_piecewise_linear_pieces`).

        Args:
            gap_m: gaps, metres, any shape ``[...]``.
        Returns:
            float64 logits of the same shape as ``gap_m``."""
        gap = np.asarray(gap_m, dtype=np.float64)
        piece = np.searchsorted(self._gap_knots, gap)
        return self._gap_slopes[piece] * gap + self._gap_intercepts[piece]

    def prob_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """p(detect) of the lead car at a gap, float64, shape of ``gap_m`` (sigmoid of :meth:`logit_at_gap`)."""
        logit = self.logit_at_gap(gap_m)
        return expit(logit)

    def prob(self, raw_inputs: np.ndarray) -> np.ndarray:
        """p(detect) for raw salient inputs ``[N, 11]``, float64 ``[N]``."""
        logit = self.logit(raw_inputs)
        return expit(logit)

"""Perception error model (PEM): salient variables of an obstacle -> logit of p(detected).

Spec section 2 (Innes & Ramamoorthy 2022, Sec. IV-A and Table I; the authors' ``pems.py``):

- input, 14 dims: one-hot class (7) + one-hot occlusion (3: none, partly, largely) + z-scored
  loc_x, loc_y, loc_z, rot_y (raw columns 7, 8, 9, 10), with the mean and unbiased (n - 1) std of the
  full 37,498-row file;
- ML-NN: Linear(14,20)-BatchNorm-ReLU-Linear(20,20)-BatchNorm-ReLU-Linear(20,1) -> logit, trained with
  BCE with logits, Adam lr 1e-3, batch 1024, 300 epochs, evaluated in eval mode.

A :class:`PEM` evaluates its network in float64 numpy with each BatchNorm folded into the linear layer
before it (exact algebra: ``gamma * (W x + b - mean) / sqrt(var + eps) + beta``), so one call costs a few
microseconds, not a torch dispatch per layer. The weights are trained in float32 with torch and stored
with ``torch.save`` as a plain dict (``torch.load(weights_only=True)`` reads it).

The braking scenario's state -> salient variables mapping (spec section 2) is
:func:`braking_salient_inputs`; :meth:`PEM.logit_at_gap` is the hot path the simulator calls.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from pemviz.data import repo_root

__all__ = [
    "ASSETS_DIR_ENV",
    "BRAKING_CAMERA_TO_LEAD_CENTRE_M",
    "BRAKING_LOC_X_M",
    "BRAKING_LOC_Y_M",
    "BRAKING_ROT_Y_RAD",
    "DEFAULT_PEM_NAME",
    "N_CLASSES",
    "N_FEATURES",
    "N_OCCLUSIONS",
    "POSE_COLUMNS",
    "PEM",
    "PEM_RECIPES",
    "NormStats",
    "PemRecipe",
    "PemFormatError",
    "assets_dir",
    "bce_from_logits",
    "braking_salient_inputs",
    "encode_salient",
    "fit_norm_stats",
    "load_pem",
    "load_reference_pem",
    "pem_path",
    "reference_pem_dir",
    "save_pem",
    "train_pem",
]

N_CLASSES = 7
"""KITTI classes of ``kitti.names`` without Misc: 0 Car, 1 Van, 2 Truck, 3 Pedestrian, 4 Person_sitting,
5 Cyclist, 6 Tram."""
N_OCCLUSIONS = 3
"""KITTI occlusion levels without 'unknown': 0 fully visible, 1 partly occluded, 2 largely occluded."""
CLASS_COLUMN = 0
OCCLUSION_COLUMN = 2
POSE_COLUMNS = (7, 8, 9, 10)
"""Raw input columns z-scored into the encoding: loc_x, loc_y, loc_z (metres), rot_y (radians)."""
N_FEATURES = N_CLASSES + N_OCCLUSIONS + len(POSE_COLUMNS)

CLASS_CAR = 0
OCCLUSION_NONE = 0
BRAKING_LOC_X_M = 0.0
"""Lateral offset of the lead in the camera frame (CARLA logs: 0.03-0.12 m)."""
BRAKING_LOC_Y_M = 1.76
"""Height of the ego's camera above the road (KITTI's own camera is at 1.65 m)."""
BRAKING_CAMERA_TO_LEAD_CENTRE_M = 2.48
"""loc_z = gap + 2.48 m: from the lead's rear to its centre."""
BRAKING_ROT_Y_RAD = -math.pi / 2
"""The lead drives in the ego's heading."""

ASSETS_DIR_ENV = "PEMVIZ_ASSETS_DIR"
DEFAULT_PEM_NAME = "ml-nn"
FORMAT_TAG = "pemviz-pem"
FORMAT_VERSION = 1
BATCH_NORM_EPS = 1e-5


class PemFormatError(ValueError):
    """A PEM weights file is not in pemviz's format (or is damaged)."""


# ------------------------------------------------------------------------------------------ encoding


@dataclass(frozen=True)
class NormStats:
    """z-score statistics of the pose columns: ``mean``, ``std`` float64 ``[4]`` for loc_x, loc_y, loc_z
    (metres) and rot_y (radians)."""

    mean: np.ndarray
    std: np.ndarray

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=np.float64).reshape(-1)
        std = np.asarray(self.std, dtype=np.float64).reshape(-1)
        if mean.shape != (len(POSE_COLUMNS),) or std.shape != (len(POSE_COLUMNS),):
            raise ValueError(f"NormStats needs 4 means and 4 stds, got shapes {mean.shape}, {std.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std)) and np.all(std > 0)):
            raise ValueError(f"NormStats must be finite with std > 0, got mean {mean}, std {std}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "std", std)


def fit_norm_stats(raw_inputs: np.ndarray) -> NormStats:
    """Mean and unbiased (n - 1) std of the pose columns of raw salient inputs ``[N, 11]`` (spec section 2).

    Raises:
        ValueError: fewer than 2 rows or not 11 columns.
    """
    raw = _check_raw(raw_inputs)
    if raw.shape[0] < 2:
        raise ValueError(f"need at least 2 rows to fit z-score statistics, got {raw.shape[0]}")
    pose = raw[:, POSE_COLUMNS]
    return NormStats(mean=pose.mean(axis=0), std=pose.std(axis=0, ddof=1))


def _check_raw(raw_inputs: np.ndarray) -> np.ndarray:
    raw = np.asarray(raw_inputs, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != 11:
        raise ValueError(f"raw salient inputs must have shape [N, 11] (KITTI columns), got {raw.shape}")
    return raw


def encode_salient(raw_inputs: np.ndarray, norm: NormStats) -> np.ndarray:
    """The 14-dim PEM input: one-hot class (7), one-hot occlusion (3), z-scored x, y, z, rot_y.

    Args:
        raw_inputs: float ``[N, 11]`` in the KITTI column layout (class, truncation, occlusion, alpha,
            dim_w, dim_l, dim_h, loc_x, loc_y, loc_z, rot_y); metres, radians.
        norm: z-score statistics (:func:`fit_norm_stats` of the training file).

    Returns:
        float64 ``[N, 14]`` (the order of the authors' ``SalientObstacleDataset``).

    Raises:
        ValueError: wrong shape, non-finite values, a class not an integer in 0..6 or an occlusion not an
            integer in 0..2 (the message names the first bad row, 0-based).
    """
    raw = _check_raw(raw_inputs)
    if not np.all(np.isfinite(raw)):
        row = int(np.flatnonzero(~np.all(np.isfinite(raw), axis=1))[0])
        raise ValueError(f"raw salient inputs: non-finite value in row {row}")
    cls = raw[:, CLASS_COLUMN]
    occ = raw[:, OCCLUSION_COLUMN]
    for what, values, n in (("class", cls, N_CLASSES), ("occlusion", occ, N_OCCLUSIONS)):
        bad = (values != np.round(values)) | (values < 0) | (values > n - 1)
        if np.any(bad):
            row = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"raw salient inputs: {what} {values[row]:g} in row {row} is not an integer in 0..{n - 1}"
            )
    n_rows = raw.shape[0]
    out = np.zeros((n_rows, N_FEATURES), dtype=np.float64)
    rows = np.arange(n_rows)
    out[rows, cls.astype(np.int64)] = 1.0
    out[rows, N_CLASSES + occ.astype(np.int64)] = 1.0
    out[:, N_CLASSES + N_OCCLUSIONS :] = (raw[:, POSE_COLUMNS] - norm.mean) / norm.std
    return out


def braking_salient_inputs(gap_m: np.ndarray) -> np.ndarray:
    """Salient variables of the lead car in the braking scenario (spec section 2).

    class Car, occlusion none, loc_x = 0.0, loc_y = 1.76 (camera height), loc_z = gap + 2.48,
    rot_y = -pi/2; the unused columns (truncation, alpha, box dimensions) are 0.

    Args:
        gap_m: gap from the ego's camera to the lead's rear, metres, any shape ``[...]``.

    Returns:
        float64 ``[M, 11]`` with ``M = gap_m.size`` (flattened, C order).
    """
    gap = np.asarray(gap_m, dtype=np.float64).reshape(-1)
    raw = np.zeros((gap.shape[0], 11), dtype=np.float64)
    raw[:, CLASS_COLUMN] = CLASS_CAR
    raw[:, OCCLUSION_COLUMN] = OCCLUSION_NONE
    raw[:, 7] = BRAKING_LOC_X_M
    raw[:, 8] = BRAKING_LOC_Y_M
    raw[:, 9] = gap + BRAKING_CAMERA_TO_LEAD_CENTRE_M
    raw[:, 10] = BRAKING_ROT_Y_RAD
    return raw


def bce_from_logits(logits: np.ndarray, labels: np.ndarray) -> float:
    """Mean binary cross-entropy, nats: ``mean(softplus(l) - y * l)`` = ``-mean(log sigmoid(+-l))``, float64."""
    logit = np.asarray(logits, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if logit.shape != y.shape:
        raise ValueError(f"logits {logit.shape} and labels {y.shape} differ in length")
    return float(np.mean(np.logaddexp(0.0, logit) - y * logit))


# ------------------------------------------------------------------------------------------- network


class MLNN(nn.Module):
    """The paper's ML-NN (and its wider / deeper variants): ``ff_nn`` = [Linear, BatchNorm?, ReLU, Dropout?]
    per hidden layer, then Linear(h, 1) -> logit ``[N, 1]``.

    With ``hidden=(20, 20)``, ``batch_norm=True``, ``dropout=0`` the state-dict keys are the authors'
    (``ff_nn.{0,1,3,4,6}.*``), so their weights load directly.
    """

    def __init__(self, in_dim: int = N_FEATURES, hidden: Sequence[int] = (20, 20), *, batch_norm: bool = True,
                 dropout: float = 0.0) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        prev = in_dim
        for width in hidden:
            layers.append(nn.Linear(prev, width))
            if batch_norm:
                layers.append(nn.BatchNorm1d(width))
            layers.append(nn.ReLU())
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
            prev = width
        layers.append(nn.Linear(prev, 1))
        self.ff_nn = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.ff_nn(x)


def _fold_layers(module: MLNN) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Affine layers ``(W [out, in], b [out])`` in float64, each BatchNorm (eval mode) folded into the
    Linear before it; a ReLU follows every layer but the last."""
    folded: list[tuple[np.ndarray, np.ndarray]] = []
    mods = list(module.ff_nn)
    for i, mod in enumerate(mods):
        if isinstance(mod, nn.Linear):
            w = mod.weight.detach().to(torch.float64).numpy().copy()
            b = mod.bias.detach().to(torch.float64).numpy().copy()
            nxt = mods[i + 1] if i + 1 < len(mods) else None
            if isinstance(nxt, nn.BatchNorm1d):
                assert nxt.running_mean is not None and nxt.running_var is not None
                scale = nxt.weight.detach().to(torch.float64).numpy() / np.sqrt(
                    nxt.running_var.detach().to(torch.float64).numpy() + nxt.eps
                )
                b = scale * (b - nxt.running_mean.detach().to(torch.float64).numpy()) + nxt.bias.detach().to(
                    torch.float64
                ).numpy()
                w = scale[:, None] * w
            folded.append((np.ascontiguousarray(w), np.ascontiguousarray(b)))
    return tuple(folded)


def _piecewise_linear_pieces(
    layers: tuple[tuple[np.ndarray, np.ndarray], ...], slope0: np.ndarray, offset0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact pieces of a ReLU network of one scalar input ``g`` whose first pre-activation is
    ``slope0 * g + offset0`` ``[H1]`` and whose later affine layers are ``layers[1:]``.

    Walks the layers keeping, for each interval of ``g``, the affine map of the current pre-activations;
    each ReLU splits an interval where a unit crosses zero. Returns ``knots`` ``[K]`` (sorted interval
    boundaries) and ``slopes``, ``intercepts`` ``[K + 1]`` of the output on each interval (interval ``i``
    is ``knots[i-1] <= g <= knots[i]``; the network is continuous, so either side of a knot is exact).
    """
    intervals = [(-math.inf, math.inf, slope0, offset0)]
    for w, b in layers[1:]:
        split: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        for lo, hi, a, c in intervals:
            with np.errstate(divide="ignore", invalid="ignore"):
                roots = -c / a
            inside = np.unique(roots[np.isfinite(roots) & (roots > lo) & (roots < hi)])
            edges = [lo, *inside.tolist(), hi]
            for left, right in zip(edges[:-1], edges[1:]):
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


# ----------------------------------------------------------------------------------------------- PEM


@dataclass(frozen=True, eq=False)
class PEM:
    """A trained PEM: network weights, z-score statistics, name and provenance.

    Build with :func:`train_pem`, :func:`load_pem`, :func:`load_reference_pem` or :meth:`from_module`.
    Attributes ``state_dict`` (torch tensors as trained), ``hidden``, ``batch_norm``, ``temperature``
    (logits are divided by it; 1.0 for the paper's ML-NN) and ``metadata`` (plain values) are stored by
    :func:`save_pem`.
    """

    name: str
    norm: NormStats
    state_dict: Mapping[str, torch.Tensor]
    hidden: tuple[int, ...] = (20, 20)
    batch_norm: bool = True
    temperature: float = 1.0
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.temperature) and self.temperature > 0):
            raise ValueError(f"PEM temperature must be finite and > 0, got {self.temperature}")
        module = self.to_module()
        layers = _fold_layers(module)
        object.__setattr__(self, "_layers", layers)
        # Braking fast path: only loc_z varies with the gap, so the network is an exactly piecewise-linear
        # function of the gap (ReLU network of one variable); precompute its pieces once.
        z_col = N_CLASSES + N_OCCLUSIONS + 2
        const = encode_salient(braking_salient_inputs(np.zeros(1)), self.norm)[0]
        const[z_col] = 0.0
        w1, b1 = layers[0]
        inv_std = 1.0 / float(self.norm.std[2])
        shift = BRAKING_CAMERA_TO_LEAD_CENTRE_M - float(self.norm.mean[2])
        slope0 = w1[:, z_col] * inv_std  # d(pre-activation)/d(gap)
        offset0 = w1 @ const + b1 + slope0 * shift
        knots, slopes, intercepts = _piecewise_linear_pieces(layers, slope0, offset0)
        object.__setattr__(self, "_gap_knots", knots)
        object.__setattr__(self, "_gap_slopes", slopes / self.temperature)
        object.__setattr__(self, "_gap_intercepts", intercepts / self.temperature)

    # -- construction ---------------------------------------------------------------------------
    @classmethod
    def from_module(cls, module: MLNN, norm: NormStats, *, name: str, hidden: Sequence[int] = (20, 20),
                    batch_norm: bool = True, temperature: float = 1.0,
                    metadata: Mapping[str, Any] | None = None) -> PEM:
        """Wrap a trained :class:`MLNN` (its weights are copied)."""
        state = {k: v.detach().clone().cpu() for k, v in module.state_dict().items()}
        return cls(name=name, norm=norm, state_dict=state, hidden=tuple(int(h) for h in hidden),
                   batch_norm=batch_norm, temperature=float(temperature), metadata=dict(metadata or {}))

    def to_module(self) -> MLNN:
        """A fresh torch :class:`MLNN` in eval mode with these weights (float32, as trained; no temperature)."""
        module = MLNN(N_FEATURES, self.hidden, batch_norm=self.batch_norm)
        try:
            module.load_state_dict(dict(self.state_dict))
        except RuntimeError as exc:
            raise PemFormatError(f"PEM {self.name!r}: weights do not fit hidden={self.hidden}, "
                                 f"batch_norm={self.batch_norm}: {exc}") from None
        return module.eval()

    def with_temperature(self, temperature: float, *, name: str | None = None) -> PEM:
        """The same network with logits divided by ``temperature`` (temperature scaling, Guo et al. 2017)."""
        return PEM(name=name or self.name, norm=self.norm, state_dict=self.state_dict, hidden=self.hidden,
                   batch_norm=self.batch_norm, temperature=float(temperature), metadata=dict(self.metadata))

    # -- evaluation -----------------------------------------------------------------------------
    def _mlp(self, x: np.ndarray) -> np.ndarray:
        """Logits float64 ``[N]`` of encoded features ``[N, 14]`` (folded layers, ReLU between)."""
        layers: tuple[tuple[np.ndarray, np.ndarray], ...] = self._layers  # type: ignore[attr-defined]
        h = x
        for i, (w, b) in enumerate(layers):
            h = h @ w.T
            h += b
            if i < len(layers) - 1:
                np.maximum(h, 0.0, out=h)
        out = h[:, 0]
        return out / self.temperature if self.temperature != 1.0 else out

    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        """The network input float64 ``[N, 14]`` for raw salient inputs ``[N, 11]`` (:func:`encode_salient`)."""
        return encode_salient(raw_inputs, self.norm)

    def logit_features(self, features: np.ndarray) -> np.ndarray:
        """Logit of p(detect), float64 ``[N]``, from encoded features ``[N, 14]``."""
        x = np.asarray(features, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != N_FEATURES:
            raise ValueError(f"PEM features must have shape [N, {N_FEATURES}], got {x.shape}")
        return self._mlp(x)

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        """Logit of p(detect) for raw salient inputs.

        Args:
            raw_inputs: float ``[N, 11]``, KITTI column layout (:data:`pemviz.data.INPUT_COLUMNS`).

        Returns:
            float64 ``[N]``, nats (log-odds); ``log p = -softplus(-logit)``, ``log(1-p) = -softplus(logit)``.

        Raises:
            ValueError: see :func:`encode_salient`.
        """
        return self._mlp(encode_salient(raw_inputs, self.norm))

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """Logit of p(detect) of the lead car at a gap (braking scenario, spec section 2).

        Equal to ``self.logit(braking_salient_inputs(gap_m))`` to float64 rounding (tested to 1e-9): with
        only the gap varying, the ReLU network is an exactly piecewise-linear function of the gap, whose
        pieces are computed once at construction (:func:`_piecewise_linear_pieces`); a call is one
        ``searchsorted`` and one multiply-add (~20 us for 1,000 gaps).

        Args:
            gap_m: gaps, metres, any shape ``[...]``.

        Returns:
            float64 logits of the same shape as ``gap_m``.
        """
        gap = np.asarray(gap_m, dtype=np.float64)
        piece = np.searchsorted(self._gap_knots, gap)  # type: ignore[attr-defined]
        return self._gap_slopes[piece] * gap + self._gap_intercepts[piece]  # type: ignore[attr-defined]

    def prob_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """p(detect) of the lead car at a gap, float64, shape of ``gap_m`` (sigmoid of :meth:`logit_at_gap`)."""
        logit = self.logit_at_gap(gap_m)
        return np.exp(-np.logaddexp(0.0, -logit))

    def prob(self, raw_inputs: np.ndarray) -> np.ndarray:
        """p(detect) for raw salient inputs ``[N, 11]``, float64 ``[N]``."""
        logit = self.logit(raw_inputs)
        return np.exp(-np.logaddexp(0.0, -logit))


# ---------------------------------------------------------------------------------------- training


def train_pem(
    inputs: np.ndarray,
    labels: np.ndarray,
    *,
    name: str = "ml-nn",
    hidden: Sequence[int] = (20, 20),
    batch_norm: bool = True,
    dropout: float = 0.0,
    epochs: int = 300,
    batch_size: int = 1024,
    lr: float = 1e-3,
    weight_decay: float = 0.0,
    seed: int = 0,
    norm: NormStats | None = None,
    progress: bool = False,
    metadata: Mapping[str, Any] | None = None,
) -> PEM:
    """Train a PEM network with the paper's recipe (spec section 2; the authors' ``train_tp_pem_det.py``).

    BCE with logits, Adam (lr 1e-3), mini-batches of 1024 reshuffled every epoch, 300 epochs, float32;
    seeded (``torch.manual_seed(seed)`` for the initial weights, a seeded generator for the shuffles), so
    the same seed gives the same weights on the same torch build.

    Args:
        inputs: raw salient inputs ``[N, 11]`` (KITTI layout).
        labels: detected, ``[N]`` in {0, 1}.
        name: the PEM's name (``ml-nn`` for the paper's model).
        hidden, batch_norm, dropout: architecture (default: the paper's 20-20 with BatchNorm).
        epochs, batch_size, lr, weight_decay: optimiser settings (weight_decay: Adam's L2 term).
        seed: random seed.
        norm: z-score statistics; default: fitted on ``inputs`` (the spec fits them on the full file,
            also when training on a cross-validation fold).
        progress: show a tqdm progress bar over epochs.
        metadata: extra provenance stored with the PEM.

    Returns:
        The trained :class:`PEM` (eval mode).

    Raises:
        ValueError: mismatched lengths, labels not in {0, 1}, bad encodings, epochs < 1 or batch_size < 2.
    """
    raw = _check_raw(inputs)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if y.shape[0] != raw.shape[0]:
        raise ValueError(f"inputs have {raw.shape[0]} rows but labels {y.shape[0]}")
    if not np.all((y == 0.0) | (y == 1.0)):
        raise ValueError("labels must be 0 or 1")
    if epochs < 1 or batch_size < 2:
        raise ValueError(f"need epochs >= 1 and batch_size >= 2, got {epochs}, {batch_size}")
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = torch.as_tensor(encode_salient(raw, norm), dtype=torch.float32)
    t = torch.as_tensor(y, dtype=torch.float32).unsqueeze(1)
    n = x.shape[0]

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 20-unit net gains nothing from threads, and one thread is reproducible
    try:
        module, last_loss = _fit(x, t, hidden=hidden, batch_norm=batch_norm, dropout=dropout, epochs=epochs,
                                 batch_size=batch_size, lr=lr, weight_decay=weight_decay, seed=seed,
                                 progress=progress, name=name)
    finally:
        torch.set_num_threads(threads)
    meta = {
        "seed": int(seed), "epochs": int(epochs), "batch_size": int(batch_size), "lr": float(lr),
        "weight_decay": float(weight_decay), "dropout": float(dropout), "n_train": int(n),
        "final_epoch_train_bce": float(last_loss), "torch_version": str(torch.__version__),
    }
    meta.update(dict(metadata or {}))
    return PEM.from_module(module, norm, name=name, hidden=hidden, batch_norm=batch_norm, metadata=meta)


def _fit(x: torch.Tensor, t: torch.Tensor, *, hidden: Sequence[int], batch_norm: bool, dropout: float, epochs: int,
         batch_size: int, lr: float, weight_decay: float, seed: int, progress: bool, name: str) -> tuple[MLNN, float]:
    """The training loop of :func:`train_pem` on encoded float32 features ``x [N, 14]`` and targets ``t [N, 1]``."""
    n = x.shape[0]
    torch.manual_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    module = MLNN(N_FEATURES, hidden, batch_norm=batch_norm, dropout=dropout)
    optimiser = torch.optim.Adam(module.parameters(), lr=lr, weight_decay=weight_decay)
    loss_fn = nn.BCEWithLogitsLoss()

    epoch_iter: Any = range(epochs)
    if progress:
        from tqdm.auto import tqdm

        epoch_iter = tqdm(epoch_iter, desc=f"train {name}", unit="epoch", mininterval=0.5)
    last_loss = float("nan")
    module.train()
    for _ in epoch_iter:
        perm = torch.randperm(n, generator=generator)
        total, count = 0.0, 0
        for start in range(0, n, batch_size):
            idx = perm[start : start + batch_size]
            if batch_norm and idx.shape[0] < 2:
                continue  # BatchNorm cannot train on one row
            optimiser.zero_grad(set_to_none=True)
            loss = loss_fn(module(x[idx]), t[idx])
            loss.backward()
            optimiser.step()
            total += float(loss.detach()) * idx.shape[0]
            count += idx.shape[0]
        last_loss = total / max(count, 1)
        if progress:
            epoch_iter.set_postfix(bce=f"{last_loss:.4f}", refresh=False)
    module.eval()
    return module, last_loss


@dataclass(frozen=True)
class PemRecipe:
    """How to train a named PEM: the architecture and optimiser settings passed to :func:`train_pem`.

    ``seed`` is the seed of the shipped weights (see ``assets/README.md`` for why it is the one chosen).
    """

    name: str
    description: str
    hidden: tuple[int, ...] = (20, 20)
    batch_norm: bool = True
    dropout: float = 0.0
    epochs: int = 300
    batch_size: int = 1024
    lr: float = 1e-3
    weight_decay: float = 0.0
    seed: int = 0

    def train(self, inputs: np.ndarray, labels: np.ndarray, *, seed: int | None = None, epochs: int | None = None,
              norm: NormStats | None = None, progress: bool = False,
              metadata: Mapping[str, Any] | None = None) -> PEM:
        """:func:`train_pem` with this recipe (``seed`` / ``epochs`` override the recipe's)."""
        return train_pem(
            inputs, labels, name=self.name, hidden=self.hidden, batch_norm=self.batch_norm, dropout=self.dropout,
            epochs=self.epochs if epochs is None else epochs, batch_size=self.batch_size, lr=self.lr,
            weight_decay=self.weight_decay, seed=self.seed if seed is None else seed, norm=norm,
            progress=progress, metadata={"recipe": self.name, **dict(metadata or {})},
        )


PEM_RECIPES: dict[str, PemRecipe] = {
    "ml-nn": PemRecipe(
        name="ml-nn",
        description="the paper's ML-NN: 14-20-20-1 with BatchNorm, Adam 1e-3, batch 1024, 300 epochs",
        seed=2,
    ),
}
"""Named PEMs that ``pemviz pem train --model NAME`` can (re)train."""


# ------------------------------------------------------------------------------------- save / load


def assets_dir() -> Path:
    """``$PEMVIZ_ASSETS_DIR`` if set, else ``<repository root>/assets``."""
    env = os.environ.get(ASSETS_DIR_ENV)
    return Path(env).expanduser() if env else repo_root() / "assets"


def pem_path(name: str = DEFAULT_PEM_NAME) -> Path:
    """Where the shipped PEM called ``name`` lives: ``<assets>/pem_<name>.pt``."""
    return assets_dir() / f"pem_{name}.pt"


def _plain(value: Any) -> Any:
    """Metadata as plain Python values (what ``torch.load(weights_only=True)`` accepts)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, np.integer, np.bool_)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if value is None or isinstance(value, bool):
        return value
    for kind in (int, float, str):  # exact builtins: subclasses (e.g. torch's TorchVersion) are not loadable
        if isinstance(value, kind):
            return kind(value)
    return str(value)


def _default_file_mode() -> int:
    """0o666 minus the process umask (what ``open()`` would give; ``mkstemp`` gives 0o600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def save_pem(pem: PEM, path: str | os.PathLike[str]) -> Path:
    """Write a PEM atomically (temporary file in the same folder, then ``os.replace``).

    The file is a ``torch.save`` of a plain dict: format tag, name, architecture, ``state_dict`` tensors,
    z-score statistics (float64 tensors), temperature and metadata; ``torch.load(weights_only=True)``
    reads it. About 10 KB for the ML-NN.

    Raises:
        OSError: the folder is not writable (nothing is left behind).
    """
    target = Path(path)
    payload = {
        "format": FORMAT_TAG,
        "version": FORMAT_VERSION,
        "name": pem.name,
        "hidden": list(pem.hidden),
        "batch_norm": bool(pem.batch_norm),
        "temperature": float(pem.temperature),
        "norm_mean": torch.as_tensor(pem.norm.mean, dtype=torch.float64),
        "norm_std": torch.as_tensor(pem.norm.std, dtype=torch.float64),
        "state_dict": {k: v.detach().cpu().clone() for k, v in pem.state_dict.items()},
        "metadata": _plain(pem.metadata),
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(payload, fh)
        os.chmod(tmp, _default_file_mode())
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def load_pem(path: str | os.PathLike[str] | None = None) -> PEM:
    """Load a PEM saved by :func:`save_pem`.

    Args:
        path: a file path, or the name of a shipped PEM (``"ml-nn"`` -> ``<assets>/pem_ml-nn.pt``, see
            :func:`pem_path`); default :data:`DEFAULT_PEM_NAME`.

    Raises:
        FileNotFoundError: no such file (the message lists the shipped PEMs).
        PemFormatError: the file is not a pemviz PEM or is damaged.
    """
    if path is None:
        path = DEFAULT_PEM_NAME
    p = Path(path)
    if isinstance(path, str) and p.suffix != ".pt" and len(p.parts) == 1:
        p = pem_path(path)
    if not p.is_file():
        shipped = sorted(f.stem[len("pem_"):] for f in assets_dir().glob("pem_*.pt"))
        raise FileNotFoundError(f"PEM file {p} not found; shipped PEMs in {assets_dir()}: {shipped or 'none'}")
    try:
        payload = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for damaged files
        raise PemFormatError(f"{p}: not a readable PEM file ({exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT_TAG:
        raise PemFormatError(f"{p}: not a pemviz PEM file (missing format tag {FORMAT_TAG!r})")
    if payload.get("version") != FORMAT_VERSION:
        raise PemFormatError(f"{p}: PEM format version {payload.get('version')}, this pemviz reads {FORMAT_VERSION}")
    try:
        return PEM(
            name=str(payload["name"]),
            norm=NormStats(mean=payload["norm_mean"].numpy(), std=payload["norm_std"].numpy()),
            state_dict=dict(payload["state_dict"]),
            hidden=tuple(int(h) for h in payload["hidden"]),
            batch_norm=bool(payload["batch_norm"]),
            temperature=float(payload["temperature"]),
            metadata=dict(payload.get("metadata") or {}),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise PemFormatError(f"{p}: damaged PEM file ({exc!r})") from None


def reference_pem_dir() -> Path:
    """``<repository root>/../shared/reference/carla-stuff-pem``: the authors' PEM (never copied into pemviz)."""
    return repo_root().parent / "shared" / "reference" / "carla-stuff-pem"


def load_reference_pem(folder: str | os.PathLike[str] | None = None) -> PEM:
    """The authors' ML-NN (CarlaStuff ``models/det_baseline_full/pem_class_train_full`` with
    ``norm_stats_mu.pt`` / ``norm_stats_std.pt``) as a :class:`PEM` named ``authors``.

    Their stats are float32 over all 11 columns; the pose columns 7..10 are used.

    Raises:
        FileNotFoundError: the folder or one of its three files is missing.
    """
    d = Path(folder) if folder is not None else reference_pem_dir()
    files = [d / "pem_class_train_full.pt", d / "norm_stats_mu.pt", d / "norm_stats_std.pt"]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"authors' PEM files missing: {', '.join(missing)}")
    state = torch.load(files[0], map_location="cpu", weights_only=True)
    mu = torch.load(files[1], map_location="cpu", weights_only=True).to(torch.float64).numpy()
    sd = torch.load(files[2], map_location="cpu", weights_only=True).to(torch.float64).numpy()
    cols = list(POSE_COLUMNS)
    return PEM(name="authors", norm=NormStats(mean=mu[cols], std=sd[cols]), state_dict=dict(state),
               metadata={"source": "craigiedon/CarlaStuff models/det_baseline_full/pem_class_train_full"})

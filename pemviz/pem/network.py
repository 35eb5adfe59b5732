"""The paper's ML-NN PEM (and wider variants): training, and exact float64 evaluation.

Innes & Ramamoorthy 2022, Sec. IV-A: Linear(14,20)-BatchNorm-ReLU-Linear(20,20)-BatchNorm-ReLU-Linear(20,1) -> logit, BCE with
logits, Adam lr 1e-3, batch 1024, 300 epochs, eval mode (the authors' ``PEMClass_Deterministic`` and
``train_tp_pem_det.py``).

A :class:`PEM` evaluates its network in float64 numpy with each BatchNorm folded into the linear layer
before it (exact algebra: ``gamma * (W x + b - mean) / sqrt(var + eps) + beta``). Along the braking
scenario only the gap varies, so the ReLU network is an exactly piecewise-linear function of the gap; its
pieces are computed once, and :meth:`PEM.logit_at_gap` (the simulator's hot path) is one ``searchsorted``
and one multiply-add.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.special import expit
from torch import nn
from tqdm.auto import tqdm

from pemviz.pem.encoding import (
    BRAKING_CAMERA_TO_LEAD_CENTRE_M,
    BRAKING_Z_FEATURE,
    N_FEATURES,
    NormStats,
    braking_features_at_z,
    check_training_data,
    encode_salient,
    fit_norm_stats,
)


class PemFormatError(ValueError):
    """A PEM weights file is not in pemviz's format (or is damaged)."""


class MLNN(nn.Module):
    """The paper's ML-NN (and its wider / deeper variants): ``ff_nn`` = [Linear, BatchNorm?, ReLU, Dropout?]
    per hidden layer, then Linear(h, out_dim) -> logit ``[N, 1]`` (or the noise PEM's ``[N, 4]``, see
    :mod:`pemviz.pem.noise`).

    With ``hidden=(20, 20)``, ``batch_norm=True``, ``dropout=0`` the state-dict keys are the authors'
    (``ff_nn.{0,1,3,4,6}.*``), so their weights load directly.
    """

    def __init__(
        self,
        in_dim: int = N_FEATURES,
        hidden: Sequence[int] = (20, 20),
        *,
        batch_norm: bool = True,
        dropout: float = 0.0,
        out_dim: int = 1,
    ) -> None:
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
        layers.append(nn.Linear(prev, out_dim))
        self.ff_nn = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.ff_nn(x)


def fold_layers(module: MLNN) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
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
                b = (
                    scale * (b - nxt.running_mean.detach().to(torch.float64).numpy())
                    + nxt.bias.detach().to(torch.float64).numpy()
                )
                w = scale[:, None] * w
            folded.append((np.ascontiguousarray(w), np.ascontiguousarray(b)))
    return tuple(folded)


def mlp_forward(layers: tuple[tuple[np.ndarray, np.ndarray], ...], x: np.ndarray) -> np.ndarray:
    """Outputs float64 ``[N, out]`` of folded affine layers (:func:`fold_layers`) on inputs ``[N, in]``, ReLU between.

    The whole batch goes through each layer at once. (Blocks of 2,048 rows were 25 % faster on the cut-in, but a row's
    result then depended on where the blocks fell, so a chunk size other than the default gave other rollouts.)"""
    h = x
    for i, (w, b) in enumerate(layers):
        h = h @ w.T
        h += b
        if i < len(layers) - 1:
            np.maximum(h, 0.0, out=h)
    return h


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
    """A trained PEM: network weights, z-score statistics, name and provenance.

    Build with :func:`train_pem`, :func:`load_pem`, :func:`load_reference_pem` or :meth:`from_module`.
    Attributes ``state_dict`` (torch tensors as trained), ``hidden``, ``batch_norm``, ``temperature``
    (logits are divided by it; 1.0 for the paper's ML-NN) and ``metadata`` (plain values) are stored by
    :func:`save_pem`.
    """

    kind: ClassVar[str] = "mlp"

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
        layers = fold_layers(module)
        object.__setattr__(self, "_layers", layers)
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
        """Wrap a trained :class:`MLNN` (its weights are copied)."""
        state = {k: v.detach().clone().cpu() for k, v in module.state_dict().items()}
        return cls(
            name=name,
            norm=norm,
            state_dict=state,
            hidden=tuple(int(h) for h in hidden),
            batch_norm=batch_norm,
            temperature=float(temperature),
            metadata=dict(metadata or {}),
        )

    def to_module(self) -> MLNN:
        """A fresh torch :class:`MLNN` in eval mode with these weights (float32, as trained; no temperature)."""
        module = MLNN(N_FEATURES, self.hidden, batch_norm=self.batch_norm)
        try:
            module.load_state_dict(dict(self.state_dict))
        except RuntimeError as exc:
            raise PemFormatError(
                f"PEM {self.name!r}: weights do not fit hidden={self.hidden}, " f"batch_norm={self.batch_norm}: {exc}"
            ) from None
        return module.eval()

    def with_temperature(self, temperature: float, *, name: str | None = None) -> PEM:
        """The same network with logits divided by ``temperature`` (temperature scaling, Guo et al. 2017)."""
        return PEM(
            name=name or self.name,
            norm=self.norm,
            state_dict=self.state_dict,
            hidden=self.hidden,
            batch_norm=self.batch_norm,
            temperature=float(temperature),
            metadata=dict(self.metadata),
        )

    # -- evaluation -----------------------------------------------------------------------------
    def _mlp(self, x: np.ndarray) -> np.ndarray:
        """Logits float64 ``[N]`` of encoded features ``[N, 14]`` (folded layers, ReLU between)."""
        out = mlp_forward(self._layers, x)[:, 0]  # type: ignore[attr-defined]
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
            raw_inputs: float ``[N, 11]``, KITTI column layout (:data:`pemviz.io.data.INPUT_COLUMNS`).

        Returns:
            float64 ``[N]``, nats (log-odds); ``log p = -softplus(-logit)``, ``log(1-p) = -softplus(logit)``.

        Raises:
            ValueError: see :func:`encode_salient`.
        """
        return self._mlp(encode_salient(raw_inputs, self.norm))

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """Logit of p(detect) of the lead car at a gap (the braking scenario's lead car).

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
        return expit(logit)

    def prob(self, raw_inputs: np.ndarray) -> np.ndarray:
        """p(detect) for raw salient inputs ``[N, 11]``, float64 ``[N]``."""
        logit = self.logit(raw_inputs)
        return expit(logit)


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
    """Train a PEM network with the paper's recipe (Innes & Ramamoorthy (2022), Sec. V; the authors' ``train_tp_pem_det.py``).

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
    raw, y = check_training_data(inputs, labels)
    if epochs < 1 or batch_size < 2:
        raise ValueError(f"need epochs >= 1 and batch_size >= 2, got {epochs}, {batch_size}")
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = torch.as_tensor(encode_salient(raw, norm), dtype=torch.float32)
    t = torch.as_tensor(y, dtype=torch.float32).unsqueeze(1)
    n = x.shape[0]

    module, last_loss = fit_network(
        x,
        t,
        loss_fn=nn.BCEWithLogitsLoss(),
        hidden=hidden,
        batch_norm=batch_norm,
        dropout=dropout,
        epochs=epochs,
        batch_size=batch_size,
        lr=lr,
        weight_decay=weight_decay,
        seed=seed,
        progress=progress,
        name=name,
    )
    meta = {
        "seed": int(seed),
        "epochs": int(epochs),
        "batch_size": int(batch_size),
        "lr": float(lr),
        "weight_decay": float(weight_decay),
        "dropout": float(dropout),
        "n_train": int(n),
        "final_epoch_train_bce": float(last_loss),
        "torch_version": str(torch.__version__),
    }
    meta.update(dict(metadata or {}))
    return PEM.from_module(module, norm, name=name, hidden=hidden, batch_norm=batch_norm, metadata=meta)


def fit_network(
    x: torch.Tensor,
    t: torch.Tensor,
    *,
    loss_fn: nn.Module,
    hidden: Sequence[int],
    batch_norm: bool,
    dropout: float,
    epochs: int,
    batch_size: int,
    lr: float,
    weight_decay: float,
    seed: int,
    progress: bool,
    name: str,
    out_dim: int = 1,
) -> tuple[MLNN, float]:
    """The training loop of :func:`train_pem` (and of the noise PEM): an :class:`MLNN` with ``out_dim`` outputs on
    float32 inputs ``x [N, 14]`` and targets ``t [N, ...]``, minimising ``loss_fn(module(x[batch]), t[batch])``.

    Adam (lr, weight_decay) over the network's and the loss's own parameters (e.g. the noise PEM's Student-t degrees
    of freedom), mini-batches reshuffled every epoch by a generator seeded with ``seed``, initial weights from
    ``torch.manual_seed(seed)``, one CPU thread (tiny networks gain nothing from threads, and one is reproducible).
    Returns the module in eval mode and the last epoch's mean training loss.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        n = x.shape[0]
        torch.manual_seed(seed)
        generator = torch.Generator().manual_seed(seed)
        module = MLNN(N_FEATURES, hidden, batch_norm=batch_norm, dropout=dropout, out_dim=out_dim)
        optimiser = torch.optim.Adam([*module.parameters(), *loss_fn.parameters()], lr=lr, weight_decay=weight_decay)

        epoch_iter: Any = range(epochs)
        if progress:
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
                epoch_iter.set_postfix(loss=f"{last_loss:.4f}", refresh=False)
        module.eval()
    finally:
        torch.set_num_threads(threads)
    return module, last_loss

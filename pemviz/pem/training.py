"""Training the network PEMs: the recipes' shared part (:class:`Recipe`, :class:`NetworkRecipe`), the paper's ML-NN
(:class:`PemRecipe`, :func:`train_pem`; Innes & Ramamoorthy 2022, Sec. IV-A, the authors' ``train_tp_pem_det.py``)
and the training loop :func:`fit_network` the noise PEM shares. Imports torch; the returned
:class:`~pemviz.pem.network.PEM` is evaluated without it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import numpy as np

from pemviz.pem.encoding import N_FEATURES, NormStats, check_training_data, encode_salient, fit_norm_stats
from pemviz.pem.network import PEM

if TYPE_CHECKING:  # annotations only: these import torch
    import torch

    from pemviz.pem.modules import MLNN

_Model = TypeVar("_Model")


class Recipe(Generic[_Model]):
    """What every recipe shares: ``train`` with the recipe's ``seed`` / ``epochs`` unless overridden (every recipe
    is a frozen dataclass with at least these fields)."""

    name: str
    epochs: int
    seed: int

    def train(
        self,
        inputs: np.ndarray,
        targets: np.ndarray,
        *,
        seed: int | None = None,
        epochs: int | None = None,
        norm: NormStats | None = None,
        progress: bool = False,
        metadata: Mapping[str, Any] | None = None,
    ) -> _Model:
        """Train on raw inputs ``[M, F]`` and the recipe's targets (detection labels ``[M]`` in {0, 1}, or metric
        errors ``[M, 2]`` in metres for a noise PEM); ``seed`` / ``epochs`` override the recipe's (``epochs`` is the
        number of trees of a tree PEM, which draws no progress bar)."""
        recipe = replace(  # type: ignore[type-var]  # every recipe is a dataclass
            self, epochs=self.epochs if epochs is None else epochs, seed=self.seed if seed is None else seed
        )
        metadata = {"recipe": self.name, **dict(metadata or {})}
        return recipe._fit(inputs, targets, norm=norm, progress=progress, metadata=metadata)

    def _fit(
        self, inputs: np.ndarray, targets: np.ndarray, /, *, norm: NormStats | None, progress: bool, metadata: Any
    ) -> _Model:
        raise NotImplementedError


@dataclass(frozen=True)
class NetworkRecipe(Recipe[_Model]):
    """A network PEM's name and the settings :func:`fit_network` reads: the ``hidden`` layers' widths, and Adam's
    ``epochs``, ``batch_size``, ``lr``, ``weight_decay`` (its L2 term) and ``seed``."""

    name: str
    description: str
    hidden: tuple[int, ...] = (20, 20)
    epochs: int = 300
    batch_size: int = 1024
    lr: float = 1e-3
    weight_decay: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class PemRecipe(NetworkRecipe[PEM]):
    """An ML-NN-style PEM: the architecture and optimiser settings of :func:`train_pem` (default: the paper's 20-20
    with BatchNorm)."""

    batch_norm: bool = True
    dropout: float = 0.0

    def _fit(self, inputs: np.ndarray, labels: np.ndarray, /, **common: Any) -> PEM:
        return train_pem(self, inputs, labels, **common)


def train_pem(
    recipe: PemRecipe,
    inputs: np.ndarray,
    labels: np.ndarray,
    *,
    norm: NormStats | None = None,
    progress: bool = False,
    metadata: Mapping[str, Any] | None = None,
) -> PEM:
    """Train a PEM network with a recipe's architecture and optimiser settings (the paper's: Innes & Ramamoorthy
    (2022), Sec. V): BCE with logits, Adam (lr 1e-3), mini-batches of 1024 reshuffled every epoch, 300 epochs,
    float32, seeded: the same seed gives the same weights on the same torch build.

    Args:
        recipe: the name, architecture (hidden, batch_norm, dropout), optimiser settings (epochs, batch_size, lr,
            weight_decay) and seed.
        inputs: raw salient inputs ``[N, 11]`` (KITTI layout).
        labels: detected, ``[N]`` in {0, 1}.
        norm: z-score statistics; default: fitted on ``inputs`` (the spec fits them on the full file,
            also when training on a cross-validation fold).
        progress: show a tqdm progress bar over epochs.
        metadata: extra provenance stored with the PEM.
    Returns:
        The trained :class:`PEM` (eval mode).
    Raises:
        ValueError: mismatched lengths, labels not in {0, 1}, bad encodings, epochs < 1 or batch_size < 2."""
    import torch
    from torch import nn

    raw, y = check_training_data(inputs, labels)
    if recipe.epochs < 1 or recipe.batch_size < 2:
        raise ValueError(f"need epochs >= 1 and batch_size >= 2, got {recipe.epochs}, {recipe.batch_size}")
    norm = norm if norm is not None else fit_norm_stats(raw)
    x = torch.as_tensor(encode_salient(raw, norm), dtype=torch.float32)
    t = torch.as_tensor(y, dtype=torch.float32).unsqueeze(1)
    module, last_loss, meta = fit_network(
        x, t, recipe, nn.BCEWithLogitsLoss(), batch_norm=recipe.batch_norm, dropout=recipe.dropout, progress=progress
    )
    meta.update(dropout=float(recipe.dropout), n_train=int(x.shape[0]), final_epoch_train_bce=float(last_loss))
    meta.update(torch_version=str(torch.__version__), **dict(metadata or {}))
    hidden, batch_norm = recipe.hidden, recipe.batch_norm
    return PEM.from_module(module, norm, name=recipe.name, hidden=hidden, batch_norm=batch_norm, metadata=meta)


def fit_network(
    x: torch.Tensor,
    t: torch.Tensor,
    recipe: NetworkRecipe[Any],
    loss_fn: torch.nn.Module,
    *,
    batch_norm: bool = False,
    dropout: float = 0.0,
    progress: bool = False,
    out_dim: int = 1,
) -> tuple[MLNN, float, dict[str, Any]]:
    """The training loop of :func:`train_pem` and the noise PEM: an :class:`MLNN` with ``out_dim`` outputs on
    float32 ``x [N, 14]`` and targets ``t [N, ...]`` minimising ``loss_fn(module(x[batch]), t[batch])`` by Adam over
    the network's and the loss's parameters, seeded shuffles and weights, one CPU thread. Returns the module in eval
    mode, the last epoch's mean loss and the settings as metadata."""
    import torch
    from tqdm.auto import tqdm

    from pemviz.pem.modules import MLNN

    seed, epochs, batch_size, lr, weight_decay = (
        recipe.seed,
        recipe.epochs,
        recipe.batch_size,
        recipe.lr,
        recipe.weight_decay,
    )
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        n = x.shape[0]
        torch.manual_seed(seed)
        generator = torch.Generator().manual_seed(seed)
        module = MLNN(N_FEATURES, recipe.hidden, batch_norm=batch_norm, dropout=dropout, out_dim=out_dim)
        optimiser = torch.optim.Adam([*module.parameters(), *loss_fn.parameters()], lr=lr, weight_decay=weight_decay)

        epoch_iter: Any = range(epochs)
        if progress:
            epoch_iter = tqdm(epoch_iter, desc=f"train {recipe.name}", unit="epoch", mininterval=0.5)
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
    meta = {"seed": int(seed), "epochs": int(epochs), "batch_size": int(batch_size), "lr": float(lr)}
    return module, last_loss, {**meta, "weight_decay": float(weight_decay)}

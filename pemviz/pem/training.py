"""Training the paper's ML-NN PEM (Innes & Ramamoorthy 2022, Sec. IV-A: BCE with logits, Adam lr 1e-3, batch
1024, 300 epochs, eval mode; the authors' ``train_tp_pem_det.py``): :func:`train_pem`, and the training loop
:func:`fit_network` that the noise PEM (:mod:`pemviz.pem.noise`) shares. Both import torch (about 1 s) when
called; the :class:`~pemviz.pem.network.PEM` they return is evaluated without it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.pem.encoding import N_FEATURES, NormStats, check_training_data, encode_salient, fit_norm_stats
from pemviz.pem.network import PEM

if TYPE_CHECKING:  # annotations only: these import torch
    import torch

    from pemviz.pem.modules import MLNN


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
    """Train a PEM network with the paper's recipe (Innes & Ramamoorthy (2022), Sec. V; the authors'
    ``train_tp_pem_det.py``).

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
    import torch
    from torch import nn

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
    loss_fn: torch.nn.Module,
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
    import torch
    from tqdm.auto import tqdm

    from pemviz.pem.modules import MLNN

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

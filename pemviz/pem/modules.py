"""The torch modules of the PEMs, for training: the ML-NN network (:class:`MLNN`) and the noise PEM's loss
(:class:`NoiseNLL`). Imports torch; evaluating or loading a PEM does not need it (:mod:`pemviz.pem.network`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import torch
from torch import nn

from pemviz.pem.encoding import N_FEATURES


class MLNN(nn.Module):
    """The paper's ML-NN (and its wider / deeper variants): ``ff_nn`` = [Linear, BatchNorm?, ReLU, Dropout?]
    per hidden layer, then Linear(h, out_dim) -> logit ``[N, 1]`` (or the noise PEM's ``[N, 4]``, see
    :mod:`pemviz.pem.noise`).

    With ``hidden=(20, 20)``, ``batch_norm=True``, ``dropout=0`` the state-dict keys are the authors'
    (``ff_nn.{0,1,3,4,6}.*``), so their weights load directly; :func:`pemviz.pem.network.mlnn_shapes` lists them."""

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


class NoiseNLL(nn.Module):
    """Mean negative log-likelihood (nats per obstacle, summed over the 2 dimensions) of targets ``[B, 2]``
    (errors over the target scale) under the network's outputs ``[B, 4]`` = (loc, log scale), with
    ``torch.distributions`` (``Normal``, ``Laplace``, ``StudentT``; the Student-t's 2 degrees of freedom
    ``DF_MIN + softplus(df_raw)`` are trained with the network).

    Raises:
        ValueError: a family not in ``FAMILIES``."""

    FAMILIES: ClassVar[tuple[str, ...]] = ("normal", "laplace", "student-t")
    """:data:`pemviz.pem.noise.FAMILIES` (that module does not import this one; a test keeps the two equal)."""
    DF_MIN: ClassVar[float] = 1.0
    """:data:`pemviz.pem.noise.DF_MIN` (a test keeps the two equal)."""

    def __init__(self, family: str) -> None:
        super().__init__()
        if family not in self.FAMILIES:
            raise ValueError(f"noise family {family!r}: use one of {', '.join(self.FAMILIES)}")
        self.family = family
        self.df_raw = nn.Parameter(torch.zeros(2)) if family == "student-t" else None

    def df(self) -> torch.Tensor:
        assert self.df_raw is not None
        return self.DF_MIN + nn.functional.softplus(self.df_raw)

    def forward(self, out: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        loc, scale = out[:, :2], torch.exp(out[:, 2:])
        dist: torch.distributions.Distribution
        if self.family == "normal":
            dist = torch.distributions.Normal(loc, scale)
        elif self.family == "laplace":
            dist = torch.distributions.Laplace(loc, scale)
        else:
            dist = torch.distributions.StudentT(self.df(), loc, scale)
        return -dist.log_prob(target).sum(dim=1).mean()

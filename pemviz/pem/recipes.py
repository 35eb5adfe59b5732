"""Named PEMs: how ``pemviz pem train --model NAME`` (re)trains each shipped PEM.

- ``ml-nn``: the paper's ML-NN (Innes & Ramamoorthy (2022), Table I), shipped as ``pemviz/assets/pem_ml-nn.pt``.
- ``gbt``: gradient-boosted trees on the same 14 features, the best model of pemviz's 5-fold
  cross-validation, shipped as ``pemviz/assets/pem_gbt.pt``.

- ``hetero-t``: the noise PEM (heteroscedastic Student-t, :mod:`pemviz.pem.noise`), chosen by 5-fold cross-validated
  NLL against Normal and Laplace heads and the homoscedastic baselines, shipped as ``pemviz/assets/noise_hetero-t.pt``.

``seed`` is the seed of the shipped weights; ``pemviz/assets/README.md`` says why each was chosen.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np

from pemviz.pem.encoding import NormStats
from pemviz.pem.network import PEM
from pemviz.pem.training import train_pem
from pemviz.pem.noise import NoisePEM, train_noise_pem
from pemviz.pem.trees import TreePEM, train_tree_pem

DEFAULT_PEM_NAME = "ml-nn"
"""The PEM :func:`pemviz.pem.load_pem` loads when given no name."""
BEST_PEM_NAME = "gbt"
"""The best cross-validated PEM (by 5-fold cross-validated BCE and ROC-AUC)."""
DEFAULT_NOISE_NAME = "hetero-t"
"""The noise PEM :func:`pemviz.pem.load_noise_pem` loads when given no name."""


_Model = TypeVar("_Model")


class _Recipe(Generic[_Model]):
    """What the recipes below share: ``train`` with the recipe's ``seed`` / ``epochs`` unless overridden."""

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
        return self._fit(
            inputs,
            targets,
            epochs=self.epochs if epochs is None else epochs,
            seed=self.seed if seed is None else seed,
            norm=norm,
            progress=progress,
            metadata={"recipe": self.name, **dict(metadata or {})},
        )

    def _fit(
        self,
        inputs: np.ndarray,
        targets: np.ndarray,
        /,
        *,
        epochs: int,
        seed: int,
        norm: NormStats | None,
        progress: bool,
        metadata: dict[str, Any],
    ) -> _Model:
        raise NotImplementedError


@dataclass(frozen=True)
class PemRecipe(_Recipe[PEM]):
    """An ML-NN-style PEM: the architecture and optimiser settings passed to :func:`pemviz.pem.training.train_pem`."""

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

    def _fit(self, inputs: np.ndarray, labels: np.ndarray, /, **common: Any) -> PEM:
        return train_pem(
            inputs,
            labels,
            name=self.name,
            hidden=self.hidden,
            batch_norm=self.batch_norm,
            dropout=self.dropout,
            batch_size=self.batch_size,
            lr=self.lr,
            weight_decay=self.weight_decay,
            **common,
        )


@dataclass(frozen=True)
class TreeRecipe(_Recipe[TreePEM]):
    """A boosted-trees PEM: the settings passed to :func:`train_tree_pem` (``epochs`` = number of trees)."""

    name: str
    description: str
    learning_rate: float = 0.05
    epochs: int = 300
    max_leaf_nodes: int = 63
    min_samples_leaf: int = 20
    l2_regularization: float = 1.0
    seed: int = 0

    def _fit(self, inputs: np.ndarray, labels: np.ndarray, /, *, epochs: int, progress: bool, **common: Any) -> TreePEM:
        return train_tree_pem(
            inputs,
            labels,
            name=self.name,
            learning_rate=self.learning_rate,
            max_iter=epochs,
            max_leaf_nodes=self.max_leaf_nodes,
            min_samples_leaf=self.min_samples_leaf,
            l2_regularization=self.l2_regularization,
            **common,
        )


PEM_RECIPES: dict[str, PemRecipe | TreeRecipe] = {
    "ml-nn": PemRecipe(
        name="ml-nn",
        description="the paper's ML-NN: 14-20-20-1 with BatchNorm, Adam 1e-3, batch 1024, 300 epochs",
        seed=2,
    ),
    "gbt": TreeRecipe(
        name="gbt",
        description="gradient-boosted trees (scikit-learn HistGradientBoosting) on the same 14 features: "
        "300 trees of 63 leaves, learning rate 0.05, L2 1.0",
    ),
}
"""Named PEMs that ``pemviz pem train --model NAME`` can (re)train."""


@dataclass(frozen=True)
class NoiseRecipe(_Recipe[NoisePEM]):
    """A heteroscedastic noise PEM: the family, architecture and optimiser settings passed to
    :func:`train_noise_pem`."""

    name: str
    description: str
    family: str = "student-t"
    hidden: tuple[int, ...] = (32, 32)
    epochs: int = 100
    batch_size: int = 512
    lr: float = 3e-3
    weight_decay: float = 0.0
    seed: int = 0

    def _fit(self, inputs: np.ndarray, errors: np.ndarray, /, **common: Any) -> NoisePEM:
        return train_noise_pem(
            inputs,
            errors,
            name=self.name,
            family=self.family,
            hidden=self.hidden,
            batch_size=self.batch_size,
            lr=self.lr,
            weight_decay=self.weight_decay,
            **common,
        )


NOISE_RECIPES: dict[str, NoiseRecipe] = {
    "hetero-t": NoiseRecipe(
        name="hetero-t",
        description="heteroscedastic noise PEM: 14-32-32-4 ReLU network -> Student-t location and log scale per "
        "dimension (range, lateral), one learned degrees of freedom each; Adam 3e-3, batch 512, 100 epochs",
    ),
}
"""Named noise PEMs that ``pemviz pem train --model NAME`` can (re)train."""

"""A gradient-boosted-trees PEM (scikit-learn's HistGradientBoostingClassifier) on the same 14 features, pemviz's best
by 5-fold cross-validation on the paper's folds (``pemviz.studies.pem_eval``).

scikit-learn fits the trees; pemviz exports them into flat float64 / int arrays (no pickle) and evaluates them
itself: :meth:`TreePEM.logit` walks all trees at once (equal to scikit-learn's ``decision_function`` to summation
order, tested), and :meth:`TreePEM.logit_at_gap` is one ``searchsorted`` into the piecewise-constant function of the
gap."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from scipy.special import expit

from pemviz.pem.encoding import (
    BRAKING_Z_FEATURE,
    N_FEATURES,
    NormStats,
    braking_features_at_z,
    braking_z_scored,
    check_features,
    check_training_data,
    encode_salient,
    fit_norm_stats,
)
from pemviz.pem.training import Recipe

TREE_ARRAYS = ("feature", "threshold", "left", "right", "is_leaf", "value", "roots")


@dataclass(frozen=True, eq=False)
class TreePEM:
    """A boosted-trees PEM: ``logit = baseline + sum over trees of the leaf value`` reached by the row.

    Arrays over all nodes of all trees (``M`` nodes, ``T`` trees): ``feature`` int64 ``[M]`` (index into the
    14 features), ``threshold`` float64 ``[M]`` (go left when ``x[feature] <= threshold``), ``left``,
    ``right`` int64 ``[M]`` (global node indices), ``is_leaf`` bool ``[M]``, ``value`` float64 ``[M]``
    (leaf values, nats), ``roots`` int64 ``[T]``."""

    kind: ClassVar[str] = "gbt"

    name: str
    norm: NormStats
    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    is_leaf: np.ndarray
    value: np.ndarray
    roots: np.ndarray
    baseline: float
    metadata: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        arrays = {
            "feature": np.asarray(self.feature, dtype=np.int64),
            "threshold": np.asarray(self.threshold, dtype=np.float64),
            "left": np.asarray(self.left, dtype=np.int64),
            "right": np.asarray(self.right, dtype=np.int64),
            "is_leaf": np.asarray(self.is_leaf, dtype=bool),
            "value": np.asarray(self.value, dtype=np.float64),
            "roots": np.asarray(self.roots, dtype=np.int64),
        }
        m = arrays["feature"].shape[0]
        if any(arrays[k].shape != (m,) for k in TREE_ARRAYS if k != "roots") or arrays["roots"].ndim != 1:
            raise ValueError("TreePEM arrays must be 1-D, all node arrays of one length")
        internal = ~arrays["is_leaf"]
        if m == 0 or arrays["roots"].size == 0:
            raise ValueError("TreePEM needs at least one tree")
        if np.any((arrays["roots"] < 0) | (arrays["roots"] >= m)):
            raise ValueError("TreePEM roots out of range")
        if np.any(
            internal & ((arrays["left"] < 0) | (arrays["left"] >= m) | (arrays["right"] < 0) | (arrays["right"] >= m))
        ):
            raise ValueError("TreePEM child index out of range")
        if np.any(internal & ((arrays["feature"] < 0) | (arrays["feature"] >= N_FEATURES))):
            raise ValueError(f"TreePEM feature index outside 0..{N_FEATURES - 1}")
        for k, v in arrays.items():
            object.__setattr__(self, k, v)
        object.__setattr__(self, "baseline", float(self.baseline))
        # Leaves point to themselves so that a fixed number of steps lands every row on its leaf.
        idx = np.arange(m)
        # derived from the fields, set on the frozen instance (not fields)
        self._left: np.ndarray
        self._right: np.ndarray
        self._feature: np.ndarray
        self._depth: int
        self._gap_z_thresholds: np.ndarray
        self._gap_values: np.ndarray
        object.__setattr__(self, "_left", np.where(internal, arrays["left"], idx))
        object.__setattr__(self, "_right", np.where(internal, arrays["right"], idx))
        object.__setattr__(self, "_feature", np.where(internal, arrays["feature"], 0))
        object.__setattr__(self, "_depth", _max_depth(arrays["roots"], self._left, self._right, internal))
        # Braking table: the loc_z thresholds, and the logit on each step (represented by its right end,
        # which belongs to it since the trees go left on <=).
        z_thr = np.unique(arrays["threshold"][internal & (arrays["feature"] == BRAKING_Z_FEATURE)])
        reps = np.append(z_thr, (z_thr[-1] + 1.0) if z_thr.size else 0.0)
        object.__setattr__(self, "_gap_z_thresholds", z_thr)
        object.__setattr__(self, "_gap_values", self.logit_features(braking_features_at_z(reps, self.norm)))

    # -- evaluation -----------------------------------------------------------------------------
    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        """The 14 encoded features float64 ``[N, 14]`` of raw salient inputs ``[N, 11]``."""
        return encode_salient(raw_inputs, self.norm)

    def logit_features(self, features: np.ndarray, *, chunk: int = 4096) -> np.ndarray:
        """Logit of p(detect), float64 ``[N]``, from encoded features ``[N, 14]`` (rows in chunks)."""
        x = check_features(features)
        out = np.empty(x.shape[0], dtype=np.float64)
        for start in range(0, x.shape[0], chunk):
            xs = x[start : start + chunk]
            node = np.broadcast_to(self.roots, (xs.shape[0], self.roots.shape[0])).copy()  # [n, T]
            rows = np.arange(xs.shape[0])[:, None]
            for _ in range(self._depth):
                go_left = xs[rows, self._feature[node]] <= self.threshold[node]
                node = np.where(go_left, self._left[node], self._right[node])
            out[start : start + chunk] = self.baseline + self.value[node].sum(axis=1)
        return out

    def logit(self, raw_inputs: np.ndarray) -> np.ndarray:
        """Logit of p(detect) for raw salient inputs ``[N, 11]`` (KITTI layout), float64 ``[N]``.

        Raises:
            ValueError: see :func:`pemviz.pem.encode_salient`."""
        return self.logit_features(encode_salient(raw_inputs, self.norm))

    def logit_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """Logit of p(detect) of the braking scenario's lead car at ``gap_m`` metres (any shape; same shape out):
        exactly ``self.logit(braking_salient_inputs(gap_m))``, looked up in the precomputed step table."""
        zn = braking_z_scored(gap_m, self.norm)
        return self._gap_values[np.searchsorted(self._gap_z_thresholds, zn, side="left")]

    def prob_at_gap(self, gap_m: np.ndarray) -> np.ndarray:
        """p(detect) at ``gap_m`` (sigmoid of :meth:`logit_at_gap`), float64, shape of ``gap_m``."""
        return expit(self.logit_at_gap(gap_m))

    def prob(self, raw_inputs: np.ndarray) -> np.ndarray:
        """p(detect) for raw salient inputs ``[N, 11]``, float64 ``[N]``."""
        return expit(self.logit(raw_inputs))

    def arrays(self) -> dict[str, np.ndarray]:
        """The node arrays by name (what :func:`pemviz.pem.save_pem` stores)."""
        return {k: getattr(self, k) for k in TREE_ARRAYS}


def _max_depth(roots: np.ndarray, left: np.ndarray, right: np.ndarray, internal: np.ndarray) -> int:
    depth, frontier = 0, roots[internal[roots]]
    while frontier.size:
        depth += 1
        children = np.concatenate([left[frontier], right[frontier]])
        frontier = children[internal[children]]
        if depth > internal.size:
            raise ValueError("TreePEM nodes contain a cycle")
    return depth


def export_hist_gradient_boosting(
    model: Any, norm: NormStats, *, name: str, metadata: Mapping[str, Any] | None = None
) -> TreePEM:
    """Flatten a fitted binary ``sklearn.ensemble.HistGradientBoostingClassifier`` (numeric features, no missing
    values; its ``_predictors`` and ``_baseline_prediction``) into a :class:`TreePEM`, tested against
    ``decision_function``.

    Raises:
        ValueError: a multi-class model or categorical splits."""
    predictors = model._predictors  # noqa: SLF001 (the fitted trees; no public accessor)
    if any(len(p) != 1 for p in predictors):
        raise ValueError("only binary classifiers can be exported")
    feature, threshold, left, right, is_leaf, value, roots = [], [], [], [], [], [], []
    offset = 0
    for (tree,) in predictors:
        nodes = tree.nodes
        if np.any(nodes["is_categorical"]):
            raise ValueError("categorical splits are not supported: encode categories as one-hot features")
        roots.append(offset)
        feature.append(nodes["feature_idx"].astype(np.int64))
        threshold.append(nodes["num_threshold"].astype(np.float64))
        left.append(nodes["left"].astype(np.int64) + offset)
        right.append(nodes["right"].astype(np.int64) + offset)
        is_leaf.append(nodes["is_leaf"].astype(bool))
        value.append(nodes["value"].astype(np.float64))
        offset += nodes.shape[0]
    baseline = float(np.asarray(model._baseline_prediction).reshape(-1)[0])  # noqa: SLF001
    return TreePEM(
        name=name,
        norm=norm,
        feature=np.concatenate(feature),
        threshold=np.concatenate(threshold),
        left=np.concatenate(left),
        right=np.concatenate(right),
        is_leaf=np.concatenate(is_leaf),
        value=np.concatenate(value),
        roots=np.asarray(roots, dtype=np.int64),
        baseline=baseline,
        metadata=dict(metadata or {}),
    )


@dataclass(frozen=True)
class TreeRecipe(Recipe[TreePEM]):
    """A boosted-trees PEM: the settings of :func:`train_tree_pem` (``epochs``: the number of trees), passed to
    scikit-learn's ``HistGradientBoostingClassifier``."""

    name: str
    description: str
    learning_rate: float = 0.05
    epochs: int = 300
    max_leaf_nodes: int = 63
    min_samples_leaf: int = 20
    l2_regularization: float = 1.0
    seed: int = 0

    def _fit(self, inputs: np.ndarray, labels: np.ndarray, /, *, progress: bool, **common: Any) -> TreePEM:
        return train_tree_pem(self, inputs, labels, **common)


def train_tree_pem(
    recipe: TreeRecipe,
    inputs: np.ndarray,
    labels: np.ndarray,
    *,
    norm: NormStats | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> TreePEM:
    """Fit gradient-boosted trees (log-loss, no early stopping) on the 14 encoded features; one thread.

    Args:
        recipe: the name and the settings passed to ``HistGradientBoostingClassifier`` (``epochs``: its ``max_iter``,
            the number of trees; ``seed``: its ``random_state``, the fit is deterministic without early stopping).
        inputs: raw salient inputs ``[N, 11]``.
        labels: the detections ``[N]`` in {0, 1}.
        norm: z-score statistics (default: fitted on ``inputs``; pemviz uses the full file's).
        metadata: extra provenance stored with the model.
    Raises:
        ValueError: mismatched lengths or labels not in {0, 1}."""
    from sklearn.ensemble import HistGradientBoostingClassifier
    from threadpoolctl import threadpool_limits

    raw, y = check_training_data(inputs, labels)
    norm = norm if norm is not None else fit_norm_stats(raw)
    settings = ("learning_rate", "max_leaf_nodes", "min_samples_leaf", "l2_regularization")
    model = HistGradientBoostingClassifier(
        **{k: getattr(recipe, k) for k in settings},
        max_iter=recipe.epochs,
        early_stopping=False,
        random_state=recipe.seed,
    )
    # One OpenMP thread: on a busy 2-core machine, 2 threads measured 40x slower (spin-waiting).
    with threadpool_limits(1):
        model.fit(encode_salient(raw, norm), y.astype(np.int64))
    meta = {
        "model": "sklearn.ensemble.HistGradientBoostingClassifier",
        "learning_rate": float(recipe.learning_rate),
        "max_iter": int(recipe.epochs),
        "max_leaf_nodes": int(recipe.max_leaf_nodes),
        "min_samples_leaf": int(recipe.min_samples_leaf),
        "l2_regularization": float(recipe.l2_regularization),
        "seed": int(recipe.seed),
        "n_train": int(raw.shape[0]),
    }
    meta.update(dict(metadata or {}))
    return export_hist_gradient_boosting(model, norm, name=recipe.name, metadata=meta)

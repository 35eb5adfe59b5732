"""Perception error models (PEMs): salient variables of an obstacle -> logit of p(detected).

Innes & Ramamoorthy 2022, Sec. IV-A and Table I. Two kinds, one interface (``name``,
``norm``, ``metadata``, ``features``, ``logit``, ``logit_at_gap``, ``prob``, ``prob_at_gap``):

- :class:`PEM`: the paper's ML-NN (and wider variants), trained with torch, evaluated in float64 numpy;
- :class:`TreePEM`: gradient-boosted trees on the same 14 features, the best cross-validated model.

Modules: ``encoding`` (14-dim input, braking scenario mapping), ``network`` (ML-NN), ``trees`` (boosted
trees), ``recipes`` (named PEMs of ``pemviz pem train``), ``store`` (files, assets, the authors' PEM).
"""

from pemviz.pem.encoding import (
    BRAKING_CAMERA_TO_LEAD_CENTRE_M,
    BRAKING_LOC_X_M,
    BRAKING_LOC_Y_M,
    BRAKING_ROT_Y_RAD,
    BRAKING_Z_FEATURE,
    N_CLASSES,
    N_FEATURES,
    N_OCCLUSIONS,
    POSE_COLUMNS,
    NormStats,
    bce_from_logits,
    braking_features_at_z,
    braking_salient_inputs,
    braking_z_scored,
    encode_salient,
    fit_norm_stats,
)
from pemviz.pem.network import MLNN, PEM, PemFormatError, train_pem
from pemviz.pem.recipes import BEST_PEM_NAME, DEFAULT_PEM_NAME, PEM_RECIPES, PemRecipe, TreeRecipe
from pemviz.pem.store import (
    ASSETS_DIR_ENV,
    AnyPEM,
    assets_dir,
    load_pem,
    load_reference_pem,
    pem_path,
    reference_pem_dir,
    resolve_pem,
    save_pem,
    shipped_pems,
)
from pemviz.pem.trees import TreePEM, export_hist_gradient_boosting, train_tree_pem

__all__ = [
    "ASSETS_DIR_ENV",
    "BEST_PEM_NAME",
    "BRAKING_CAMERA_TO_LEAD_CENTRE_M",
    "BRAKING_LOC_X_M",
    "BRAKING_LOC_Y_M",
    "BRAKING_ROT_Y_RAD",
    "BRAKING_Z_FEATURE",
    "DEFAULT_PEM_NAME",
    "MLNN",
    "N_CLASSES",
    "N_FEATURES",
    "N_OCCLUSIONS",
    "PEM",
    "PEM_RECIPES",
    "POSE_COLUMNS",
    "AnyPEM",
    "NormStats",
    "PemFormatError",
    "PemRecipe",
    "TreePEM",
    "TreeRecipe",
    "assets_dir",
    "bce_from_logits",
    "braking_features_at_z",
    "braking_salient_inputs",
    "braking_z_scored",
    "encode_salient",
    "export_hist_gradient_boosting",
    "fit_norm_stats",
    "load_pem",
    "load_reference_pem",
    "pem_path",
    "reference_pem_dir",
    "resolve_pem",
    "save_pem",
    "shipped_pems",
    "train_pem",
    "train_tree_pem",
]

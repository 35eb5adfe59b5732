"""Perception error models (PEMs): salient variables of an obstacle -> logit of p(detected).

Innes & Ramamoorthy 2022, Sec. IV-A and Table I. Two kinds, one interface (``name``,
``norm``, ``metadata``, ``features``, ``logit``, ``logit_at_gap``, ``prob``, ``prob_at_gap``):

- :class:`PEM`: the paper's ML-NN (and wider variants), trained with torch, evaluated in float64 numpy;
- :class:`TreePEM`: gradient-boosted trees on the same 14 features, the best cross-validated model.

Beyond detection, a noise PEM gives a detected obstacle's measurement error (range, lateral; metres):
:class:`NoisePEM` (heteroscedastic, the shipped ``hetero-t``) and :class:`HomoscedasticNoise` (the baseline), with
the interface ``noise_params``, ``log_prob``, ``cdf``, ``interval``, ``sample``; :class:`NoisyPEM` pairs a detection
head and a noise head.

Modules: ``encoding`` (14-dim input, braking scenario mapping), ``network`` (ML-NN), ``trees`` (boosted
trees), ``camera`` (pixel box errors -> metric errors), ``noise`` (noise PEMs), ``perception`` (:class:`NoisyPEM`),
``recipes`` (named PEMs of ``pemviz pem train``), ``store`` (files, assets, the authors' PEM), ``modules`` (the torch
modules for training: :class:`MLNN`, the noise loss).

Importing this package, loading a PEM and evaluating it do not import torch (about 1 s): the files are read into
numpy arrays (:mod:`pemviz.core.torch_payload`). ``MLNN`` is imported from :mod:`pemviz.pem.modules`, with torch, when
first named; training and :meth:`PEM.to_module` import torch.
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
from pemviz.pem.camera import KITTI_FOCAL_PX, MIN_RANGE_M, box_errors_to_metric
from pemviz.pem.network import PEM, PemFormatError
from pemviz.pem.training import train_pem
from pemviz.pem.noise import (
    FAMILIES,
    NOISE_DIMS,
    HomoscedasticNoise,
    NoiseData,
    NoiseModel,
    NoisePEM,
    fit_homoscedastic,
    noise_training_data,
    train_noise_pem,
)
from pemviz.pem.perception import NoisyPEM
from pemviz.pem.recipes import (
    BEST_PEM_NAME,
    DEFAULT_NOISE_NAME,
    DEFAULT_PEM_NAME,
    NOISE_RECIPES,
    PEM_RECIPES,
    NoiseRecipe,
    PemRecipe,
    TreeRecipe,
)
from pemviz.pem.store import (
    ASSETS_DIR_ENV,
    AnyPEM,
    assets_dir,
    load_noise_pem,
    load_noisy_pem,
    load_pem,
    load_reference_pem,
    noise_pem_path,
    pem_path,
    reference_pem_dir,
    resolve_pem,
    save_noise_pem,
    save_noisy_pem,
    save_pem,
    shipped_noise_pems,
    shipped_pems,
)
from pemviz.pem.trees import TreePEM, export_hist_gradient_boosting, train_tree_pem


def __getattr__(name: str) -> object:
    """``MLNN``, the torch module, imported when first named (torch takes about 1 s to import)."""
    if name == "MLNN":
        from pemviz.pem.modules import MLNN

        return MLNN
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "ASSETS_DIR_ENV",
    "BEST_PEM_NAME",
    "BRAKING_CAMERA_TO_LEAD_CENTRE_M",
    "BRAKING_LOC_X_M",
    "BRAKING_LOC_Y_M",
    "BRAKING_ROT_Y_RAD",
    "BRAKING_Z_FEATURE",
    "DEFAULT_NOISE_NAME",
    "DEFAULT_PEM_NAME",
    "FAMILIES",
    "KITTI_FOCAL_PX",
    "MIN_RANGE_M",
    "MLNN",
    "NOISE_DIMS",
    "NOISE_RECIPES",
    "N_CLASSES",
    "N_FEATURES",
    "N_OCCLUSIONS",
    "PEM",
    "PEM_RECIPES",
    "POSE_COLUMNS",
    "AnyPEM",
    "HomoscedasticNoise",
    "NoiseData",
    "NoiseModel",
    "NoisePEM",
    "NoiseRecipe",
    "NoisyPEM",
    "NormStats",
    "PemFormatError",
    "PemRecipe",
    "TreePEM",
    "TreeRecipe",
    "assets_dir",
    "bce_from_logits",
    "box_errors_to_metric",
    "braking_features_at_z",
    "braking_salient_inputs",
    "braking_z_scored",
    "encode_salient",
    "export_hist_gradient_boosting",
    "fit_homoscedastic",
    "fit_norm_stats",
    "load_noise_pem",
    "load_noisy_pem",
    "load_pem",
    "load_reference_pem",
    "noise_pem_path",
    "noise_training_data",
    "pem_path",
    "reference_pem_dir",
    "resolve_pem",
    "save_noise_pem",
    "save_noisy_pem",
    "save_pem",
    "shipped_noise_pems",
    "shipped_pems",
    "train_noise_pem",
    "train_pem",
    "train_tree_pem",
]

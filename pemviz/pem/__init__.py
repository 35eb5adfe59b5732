"""Perception error models (PEMs): salient variables of an obstacle -> logit of p(detected).

Innes & Ramamoorthy 2022, Sec. IV-A and Table I. Two kinds, one interface (``name``,
``norm``, ``metadata``, ``features``, ``logit``, ``logit_at_gap``, ``prob``, ``prob_at_gap``):

- :class:`PEM`: the paper's ML-NN (and wider variants), trained with torch, evaluated in float64 numpy;
- :class:`TreePEM`: gradient-boosted trees on the same 14 features, the best cross-validated model.

Beyond detection, a noise PEM gives a detected obstacle's measurement error (range, lateral; metres):
:class:`~pemviz.pem.noise.NoisePEM` (heteroscedastic, the shipped ``hetero-t``) and
:class:`~pemviz.pem.noise.HomoscedasticNoise` (the baseline), with the interface ``noise_params``, ``log_prob``,
``cdf``, ``interval``, ``sample``; :class:`NoisyPEM` pairs a detection head and a noise head.

Modules: ``encoding`` (14-dim input, braking scenario mapping), ``network`` (ML-NN), ``trees`` (boosted
trees), ``camera`` (pixel box errors -> metric errors), ``noise`` (noise PEMs), ``perception`` (:class:`NoisyPEM`),
``recipes`` (named PEMs of ``pemviz pem train``), ``store`` (files, assets, the authors' PEM), ``modules`` (the torch
modules for training: :class:`~pemviz.pem.modules.MLNN`, the noise loss).

This package's names (:data:`__all__`) are the ones the user guide imports from it: the two kinds of PEM and the
noisy one, the PEM's inputs (:func:`encode_salient`, :func:`fit_norm_stats`, :func:`braking_salient_inputs`) and the
files (:func:`load_pem`, :func:`save_pem`, :func:`shipped_pems`, :func:`resolve_pem`, :func:`load_noise_pem`,
:func:`save_noisy_pem`, :func:`load_noisy_pem`); every other name has one import path, its module's.

Importing this package, loading a PEM and evaluating it do not import torch (about 1 s): the files are read into
numpy arrays (:mod:`pemviz.core.torch_payload`). Training, :meth:`PEM.to_module` and :mod:`pemviz.pem.modules`
(``from pemviz.pem.modules import MLNN``) import torch.
"""

from pemviz.pem.encoding import braking_salient_inputs, encode_salient, fit_norm_stats
from pemviz.pem.network import PEM
from pemviz.pem.perception import NoisyPEM
from pemviz.pem.store import (
    load_noise_pem,
    load_noisy_pem,
    load_pem,
    resolve_pem,
    save_noisy_pem,
    save_pem,
    shipped_pems,
)
from pemviz.pem.trees import TreePEM

__all__ = [
    "PEM",
    "NoisyPEM",
    "TreePEM",
    "braking_salient_inputs",
    "encode_salient",
    "fit_norm_stats",
    "load_noise_pem",
    "load_noisy_pem",
    "load_pem",
    "resolve_pem",
    "save_noisy_pem",
    "save_pem",
    "shipped_pems",
]

"""Perception error models (PEMs): salient variables of an obstacle -> logit of p(detected).

Innes & Ramamoorthy 2022, Sec. IV-A and Table I. Two kinds, one interface (``name``, ``norm``, ``metadata``,
``features``, ``logit``, ``logit_at_gap``, ``prob``, ``prob_at_gap``): :class:`PEM`, the paper's ML-NN evaluated in
float64 numpy, and :class:`TreePEM`, gradient-boosted trees on the same 14 features. A noise PEM gives a detected
obstacle's measurement error (range, lateral; metres): :class:`~pemviz.pem.noise.NoisePEM` and
:class:`~pemviz.pem.noise.HomoscedasticNoise`; :class:`NoisyPEM` pairs a detection head and a noise head.

:data:`__all__` holds the names the user guide imports from here; every other name has one import path, its
module's. Importing this package, loading a PEM and evaluating it do not import torch
(:mod:`pemviz.core.torch_payload`); training, :meth:`PEM.to_module` and :mod:`pemviz.pem.modules` do."""

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

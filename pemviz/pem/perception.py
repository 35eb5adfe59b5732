"""A perception model with two heads: whether an obstacle is detected, and if so how wrong its measurement is.

Per obstacle and step, with ``x`` the 14-dim encoding of its salient variables:

    p(a, e | x) = p_PEM(a | x) * p_noise(e | x)^a,    a in {0, 1} (missed, detected), e = (dZ, dX) metres,

the detection head any PEM (:class:`pemviz.pem.PEM`, :class:`pemviz.pem.TreePEM`: a logit of p(detected); Innes &
Ramamoorthy 2022, Sec. IV-A) and the noise head a :class:`pemviz.pem.noise.NoiseModel`. A missed obstacle has no
measurement, so its error does not enter the likelihood. ``pemviz.pem.store`` saves and loads the pair as one file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit, log_expit

from pemviz.pem.encoding import encode_salient
from pemviz.pem.network import PEM
from pemviz.pem.noise import NoiseModel
from pemviz.pem.trees import TreePEM


@dataclass(frozen=True, eq=False)
class NoisyPEM:
    """A detection head (``detect``: logit of p(detected)) and a noise head (``noise``) on the same 14 features.

    Both heads must share their z-score statistics (pemviz fits them on the full KITTI file), so one encoding
    (:meth:`features`) feeds both.

    Raises:
        ValueError: the heads' z-score statistics differ.
    """

    detect: PEM | TreePEM
    noise: NoiseModel

    def __post_init__(self) -> None:
        a, b = self.detect.norm, self.noise.norm
        if not (np.array_equal(a.mean, b.mean) and np.array_equal(a.std, b.std)):
            raise ValueError(
                f"the detection head {self.detect.name!r} and the noise head {self.noise.name!r} encode the salient "
                f"variables differently (z-score means {a.mean.tolist()} vs {b.mean.tolist()}); train both with the "
                "same statistics"
            )

    @property
    def name(self) -> str:
        return f"{self.detect.name}+{self.noise.name}"

    def features(self, raw_inputs: np.ndarray) -> np.ndarray:
        """The 14 encoded features float64 ``[R, 14]`` of raw salient inputs ``[R, 11]``
        (:func:`pemviz.pem.encode_salient`)."""
        return encode_salient(raw_inputs, self.detect.norm)

    def logit(self, features: np.ndarray) -> np.ndarray:
        """Logit of p(detected), float64 ``[R]`` (nats), of encoded features ``[R, 14]``."""
        return self.detect.logit_features(features)

    def noise_params(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The noise head's ``(loc [R, 2], log_scale [R, 2])`` (metres; log metres) of features ``[R, 14]``."""
        return self.noise.noise_params(features)

    def log_prob(self, features: np.ndarray, detected: np.ndarray, errors: np.ndarray) -> np.ndarray:
        """log p(detected, errors | features), float64 ``[R]``, nats:
        ``log_expit(+-logit) + detected * log p_noise(errors)``.

        Args:
            features: encoded features ``[R, 14]``.
            detected: bool ``[R]``.
            errors: ``[R, 2]`` (range, lateral; metres); ignored (may be NaN) where not detected.

        Raises:
            ValueError: shapes other than ``[R, 14]``, ``[R]`` and ``[R, 2]``.
        """
        x = np.asarray(features, dtype=np.float64)
        hit = np.asarray(detected, dtype=bool)
        err = np.asarray(errors, dtype=np.float64)
        if x.ndim != 2 or hit.shape != (x.shape[0],) or err.shape != (x.shape[0], 2):
            raise ValueError(f"need features [R, 14], detected [R] and errors [R, 2], got {x.shape}, {hit.shape}, "
                             f"{err.shape}")  # fmt: skip
        logit = self.logit(x)
        out = np.where(hit, log_expit(logit), log_expit(-logit))
        if np.any(hit):
            out[hit] += self.noise.log_prob(x[hit], err[hit])
        return out

    def sample(self, features: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """One perception per row: ``(detected bool [R], errors float64 [R, 2])`` (metres; 0 where missed).

        The uniforms of the detections, then the errors of every row, are drawn from ``rng`` whatever is detected, so
        a seed fixes the errors' random numbers independently of the detections (common random numbers).
        """
        x = np.asarray(features, dtype=np.float64)
        detected = rng.random(x.shape[0]) < expit(self.logit(x))
        errors = self.noise.sample(x, rng)
        errors[~detected] = 0.0
        return detected, errors

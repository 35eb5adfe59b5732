"""Detectors' measurement errors: the location-scale families a detected object's error is drawn from, their
quantiles and log densities in closed form, and the helpers that draw and score the errors of a
:class:`~pemviz.core.detectors.NoisyDetector` (through :class:`ErrorModelOf` wrappers). Re-exported by
:mod:`pemviz.core.detectors`."""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from pemviz.core import exact, libm
from pemviz.core.exact import row_sum
from pemviz.core.t_quantile import student_t_quantile

NOISE_FAMILIES = ("normal", "laplace", "student-t")
"""The location-scale families of measurement errors."""


def _check_family(family: str) -> None:
    if family not in NOISE_FAMILIES:
        raise ValueError(f"unknown error family {family!r}; use one of {', '.join(NOISE_FAMILIES)}")


def standard_quantile(family: str, df: np.ndarray | None, u: np.ndarray) -> np.ndarray:
    """F^-1(u) of the standard ``family`` (Student-t with ``df`` degrees of freedom, broadcast against ``u``),
    float64, in closed form with scipy.special (tested against ``scipy.stats``); Student-t quantiles with df >= 1
    from :func:`pemviz.core.t_quantile.student_t_quantile`, others from ``stdtrit``.

    Raises:
        ValueError: an unknown family."""
    from scipy.special import ndtri, stdtrit

    _check_family(family)
    u = np.asarray(u, dtype=np.float64)
    if family == "normal":
        return ndtri(u)
    if family == "laplace":  # log 2u below the median, -log 2(1 - u) above: no cancellation in either tail
        with np.errstate(divide="ignore"):
            return np.where(u < 0.5, libm.log(2.0 * u), -libm.log(2.0 * (1.0 - u)))
    nu = np.asarray(df, dtype=np.float64)
    if not (np.all(np.isfinite(nu)) and np.all(nu >= 1.0)):
        return stdtrit(nu, u)
    if nu.ndim == 0:
        return student_t_quantile(float(nu), u)
    if nu.ndim == 1 and u.ndim >= 1 and u.shape[-1] == nu.size:  # one df per column (a noise PEM's components)
        return student_t_quantile(nu, u)
    return stdtrit(nu, u)


def standard_log_density(family: str, df: np.ndarray | None, z: np.ndarray) -> np.ndarray:
    """log f(z) of the standard ``family`` (nats), float64, in closed form (see :func:`standard_quantile`).

    Raises:
        ValueError: an unknown family."""
    _check_family(family)
    z = np.asarray(z, dtype=np.float64)
    if family == "normal":
        return -0.5 * z * z - 0.5 * math.log(2.0 * math.pi)
    if family == "laplace":
        return -np.abs(z) - math.log(2.0)
    nu = np.asarray(df, dtype=np.float64)
    return _t_log_constant(nu.tobytes(), nu.shape) - (nu + 1.0) / 2.0 * libm.log1p(z * z / nu)


@functools.lru_cache(maxsize=64)
def _t_log_constant(nu_bytes: bytes, shape: tuple[int, ...]) -> np.ndarray:
    """``log Gamma((nu + 1) / 2) - log Gamma(nu / 2) - log(nu pi) / 2`` of the Student-t degrees of freedom given as
    float64 bytes (read-only), computed once per df."""
    from scipy.special import gammaln

    nu = np.frombuffer(nu_bytes, dtype=np.float64).reshape(shape)
    out = gammaln((nu + 1.0) / 2.0) - gammaln(nu / 2.0) - 0.5 * libm.log(nu * math.pi)
    out.flags.writeable = False
    return out


def noise_quantile(
    family: str, df: np.ndarray | None, loc: np.ndarray, log_scale: np.ndarray, u: np.ndarray
) -> np.ndarray:
    """Errors ``loc + exp(log_scale) F^-1(u)`` of a location-scale family, float64 [R, D] from uniforms [R, D] in (0, 1)
    (F the standard ``family``'s CDF; Student-t with ``df`` [D]); the scale from :func:`pemviz.core.exact.exp`, so
    that an error is the same on every CPU (numpy's vector exp rounds its last bit by the CPU).

    Raises:
        ValueError: an unknown family."""
    z = standard_quantile(family, df, u)
    return np.asarray(loc, dtype=np.float64) + exact.exp(np.asarray(log_scale, dtype=np.float64)) * z


def noise_log_density(
    family: str, df: np.ndarray | None, loc: np.ndarray, log_scale: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """``sum_d log f((e_d - loc_d) / scale_d) - log scale_d``, float64 [R] (nats): the log density of errors [R, D]
    whose components are independent of a location-scale family.

    Raises:
        ValueError: an unknown family."""
    z = (np.asarray(noise, dtype=np.float64) - loc) * exact.exp(-np.asarray(log_scale, dtype=np.float64))
    return row_sum(standard_log_density(family, df, z) - log_scale)


def noise_names_of(detector: object) -> tuple[str, ...]:
    """The measurement-error components a detector draws (``()``: it only detects)."""
    return tuple(getattr(detector, "noise_names", ()) or ())


def draw_noise(detector: Any, rows: np.ndarray, u: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The measurement errors of the rows ``hit`` drawn from ``detector``'s error model and their log density:
    ``noise_from_uniforms`` then ``noise_log_prob``, or bit for bit the same in one evaluation,
    ``detector.noise_draw(rows, u, hit)`` where it has it.

    Args:
        detector: a :class:`~pemviz.core.detectors.NoisyDetector`.
        rows: float64 [R, G] object rows.
        u: float64 [H, D] uniforms in (0, 1) of the H rows of ``hit``, in order.
        hit: bool [R].
    Returns:
        (errors float64 [H, D], log density float64 [H] in nats)."""
    combined = getattr(detector, "noise_draw", None)
    if combined is not None:
        errors, log_density = combined(rows, u, hit)
        return np.asarray(errors, dtype=np.float64), np.asarray(log_density, dtype=np.float64)
    picked = rows[hit]
    errors = np.asarray(detector.noise_from_uniforms(picked, u), dtype=np.float64)
    return errors, np.asarray(detector.noise_log_prob(picked, errors), dtype=np.float64)


def error_model_of(detector: object) -> object:
    """The detector whose error model ``detector`` uses: itself, or behind :class:`ErrorModelOf` wrappers (e.g.
    :class:`~pemviz.core.detectors.ArrayRQMC`, :class:`~pemviz.core.scored_target.ScoredTarget`) the wrapped one, whose
    densities theirs are."""
    while isinstance(detector, ErrorModelOf):
        detector = detector._errors
    return detector


class ErrorModelOf:
    """A wrapper of a detector whose measurement-error model (:class:`~pemviz.core.detectors.NoisyDetector`) is the
    wrapped one's, named by the class attribute ``_error_model_of``; ``noise_names`` is empty when the wrapped detector
    only detects."""

    _error_model_of: str

    @property
    def _errors(self) -> Any:
        return getattr(self, self._error_model_of)

    @property
    def noise_names(self) -> tuple[str, ...]:
        """The wrapped detector's measurement errors, if it has an error model."""
        return noise_names_of(self._errors)

    @property
    def noise_family(self) -> str:
        return self._errors.noise_family

    @property
    def noise_df(self) -> np.ndarray | None:
        return self._errors.noise_df

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The wrapped detector's error parameters (:class:`~pemviz.core.detectors.NoisyDetector`)."""
        return self._errors.noise_params(rows)

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The wrapped detector's errors from uniforms (:class:`~pemviz.core.detectors.NoisyDetector`)."""
        return self._errors.noise_from_uniforms(rows, u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """The wrapped detector's log density of the errors (:class:`~pemviz.core.detectors.NoisyDetector`)."""
        return self._errors.noise_log_prob(rows, noise)

    def noise_draw(self, rows: np.ndarray, u: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The wrapped detector's errors of the rows ``hit`` and their log density (:func:`draw_noise`)."""
        return draw_noise(self._errors, rows, u, hit)

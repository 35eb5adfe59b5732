"""A perception model with two heads: whether an obstacle is detected, and if so how wrong its measurement is: p(a,
e | x) = p_PEM(a | x) * p_noise(e | x)^a, a in {0, 1}, e = (dZ, dX) metres, x the 14-dim encoding; the detection
head any PEM (Innes & Ramamoorthy 2022, Sec. IV-A), the noise head a :class:`pemviz.pem.noise.NoiseModel`.
``pemviz.pem.store`` saves the pair as one file."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import expit, log_expit

from pemviz.core.detector_noise import noise_log_density, noise_quantile
from pemviz.pem.encoding import CODE_COLUMNS, SalientCodes, codes_of_columns, encode_salient
from pemviz.pem.network import PEM
from pemviz.pem.noise import NoiseModel, NoisePEM
from pemviz.pem.trees import TreePEM


@dataclass(frozen=True, eq=False)
class NoisyPEM:
    """A detection head (``detect``: logit of p(detected)) and a noise head (``noise``) on the same 14 features.

    Both heads must share their z-score statistics (pemviz fits them on the full KITTI file), so one encoding
    (:meth:`features`) feeds both.

    Raises:
        ValueError: the heads' z-score statistics differ."""

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
            ValueError: shapes other than ``[R, 14]``, ``[R]`` and ``[R, 2]``."""
        x = np.asarray(features, dtype=np.float64)
        hit = np.asarray(detected, dtype=bool)
        err = np.asarray(errors, dtype=np.float64)
        if x.ndim != 2 or hit.shape != (x.shape[0],) or err.shape != (x.shape[0], 2):
            raise ValueError(
                f"need features [R, 14], detected [R] and errors [R, 2], got {x.shape}, {hit.shape}, " f"{err.shape}"
            )
        logit = self.logit(x)
        out = np.where(hit, log_expit(logit), log_expit(-logit))
        if np.any(hit):
            out[hit] += self.noise.log_prob(x[hit], err[hit])
        return out

    def sample(self, features: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """One perception per row: ``(detected bool [R], errors float64 [R, 2])`` (metres; 0 where missed); the
        errors' uniforms are drawn whatever is detected (common random numbers)."""
        x = np.asarray(features, dtype=np.float64)
        detected = rng.random(x.shape[0]) < expit(self.logit(x))
        errors = self.noise.sample(x, rng)
        errors[~detected] = 0.0
        return detected, errors


@dataclass(frozen=True, eq=False)
class SalientDetector:
    """A PEM as the detector of a scene's objects, reading each row's 11 KITTI salient variables (the columns
    ``salient``), with the noise PEM's errors when ``noise`` is given (a
    :class:`pemviz.core.detectors.NoisyDetector`, :class:`NoisyPEM`); rows whose ``visible`` column is 0 are never
    detected (logit -inf).

    Args:
        detect: the detection PEM (:class:`pemviz.pem.PEM` or :class:`pemviz.pem.TreePEM`).
        salient: the row columns of the 11 raw salient inputs (a slice or indices).
        noise: the noise PEM (:class:`pemviz.pem.noise.NoiseModel`), or None: detections measure exactly.
        noise_names: the error components' names (range, lateral), with ``noise``.
        visible: the row column of the 0/1 visibility flag, or None: every object can be seen."""

    detect: Any
    salient: Any
    noise: NoiseModel | None = None
    noise_names: tuple[str, ...] = ()
    visible: int | None = None

    def __post_init__(self) -> None:
        if (self.noise is None) != (not self.noise_names):
            raise ValueError("SalientDetector: give the noise model and its error names together")
        self._step: _Step | None  # the kept step of _evaluate (not a field: set by object.__setattr__)
        object.__setattr__(self, "_step", None)

    @property
    def _noise(self) -> NoiseModel:
        """The noise PEM, which only a detector with one (``noise_names``) is asked about."""
        if self.noise is None:
            raise AttributeError("SalientDetector: no noise model (noise=None): detections measure exactly")
        return self.noise

    def __getstate__(self) -> dict[str, Any]:
        """The fields without the kept step (a copy sent to another process starts with none)."""
        return {k: v for k, v in self.__dict__.items() if k != "_step"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        object.__setattr__(self, "_step", None)

    def _raw(self, rows: np.ndarray) -> np.ndarray:
        return np.asarray(rows, dtype=np.float64)[:, self.salient]

    def _encodes(self) -> bool:
        """Whether the detection PEM is one of pemviz's (:class:`pemviz.pem.PEM`, :class:`pemviz.pem.TreePEM`), whose
        logit of raw inputs is ``logit_features(encode_salient(raw, norm))``: its encoding can then be kept and shared
        with the noise head."""
        return type(self.detect) in (PEM, TreePEM)

    def _code_columns(self, width: int) -> np.ndarray:
        """The row columns of the raw inputs the encoding reads (:data:`~pemviz.pem.encoding.CODE_COLUMNS`), for rows
        of ``width`` columns."""
        return np.arange(width)[self.salient][list(CODE_COLUMNS)]

    def _shares_encoding(self) -> bool:
        """Whether the noise head encodes the salient variables as the detection PEM does (same z-score statistics)."""
        a, b = self.detect.norm, self._noise.norm
        return a is b or (np.array_equal(a.mean, b.mean) and np.array_equal(a.std, b.std))

    def _evaluate(self, rows: np.ndarray) -> _Step:
        """The detection head's work on rows [R, G] (visibility, encoding, logits), kept for a read-only ``rows``
        and recognised by identity when the sampler, the target and the noise head ask again within the step;
        repeated rows (:func:`repeated_rows`) are asked about once, with the same bits
        (:class:`pemviz.pem.network.GridMLP`)."""
        kept = self._step
        if kept is not None and kept.rows is rows:
            return kept
        rows_in = rows
        rows = np.asarray(rows, dtype=np.float64)
        out = np.full(rows.shape[0], -np.inf)
        seen = np.ones(rows.shape[0], bool) if self.visible is None else rows[:, self.visible] > 0.5
        codes, inverse = None, None
        if seen.any():
            if self._encodes():  # the columns the encoding reads, feature by feature, of the seen rows
                columns = np.empty((len(CODE_COLUMNS), int(np.count_nonzero(seen))))
                for k, c in enumerate(self._code_columns(rows.shape[1])):
                    np.compress(seen, rows[:, c], out=columns[k])
                groups = repeated_rows(columns)
                if groups is not None:  # many rollouts in the same state: each distinct row asked once
                    first, inverse = groups
                    columns = columns[:, first]
                codes = codes_of_columns(columns, self.detect.norm)
                if type(self.detect) is PEM:
                    logits = self.detect.logit_codes(codes)
                else:
                    logits = self.detect.logit_features(codes.features())
                out[seen] = logits if inverse is None else logits[inverse]
            else:
                out[seen] = self.detect.logit(self._raw(rows)[seen])
        step = _Step(rows_in, seen, codes, out, inverse)
        if isinstance(rows_in, np.ndarray) and not rows_in.flags.writeable:
            out.flags.writeable = False
            object.__setattr__(self, "_step", step)
        return step

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        """logit p_PEM(detect | salient variables), float64 [R] (nats; -inf where not visible), for rows [R, G]."""
        logits = self._evaluate(rows).logits
        return logits.copy() if not logits.flags.writeable else logits

    @property
    def noise_family(self) -> str:
        return self._noise.family

    @property
    def noise_df(self) -> np.ndarray | None:
        return self._noise.df

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(loc [R, D], log_scale [R, D]) of the noise PEM at the rows' salient variables (metres; log metres)."""
        return self._noise.noise_params(self._noise.features(self._raw(rows)))

    def _noise_params(self, codes: SalientCodes) -> tuple[np.ndarray, np.ndarray]:
        noise = self._noise
        if type(noise) is NoisePEM:
            return noise.noise_params_codes(codes)
        return noise.noise_params(codes.features())

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Errors [R, D] (metres) from uniforms [R, D] by the noise PEM's inverse CDF."""
        return noise_quantile(self._noise.family, self._noise.df, *self.noise_params(rows), u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """log p_noise(errors | salient variables), float64 [R] (nats)."""
        return noise_log_density(self._noise.family, self._noise.df, *self.noise_params(rows), noise)

    def noise_draw(self, rows: np.ndarray, u: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The errors of the rows ``hit`` and their log density, the noise head evaluated once: exactly ``e =
        noise_from_uniforms(rows[hit], u)`` and ``noise_log_prob(rows[hit], e)``, reusing the detection head's
        encoding where it fits.

        Args:
            rows: float64 [R, G] object rows.
            u: float64 [H, D] uniforms in (0, 1) of the H rows of ``hit``, in order.
            hit: bool [R], the rows measured (detected).
        Returns:
            (errors float64 [H, D] in metres, log density float64 [H] in nats)."""
        kept = self._step
        if (
            kept is not None
            and kept.rows is rows
            and kept.codes is not None
            and self._shares_encoding()
            and np.all(kept.seen[hit])
        ):
            which = np.flatnonzero(hit[kept.seen])  # the hit rows among the seen ones
            if kept.inverse is not None:  # among the distinct ones: each asked once
                which = kept.inverse[which]
                needed = np.zeros(kept.codes.code.shape[0], bool)
                needed[which] = True
                ask = np.flatnonzero(needed)
                position = np.cumsum(needed) - 1
                loc, log_scale = (a[position[which]] for a in self._noise_params(kept.codes.take(ask)))
            else:
                loc, log_scale = self._noise_params(kept.codes.take(which))
        else:
            loc, log_scale = self._noise.noise_params(self._noise.features(self._raw(rows)[hit]))
        errors = noise_quantile(self._noise.family, self._noise.df, loc, log_scale, u)
        return errors, noise_log_density(self._noise.family, self._noise.df, loc, log_scale, errors)


@dataclass(frozen=True)
class _Step:
    """What :meth:`SalientDetector._evaluate` kept of one array of rows [R, G]: the array itself, ``seen`` bool [R]
    (visible rows), the encoding of the S seen rows (None: not encoded, or none seen; of the D distinct ones when
    ``inverse`` is given), the logits float64 [R] (read-only) and ``inverse``: None, or int [S], seen row i's encoding
    is ``codes.take(inverse)[i]`` (:func:`repeated_rows`)."""

    rows: Any
    seen: np.ndarray
    codes: SalientCodes | None
    logits: np.ndarray
    inverse: np.ndarray | None = None


PROBE_ROWS = 256
"""Rows at fixed positions that :func:`repeated_rows` looks at first."""
PROBE_DISTINCT = 128
"""At most this many distinct rows among the probe: grouping pays (the first steps of a cut-in run, before the
rollouts' perceptions have set their egos apart, ask about a few hundred distinct rows of 40,960)."""


def repeated_rows(columns: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(first [D], inverse [S])`` with ``columns[:, first][:, inverse] == columns`` when the S rows (float64 ``[K,
    S]``, feature by feature) hold few distinct ones, else None: :data:`PROBE_ROWS` rows are probed first (more than
    :data:`PROBE_DISTINCT` distinct: None), then rows are grouped by a float64 key and checked equal to their
    group's first."""
    s = columns.shape[1]
    if s < 4 * PROBE_ROWS:
        return None
    probe = columns[:, :: s // PROBE_ROWS][:, :PROBE_ROWS]
    if np.unique(_row_keys(probe)).size > PROBE_DISTINCT:
        return None
    keys = _row_keys(columns)
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    if first.size > s // 4 or not np.array_equal(columns[:, first][:, inverse.reshape(-1)], columns):
        return None
    return first, inverse.reshape(-1)


def _row_keys(columns: np.ndarray) -> np.ndarray:
    """float64 [S]: sum_k columns[k] w_k for fixed weights w, elementwise in a fixed order (equal rows, equal keys)."""
    key = columns[0].copy()
    term = np.empty_like(key)
    for k in range(1, columns.shape[0]):
        np.multiply(columns[k], 1.0 + k * 0.6180339887498949, out=term)
        key += term
    return key

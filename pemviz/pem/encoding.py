"""PEM inputs: the 14-dim encoding of KITTI salient variables and the braking scenario's mapping.

Innes & Ramamoorthy 2022, Sec. IV-A (the authors' ``SalientObstacleDataset`` in ``pems.py``): one-hot class (7) +
one-hot occlusion (3: none, partly, largely) + loc_x, loc_y, loc_z, rot_y (raw columns 7..10) z-scored with the
mean and unbiased (n - 1) std of the full 37,498-row file."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

N_CLASSES = 7
"""KITTI classes of ``kitti.names`` without Misc: 0 Car, 1 Van, 2 Truck, 3 Pedestrian, 4 Person_sitting,
5 Cyclist, 6 Tram."""
N_OCCLUSIONS = 3
"""KITTI occlusion levels without 'unknown': 0 fully visible, 1 partly occluded, 2 largely occluded."""
CLASS_COLUMN = 0
OCCLUSION_COLUMN = 2
INPUT_COLUMNS = (
    "class",
    "truncation",
    "occlusion",
    "alpha",
    "dim_w",
    "dim_l",
    "dim_h",
    "loc_x",
    "loc_y",
    "loc_z",
    "rot_y",
)
"""A PEM's 11 raw inputs, the KITTI salient variables, in column order (``class`` an index, ``truncation`` and
``occlusion`` codes, angles in radians, sizes and positions in metres): the data files' columns
(:mod:`pemviz.io.data` reads them) and every scene's object rows."""

POSE_COLUMNS = (7, 8, 9, 10)
"""Raw input columns z-scored into the encoding: loc_x, loc_y, loc_z (metres), rot_y (radians)."""
N_FEATURES = N_CLASSES + N_OCCLUSIONS + len(POSE_COLUMNS)

CLASS_CAR = 0
OCCLUSION_NONE = 0
BRAKING_LOC_X_M = 0.0
"""Lateral offset of the lead in the camera frame (CARLA logs: 0.03-0.12 m)."""
BRAKING_LOC_Y_M = 1.76
"""Height of the ego's camera above the road (KITTI's own camera is at 1.65 m)."""
BRAKING_CAMERA_TO_LEAD_CENTRE_M = 2.48
"""loc_z = gap + 2.48 m: from the lead's rear to its centre."""
BRAKING_ROT_Y_RAD = -math.pi / 2
"""The lead drives in the ego's heading."""


BRAKING_Z_FEATURE = N_CLASSES + N_OCCLUSIONS + 2
"""Index of the z-scored loc_z in the 14-dim encoding: the only feature that varies with the gap."""


@dataclass(frozen=True)
class NormStats:
    """z-score statistics of the pose columns: ``mean``, ``std`` float64 ``[4]`` for loc_x, loc_y, loc_z
    (metres) and rot_y (radians)."""

    mean: np.ndarray
    std: np.ndarray

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=np.float64).reshape(-1)
        std = np.asarray(self.std, dtype=np.float64).reshape(-1)
        if mean.shape != (len(POSE_COLUMNS),) or std.shape != (len(POSE_COLUMNS),):
            raise ValueError(f"NormStats needs 4 means and 4 stds, got shapes {mean.shape}, {std.shape}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(std)) and np.all(std > 0)):
            raise ValueError(f"NormStats must be finite with std > 0, got mean {mean}, std {std}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "std", std)


def fit_norm_stats(raw_inputs: np.ndarray) -> NormStats:
    """Mean and unbiased (n - 1) std of the pose columns of raw salient inputs ``[N, 11]`` (as the authors' training
    code).

    Raises:
        ValueError: fewer than 2 rows or not 11 columns."""
    raw = _check_raw(raw_inputs)
    if raw.shape[0] < 2:
        raise ValueError(f"need at least 2 rows to fit z-score statistics, got {raw.shape[0]}")
    pose = raw[:, POSE_COLUMNS]
    return NormStats(mean=pose.mean(axis=0), std=pose.std(axis=0, ddof=1))


def _check_raw(raw_inputs: np.ndarray) -> np.ndarray:
    raw = np.asarray(raw_inputs, dtype=np.float64)
    if raw.ndim != 2 or raw.shape[1] != 11:
        raise ValueError(f"raw salient inputs must have shape [N, 11] (KITTI columns), got {raw.shape}")
    return raw


def check_features(features: np.ndarray, kind: str = "PEM", rows: str = "N") -> np.ndarray:
    """Encoded features as float64 ``[rows, 14]`` (:func:`encode_salient`'s layout).

    Raises:
        ValueError: another shape (the message names the ``kind`` of PEM)."""
    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != N_FEATURES:
        raise ValueError(f"{kind} features must have shape [{rows}, {N_FEATURES}], got {x.shape}")
    return x


def check_training_data(inputs: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Raw salient inputs float64 [N, 11] and labels float64 [N] in {0, 1}, checked for training.

    Raises:
        ValueError: wrong input shape, NaN, mismatched lengths, or labels other than 0 and 1."""
    raw = _check_raw(inputs)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if y.shape[0] != raw.shape[0]:
        raise ValueError(f"inputs have {raw.shape[0]} rows but labels {y.shape[0]}")
    if not np.all((y == 0.0) | (y == 1.0)):
        raise ValueError("labels must be 0 or 1")
    return raw, y


ONE_HOT_GROUPS = (tuple(range(N_CLASSES)), tuple(range(N_CLASSES, N_CLASSES + N_OCCLUSIONS)))
"""The encoding's one-hot column groups: the class's, then the occlusion's."""


@dataclass(frozen=True)
class SalientCodes:
    """The 14-dim encoding of N rows held compactly: ``pose_t`` float64 ``[4, N]`` (the z-scored loc_x, loc_y, loc_z,
    rot_y, feature by feature) and ``code`` int64 ``[N]`` = class x 3 + occlusion, the one-hot columns' combination
    (:data:`ONE_HOT_GROUPS`)."""

    pose_t: np.ndarray
    code: np.ndarray

    def features(self) -> np.ndarray:
        """The encoding float64 ``[N, 14]`` (:func:`encode_salient`)."""
        n_rows = self.code.shape[0]
        out = np.zeros((n_rows, N_FEATURES), dtype=np.float64)
        rows = np.arange(n_rows)
        out[rows, self.code // N_OCCLUSIONS] = 1.0
        out[rows, N_CLASSES + self.code % N_OCCLUSIONS] = 1.0
        out[:, N_CLASSES + N_OCCLUSIONS :] = self.pose_t.T
        return out

    def take(self, index: np.ndarray) -> SalientCodes:
        """The codes of rows ``index`` (int indices or a bool mask)."""
        return SalientCodes(self.pose_t[:, index], self.code[index])


CODE_COLUMNS = (CLASS_COLUMN, OCCLUSION_COLUMN, *POSE_COLUMNS)
"""The raw input columns the encoding reads (class, occlusion, loc_x, loc_y, loc_z, rot_y); the others (truncation,
alpha, the box's dimensions) do not enter it."""


def codes_of_columns(columns: np.ndarray, norm: NormStats) -> SalientCodes:
    """:class:`SalientCodes` of raw columns :data:`CODE_COLUMNS` given feature by feature, float64 ``[6, N]``: the
    z-scores of :func:`encode_salient` bit for bit.

    Raises:
        ValueError: a non-finite value, a class not an integer in 0..6 or an occlusion not an integer in 0..2 (the
            message names the first bad row, 0-based)."""
    if not np.isfinite(columns).all():
        row = int(np.flatnonzero(~np.all(np.isfinite(columns), axis=0))[0])
        raise ValueError(f"raw salient inputs: non-finite value in row {row}")
    levels = []
    for what, values, n in (("class", columns[0], N_CLASSES), ("occlusion", columns[1], N_OCCLUSIONS)):
        with np.errstate(invalid="ignore"):  # a value out of int64's range converts to some other number: bad below
            level = values.astype(np.int64)
        # the level of an integral value equals it; a level in 0..n - 1 that equals the value is that integer
        bad = level != values
        bad |= level.view(np.uint64) > n - 1  # a negative level wraps to a huge unsigned one
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise ValueError(f"raw salient inputs: {what} {values[row]:g} in row {row} is not an integer in 0..{n - 1}")
        levels.append(level)
    pose_t = (columns[2:] - norm.mean[:, None]) / norm.std[:, None]
    return SalientCodes(pose_t, levels[0] * N_OCCLUSIONS + levels[1])


def salient_codes(raw_inputs: np.ndarray, norm: NormStats) -> SalientCodes:
    """:func:`encode_salient`'s encoding as :class:`SalientCodes` (its checks and errors, the same z-scores bit for
    bit)."""
    raw = _check_raw(raw_inputs)
    if not np.isfinite(raw).all():
        row = int(np.flatnonzero(~np.all(np.isfinite(raw), axis=1))[0])
        raise ValueError(f"raw salient inputs: non-finite value in row {row}")
    return codes_of_columns(raw[:, CODE_COLUMNS].T, norm)


def encode_salient(raw_inputs: np.ndarray, norm: NormStats) -> np.ndarray:
    """The 14-dim PEM input: one-hot class (7), one-hot occlusion (3), z-scored x, y, z, rot_y.

    Args:
        raw_inputs: float ``[N, 11]`` in the KITTI column layout (class, truncation, occlusion, alpha,
            dim_w, dim_l, dim_h, loc_x, loc_y, loc_z, rot_y); metres, radians.
        norm: z-score statistics (:func:`fit_norm_stats` of the training file).
    Returns:
        float64 ``[N, 14]`` (the order of the authors' ``SalientObstacleDataset``).
    Raises:
        ValueError: wrong shape, non-finite values, a class not an integer in 0..6 or an occlusion not an
            integer in 0..2 (the message names the first bad row, 0-based)."""
    return salient_codes(raw_inputs, norm).features()


def braking_salient_inputs(gap_m: np.ndarray) -> np.ndarray:
    """Salient variables of the lead car in the braking scenario: class Car, no occlusion, loc_x = 0.0, loc_y = 1.76
    (camera height), loc_z = gap + 2.48, rot_y = -pi/2, the other columns 0.

    Args:
        gap_m: gap from the ego's camera to the lead's rear, metres, any shape ``[...]``.
    Returns:
        float64 ``[M, 11]`` with ``M = gap_m.size`` (flattened, C order)."""
    gap = np.asarray(gap_m, dtype=np.float64).reshape(-1)
    raw = np.zeros((gap.shape[0], 11), dtype=np.float64)
    raw[:, CLASS_COLUMN] = CLASS_CAR
    raw[:, OCCLUSION_COLUMN] = OCCLUSION_NONE
    raw[:, 7] = BRAKING_LOC_X_M
    raw[:, 8] = BRAKING_LOC_Y_M
    raw[:, 9] = gap + BRAKING_CAMERA_TO_LEAD_CENTRE_M
    raw[:, 10] = BRAKING_ROT_Y_RAD
    return raw


def bce_from_logits(logits: np.ndarray, labels: np.ndarray) -> float:
    """Mean binary cross-entropy, nats: ``mean(softplus(l) - y * l)`` = ``-mean(log sigmoid(+-l))``, float64."""
    logit = np.asarray(logits, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if logit.shape != y.shape:
        raise ValueError(f"logits {logit.shape} and labels {y.shape} differ in length")
    return float(np.mean(np.logaddexp(0.0, logit) - y * logit))


def braking_features_at_z(z_scored: np.ndarray, norm: NormStats) -> np.ndarray:
    """Encoded features ``[M, 14]`` of the braking scenario's lead car with the z-scored loc_z set directly.

    The encoding of :func:`braking_salient_inputs` with column :data:`BRAKING_Z_FEATURE` replaced by
    ``z_scored`` ``[M]``: lets a PEM tabulate itself along the gap without rounding loc_z twice."""
    zn = np.asarray(z_scored, dtype=np.float64).reshape(-1)
    feats = np.repeat(encode_salient(braking_salient_inputs(np.zeros(1)), norm), zn.shape[0], axis=0)
    feats[:, BRAKING_Z_FEATURE] = zn
    return feats


def braking_z_scored(gap_m: np.ndarray, norm: NormStats) -> np.ndarray:
    """The z-scored loc_z of the lead at ``gap_m`` (same shape), with exactly the arithmetic of
    :func:`encode_salient` on :func:`braking_salient_inputs` (so comparisons with tree thresholds agree)."""
    gap = np.asarray(gap_m, dtype=np.float64)
    return ((gap + BRAKING_CAMERA_TO_LEAD_CENTRE_M) - norm.mean[2]) / norm.std[2]

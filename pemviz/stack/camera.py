"""The camera stage of a perception stack, for any scene: what a KITTI-like pinhole camera sees of an object (its 11
salient variables, the detection PEM's and noise PEM's inputs) and where it measures a detected object, given the
noise PEM's errors. Every function is elementwise over arrays of one shape (e.g. ``[M, N]``: M objects, N rollouts).

The camera (pinhole, KITTI's camera 2: :data:`pemviz.pem.camera.KITTI_FOCAL_PX`, the :data:`KITTI_IMAGE_SIZE_PX`
image) looks along the road from ``camera_height_m`` above it, in KITTI's frame (Geiger et al. 2013, "Vision meets
robotics: the KITTI dataset", IJRR 32(11)): x right, y down, z forward. An object is an upright box
(:class:`ObjectKind`) on the road at ``(loc_x_m, loc_z_m)``, turned by ``rot_y_rad`` (KITTI's rotation_y); its
truncation, occluded share and visibility follow from its 2D image box (:func:`image_box`, :func:`occluded_share`,
:func:`views`), its measurement from the noise PEM's errors (:func:`measure`).

Units: metres, radians."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.core import libm
from pemviz.pem.camera import KITTI_FOCAL_PX, KITTI_PRINCIPAL_POINT_PX, MIN_RANGE_M
from pemviz.pem.encoding import INPUT_COLUMNS

KITTI_IMAGE_SIZE_PX = (1242, 375)
"""Width and height of KITTI's camera-2 images, pixels (the KITTI object benchmark's left colour images)."""
IMAGE_BOUNDS = (
    -KITTI_PRINCIPAL_POINT_PX[0] / KITTI_FOCAL_PX,
    (KITTI_IMAGE_SIZE_PX[0] - KITTI_PRINCIPAL_POINT_PX[0]) / KITTI_FOCAL_PX,
    -KITTI_PRINCIPAL_POINT_PX[1] / KITTI_FOCAL_PX,
    (KITTI_IMAGE_SIZE_PX[1] - KITTI_PRINCIPAL_POINT_PX[1]) / KITTI_FOCAL_PX,
)
"""The image's edges in normalised coordinates ``(u_left, u_right, v_top, v_bottom)`` = ``(pixel - c) / f``."""

SALIENT_NAMES: tuple[str, ...] = tuple(INPUT_COLUMNS)
"""The 11 salient variables a row of :func:`salient_rows` holds, in the PEMs' raw-input order
(:data:`pemviz.pem.encoding.INPUT_COLUMNS`); the dimension columns hold (height, width, length), KITTI's label order."""

KITTI_CLASSES = {"car": 0, "van": 1, "truck": 2, "pedestrian": 3, "person_sitting": 4, "cyclist": 5, "tram": 6}
"""KITTI's object classes as the PEMs index them (:data:`pemviz.pem.encoding.N_CLASSES`; Misc left out)."""

_MIN_DEPTH_M = 0.1
"""Corner depths are clamped to at least this before dividing (an object reaching behind the camera is largely
truncated; it is not visible unless its centre is :data:`MIN_RANGE_M` ahead)."""


@dataclass(frozen=True)
class ObjectKind:
    """What kind of object the camera sees: its KITTI class and box (metres).

    Attributes:
        kitti_class: a key of :data:`KITTI_CLASSES` (``pedestrian``, ``car``, ``cyclist`` ...).
        height_m, width_m, length_m: the box (KITTI's h, w, l; e.g. a pedestrian 1.75, 0.6, 0.8).
    Raises:
        ValueError: an unknown class, or a dimension not in (0, 30] m."""

    kitti_class: str
    height_m: float
    width_m: float
    length_m: float

    def __post_init__(self) -> None:
        if self.kitti_class not in KITTI_CLASSES:
            raise ValueError(
                f"ObjectKind: kitti_class must be one of {', '.join(KITTI_CLASSES)}, got " f"{self.kitti_class!r}"
            )
        if not all(0.0 < d <= 30.0 for d in (self.height_m, self.width_m, self.length_m)):
            raise ValueError(f"ObjectKind: height_m, width_m and length_m must be in (0, 30] m, got {self}")

    @property
    def class_index(self) -> int:
        """The class's index in the PEMs' one-hot encoding."""
        return KITTI_CLASSES[self.kitti_class]


PEDESTRIAN = ObjectKind("pedestrian", 1.75, 0.6, 0.8)
"""An adult pedestrian: about KITTI's mean pedestrian box (h 1.76, w 0.66, l 0.84 m)."""
CAR = ObjectKind("car", 1.5, 1.7, 4.2)
"""A passenger car."""


@dataclass(frozen=True)
class ImageBox:
    """2D image boxes in normalised image coordinates (``u = X / Z`` right, ``v = Y / Z`` down; pixels are
    ``f u + c``): float64 arrays of one shape, e.g. ``[M, N]`` (M objects, N rollouts).

    Attributes:
        u_lo, u_hi: the left and right edges.
        v_top, v_bot: the top and bottom edges (``v_top < v_bot``)."""

    u_lo: np.ndarray
    u_hi: np.ndarray
    v_top: np.ndarray
    v_bot: np.ndarray

    @property
    def area(self) -> np.ndarray:
        """The box's area (normalised units squared)."""
        return (self.u_hi - self.u_lo) * (self.v_bot - self.v_top)

    @staticmethod
    def stack(boxes: list[ImageBox] | tuple[ImageBox, ...]) -> ImageBox:
        """The boxes of several objects (each of shape ``S``, e.g. one per kind) as one of shape ``[M] + S``."""
        return ImageBox(*(np.stack([getattr(b, name) for b in boxes]) for name in ("u_lo", "u_hi", "v_top", "v_bot")))


def image_box(
    kind: ObjectKind,
    loc_x_m: np.ndarray,
    loc_z_m: np.ndarray,
    rot_y_rad: np.ndarray | float,
    camera_height_m: float = 1.65,
) -> ImageBox:
    """The 2D image box of upright boxes standing on the road (KITTI, eq. 5): the box around the projections of the
    footprint's corners, raised to the object's height (depths clamped to at least 0.1 m).

    Args:
        kind: the objects' class and box.
        loc_x_m: the objects' centres in the camera frame, to the right (metres).
        loc_z_m: forward (metres), the shape of ``loc_x_m``.
        rot_y_rad: KITTI's rotation_y (radians), as :func:`view`.
        camera_height_m: the camera above the road (metres).
    Returns:
        :class:`ImageBox` of the broadcast shape of ``loc_x_m`` and ``loc_z_m``."""
    x = np.asarray(loc_x_m, dtype=np.float64)
    z = np.asarray(loc_z_m, dtype=np.float64)
    rot = np.broadcast_to(np.asarray(rot_y_rad, dtype=np.float64), x.shape)
    c, s = np.abs(np.cos(rot)), np.abs(np.sin(rot))
    half_x = 0.5 * (c * kind.length_m + s * kind.width_m)  # the footprint's axis-aligned half extents (camera x, z)
    half_z = 0.5 * (s * kind.length_m + c * kind.width_m)
    z_near = np.maximum(z - half_z, _MIN_DEPTH_M)
    z_far = np.maximum(z + half_z, _MIN_DEPTH_M)
    x_lo, x_hi = x - half_x, x + half_x
    u_hi = np.maximum(x_hi / z_near, x_hi / z_far)
    u_lo = np.minimum(x_lo / z_near, x_lo / z_far)
    v_top = (camera_height_m - kind.height_m) / np.where(kind.height_m > camera_height_m, z_near, z_far)
    v_bot = camera_height_m / z_near
    return ImageBox(u_lo, u_hi, v_top, v_bot)


def occluded_share(
    boxes: ImageBox, depth_m: np.ndarray | None = None, pairs: tuple[tuple[int, int], ...] | None = None
) -> np.ndarray:
    """The share of each object's 2D box covered by the boxes of nearer objects: ``min(1, sum over nearer i of
    area(box_i & box_j) / area(box_j))``; exact where the nearer boxes do not overlap each other on ``box_j``, an
    upper bound where they do.

    Args:
        boxes: the M objects' boxes, arrays ``[M] + S`` (:meth:`ImageBox.stack`, or :func:`image_box` of ``[M, N]``
            positions).
        depth_m: float64 ``[M] + S`` (or broadcastable), each object's centre depth (m): ``i`` hides ``j`` where
            ``depth_m[i] < depth_m[j]``. Needed unless ``pairs`` is given.
        pairs: instead of depths, the ``(i, j)`` pairs in which ``i`` is nearer than ``j`` everywhere, summed in the
            order given (the same bits whatever ``S``).
    Returns:
        float64 ``[M] + S``, in [0, 1].
    Raises:
        ValueError: neither ``depth_m`` nor ``pairs``, or ``depth_m`` of another leading size than the boxes."""
    m = np.shape(boxes.u_lo)[0]
    if pairs is None:
        if depth_m is None:
            raise ValueError("occluded_share: give depth_m (each object's centre depth, m) or pairs (nearer, farther)")
        depth = np.asarray(depth_m, dtype=np.float64)
        if depth.ndim == 0 or depth.shape[0] != m:
            raise ValueError(f"occluded_share: depth_m must have {m} rows (one per object), got shape {depth.shape}")
    covered = np.zeros(np.broadcast_shapes(np.shape(boxes.u_lo), np.shape(boxes.v_top)))
    for i, j in pairs if pairs is not None else [(i, j) for j in range(m) for i in range(m) if i != j]:
        du = np.minimum(boxes.u_hi[i], boxes.u_hi[j]) - np.maximum(boxes.u_lo[i], boxes.u_lo[j])
        dv = np.minimum(boxes.v_bot[i], boxes.v_bot[j]) - np.maximum(boxes.v_top[i], boxes.v_top[j])
        overlap = np.maximum(du, 0.0) * np.maximum(dv, 0.0)
        covered[j] += overlap if pairs is not None else np.where(depth[i] < depth[j], overlap, 0.0)
    return np.minimum(covered / boxes.area, 1.0)


def occlusion_level(share: np.ndarray, partly: float = 0.01, largely: float = 0.35) -> np.ndarray:
    """KITTI's occlusion level, float64 0.0 (fully visible), 1.0 (partly) or 2.0 (largely occluded), elementwise, from
    the occluded share (:func:`occluded_share`): 1 from ``partly``, 2 from ``largely`` (the cut-in's thresholds;
    KITTI labels the level by eye, it gives no share)."""
    level = (share >= partly).astype(np.float64)
    level += share >= largely
    return level


@dataclass(frozen=True)
class CameraView:
    """What the camera sees of each object: float64 arrays of the objects' shape.

    Attributes:
        salient: ``[..., 11]``, the salient variables (:data:`SALIENT_NAMES`): a PEM's raw inputs.
        range_m: the ground-plane distance from the camera to the object's centre, ``sqrt(loc_x^2 + loc_z^2)``.
        truncation: the share of the 2D box outside the image, in [0, 1].
        visible: bool, whether the camera can see it at all (a PEM detector should never detect an object that is
            not: :func:`pemviz.stack.detector.camera_detector` gives it logit -inf).
        occluded: the share of the 2D box covered by nearer objects (:func:`occluded_share`; 0 from :func:`view`)."""

    salient: np.ndarray
    range_m: np.ndarray
    truncation: np.ndarray
    visible: np.ndarray
    occluded: np.ndarray | float = 0.0


def view(
    kind: ObjectKind,
    loc_x_m: np.ndarray,
    loc_z_m: np.ndarray,
    rot_y_rad: np.ndarray | float,
    camera_height_m: float = 1.65,
    occlusion: np.ndarray | float = 0.0,
) -> CameraView:
    """The camera's view of objects of one kind (module docstring), none hiding another (:func:`views` for objects
    that can).

    Args:
        kind: the objects' class and box.
        loc_x_m: the objects' centres in the camera frame, to the right (m).
        loc_z_m: forward (m), the shape of ``loc_x_m``.
        rot_y_rad: KITTI's rotation_y (radians; 0: facing the camera's right, pi: its left, -pi/2: forward),
            broadcastable to them.
        camera_height_m: the camera above the road (m; KITTI's is 1.65): the salient ``loc_y``, the box's bottom.
        occlusion: KITTI's occlusion level (0, 1 or 2), broadcastable.
    Returns:
        :class:`CameraView`.
    Raises:
        ValueError: ``camera_height_m`` not in (0, 10] m."""
    if not 0.0 < camera_height_m <= 10.0:
        raise ValueError(f"view: camera_height_m must be in (0, 10] m, got {camera_height_m}")
    x = np.asarray(loc_x_m, dtype=np.float64)
    z = np.asarray(loc_z_m, dtype=np.float64)
    rot = np.broadcast_to(np.asarray(rot_y_rad, dtype=np.float64), x.shape)
    box = image_box(kind, x, z, rot, camera_height_m)
    left, right, top, bottom = IMAGE_BOUNDS
    inside = np.maximum(np.minimum(box.u_hi, right) - np.maximum(box.u_lo, left), 0.0) * np.maximum(
        np.minimum(box.v_bot, bottom) - np.maximum(box.v_top, top), 0.0
    )
    truncation = 1.0 - inside / box.area
    salient = np.empty(x.shape + (len(SALIENT_NAMES),))
    salient[..., 0] = kind.class_index
    salient[..., 1] = truncation
    salient[..., 2] = occlusion
    alpha = rot - libm.atan2(x, z)  # KITTI's observation angle: rotation_y minus the ray's angle, in [-pi, pi)
    salient[..., 3] = np.mod(alpha + np.pi, 2.0 * np.pi) - np.pi
    salient[..., 4] = kind.height_m
    salient[..., 5] = kind.width_m
    salient[..., 6] = kind.length_m
    salient[..., 7] = x
    salient[..., 8] = camera_height_m  # the box's bottom centre on the road, below the camera
    salient[..., 9] = z
    salient[..., 10] = rot
    visible = (z >= MIN_RANGE_M) & (inside > 0.0)
    return CameraView(salient, np.sqrt(x * x + z * z), truncation, visible)


def views(
    kinds: list[ObjectKind] | tuple[ObjectKind, ...],
    loc_x_m: np.ndarray,
    loc_z_m: np.ndarray,
    rot_y_rad: np.ndarray | float,
    camera_height_m: float = 1.65,
    partly: float = 0.01,
    largely: float = 0.35,
    hidden: float = 0.8,
) -> CameraView:
    """The camera's view of M objects that can hide each other: :func:`view` of each, with the share of its box covered
    by nearer objects (:func:`occluded_share`), KITTI's occlusion level from it (:func:`occlusion_level`) and not
    visible from ``hidden`` on.

    Args:
        kinds: the M objects' kinds.
        loc_x_m: float64 ``[M, ...]``, the centres in the camera frame, to the right (m).
        loc_z_m: float64 ``[M, ...]``, forward (m).
        rot_y_rad: broadcastable to them (radians).
        camera_height_m: as :func:`view`.
        partly: the share from which an object is partly occluded (level 1).
        largely: the share from which it is largely occluded (level 2).
        hidden: the share from which it is hidden, not visible.
    Returns:
        :class:`CameraView` of arrays ``[M, ...]`` (``salient`` ``[M, ..., 11]``; ``occluded`` the share).
    Raises:
        ValueError: ``len(kinds)`` not the positions' first axis, thresholds not ``0 < partly < largely < hidden <=
            1``, or ``camera_height_m`` not in (0, 10] m."""
    x = np.asarray(loc_x_m, dtype=np.float64)
    z = np.asarray(loc_z_m, dtype=np.float64)
    if x.ndim == 0 or x.shape != z.shape or x.shape[0] != len(kinds):
        raise ValueError(
            f"views: loc_x_m and loc_z_m must be [M, ...] of one shape with M = {len(kinds)} (one row per kind), got "
            f"{x.shape} and {z.shape}"
        )
    if not 0.0 < partly < largely < hidden <= 1.0:
        raise ValueError(f"views: thresholds must be 0 < partly < largely < hidden <= 1, got {partly, largely, hidden}")
    rot = np.broadcast_to(np.asarray(rot_y_rad, dtype=np.float64), x.shape)
    each = [view(k, x[i], z[i], rot[i], camera_height_m) for i, k in enumerate(kinds)]
    boxes = ImageBox.stack([image_box(k, x[i], z[i], rot[i], camera_height_m) for i, k in enumerate(kinds)])
    share = occluded_share(boxes, z)
    salient = np.stack([v.salient for v in each])
    salient[..., 2] = occlusion_level(share, partly, largely)
    visible = np.stack([v.visible for v in each]) & (share < hidden)
    return CameraView(
        salient, np.stack([v.range_m for v in each]), np.stack([v.truncation for v in each]), visible, share
    )


def measure(
    loc_x_m: np.ndarray, loc_z_m: np.ndarray, noise: np.ndarray | None, measured: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where the camera measures the objects (module docstring): ``Z_m = Z + dZ``, ``X_m = (X + dX) Z_m / Z``.

    Args:
        loc_x_m: the true centres in the camera frame, to the right (m), shape ``S``.
        loc_z_m: forward (m), shape ``S``.
        noise: float64 ``S + [2]``, each object's (range error, lateral error) in metres as the noise PEM draws them
            (:data:`pemviz.stack.detector.NOISE_NAMES`), read only where ``measured``; None: exact measurements.
        measured: bool ``S``, the objects detected (and visible).
    Returns:
        ``(x_m, z_m)``: the measured centre to the right and the measured range forward (m, at least
        :data:`MIN_RANGE_M`: the pinhole reads no range behind the camera); the true values where not measured, so
        that every entry is finite.
    Raises:
        ValueError: ``noise`` not of shape ``S + [2]``."""
    x = np.asarray(loc_x_m, dtype=np.float64)
    z_true = np.maximum(np.asarray(loc_z_m, dtype=np.float64), MIN_RANGE_M)
    if noise is None:
        return x + 0.0, z_true
    noise = np.asarray(noise, dtype=np.float64)
    if noise.shape != x.shape + (2,):
        raise ValueError(
            f"measure: noise must be float64 {list(x.shape) + [2]} (range, lateral error; metres), got "
            f"shape {noise.shape}"
        )
    d_range = np.where(measured, noise[..., 0], 0.0)
    d_lat = np.where(measured, noise[..., 1], 0.0)
    z_meas = np.maximum(z_true + d_range, MIN_RANGE_M)
    return (x + d_lat) * (z_meas / z_true), z_meas

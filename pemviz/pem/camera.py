"""Camera geometry: the detector's pixel box errors as metric measurement errors of the obstacle.

KITTI's camera 2 is a pinhole (Hartley & Zisserman 2003, *Multiple View Geometry*, eq. 6.1; Geiger et al. 2013,
"Vision meets robotics: the KITTI dataset", eq. 5): ``u = f X / Z + c_u``, ``v = f Y / Z + c_v``, so an obstacle of
height ``H`` at range ``Z`` spans ``h = f H / Z`` pixels. With the detected box ``cx_d = cx_t + e_cx``, ``h_d = h_t
+ e_h`` (errors detector minus ground truth, :func:`pemviz.io.data.load_salient_label_table`):

- **range error** (metres, along z): ``dZ = Z (h_t / h_d - 1) = -Z e_h / h_d``, about ``-Z^2 e_h / (f H)``: it grows
  with the square of the range;
- **lateral error** (metres, along x): ``dX = e_cx Z / f``, linear in the range.

``f`` is :data:`KITTI_FOCAL_PX` (the ``P2`` matrix of KITTI's calibration files)."""

from __future__ import annotations

import numpy as np

KITTI_FOCAL_PX = 721.5377
"""Focal length of KITTI's camera 2, pixels: ``P2[0, 0]`` (= ``P2[1, 1]``) of the calibration files, e.g.
``calib/000000.txt`` of the KITTI object benchmark (also in craigiedon/PyTorch-YOLOv3-kitti,
``calibration/testing/calib/``: 87 of its 95 files; the other 8 have 707.0493). Images are 1242 x 375 pixels."""
KITTI_PRINCIPAL_POINT_PX = (609.5593, 172.854)
"""``(c_u, c_v)`` of the same ``P2``, pixels (unused by the error formulas: they cancel in differences)."""

MIN_RANGE_M = 1.0
"""Obstacles whose centre lies less than this ahead of the camera (metres) have no metric error: the pinhole range
is undefined at Z <= 0, and on KITTI all such obstacles are cut by the image's edge (42 detected rows)."""


def box_errors_to_metric(
    range_m: np.ndarray,
    det_height_px: np.ndarray,
    err_cx_px: np.ndarray,
    err_h_px: np.ndarray,
    focal_px: float = KITTI_FOCAL_PX,
) -> np.ndarray:
    """Range and lateral measurement errors (metres) of obstacles from the detector's pixel box errors: ``dZ = -Z e_h /
    h_d`` and ``dX = e_cx Z / f`` (pinhole camera, Hartley & Zisserman 2003, eq. 6.1).

    Args:
        range_m: true range ``Z`` along camera z (the label's loc_z), metres, ``[R]``.
        det_height_px: height ``h_d`` of the detected box, pixels, ``[R]``.
        err_cx_px: centre-x error ``e_cx`` (detected minus true), pixels, ``[R]``.
        err_h_px: height error ``e_h`` (detected minus true), pixels, ``[R]``.
        focal_px: focal length ``f``, pixels (default KITTI's camera 2).
    Returns:
        float64 ``[R, 2]``: the range error ``dZ`` and the lateral error ``dX`` (metres; measured minus true).
    Raises:
        ValueError: arrays of different lengths, a box height (``h_d``, ``h_d - e_h``) <= 0, a range below
            :data:`MIN_RANGE_M` or a focal length <= 0."""
    z, h_d, e_cx, e_h = (
        np.asarray(a, dtype=np.float64).reshape(-1) for a in (range_m, det_height_px, err_cx_px, err_h_px)
    )
    if not (z.shape == h_d.shape == e_cx.shape == e_h.shape):
        raise ValueError(
            f"range, box height and errors must have one length each, got {z.shape}, {h_d.shape}, "
            f"{e_cx.shape}, {e_h.shape}"
        )
    if not focal_px > 0:
        raise ValueError(f"focal length must be > 0 pixels, got {focal_px}")
    if np.any(h_d <= 0) or np.any(h_d - e_h <= 0):
        raise ValueError("detected and true box heights (h_d, h_d - e_h) must be > 0 pixels")
    if np.any(~(z >= MIN_RANGE_M)):
        raise ValueError(f"ranges must be >= {MIN_RANGE_M} m (obstacles ahead of the camera), got min {z.min():g}")
    return np.stack([-z * e_h / h_d, e_cx * z / focal_px], axis=1)

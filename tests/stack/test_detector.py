"""The library's camera and noisy detector (pemviz.stack.camera, pemviz.stack.detector): salient variables of a seen
object, measurements, and the detections' log-probability and the errors' log-density kept apart."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.core.detectors import draw_step
from pemviz.core.event_probs import event_log_probs
from pemviz.stack import camera
from pemviz.stack.detector import NOISE_NAMES, ahead_rows, camera_detector, perceive

NAMES = ("range_m", *camera.SALIENT_NAMES, "visible")


def rows_of(loc_x, loc_z):
    v = camera.view(camera.PEDESTRIAN, np.asarray(loc_x, float), np.asarray(loc_z, float), 0.0)
    return np.column_stack([v.range_m, v.salient, v.visible]), v


def test_view_gives_kitti_salient_variables_truncation_and_visibility():
    rows, v = rows_of([0.0, 0.0, 1.5], [20.0, 0.5, 2.0])
    assert rows[0, 1] == 3 and rows[0, 2] == 0.0 and rows[0, 9] == 1.65 and rows[0, 10] == 20.0  # class, trunc, loc
    assert v.visible.tolist() == [True, False, True] and 0.0 < v.truncation[2] < 1.0
    with pytest.raises(ValueError, match="kitti_class"):
        camera.ObjectKind("dog", 1.0, 1.0, 1.0)


def test_measure_moves_range_along_the_ray_and_keeps_unmeasured_objects_true():
    x, z = camera.measure(
        np.array([1.0, 1.0]), np.array([10.0, 10.0]), np.array([[2.0, 0.5], [2.0, 0.5]]), np.array([True, False])
    )
    assert z.tolist() == [12.0, 10.0] and x[0] == pytest.approx(1.5 * 1.2) and x[1] == 1.0
    with pytest.raises(ValueError, match="noise must be"):
        camera.measure(np.zeros(2), np.ones(2), np.zeros((2, 3)), np.ones(2, bool))


def test_camera_detector_never_detects_an_unseen_object_and_splits_what_draw_step_sums():
    det = camera_detector(NAMES)
    assert det.noise_names == NOISE_NAMES
    rows, _ = rows_of(np.linspace(-3, 3, 50), np.linspace(0.5, 40, 50))
    assert np.isneginf(det.detect_logit(rows)[~rows[:, -1].astype(bool)]).all()
    u = np.random.default_rng(0).random((50, 3))
    step = draw_step(det, det, rows, u)
    parts = event_log_probs(det, rows, step.detected, step.noise)
    assert np.allclose(parts.detections + parts.errors, step.log_p, rtol=1e-12, atol=1e-12)
    assert (parts.detections <= 0).all() and (parts.errors[~step.detected] == 0).all()
    drawn = perceive(det, rows, np.random.default_rng(1))
    assert drawn.noise.shape == (50, 2) and not drawn.detected[~rows[:, -1].astype(bool)].any()
    assert ahead_rows(NAMES, camera.PEDESTRIAN)(np.array([10.0, 20.0])).shape == (2, len(NAMES))


def test_camera_detector_refuses_rows_without_the_salient_variables():
    with pytest.raises(ValueError, match="lack the salient variables"):
        camera_detector(("range_m", "class"))

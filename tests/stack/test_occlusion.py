"""The stack's occlusion between objects (pemviz.stack.camera): image boxes, the occluded share and KITTI's level, on
boxes computed by hand from the pinhole's ``u = X / Z``, ``v = Y / Z``."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.scenarios.cut_in.scenario import CutInParams
from pemviz.scenarios.cut_in.scene import CutInMemory, camera_view, traffic_at
from pemviz.stack import camera
from pemviz.stack.camera import CAR, ObjectKind

FORWARD = -np.pi / 2  # KITTI's rotation_y of a car driving away from the camera


def _share_behind(z1: float, z2: float, camera_height_m: float = 1.65) -> tuple[float, float, bool]:
    """The occluded share, level and visibility of a car at depth z2 straight behind one at z1 (centres on the axis)."""
    v = camera.views([CAR, CAR], np.zeros((2, 1)), np.array([[z1], [z2]]), FORWARD, camera_height_m)
    assert v.occluded[0, 0] == 0.0 and v.visible[0, 0]  # nothing in front of the near car
    return float(v.occluded[1, 0]), float(v.salient[1, 0, 2]), bool(v.visible[1, 0])


def test_a_car_far_behind_a_car_shows_over_its_roof_by_hand():
    # CAR: h 1.5, w 1.7, l 4.2; driving forward its faces are at z -+ 2.1 and its sides at -+ 0.85
    share, level, visible = _share_behind(20.0, 80.0)
    near_top = 0.15 / 22.1  # the near roof's far edge: (1.65 - 1.5) / Z_far
    far_top, far_bottom = 0.15 / 82.1, 1.65 / 77.9  # the far box: inside the near one across (0.85/77.9 < 0.85/17.9)
    expected = (far_bottom - near_top) / (far_bottom - far_top)
    assert share == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.7437, abs=1e-4)  # a quarter of its box shows over the lead's roof
    assert level == 2.0 and visible  # largely occluded, still visible: the PEMs see occlusion level 2


def test_a_car_up_to_about_three_times_as_far_is_hidden_behind_a_car_at_the_default_camera_height():
    for z1, hidden_up_to in ((10.0, 37.37), (20.0, 67.33), (30.0, 97.33)):  # docs/realistic-stack.md's figures
        assert not _share_behind(z1, hidden_up_to - 0.1)[2]
        share, _, visible = _share_behind(z1, hidden_up_to + 0.1)
        assert visible and 0.79 < share < 0.8
    by_hand = (1.65 / 57.9 - 0.15 / 22.1) / (1.65 / 57.9 - 0.15 / 62.1)  # 60 m behind 20 m: hidden
    assert _share_behind(20.0, 60.0) == (pytest.approx(by_hand, rel=1e-12), 2.0, False)
    assert _share_behind(20.0, 80.0, camera_height_m=1.5)[0] == 1.0  # a camera at roof height sees nothing over it


def test_who_is_nearer_is_decided_per_element_and_pairs_give_the_same_bits():
    kinds = [CAR, CAR]
    x = np.zeros((2, 2))
    z = np.array([[20.0, 60.0], [60.0, 20.0]])  # rollout 2: the cars swapped
    v = camera.views(kinds, x, z, FORWARD)
    assert v.occluded[1, 0] == v.occluded[0, 1] > 0.8 and v.occluded[0, 0] == v.occluded[1, 1] == 0.0
    boxes = camera.ImageBox.stack([camera.image_box(k, x[i], z[i], FORWARD) for i, k in enumerate(kinds)])
    by_pairs = camera.occluded_share(camera.ImageBox(*(a[:, :1] for a in vars(boxes).values())), pairs=((0, 1),))
    assert by_pairs[1, 0] == v.occluded[1, 0]


def test_two_nearer_boxes_add_up_and_the_share_stops_at_one():
    # two pedestrians side by side 10 m ahead, a car 30 m ahead behind both: each pedestrian covers its own strip
    ped = ObjectKind("pedestrian", 1.75, 0.6, 0.6)
    x, z = np.array([[-0.5], [0.5], [0.0]]), np.array([[10.0], [10.0], [30.0]])
    boxes = camera.ImageBox.stack([camera.image_box(k, x[i], z[i], 0.0) for i, k in enumerate((ped, ped, CAR))])
    one = camera.occluded_share(camera.ImageBox(*(a[[0, 2]] for a in vars(boxes).values())), np.array([10.0, 30.0]))
    both = camera.occluded_share(boxes, z)
    assert both[2, 0] == pytest.approx(2.0 * one[1, 0], rel=1e-12)  # symmetric strips, disjoint
    big = ObjectKind("truck", 3.5, 2.5, 8.0)
    placed = ((big, 12.0), (big, 12.5), (CAR, 40.0))
    boxes = camera.ImageBox.stack([camera.image_box(k, 0.0, zz, FORWARD) for k, zz in placed])
    share = camera.occluded_share(boxes, np.array([12.0, 12.5, 40.0]))
    assert share[2] == 1.0 and share[1] == 1.0  # covered twice over: capped at the whole box


def test_the_cut_in_occlusion_is_the_stack_s():
    p = CutInParams()
    x, y = np.array([15.0, 30.0, 60.0]), np.array([p.ego_y_m, p.ego_y_m + 2.0, p.ego_y_m])
    tr, _ = traffic_at(p, 0, x, y, np.zeros(3), np.full(3, 20.0), CutInMemory.initial(3))
    ego_x = np.array([0.0, 5.0])
    mine = camera_view(p, tr, ego_x)
    kind = ObjectKind("car", p.vehicle_height_m, p.vehicle_width_m, p.vehicle_length_m)
    loc_z = x[:, None] - (ego_x + p.camera_offset_m)
    stack_view = camera.views(
        [kind] * 3,
        np.broadcast_to((y - p.ego_y_m)[:, None], loc_z.shape),
        loc_z,
        FORWARD,
        p.camera_height_m,
        p.occlusion_partly,
        p.occlusion_largely,
        p.occlusion_hidden,
    )
    np.testing.assert_allclose(mine.occluded_fraction, stack_view.occluded, rtol=1e-12)
    assert mine.occluded_fraction[2].min() > 0.0 and mine.occluded_fraction[1].min() > 0.0
    np.testing.assert_array_equal(mine.visible, stack_view.visible)


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: camera.occluded_share(camera.image_box(CAR, np.zeros(2), np.ones(2), 0.0)), "give depth_m"),
        (lambda: camera.occluded_share(camera.image_box(CAR, np.zeros(2), np.ones(2), 0.0), np.ones(3)), "2 rows"),
        (lambda: camera.views([CAR], np.zeros((2, 1)), np.ones((2, 1)), 0.0), "M = 1"),
        (lambda: camera.views([CAR], np.zeros((1, 1)), np.ones((1, 1)), 0.0, hidden=0.2), "0 < partly"),
    ],
)
def test_bad_input_is_refused_in_one_line(call, message):
    with pytest.raises(ValueError, match=message):
        call()

"""The spec's camera convention: numpy math checked against OpenCV and against itself."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from dataset_spec import camera as C
from dataset_spec import boxes as B
from dataset_spec.synthetic import look_at, simple_intrinsics


@pytest.fixture
def cam():
    return simple_intrinsics(160, 90), look_at((3.0, -7.0, 1.4), (0.0, 0.0, 0.5))


def test_projection_matches_cv2_projectPoints(cam):
    K, c2w = cam
    pts = np.random.default_rng(1).uniform(-3, 3, (50, 3))
    uv, z = C.project_points(K, c2w, pts)
    w2c = C.world_to_camera(c2w)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    ref, _ = cv2.projectPoints(pts, rvec, w2c[:3, 3], K, None)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-6)
    assert np.all(z > 0)


def test_pixel_rays_round_trip(cam):
    K, c2w = cam
    uv = np.array([[0.0, 0.0], [159.0, 89.0], [80.3, 40.7]])
    origins, dirs = C.pixel_rays(K, c2w, uv)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    back, z = C.project_points(K, c2w, origins + 5.0 * dirs)
    np.testing.assert_allclose(back, uv, atol=1e-9)
    assert np.all(z > 0)  # rays point into the scene (+z forward), unlike the original code


def test_camera_looks_forward_with_y_down(cam):
    K, c2w = cam
    forward = c2w[:3, 3] + 10 * c2w[:3, 2]
    uv, z = C.project_points(K, c2w, np.array([forward, forward + [0, 0, 1.0]]))
    np.testing.assert_allclose(uv[0], K[:2, 2])
    assert uv[1, 1] < uv[0, 1]  # world up appears higher in the image (smaller v)


def test_unproject_depth_inverts_projection(cam):
    K, c2w = cam
    depth = np.full((90, 160), 7.5, np.float32)
    depth[0, 0] = 0
    pts = C.unproject_depth(K, c2w, depth)
    uv, z = C.project_points(K, c2w, pts[10, 20])
    np.testing.assert_allclose(uv, [20, 10], atol=1e-6)
    np.testing.assert_allclose(z, 7.5, atol=1e-5)
    assert np.isnan(pts[0, 0]).all()


def test_blender_axes_flip_is_involution():
    c2w = look_at((1, 2, 3), (0, 0, 0))
    b = C.opencv_to_blender_camera_to_world(c2w)
    np.testing.assert_allclose(C.blender_to_opencv_camera_to_world(b), c2w)
    np.testing.assert_allclose(-b[:3, 2], c2w[:3, 2])  # Blender looks down -z


@pytest.mark.parametrize("fit,shift", [("AUTO", (0, 0)), ("HORIZONTAL", (0.1, -0.05)), ("VERTICAL", (-0.2, 0.1))])
def test_intrinsics_from_blender_principal_point_and_focal(fit, shift):
    K = C.intrinsics_from_blender(lens_mm=35, sensor_width_mm=36, sensor_height_mm=24, sensor_fit=fit,
                                  shift_x=shift[0], shift_y=shift[1], width=200, height=100)
    assert C.check_intrinsics(K) is None
    view = 200 if fit != "VERTICAL" else 100
    sensor = 36 if fit != "VERTICAL" else 24
    assert K[0, 0] == pytest.approx(35 / sensor * view)
    assert K[0, 2] == pytest.approx(99.5 - shift[0] * view)
    assert K[1, 2] == pytest.approx(49.5 + shift[1] * view)


def test_scale_intrinsics_maps_pixel_edges(cam):
    K, _ = cam
    K2 = C.scale_intrinsics(K, 0.5, 0.5)
    # the image's left edge (-0.5) and right edge (W-0.5) map to the resized image's edges
    x = np.array([-0.5, 159.5])
    x_cam = (x - K[0, 2]) / K[0, 0]
    np.testing.assert_allclose(x_cam * K2[0, 0] + K2[0, 2], [-0.5, 79.5])


def test_matrix_checks_catch_bad_matrices():
    assert C.check_intrinsics(np.array([[1, 0, 0], [1, 1, 0], [0, 0, 1.0]])) == "K is not upper-triangular"
    assert C.check_intrinsics(np.eye(2)) is not None
    bad = np.eye(4)
    bad[0, 0] = 2
    assert "orthonormal" in C.check_rigid(bad)
    refl = np.diag([1, 1, -1, 1.0])
    assert "reflection" in C.check_rigid(refl)
    assert C.check_rigid(look_at((1, 2, 3), (0, 0, 0))) is None


def test_box_corners_round_trip_and_order():
    center, size, yaw = np.array([1.0, 2.0, 0.75]), np.array([4.0, 2.0, 1.5]), 0.7
    corners = B.box_corners(center, size, yaw)
    c2, s2, y2 = B.box_from_corners(corners)
    np.testing.assert_allclose(c2, center)
    np.testing.assert_allclose(s2, size)
    assert y2 == pytest.approx(yaw)
    assert np.all(corners[:4, 2] < corners[4:, 2])  # bottom face first
    assert B.points_in_box(corners.mean(0, keepdims=True), center, size, yaw).all()


def test_box_behind_camera_does_not_wrap(cam):
    K, c2w = cam
    eye, fwd = c2w[:3, 3], c2w[:3, 2]
    behind = B.box_corners(eye - 5 * fwd, (1, 1, 1), 0.0)
    assert B.project_box_2d(K, c2w, behind) is None
    # a long box from behind the camera to the front: clipped box stays finite and sane
    straddle = B.box_corners(eye + 0.0 * fwd + [0, 0, -1.0], (20, 1, 0.5), float(np.arctan2(fwd[1], fwd[0])))
    box = B.project_box_2d(K, c2w, straddle)
    assert box is not None and np.all(np.isfinite(box)) and box[0] < box[2] and box[1] < box[3]


def test_yolo_conversion_and_iou():
    box = np.array([10.0, 20.0, 30.0, 60.0])
    y = B.box_to_yolo(box, 100, 80)
    np.testing.assert_allclose(B.yolo_to_box(y, 100, 80), box)
    full = np.array([-0.5, -0.5, 99.5, 79.5])
    np.testing.assert_allclose(B.box_to_yolo(full, 100, 80), [0.5, 0.5, 1.0, 1.0])
    iou = B.box_iou(np.array([[0, 0, 10, 10.0]]), np.array([[0, 0, 10, 10.0], [5, 0, 15, 10.0], [20, 20, 30, 30.0]]))
    np.testing.assert_allclose(iou, [[1.0, 1 / 3, 0.0]])


@pytest.mark.parametrize("skew", [0.0, 0.7])
def test_mirror_camera_sees_the_mirrored_world_as_the_flipped_image(cam, skew):
    K, c2w = cam
    K = K.copy()
    K[0, 1] = skew
    width = 160
    pts = np.random.default_rng(2).uniform(-3, 3, (40, 3))
    uv, z = C.project_points(K, c2w, pts)
    K2, c2w2 = C.mirror_camera(K, c2w, width)
    assert C.check_rigid(c2w2) is None and C.check_intrinsics(K2) is None
    uv2, z2 = C.project_points(K2, c2w2, pts * [-1.0, 1.0, 1.0])
    np.testing.assert_allclose(uv2[:, 0], width - 1 - uv[:, 0], atol=1e-9)
    np.testing.assert_allclose(uv2[:, 1], uv[:, 1], atol=1e-9)
    np.testing.assert_allclose(z2, z, atol=1e-9)
    np.testing.assert_allclose(c2w2[2, 3], c2w[2, 3])  # camera height (and the ground plane) unchanged
    K3, c2w3 = C.mirror_camera(K2, c2w2, width)  # an involution
    np.testing.assert_allclose(K3, K)
    np.testing.assert_allclose(c2w3, c2w)


def test_flip_box_x_matches_yolo_and_preserves_size():
    box = np.array([3.0, 5.0, 40.0, 30.0])
    f = B.flip_box_x(box, 64)
    np.testing.assert_allclose(B.flip_box_x(f, 64), box)
    y, yf = B.box_to_yolo(box, 64, 48), B.box_to_yolo(f, 64, 48)
    np.testing.assert_allclose(yf, [1 - y[0], y[1], y[2], y[3]])
    whole = np.array([-0.5, -0.5, 63.5, 47.5])  # the whole image maps onto itself
    np.testing.assert_allclose(B.flip_box_x(whole, 64), whole)


def test_camera_info_resized_mirrored_and_shifted_see_the_same_world(cam):
    from dataset_spec import CameraInfo

    K, c2w = cam
    info = CameraInfo("c", 160, 90, K, c2w)
    pts = np.random.default_rng(2).uniform(-3, 3, (40, 3))
    uv, z = info.project(pts)
    half = info.resized(80, 45)
    uv_half, z_half = half.project(pts)
    np.testing.assert_allclose(uv_half, (uv + 0.5) * 0.5 - 0.5, atol=1e-9)  # pixel edges scale, centres at +0.5
    mirrored_uv, mirrored_z = info.mirrored().project(pts * [-1, 1, 1])  # the mirrored world, the flipped image
    np.testing.assert_allclose(mirrored_uv, np.stack([159 - uv[:, 0], uv[:, 1]], 1), atol=1e-9)
    np.testing.assert_allclose(mirrored_z, z, atol=1e-9)
    np.testing.assert_allclose(info.shifted(3, -2).project(pts)[0], uv + [3, -2], atol=1e-9)
    origins, dirs = half.pixel_rays(uv_half)
    np.testing.assert_allclose(origins + dirs * np.linalg.norm(pts - origins, axis=1)[:, None], pts, atol=1e-6)

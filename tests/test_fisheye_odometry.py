"""Visual odometry from the downward fisheye, on fisheye views of a textured plane moved by known motions."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from perception.cameras import OmniCamera
from perception.fisheye_odometry import FisheyeOdometry, FisheyeOdometryConfig, rays_to_ground

SIZE = 400
PLANE = (0.0, 0.0, -0.3)  # the ground 0.3 m below the body origin
TEX_M = 8.0  # the texture covers 8 m x 8 m about the world origin
TEX_PX = 2048


def _camera(height=0.6) -> OmniCamera:
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # looking down
    T[:3, 3] = (0.0, 0.0, height)
    return OmniCamera.equidistant((SIZE, SIZE), math.radians(180.0), SIZE / 2 - 10, T_body_cam=T)


def _texture(seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tex = rng.random((TEX_PX, TEX_PX)).astype(np.float32)
    tex = cv2.GaussianBlur(tex, (0, 0), 2.0)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return tex


def _render(cam: OmniCamera, tex: np.ndarray, pose, contrast=1.0) -> np.ndarray:
    """The fisheye view of the textured ground z = c (body frame) with the body at pose (x, y, yaw)."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    g = rays_to_ground(cam, np.column_stack([xx.ravel(), yy.ravel()]).astype(float), PLANE)
    x, y, yaw = pose
    cy, sy = math.cos(yaw), math.sin(yaw)
    wx = x + cy * g[:, 0] - sy * g[:, 1]
    wy = y + sy * g[:, 0] + cy * g[:, 1]
    u = ((wx + TEX_M / 2) / TEX_M * TEX_PX).reshape(SIZE, SIZE).astype(np.float32)
    v = ((wy + TEX_M / 2) / TEX_M * TEX_PX).reshape(SIZE, SIZE).astype(np.float32)
    img = cv2.remap(tex, u, v, cv2.INTER_LINEAR, borderValue=0.5)
    img = 0.5 + contrast * (img - 0.5)
    img[~np.isfinite(u)] = 0.0
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)


def _after(twist, dt):
    """The pose (x, y, yaw) after ``dt`` at a constant body twist (v_x, v_y, omega) from the origin."""
    vx, vy, w = twist
    a = w * dt
    if abs(w) < 1e-12:
        return vx * dt, vy * dt, 0.0
    return (
        (vx * math.sin(a) + vy * (math.cos(a) - 1.0)) / w,
        (vx * (1.0 - math.cos(a)) + vy * math.sin(a)) / w,
        a,
    )


def _with_rover_parts(img: np.ndarray) -> np.ndarray:
    out = img.copy()
    out[250:330, 60:120] = 20  # a wheel, fixed in the image
    out[250:330, 280:340] = 20
    shade = np.zeros_like(out, bool)
    shade[120:230, 150:260] = True  # the body's shadow, fixed in the image
    out[shade] = (out[shade] * 0.45).astype(np.uint8)
    return out


@pytest.mark.parametrize("twist", [(0.5, 0.0, 0.0), (0.4, 0.05, 0.3), (0.2, -0.1, -0.5), (0.0, 0.0, 0.0)])
def test_the_twist_of_a_known_motion_is_recovered(twist):
    cam, tex, dt = _camera(), _texture(), 1.0 / 30.0
    odo = FisheyeOdometry(cam, ground_plane=PLANE)
    assert odo.update(_render(cam, tex, (0.1, -0.2, 0.3)), 0.0) is None
    x, y, a = _after(twist, dt)
    c, s = math.cos(0.3), math.sin(0.3)
    est = odo.update(_render(cam, tex, (0.1 + c * x - s * y, -0.2 + s * x + c * y, 0.3 + a)), dt)
    assert est.valid, est.reason
    assert est.n_inliers >= 100
    assert est.v_x == pytest.approx(twist[0], abs=0.01 * max(abs(twist[0]), 0.1))
    assert est.v_y == pytest.approx(twist[1], abs=0.005)
    assert est.omega == pytest.approx(twist[2], abs=0.01)
    assert np.all(np.isfinite(est.twist_std)) and est.twist_std[0] < 0.01


def test_the_rovers_parts_and_shadow_fixed_in_the_image_are_left_out():
    cam, tex, dt, twist = _camera(), _texture(1), 1.0 / 30.0, (0.4, 0.0, 0.2)
    odo = FisheyeOdometry(cam, ground_plane=PLANE)
    pose = np.zeros(3)
    errs = []
    for k in range(8):
        x, y, a = _after(twist, dt)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        est = odo.update(_with_rover_parts(_render(cam, tex, tuple(pose))), k * dt)
        pose = pose + np.array([c * x - s * y, s * x + c * y, a])
        if est is not None:
            assert est.valid, est.reason
            errs.append(np.abs(est.twist - twist))
    errs = np.array(errs)
    assert errs[:, 0].max() < 0.01 and errs[:, 1].max() < 0.01 and errs[:, 2].max() < 0.02
    # the wheels' edges were learned as the rover's (they stand still); the open ground was not
    learned = odo.learned_mask
    assert not learned[245:335, 55:125].all()
    assert learned[60:100, 180:220].all()
    # no feature is taken on the shadow's edge (the paper's mask): within 4 px of its border
    near_edge = (np.abs(est.prev_px[:, 1] - 120) < 4) | (np.abs(est.prev_px[:, 1] - 230) < 4)
    near_edge |= (np.abs(est.prev_px[:, 0] - 150) < 4) | (np.abs(est.prev_px[:, 0] - 260) < 4)
    inside = (est.prev_px[:, 0] > 146) & (est.prev_px[:, 0] < 264) & (est.prev_px[:, 1] > 116)
    inside &= est.prev_px[:, 1] < 234
    assert not (near_edge & inside).any()


def test_a_given_mask_keeps_features_off_the_rover():
    cam, tex = _camera(), _texture(2)
    mask = np.ones((SIZE, SIZE), bool)
    mask[250:330, 60:120] = False
    odo = FisheyeOdometry(cam, ground_plane=PLANE, mask=mask)
    odo.update(_with_rover_parts(_render(cam, tex, (0.0, 0.0, 0.0))), 0.0)
    est = odo.update(_with_rover_parts(_render(cam, tex, (0.015, 0.0, 0.0))), 1.0 / 30.0)
    assert est.valid
    inside = (est.prev_px[:, 1] >= 250) & (est.prev_px[:, 1] < 330) & (est.prev_px[:, 0] >= 60)
    inside &= est.prev_px[:, 0] < 120
    assert not inside.any()


def test_a_textureless_or_black_frame_is_invalid_not_a_confident_zero():
    cam = _camera()
    for frame in (np.full((SIZE, SIZE), 128, np.uint8), np.zeros((SIZE, SIZE), np.uint8)):
        odo = FisheyeOdometry(cam, ground_plane=PLANE)
        odo.update(frame, 0.0)
        est = odo.update(frame, 1.0 / 30.0)
        assert not est.valid and est.quality == 0.0 and math.isnan(est.v_x)


def test_bad_input_is_refused_with_a_clear_error():
    cam = _camera()
    with pytest.raises(ValueError, match="mask: 100 x 50 px, but the fisheye's images are 400 x 400"):
        FisheyeOdometry(cam, ground_plane=PLANE, mask=np.ones((50, 100), bool))
    odo = FisheyeOdometry(cam)
    with pytest.raises(ValueError, match="ground_plane: the fisheye odometry needs the ground"):
        odo.update(np.zeros((SIZE, SIZE), np.uint8), 0.0)
    with pytest.raises(ValueError, match="ground_plane"):
        FisheyeOdometry(cam, ground_plane=(0.0, float("nan"), -0.3))
    with pytest.raises(ValueError, match="FisheyeOdometryConfig.window"):
        FisheyeOdometryConfig(window=8)
    odo = FisheyeOdometry(cam, ground_plane=PLANE)
    odo.update(np.zeros((SIZE, SIZE), np.uint8), 1.0)
    with pytest.raises(ValueError, match="not after"):
        odo.update(np.zeros((SIZE, SIZE), np.uint8), 1.0)


def test_rays_meet_the_ground_where_projection_puts_them():
    cam = _camera()
    pts = np.array([[0.3, 0.2, -0.3], [-0.5, 0.4, -0.3], [0.0, 0.0, -0.3], [1.0, -1.2, -0.3]])
    cam_pts = (np.linalg.inv(cam.T_body_cam) @ np.column_stack([pts, np.ones(4)]).T).T[:, :3]
    px = cam.world2cam(cam_pts)
    assert rays_to_ground(cam, px, PLANE) == pytest.approx(pts, abs=1e-6)
    # a ray within 20 degrees of the horizon is not used
    far = cam.world2cam((np.linalg.inv(cam.T_body_cam) @ np.array([5.0, 0.0, -0.3, 1.0]))[:3])
    assert np.isnan(rays_to_ground(cam, far[None], PLANE, min_depression_deg=20.0)).all()

"""Visual odometry from the downward fisheye, on fisheye views of a textured plane moved by known motions."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from perception.models.cameras import OmniCamera
from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig, rays_to_ground

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
    with pytest.raises(ValueError, match="not a finite time after"):
        odo.update(np.zeros((SIZE, SIZE), np.uint8), 1.0)
    # a plane the camera cannot stand over: the sign turned (the camera 0.6 m up, the plane 0.9 m
    # up), or in millimetres (the camera 300 m above it, past the 1.5 m of ground used)
    with pytest.raises(ValueError, match="0.300 m below the ground plane.*check ground_plane's sign"):
        FisheyeOdometry(cam, ground_plane=(0.0, 0.0, 0.9))
    with pytest.raises(ValueError, match="stands 300.6 m above.*give the plane in metres"):
        FisheyeOdometry(cam, ground_plane=(0.0, 0.0, -300.0))
    with pytest.raises(ValueError, match="mask: zero everywhere"):
        FisheyeOdometry(cam, ground_plane=PLANE, mask=np.zeros((SIZE, SIZE), bool))
    # ... given for one frame (the kinematics' plane), the pair is invalid and says why
    tex = _texture()
    odo = FisheyeOdometry(cam)
    odo.update(_render(cam, tex, (0.0, 0.0, 0.0)), 0.0, ground_plane=PLANE)
    est = odo.update(_render(cam, tex, (0.01, 0.0, 0.0)), 1.0 / 30.0, ground_plane=(0.0, 0.0, 0.9))
    assert not est.valid and "the ground is not in view in this frame" in est.reason and math.isnan(est.v_x)


def test_an_omnidirectional_calibration_that_cannot_see_its_ground_plane_is_refused(tmp_path):
    from dataclasses import replace

    from perception.models.calib_io import CalibrationError, read_yaml

    cam = _rover_fisheye()
    assert cam.ground_view_error(ROVER_PLANE) == ""
    assert "ground_plane: not set" in cam.ground_view_error()
    with pytest.raises(CalibrationError, match="0.385 m below the ground plane"):
        replace(cam, ground_plane=(0.0, 0.0, 0.265))
    up = cam.T_body_cam.copy()
    up[:3, :3] = np.eye(3)  # the optical axis along the body's +z: the ground 180 deg off it
    with pytest.raises(CalibrationError, match="180 deg off its optical axis, outside its 185 deg"):
        replace(cam, T_body_cam=up, ground_plane=ROVER_PLANE)
    tilted = cam.T_body_cam.copy()  # tilted by 80 deg: the ground below still in the 185 deg view
    tilted[:3, :3] = tilted[:3, :3] @ np.array(
        [[math.cos(1.396), 0.0, math.sin(1.396)], [0.0, 1.0, 0.0], [-math.sin(1.396), 0.0, math.cos(1.396)]]
    )
    assert replace(cam, T_body_cam=tilted, ground_plane=ROVER_PLANE).ground_view_error() == ""
    assert "more than the 0.1 m" in cam.ground_view_error(ROVER_PLANE, max_height=0.1)
    # the field of view in the file's own key and unit; a folder given for the file
    text = cam.save(tmp_path / "omni.yaml").read_text()
    (tmp_path / "wide.yaml").write_text(
        "\n".join("max_fov_deg: 400.0" if ln.startswith("max_fov_deg") else ln for ln in text.splitlines())
    )
    with pytest.raises(CalibrationError, match="max_fov_deg: 400 deg is impossible; use \\(0, 360\\)"):
        OmniCamera.load(tmp_path / "wide.yaml")
    with pytest.raises(CalibrationError, match="a folder, not a calibration file"):
        read_yaml(tmp_path, CalibrationError, "calibration file")


def test_rays_meet_the_ground_where_projection_puts_them():
    cam = _camera()
    pts = np.array([[0.3, 0.2, -0.3], [-0.5, 0.4, -0.3], [0.0, 0.0, -0.3], [1.0, -1.2, -0.3]])
    cam_pts = (np.linalg.inv(cam.T_body_cam) @ np.column_stack([pts, np.ones(4)]).T).T[:, :3]
    px = cam.world2cam(cam_pts)
    assert rays_to_ground(cam, px, PLANE) == pytest.approx(pts, abs=1e-6)
    # a ray within 20 degrees of the horizon is not used
    far = cam.world2cam((np.linalg.inv(cam.T_body_cam) @ np.array([5.0, 0.0, -0.3, 1.0]))[:3])
    assert np.isnan(rays_to_ground(cam, far[None], PLANE, min_depression_deg=20.0)).all()


def _rover_fisheye(size=(320, 240)) -> OmniCamera:
    """The rover's fisheye mount: 0.12 m below the body origin (0.145 m above the ground), looking down."""
    m = np.eye(4)
    m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    m[:3, 3] = (0.0, 0.0, -0.12)
    return OmniCamera.equidistant(size, math.radians(185.0), size[0] * 150.0 / 320.0, T_body_cam=m)


ROVER_PLANE = (0.0, 0.0, -0.265)  # the rover's ground: the body origin 0.265 m above it


def relief_height(wx, wy, amplitude: float, wavelength: float = 1.5):
    """A smooth relief A sin(2 pi x / L) sin(2 pi 0.8 y / L + 1) over the world plane [m]."""
    k = 2 * math.pi / wavelength
    return amplitude * np.sin(k * wx) * np.sin(0.8 * k * wy + 1.0)


def render_relief(cam: OmniCamera, tex: np.ndarray, pose, amplitude: float) -> np.ndarray:
    """The fisheye view of the textured ground ROVER_PLANE + relief, the body at pose (x, y, yaw)."""
    w, h = cam.image_size
    yy, xx = np.mgrid[0:h, 0:w]
    rays = cam.cam2world(np.column_stack([xx.ravel(), yy.ravel()]).astype(float))
    R, o = cam.T_body_cam[:3, :3], cam.T_body_cam[:3, 3]
    d = rays @ R.T
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)

    def world(dist):
        p = o + dist[:, None] * d
        return x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]

    with np.errstate(divide="ignore", invalid="ignore"):
        dist = (ROVER_PLANE[2] - o[2]) / d[:, 2]
        for _ in range(8):  # the ray's meeting with the relief, by fixed-point iteration
            wx, wy = world(dist)
            dist = (ROVER_PLANE[2] + relief_height(wx, wy, amplitude) - o[2]) / d[:, 2]
    wx, wy = world(dist)
    u = ((wx + TEX_M / 2) / TEX_M * TEX_PX).reshape(h, w).astype(np.float32)
    v = ((wy + TEX_M / 2) / TEX_M * TEX_PX).reshape(h, w).astype(np.float32)
    bad = ~(np.isfinite(u) & (d[:, 2] < -0.05).reshape(h, w))
    u[bad], v[bad] = -1.0, -1.0
    img = cv2.remap(tex, u, v, cv2.INTER_LINEAR, borderValue=0.0)
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)


def _moved(points_body, motion, dt):
    """Body-frame points of the first frame seen from the body moved by (v, omega) over dt."""
    from perception.odometry.flow import _rotation

    R = _rotation(np.asarray(motion[3:6]) * dt)
    return (points_body - np.asarray(motion[:3]) * dt) @ R  # R^T (X - v dt), row-wise


def test_the_two_view_fit_recovers_a_known_motion_over_unknown_relief():
    from perception.odometry.fisheye import two_view_motion

    cam = _rover_fisheye()
    rng = np.random.default_rng(4)
    n = 250
    xy = rng.uniform(-0.35, 0.35, (n, 2))
    heights = rng.uniform(-0.03, 0.03, n)  # relief the plane does not know
    X = np.column_stack([xy, ROVER_PLANE[2] + heights])
    motion = np.array([0.45, -0.04, 0.01, 0.15, -0.2, 0.3])  # v [m/s], omega [rad/s]
    dt = 1.0 / 30.0
    R_bc, o = cam.T_body_cam[:3, :3], cam.T_body_cam[:3, 3]

    def rays(points):
        pc = (points - o) @ R_bc
        return pc / np.linalg.norm(pc, axis=1, keepdims=True)

    r0, r1 = rays(X), rays(_moved(X, motion, dt))
    init = np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.25])
    # (a loose prior on the roll and pitch rates: they trade against the sideways and forward
    # translation, which a tight one would bias)
    fit = two_view_motion(r0, r1, dt, cam.T_body_cam, ROVER_PLANE, init, px_per_rad=95.0, rate_std=10.0)
    assert fit is not None
    assert np.max(fit.residual_px) < 0.01
    # the rotation and the translation's direction are exact whatever the relief
    assert fit.motion[3:6] == pytest.approx(motion[3:6], abs=1e-4)
    from perception.odometry.flow import _rotation

    shift = motion[:3] * dt + (_rotation(motion[3:6] * dt) - np.eye(3)) @ o  # the camera's
    direction = fit.camera_shift / np.linalg.norm(fit.camera_shift)
    assert direction == pytest.approx(shift / np.linalg.norm(shift), abs=1e-4)
    # the heights come out up to the scale, which the prior (zero mean) sets
    k = np.linalg.norm(fit.camera_shift) / np.linalg.norm(shift)
    assert abs(k - 1.0) < 0.05
    assert np.corrcoef(fit.heights, heights)[0, 1] > 0.99
    # with noise, the covariance is of the right size
    noisy = r1 + rng.normal(0.0, 0.2 / 95.0, r1.shape)
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    fit = two_view_motion(r0, noisy, dt, cam.T_body_cam, ROVER_PLANE, init, px_per_rad=95.0, pixel_std=0.2)
    assert fit is not None
    std = np.sqrt(np.diag(fit.cov))
    assert abs(fit.motion[5] - motion[5]) < 4.0 * std[5] and std[5] < 0.05
    # too few points, or rays that miss the plane: no fit
    assert two_view_motion(r0[:5], r1[:5], dt, cam.T_body_cam, ROVER_PLANE, init, px_per_rad=95.0) is None
    up = r0.copy()
    up[0] = -up[0]
    assert two_view_motion(up, r1, dt, cam.T_body_cam, ROVER_PLANE, init, px_per_rad=95.0) is None


def test_relief_under_the_fisheye_does_not_bias_the_yaw_rate():
    """A 3 cm relief under a camera 0.145 m up: the two-view fit keeps the yaw rate within 0.01 rad/s."""
    cam, tex, dt, twist = _rover_fisheye(), _texture(3), 1.0 / 30.0, (0.4, 0.0, 0.2)
    frames, pose = [], np.array([0.3, -0.2, 0.4])
    for _ in range(16):
        frames.append(render_relief(cam, tex, tuple(pose), 0.03))
        x, y, a = _after(twist, dt)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * x - s * y, s * x + c * y, a])
    mae = {}
    for two_view in (True, False):
        odo = FisheyeOdometry(cam, FisheyeOdometryConfig(two_view=two_view), ground_plane=ROVER_PLANE)
        errs = []
        for k, img in enumerate(frames):
            est = odo.update(img, k * dt)
            if est is not None:
                assert est.valid, est.reason
                errs.append(np.abs(est.twist - twist))
        mae[two_view] = np.mean(errs, axis=0)
    assert mae[True][2] < 0.01 and mae[True][1] < 0.005
    assert mae[False][2] > 3.0 * mae[True][2]  # the plane alone takes the relief into the yaw rate
    assert mae[True][0] < 0.05  # the speed's scale still rests on the plane (at most an eighth)


def _fisheye_folder(tmp_path, twist=(0.4, 0.0, 0.2), n=8, dt=1.0 / 30.0):
    """A folder of the rover fisheye's views of a textured plane driven at ``twist``, and its calibration."""
    cam, tex = _rover_fisheye(), _texture(5)
    folder = tmp_path / "fisheye"
    folder.mkdir()
    pose = np.array([0.2, -0.1, 0.3])
    for k in range(n):
        cv2.imwrite(str(folder / f"{k:04d}.png"), render_relief(cam, tex, tuple(pose), 0.0))
        x, y, a = _after(twist, dt)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * x - s * y, s * x + c * y, a])
    return cam, folder


def test_the_fisheye_odometry_runs_on_an_image_folder(tmp_path):
    import csv
    from dataclasses import replace

    from perception.logs.offline import run_folder_odometry
    from perception.models.calib_io import CalibrationError

    cam, folder = _fisheye_folder(tmp_path)
    calib = tmp_path / "omni.yaml"
    replace(cam, ground_plane=ROVER_PLANE).save(calib)
    res = run_folder_odometry(folder, calib, 30.0, tmp_path / "out", mcap=False)
    assert res.frames == 8 and res.valid == 7
    rows = list(csv.DictReader(open(res.csv_path)))
    vx = np.array([float(r["v_x"]) for r in rows[1:]])
    w = np.array([float(r["omega"]) for r in rows[1:]])
    assert np.abs(vx - 0.4).max() < 0.02 and np.abs(w - 0.2).max() < 0.02
    # a mask of the rover's parts beside the calibration: the features keep off it
    mask = np.full((240, 320), 255, np.uint8)
    mask[:, :40] = 0
    cv2.imwrite(str(tmp_path / "parts.png"), mask)
    text = calib.read_text() + "mask: parts.png\n"
    (tmp_path / "masked.yaml").write_text(text)
    res = run_folder_odometry(folder, tmp_path / "masked.yaml", 30.0, tmp_path / "out2", mcap=False)
    assert res.valid == 7
    # bad input: no ground plane, a mask of another size, a missing mask; nothing is written
    cam.save(tmp_path / "bare.yaml")
    with pytest.raises(CalibrationError, match="ground_plane: not set.*add ground_plane: \\[0, 0, -h\\]"):
        run_folder_odometry(folder, tmp_path / "bare.yaml", 30.0, tmp_path / "out3")
    cv2.imwrite(str(tmp_path / "small.png"), mask[:100, :100])
    (tmp_path / "small.yaml").write_text(calib.read_text() + "mask: small.png\n")
    with pytest.raises(CalibrationError, match="mask: 100 x 100 px, but the fisheye's images are 320 x 240"):
        run_folder_odometry(folder, tmp_path / "small.yaml", 30.0, tmp_path / "out4")
    (tmp_path / "gone.yaml").write_text(calib.read_text() + "mask: gone.png\n")
    with pytest.raises(CalibrationError, match="gone.png is missing"):
        run_folder_odometry(folder, tmp_path / "gone.yaml", 30.0, tmp_path / "out5")
    assert not any((tmp_path / f"out{k}").exists() for k in (3, 4, 5))
    # a sign turned in the plane is refused before any frame; so is a folder with no image of
    # the calibration's size; an odd first image among good ones is only left out
    (tmp_path / "flipped.yaml").write_text(calib.read_text().replace("-0.265", "0.265"))
    with pytest.raises(CalibrationError, match="below the ground plane.*check ground_plane's sign"):
        run_folder_odometry(folder, tmp_path / "flipped.yaml", 30.0, tmp_path / "out6")
    big, odd = tmp_path / "big", tmp_path / "odd"
    big.mkdir()
    odd.mkdir()
    for k, f in enumerate(sorted(folder.iterdir())):
        img = cv2.imread(str(f))
        cv2.imwrite(str(big / f.name), cv2.resize(img, (640, 480)))
        cv2.imwrite(str(odd / f.name), cv2.resize(img, (640, 480)) if k == 0 else img)
    with pytest.raises(ValueError, match="640x480 px, and no image of .*big has the calibration's 320x240"):
        run_folder_odometry(big, calib, 30.0, tmp_path / "out7")
    assert not any((tmp_path / f"out{k}").exists() for k in (6, 7))
    res = run_folder_odometry(odd, calib, 30.0, tmp_path / "out8", mcap=False)
    assert res.valid == 6  # the 6 pairs of the 7 good frames


def test_the_omnidirectional_calibration_keeps_its_ground_plane_and_mask(tmp_path):
    from dataclasses import replace

    from perception.models.calib_io import CalibrationError
    from perception.odometry.fisheye import read_mask

    cam = replace(_rover_fisheye(), ground_plane=ROVER_PLANE, mask_file=tmp_path / "parts.png")
    back = OmniCamera.load(cam.save(tmp_path / "omni.yaml"))
    assert (
        back.ground_plane == pytest.approx(ROVER_PLANE)
        and back.mask_file == (tmp_path / "parts.png").resolve()
    )
    assert OmniCamera.load(_rover_fisheye().save(tmp_path / "bare.yaml")).ground_plane is None
    (tmp_path / "bad.yaml").write_text((tmp_path / "bare.yaml").read_text() + "mask: 3\n")
    with pytest.raises(CalibrationError, match="mask: 3; give the path of a mask image"):
        OmniCamera.load(tmp_path / "bad.yaml")
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(CalibrationError, match="junk.png is not a readable image"):
        read_mask(tmp_path / "junk.png")
    # read as stored: 16 bits with 1 on the ground, colour, and parts marked by transparency
    m16 = np.ones((240, 320), np.uint16)
    m16[:, :40] = 0
    cv2.imwrite(str(tmp_path / "m16.png"), m16)
    assert np.array_equal(read_mask(tmp_path / "m16.png"), m16 > 0)
    rgba = np.full((240, 320, 4), 255, np.uint8)
    rgba[:50, :, 3] = 0  # transparent: a part
    rgba[:, 300:, :3] = 0  # black, opaque: a part
    cv2.imwrite(str(tmp_path / "rgba.png"), rgba)
    want = np.ones((240, 320), bool)
    want[:50], want[:, 300:] = False, False
    assert np.array_equal(read_mask(tmp_path / "rgba.png"), want)
    cv2.imwrite(str(tmp_path / "zeros.png"), np.zeros((240, 320), np.uint8))
    with pytest.raises(CalibrationError, match="zeros.png is zero everywhere, so no ground is left"):
        read_mask(tmp_path / "zeros.png")
    # the one-camera rig's settings: inside the fisheye's ground view, more features on a finer image
    cfg = FisheyeOdometryConfig.for_ground_view(65.0, 640)
    assert cfg.view_limit_deg == 60.0 and cfg.min_depression_deg == 25.0 and cfg.max_features == 600
    assert FisheyeOdometryConfig.for_ground_view(None).view_limit_deg is None


@pytest.mark.parametrize("omega", [0.6, -0.6])
def test_a_turn_leaves_no_sideways_velocity(omega):
    """The two-view chord turned to the mid-pair velocity: a turn has v_y 0, not v_x omega dt / 2."""
    cam, tex, dt, twist = _camera(), _texture(), 1.0 / 30.0, (0.5, 0.0, omega)
    odo = FisheyeOdometry(cam, ground_plane=PLANE)
    odo.update(_render(cam, tex, (0.1, -0.2, 0.3)), 0.0)
    x, y, a = _after(twist, dt)
    c, s = math.cos(0.3), math.sin(0.3)
    est = odo.update(_render(cam, tex, (0.1 + c * x - s * y, -0.2 + s * x + c * y, 0.3 + a)), dt)
    assert est.valid and abs(est.v_y) < 0.002 < 0.5 * abs(omega) * dt * 0.5  # the chord's would be 0.005
    assert est.v_x == pytest.approx(0.5, abs=0.003) and est.omega == pytest.approx(omega, abs=0.003)


def _pair_estimate(twist=(0.5, 0.02, 0.2), config=None):
    """The estimate of one known motion of the synthetic camera over the plane."""
    cam, tex, dt = _camera(), _texture(3), 1.0 / 30.0
    odo = FisheyeOdometry(cam, config, ground_plane=PLANE)
    odo.update(_render(cam, tex, (0.0, 0.0, 0.0)), 0.0)
    return odo.update(_render(cam, tex, _after(twist, dt)), dt)


def test_a_free_fit_that_drifted_along_the_scale_is_still_used(monkeypatch):
    """The rays leave the scale free: a fit whose heights all moved toward the camera reads a
    shorter move (by 3 on the rough missions), which the ground plane's scale makes up. Over a
    3 cm relief the refinement is still used: the yaw rate stays clear of the relief."""
    import dataclasses

    import perception.odometry.fisheye as fo

    real = fo.two_view_motion

    def drifted(*a, **k):
        fit = real(*a, **k)
        if fit is None:
            return None
        dt = a[2]
        lever = fit.camera_shift - fit.motion[0:3] * dt  # the rotation's lever on the mount, (R - I) o
        m = fit.motion.copy()
        m[0:3] = (fit.camera_shift / 3.0 - lever) / dt  # the camera's move a third as long
        return dataclasses.replace(fit, motion=m, camera_shift=fit.camera_shift / 3.0)

    monkeypatch.setattr(fo, "two_view_motion", drifted)
    cam, tex, dt, twist = _rover_fisheye(), _texture(3), 1.0 / 30.0, (0.4, 0.0, 0.2)
    pose = np.array([0.3, -0.2, 0.4])
    odo = FisheyeOdometry(cam, FisheyeOdometryConfig(plane_test=0.0), ground_plane=ROVER_PLANE)
    errs = []
    for k in range(10):
        est = odo.update(render_relief(cam, tex, tuple(pose), 0.03), k * dt)
        if est is not None:
            assert est.valid, est.reason
            errs.append(np.abs(est.twist - twist))
        x, y, a = _after(twist, dt)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        pose = pose + np.array([c * x - s * y, s * x + c * y, a])
    mae = np.mean(errs, axis=0)
    assert mae[2] < 0.01 and mae[0] < 0.05  # (the plane's fit alone errs 3 times as much in yaw)


def test_the_planes_fit_used_alone_carries_the_scales_error(monkeypatch):
    """Where the two-view refinement fails, the rigid fit on the plane stands, and its speed's
    deviation holds the scale's error (the plane is the wheels', not the ground's in view)."""
    import perception.odometry.fisheye as fo

    ref = _pair_estimate()
    monkeypatch.setattr(fo, "two_view_motion", lambda *a, **k: None)
    est = _pair_estimate()
    assert est.valid, est.reason
    assert est.v_x == pytest.approx(0.5, abs=0.01)
    speed = math.hypot(est.v_x, est.v_y)
    rel = FisheyeOdometryConfig().scale_std
    assert est.twist_std[0] >= rel * speed * 0.99
    assert est.twist_std[0] == pytest.approx(ref.twist_std[0], rel=0.5)


def test_the_wheels_tracks_give_the_scale_over_relief():
    """Over a 3 cm relief the wheels' plane misses the ground in view by a tenth of the camera's
    height; the ground the front wheels rolled over, seen again, gives the scale once the tracks
    are in view, 0.7 s into the drive (the speed's mean error 0.015 m/s against the plane's 0.021
    from 0.8 s on: the tracks are carried with the estimated motion, whose scale erred by a tenth
    before, and their places along the drive with it; carried by the true motion, 0.005)."""
    from perception.odometry.flow import ground_plane_from_wheels

    cam, tex, dt, speed = _rover_fisheye(), _texture(6), 1.0 / 30.0, 0.5
    wheels = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])
    cfg = FisheyeOdometryConfig.for_ground_view(75.0, cam.image_size[0])
    assert cfg.view_limit_deg == 60.0 and cfg.track_view_deg == 70.0
    runs = {True: FisheyeOdometry(cam, cfg), False: FisheyeOdometry(cam, cfg)}
    errs: dict[bool, list[float]] = {True: [], False: []}
    anchored = 0
    for k in range(40):
        pose = (0.1 + speed * dt * k, 0.35, 0.0)
        img = render_relief(cam, tex, pose, 0.03)
        contacts = np.column_stack(
            [wheels, ROVER_PLANE[2] + relief_height(pose[0] + wheels[:, 0], pose[1] + wheels[:, 1], 0.03)]
        )
        centres = contacts + np.array([0.0, 0.0, 0.115])
        plane = ground_plane_from_wheels(centres, 0.115)
        for tracks, odo in runs.items():
            est = odo.update(img, k * dt, ground_plane=plane, contacts=contacts if tracks else None)
            if est is not None and k >= 25:
                assert est.valid, est.reason
                errs[tracks].append(abs(est.v_x - speed))
        anchored += len(runs[True].tracks) >= 2 and runs[True].last_scale_source == "tracks"
    assert anchored >= 15  # the tracks set the scale from about 0.7 s on
    with_tracks, plane_only = np.mean(errs[True]), np.mean(errs[False])
    assert plane_only > 0.018  # the relief under the camera errs the plane's scale by 4 % or more
    assert with_tracks < 0.75 * plane_only and with_tracks < 0.017

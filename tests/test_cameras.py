"""Camera models against known answers: projections, round trips, homography, YAML (no simulator)."""

import math

import numpy as np
import pytest

from perception.models.cameras import CalibrationError, OmniCamera, PinholeCamera


def down_looking_T(height: float, x: float = 0.0) -> np.ndarray:
    """Camera at (x, 0, height) in the body frame looking down, image up = body forward."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = [x, 0.0, height]
    return T


@pytest.fixture
def pinhole():
    return PinholeCamera(
        K=np.array([[402.0, 0.0, 318.5], [0.0, 401.0, 241.2], [0.0, 0.0, 1.0]]),
        distortion=np.array([-0.12, 0.03, 0.001, -0.0007, -0.004]),
        image_size=(640, 480),
        T_body_cam=down_looking_T(0.535, 0.95),
        ground_plane=(0.0, 0.0, -0.265),
    )


def test_pinhole_from_fov_matches_the_field_of_view():
    cam = PinholeCamera.from_fov((640, 480), math.radians(77.0), math.radians(57.0))
    h, v = cam.fov
    assert math.degrees(h) == pytest.approx(77.0, abs=1e-9)
    assert math.degrees(v) == pytest.approx(57.0, abs=1e-9)
    # a point on the edge of the horizontal field lands on the image border (x = -0.5)
    px = cam.project(np.array([-math.tan(h / 2), 0.0, 1.0]))
    assert px[0] == pytest.approx(-0.5, abs=1e-9)


def test_pinhole_distorted_round_trip(pinhole):
    rng = np.random.default_rng(1)
    pix = np.column_stack([rng.uniform(0, 639, 2000), rng.uniform(0, 479, 2000)])
    rays = pinhole.unproject(pix)
    assert np.allclose(np.linalg.norm(rays, axis=1), 1.0)
    back = pinhole.project(rays * rng.uniform(0.2, 5.0, (2000, 1)))
    assert np.abs(back - pix).max() < 1e-6
    assert np.isnan(pinhole.project(np.array([0.1, 0.2, -1.0]))).all()


def test_ground_homography_maps_body_ground_points_to_pixels(pinhole):
    rng = np.random.default_rng(2)
    xy = np.column_stack([rng.uniform(0.6, 1.3, 200), rng.uniform(-0.5, 0.5, 200)])
    p_body = np.column_stack([xy, np.full(200, -0.265), np.ones(200)])
    p_cam = (np.linalg.inv(pinhole.T_body_cam) @ p_body.T).T[:, :3]
    pix = pinhole.project(p_cam)
    und = pinhole.undistort_points(pix)
    H = pinhole.ground_homography()
    q = np.column_stack([xy, np.ones(200)]) @ H.T
    assert np.abs(q[:, :2] / q[:, 2:] - und).max() < 1e-6
    assert np.abs(pinhole.pixels_to_ground(pix) - xy).max() < 1e-9


def test_ground_homography_on_a_sloped_plane(pinhole):
    plane = (0.05, -0.02, -0.27)
    xy = np.array([[0.8, 0.1], [1.2, -0.3]])
    z = plane[0] * xy[:, 0] + plane[1] * xy[:, 1] + plane[2]
    p_cam = (np.linalg.inv(pinhole.T_body_cam) @ np.column_stack([xy, z, np.ones(2)]).T).T[:, :3]
    assert np.allclose(pinhole.pixels_to_ground(pinhole.project(p_cam), plane), xy, atol=1e-9)


def test_pinhole_yaml_round_trip_and_errors(pinhole, tmp_path):
    path = pinhole.save(tmp_path / "cam.yaml")
    back = PinholeCamera.load(path)
    assert np.allclose(back.K, pinhole.K) and np.allclose(back.distortion, pinhole.distortion)
    assert np.allclose(back.T_body_cam, pinhole.T_body_cam) and back.ground_plane == pinhole.ground_plane
    text = path.read_text()
    (tmp_path / "missing.yaml").write_text(text.replace("distortion", "distortionz"))
    with pytest.raises(CalibrationError, match="missing key 'distortion'"):
        PinholeCamera.load(tmp_path / "missing.yaml")
    (tmp_path / "unknown.yaml").write_text(text + "focal: 3\n")
    with pytest.raises(CalibrationError, match="unknown key 'focal'"):
        PinholeCamera.load(tmp_path / "unknown.yaml")
    with pytest.raises(CalibrationError, match="not found"):
        PinholeCamera.load(tmp_path / "nope.yaml")
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(CalibrationError, match="T_body_cam"):
        PinholeCamera(K=pinhole.K, T_body_cam=bad)
    with pytest.raises(CalibrationError, match="hfov"):
        PinholeCamera.from_fov((640, 480), math.radians(185.0))
    with pytest.raises(CalibrationError, match="image_size"):
        PinholeCamera.from_fov((0, 480), 1.0)


@pytest.fixture(scope="module")
def omni():
    return OmniCamera.equidistant((640, 480), math.radians(190.0), 235.0, T_body_cam=down_looking_T(-0.09))


def test_omni_round_trip_over_the_whole_field_of_view(omni):
    rng = np.random.default_rng(3)
    n = 50000
    alpha = np.arccos(1 - rng.uniform(0, 1 - math.cos(omni.max_fov / 2), n))
    alpha[:4] = [0.0, 1e-9, omni.max_fov / 2, math.pi / 2]
    phi = rng.uniform(-np.pi, np.pi, n)
    rays = np.column_stack([np.sin(alpha) * np.cos(phi), np.sin(alpha) * np.sin(phi), np.cos(alpha)])
    back = omni.cam2world(omni.world2cam(rays))
    err = 2 * np.arcsin(np.linalg.norm(back - rays, axis=1) / 2)  # angle between unit vectors
    assert err.max() < 1e-6
    # rays behind the field of view are rejected, not folded back into the image
    assert np.isnan(omni.world2cam(np.array([1.0, 0.0, -0.2]))).all()


def test_omni_equidistant_model_is_equidistant(omni):
    k = 235.0 / (omni.max_fov / 2)
    for deg in (10.0, 45.0, 90.0, 95.0):
        a = math.radians(deg)
        px = omni.world2cam(np.array([math.sin(a), 0.0, math.cos(a)]))
        assert px[0] - omni.center[0] == pytest.approx(k * a, abs=0.1)  # degree-4 fit of the ideal


def test_omni_affine_stretch_round_trip_and_yaml(omni, tmp_path):
    cam = OmniCamera(
        image_size=(640, 480),
        center=(322.3, 236.9),
        affine=(1.01, 0.004, -0.003),
        poly=omni.poly,
        max_fov=omni.max_fov,
    )
    pix = np.array([[100.0, 200.0], [322.3, 236.9], [450.0, 380.0]])
    assert np.abs(cam.world2cam(cam.cam2world(pix)) - pix).max() < 1e-9
    back = OmniCamera.load(cam.save(tmp_path / "omni.yaml"))
    assert back.poly == pytest.approx(cam.poly) and back.affine == pytest.approx(cam.affine)
    assert back.max_fov == pytest.approx(cam.max_fov)
    text = (tmp_path / "omni.yaml").read_text()
    (tmp_path / "bad.yaml").write_text(text.replace("max_fov_deg", "fov_deg"))
    with pytest.raises(CalibrationError, match="max_fov_deg"):
        OmniCamera.load(tmp_path / "bad.yaml")
    with pytest.raises(CalibrationError, match="a0 must be positive"):
        OmniCamera((640, 480), (320, 240), (1, 0, 0), tuple(-np.asarray(omni.poly)), omni.max_fov)
    with pytest.raises(CalibrationError, match="does not reach"):
        OmniCamera((640, 480), (320, 240), (1, 0, 0), (141.0, 0.0, 0.001), omni.max_fov)


def test_omni_fit_recovers_a_known_model_from_noisy_corners():
    from perception.models.calibration import fit_omni_camera

    base = OmniCamera.equidistant((640, 480), math.radians(190), 300.8)
    true = OmniCamera(
        image_size=(640, 480),
        center=(322.3, 236.1),
        affine=(1.002, 0.001, -0.0015),
        poly=base.poly,
        max_fov=base.max_fov,
    )
    rng = np.random.default_rng(0)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.abs(d[:, 2]) - 0.05  # up to ~93 deg from the axis
    px = true.world2cam(d)
    ok = np.isfinite(px[:, 0]) & (px[:, 1] > 0) & (px[:, 1] < 479)
    px = px[ok] + rng.normal(scale=0.1, size=(ok.sum(), 2))
    px[:5] += 8.0  # five mismatched corners
    fit = fit_omni_camera(px, d[ok], (640, 480), true.max_fov)
    assert fit.inliers.sum() == ok.sum() - 5 and not fit.inliers[:5].any()
    assert fit.rms_px == pytest.approx(0.1 * math.sqrt(2), rel=0.15)  # the pixel noise
    np.testing.assert_allclose(fit.camera.center, true.center, atol=0.05)
    rays = rng.normal(size=(2000, 3))
    rays[:, 2] = np.abs(rays[:, 2])
    gap = np.hypot(*(fit.camera.world2cam(rays) - true.world2cam(rays)).T)
    assert np.nanmax(gap) < 0.1


def test_omni_fit_rejects_too_few_corners():
    from perception.models.calibration import fit_omni_camera

    with pytest.raises(CalibrationError, match="usable corners"):
        fit_omni_camera(np.ones((10, 2)), np.ones((10, 3)), (640, 480), math.radians(190))
    with pytest.raises(CalibrationError, match="differ in number"):
        fit_omni_camera(np.ones((10, 2)), np.ones((9, 3)), (640, 480), math.radians(190))


def test_omni_fast_projection_matches_the_refined_one(omni):
    """The table-interpolated projection (used for many points) is within 1e-4 px of Newton's."""
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(20000, 3))
    pts[:3] = [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (np.nan, 0.0, 1.0)]  # on the axis, behind, NaN
    fast, exact = omni.world2cam(pts, refine=False), omni.world2cam(pts, refine=True)
    inside = np.isfinite(exact).all(axis=1)
    np.testing.assert_array_equal(np.isfinite(fast).all(axis=1), inside)
    assert inside[0] and not inside[1] and not inside[2]
    assert np.abs(fast[inside] - exact[inside]).max() < 1e-4
    u, v = omni.project_xyz(*pts[inside].T)
    np.testing.assert_allclose(np.c_[u, v], exact[inside], atol=1e-4)

"""Axle roll, height and steering from synthetic fisheye images of the markers (no simulator).

The images are made through the OmniCamera model: each pixel's ray (4x supersampled) is tested
against every marker square at its known pose, so blob centroids carry the same perspective and
fisheye effects as a real camera's.
"""

import math

import cv2
import numpy as np
import pytest

from perception.kinematics.markers import (
    MarkerConfig,
    SteeringCalibration,
    assign_markers,
    measure_axles,
    segment_magenta,
    steering_ratio,
)
from perception.models.cameras import OmniCamera
from perception.models.rover import MARKERS, PLATE, ROD, RoverKinematicModel

R_BODY_FISHEYE = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
MAGENTA = np.array([230.0, 30.0, 230.0])


def rover_model() -> RoverKinematicModel:
    T = np.eye(4)
    T[:3, :3] = R_BODY_FISHEYE
    T[:3, 3] = (0.0, 0.0, -0.12)
    return RoverKinematicModel(
        axle_x=0.4,
        nominal_depth=0.15,
        track=0.6,
        wheel_radius=0.115,
        wheel_width=0.08,
        plate_offset=0.033,
        plate_marker_y=0.15,
        arm_tip=(-0.0968, -0.0726, -0.0448),
        marker_size=0.035,
        correction_marker_arc=math.radians(16),
        T_body_cam=T,
    )


def fisheye(model) -> OmniCamera:
    return OmniCamera.equidistant((640, 480), math.radians(190.0), 300.8, T_body_cam=model.T_body_cam)


def render_markers(model, camera, psi, depth, delta, shade=1.0, ss=4, rng=None, background=None):
    """RGB fisheye image of the 8 magenta squares over a grey textured background (or ``background``)."""
    w, h = camera.image_size
    rng = rng or np.random.default_rng(0)
    if background is None:
        bg = cv2.GaussianBlur(rng.normal(100, 25, size=(h, w)).astype(np.float32), (0, 0), 1.5)
        img = np.repeat(bg[..., None], 3, axis=2)
    else:
        img = np.asarray(background, np.float32).copy()
    pos = model.marker_positions(psi, depth, delta)
    nrm = model.marker_normals(psi, delta)
    T_cb = np.linalg.inv(model.T_body_cam)
    half = model.marker_size / 2
    for name in MARKERS:
        p, n = pos[name], nrm[name]
        u = np.cross(n, [0.0, 0.0, 1.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        corners = np.array([p + a * half * u + b * half * v for a in (-1, 1) for b in (-1, 1)])
        px = camera.world2cam(corners @ T_cb[:3, :3].T + T_cb[:3, 3])
        assert np.isfinite(px).all(), f"{name} leaves the field of view"
        x0, y0 = np.floor(px.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
        sx = x0 - 0.5 + (np.arange((x1 - x0 + 1) * ss) + 0.5) / ss
        sy = y0 - 0.5 + (np.arange((y1 - y0 + 1) * ss) + 0.5) / ss
        gx, gy = np.meshgrid(sx, sy)
        rays = camera.cam2world(np.stack([gx, gy], -1).reshape(-1, 2)) @ model.T_body_cam[:3, :3].T
        o = model.T_body_cam[:3, 3]
        t = ((p - o) @ n) / (rays @ n)
        hit = o + t[:, None] * rays - p
        inside = (t > 0) & (np.abs(hit @ u) <= half) & (np.abs(hit @ v) <= half)
        cov = inside.reshape(len(sy), len(sx)).astype(np.float32)
        cov = cov.reshape(y1 - y0 + 1, ss, x1 - x0 + 1, ss).mean(axis=(1, 3))
        patch = img[y0 : y1 + 1, x0 : x1 + 1]
        img[y0 : y1 + 1, x0 : x1 + 1] = patch * (1 - cov[..., None]) + shade * MAGENTA * cov[..., None]
    return np.clip(img + 0.5, 0, 255).astype(np.uint8)


def predicted_pixels(model, camera, psi, depth, delta):
    pos = model.marker_positions(psi, depth, delta)
    T_cb = np.linalg.inv(model.T_body_cam)
    return {m: camera.world2cam(T_cb[:3, :3] @ p + T_cb[:3, 3]) for m, p in pos.items()}


# feasible states: the axle beam stays below the body (depth > 0.1 m + 0.22 m |sin psi|)
POSES = [
    ((0.0, 0.0), (0.15, 0.15), (0.0, 0.0)),
    ((0.2, -0.15), (0.17, 0.15), (0.3, -0.3)),
    ((-0.34, 0.34), (0.19, 0.18), (-0.52, 0.52)),  # full roll and full lock
    ((0.12, 0.05), (0.14, 0.13), (0.45, 0.2)),
]


@pytest.mark.parametrize("shade", [1.0, 0.3])  # sunlit, and in the rover's shadow
@pytest.mark.parametrize("pose", POSES)
def test_roll_height_and_steering_from_synthetic_markers(pose, shade):
    model = rover_model()
    cam = fisheye(model)
    psi, depth, lam = pose
    delta = model.wheel_angles(*lam)
    img = render_markers(model, cam, psi, depth, delta, shade=shade)
    cfg = MarkerConfig()
    cent, _, _ = segment_magenta(img, cfg)
    # predictions from a previous state some way off, as between frames
    prev = predicted_pixels(model, cam, np.array(psi) * 0.8, np.array(depth) + 0.005, delta * 0.9)
    found = assign_markers(prev, cent, gate=cfg.gate_frac * 640)
    assert set(found) == set(MARKERS)
    meas = measure_axles(model, cam, {m: cent[j] for m, j in found.items()}, psi, depth)
    err_psi = np.degrees(np.abs(meas.psi - psi))
    err_d = np.abs(meas.depth - depth) * 1000
    err_lam = np.degrees(np.abs(meas.lam - lam))
    print(
        f"{pose} shade {shade}: psi {err_psi.round(3)} deg, d {err_d.round(2)} mm, lam {err_lam.round(3)} deg"
    )
    assert err_psi.max() < 0.2 and err_d.max() < 1.0 and err_lam.max() < 0.3


def test_steering_ratio_calibration_round_trip(tmp_path):
    """The paper's eq. (5) map. On this rover the inner tie-rod end passes closest to its plate
    marker near full lock, where the ratio stops being monotonic: the sweep covers +-24 deg and a
    full-lock sweep is refused."""
    from perception.models.calib_io import CalibrationError

    model = rover_model()

    def sweep(limit_deg):
        lams = np.radians(np.linspace(-limit_deg, limit_deg, 121))
        out = []
        for axle in ("F", "R"):
            r = []
            for lam in lams:
                p = model.marker_positions((0, 0), (0.15, 0.15), model.wheel_angles(lam, lam))
                r.append(
                    steering_ratio(p[PLATE[axle][0]], p[PLATE[axle][1]], p[ROD[axle][0]], p[ROD[axle][1]])
                )
            out.append(r)
        return out, [lams, lams]

    with pytest.raises(CalibrationError, match="not monotonic"):
        SteeringCalibration.fit(*sweep(30.0))
    cal = SteeringCalibration.fit(*sweep(24.0))
    path = cal.save(tmp_path / "steer.yaml")
    back = SteeringCalibration.load(path)
    # the ratio does not depend on roll or height, only on steering
    p = model.marker_positions((0.25, -0.2), (0.17, 0.13), model.wheel_angles(0.21, -0.38))
    assert back.steering("F", steering_ratio(p["A1"], p["A2"], p["B1"], p["B2"])) == pytest.approx(
        0.21, abs=2e-4
    )
    assert back.steering("R", steering_ratio(p["C1"], p["C2"], p["D1"], p["D2"])) == pytest.approx(
        -0.38, abs=2e-4
    )
    assert math.isnan(back.steering("F", 100.0))  # outside the sweep


def test_lost_markers_leave_their_degrees_of_freedom_unmeasured():
    model = rover_model()
    cam = fisheye(model)
    psi, depth, delta = (0.1, -0.1), (0.15, 0.15), model.wheel_angles(0.2, -0.2)
    pix = predicted_pixels(model, cam, psi, depth, delta)
    del pix["A2"], pix["D1"], pix["D2"]
    # exact centre projections, so no blob-centroid refinement
    meas = measure_axles(model, cam, pix, fallback_psi=(0.1, -0.1), fallback_depth=(0.15, 0.15), refine=False)
    assert np.isnan(meas.psi[0]) and np.isnan(meas.depth[0])  # front plate incomplete
    assert meas.psi[1] == pytest.approx(-0.1, abs=1e-9)
    # front steering still measured on the fallback roll; rear steering lost
    assert meas.lam[0] == pytest.approx(0.2, abs=1e-6) and np.isnan(meas.lam[1])


def test_no_markers_black_and_saturated_frames():
    cfg = MarkerConfig()
    for img in (np.zeros((480, 640, 3), np.uint8), np.full((480, 640, 3), 255, np.uint8)):
        cent, areas, _ = segment_magenta(img, cfg)
        assert len(cent) == 0
    model = rover_model()
    meas = measure_axles(model, fisheye(model), {}, (0, 0), (0.15, 0.15))
    assert np.isnan(meas.psi).all() and np.isnan(meas.lam).all()


def test_kinematic_model_yaml_round_trip_and_errors(tmp_path):
    from perception.models.calib_io import CalibrationError

    model = rover_model()
    back = RoverKinematicModel.load(model.save(tmp_path / "rover.yaml"))
    assert back.arm_tip == pytest.approx(model.arm_tip) and np.allclose(back.T_body_cam, model.T_body_cam)
    text = (tmp_path / "rover.yaml").read_text().replace("plate_offset", "plate_ofset")
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(CalibrationError, match="plate_ofset|plate_offset"):
        RoverKinematicModel.load(tmp_path / "bad.yaml")


def test_estimator_flags_unusable_frames_and_stays_finite():
    from perception.kinematics.fisheye import DOF_NAMES, KinematicStateEstimator

    model = rover_model()
    cam = fisheye(model)
    est = KinematicStateEstimator(cam, model)
    psi, depth, lam = (0.1, -0.05), (0.15, 0.15), (0.2, -0.2)
    good = render_markers(model, cam, psi, depth, model.wheel_angles(*lam))
    s = est.update(good, 0.0)
    assert all(s.valid[k] for k in ("psi_F", "psi_R", "d_F", "d_R", "lam_F", "lam_R"))
    assert not any(s.valid[f"theta_{w}"] for w in ("FL", "FR", "RL", "RR"))  # no previous frame yet
    np.testing.assert_allclose(s.psi, psi, atol=math.radians(0.2))
    for t, bad in enumerate(
        [
            np.zeros((480, 640, 3), np.uint8),  # black
            np.full((480, 640, 3), 255, np.uint8),  # saturated
            np.zeros((240, 320, 3), np.uint8),  # wrong size
            np.zeros((480, 640), np.float32),  # wrong type
            render_markers(model, cam, psi, depth, model.wheel_angles(*lam), shade=0.0),  # no markers
        ],
        start=1,
    ):
        s = est.update(bad, t / 30)
        assert not any(s.valid[k] for k in DOF_NAMES) and s.quality == 0.0
        assert np.isfinite(np.r_[s.psi, s.depth, s.lam, s.theta, s.theta_dot]).all()
        np.testing.assert_allclose(s.psi, psi, atol=math.radians(0.2))  # the last good state
    with pytest.raises(ValueError, match="T_body_cam"):
        KinematicStateEstimator(OmniCamera.equidistant((640, 480), math.radians(190), 300.8), model)


def test_correction_marker_reacquires_after_drift_beyond_the_limit():
    """Eq. 7: small corrections at once; a large one only when a later turn asks for the same."""
    from perception.kinematics.fisheye import KinematicStateEstimator

    model = rover_model()
    est = KinematicStateEstimator(fisheye(model), model)
    est._offset[0] = 0.0  # the marker's phase equals theta (mod 2 pi)
    assert est._correct(0, 10.0, 10.1 - 2 * math.pi) == pytest.approx(10.1)  # 0.1 rad: taken
    # drifted 0.35 rad: refused, also later in the same pass ...
    assert est._correct(0, 20.0, 20.35) is None
    assert est._correct(0, 20.2, 20.55) is None
    # ... and a turn later, a sighting asking for another correction is refused too
    assert est._correct(0, 26.0, 26.0 - 0.5) is None
    # the next turn agrees with that one: taken
    assert est._correct(0, 32.0, 32.0 - 0.48) == pytest.approx(31.52)
    # after a correction, a lone far sighting is refused again
    assert est._correct(0, 40.0, 40.4) is None


@pytest.mark.parametrize("pose", POSES[:2])
def test_regions_of_interest_give_the_centres_of_the_whole_frame(pose):
    """The boxes, laid side by side in one image, find each marker's centre exactly as the full frame does."""
    model = rover_model()
    cam = fisheye(model)
    psi, depth, lam = pose
    img = render_markers(model, cam, psi, depth, model.wheel_angles(*lam))
    cfg = MarkerConfig()
    full, full_area, _ = segment_magenta(img, cfg)
    at = np.array(list(predicted_pixels(model, cam, psi, depth, model.wheel_angles(*lam)).values()))
    boxes = np.hstack([at - 30, at + 31])
    roi, roi_area, mask = segment_magenta(img, cfg, boxes)
    assert len(roi) == len(full) == len(MARKERS)
    order_f, order_r = np.lexsort(full.T), np.lexsort(roi.T)
    np.testing.assert_allclose(roi[order_r], full[order_f], atol=1e-9)
    np.testing.assert_array_equal(roi_area[order_r], full_area[order_f])
    # a box that cuts a blob leaves it out, rather than giving a shifted centre
    cut = segment_magenta(img, cfg, np.hstack([at[:1] - 30, at[:1] + 2]))[0]
    assert len(cut) == 0
    assert mask.shape == img.shape[:2]


def test_a_lost_wheel_stays_tracked_for_track_hold_frames(monkeypatch):
    """After a missed rotation the wheel is searched near its last one (and may be taken on a
    decisive alignment) for ``track_hold`` frames; then the wide, feature-confirmed search starts."""
    import perception.kinematics.fisheye as fk
    from perception.kinematics.wheel_rotation import RotationMeasurement

    model = rover_model()
    cam = fisheye(model)
    est = fk.KinematicStateEstimator(cam, model)
    cfg = est.config
    img = render_markers(model, cam, (0.0, 0.0), (0.15, 0.15), model.wheel_angles(0.0, 0.0))
    calls = []

    def fake(pairs, radius, tread, priors, spans, check=None):
        calls.append((list(priors), list(spans), list(check)))
        lost = len(calls) > 1  # FL's rotation is missed from the second frame pair on
        return [RotationMeasurement(math.nan if (k == 0 and lost) else 0.5, 0, 0, 0, not (k == 0 and lost))
                for k in range(len(pairs))]  # fmt: skip

    monkeypatch.setattr(fk, "measure_pairs", fake)
    n = cfg.track_hold + 4
    for k in range(n + 1):
        est.update(img, k / 30)
    # the first pair: every wheel searched widely; then FL near its last rotation (0.5) ...
    fl = [(c[0][0], c[1][0], c[2][0]) for c in calls if len(c[0]) == 4]
    assert fl[0][1:] == (cfg.acquire_span, 2)
    for prior, span, check in fl[1 : 2 + cfg.track_hold]:
        assert (prior, span, check) == (0.5, cfg.track_span, int(cfg.tread.check_strong))
    # ... until it has been missed track_hold + 1 times in a row
    for _, span, check in fl[2 + cfg.track_hold :]:
        assert (span, check) == (cfg.acquire_span, 2)
    assert len(fl) == n


def mounted_off(model, camera, rotation_deg, shift):
    """(model, camera) with the fisheye turned by ``rotation_deg`` (its own frame) and moved by
    ``shift`` [m] off the calibration ``model`` and ``camera`` carry: the truth a mount error makes."""
    import dataclasses

    T = model.T_body_cam.copy()
    T[:3, :3] = T[:3, :3] @ cv2.Rodrigues(np.radians(rotation_deg))[0]
    T[:3, 3] += shift
    return dataclasses.replace(model, T_body_cam=T), dataclasses.replace(camera, T_body_cam=T)


def test_zeroing_the_steering_at_rest_takes_out_a_fisheye_mount_error(caplog):
    """A fisheye mounted 0.3-0.45 degrees (and 2 mm) off its calibration reads up to 40 mrad of
    steering; a frame at rest with the steering centred takes out three quarters of it over rolled,
    sunk and steered states."""
    from perception.kinematics.fisheye import KinematicStateEstimator

    nominal = rover_model()
    cam = fisheye(nominal)
    true, true_cam = mounted_off(nominal, cam, [0.45, -0.4, 0.3], (0.002, -0.002, 0.001))
    rng = np.random.default_rng(3)
    rest = render_markers(true, true_cam, (0.02, -0.01), (0.155, 0.148), np.zeros(4), rng=rng)
    states = [((0.08, -0.05), (0.16, 0.14), (0.2, -0.15)), ((-0.06, 0.03), (0.14, 0.15), (-0.2, 0.1))]
    frames = [render_markers(true, true_cam, p, d, true.wheel_angles(*lam), rng=rng) for p, d, lam in states]
    errors = {}
    for zeroed in (False, True):
        errs = []
        for (_, _, lam), img in zip(states, frames, strict=True):
            est = KinematicStateEstimator(cam, nominal)
            if zeroed:
                offsets = est.zero_steering(rest)
                assert offsets is not None and np.abs(offsets).max() > 0.005
                np.testing.assert_allclose(est.steering_zero, offsets)
            s = est.update(img, 0.0)
            assert s.markers_found == len(MARKERS)
            errs.append(np.abs(s.delta - nominal.wheel_angles(*lam)).max())
        errors[zeroed] = max(errs)
    assert errors[False] > 0.01  # the mount error shows as steering
    assert errors[True] < min(0.3 * errors[False], 0.012)  # 40 -> 10 mrad at worst here
    est.reset()
    assert not est.steering_zero.any()
    # a frame that is not of centred steering, or has no markers, sets no zero
    steered = render_markers(true, true_cam, (0, 0), (0.15, 0.15), nominal.wheel_angles(0.3, 0), rng=rng)
    with caplog.at_level("WARNING"):
        assert est.zero_steering(steered) is None
        assert est.zero_steering(np.zeros((480, 640, 3), np.uint8)) is None
    assert "centred" in caplog.text and "markers found" in caplog.text
    assert not est.steering_zero.any()
    with pytest.raises(ValueError, match="uint8"):
        est.zero_steering(np.zeros((480, 640), np.float32))


def test_zeroing_the_depths_at_rest_takes_out_a_fisheye_mount_error(caplog):
    """A fisheye mounted 2-3 mm and 0.3-0.45 degrees off its calibration reads the axles 1-4 mm
    too deep or shallow, differently per axle; a frame at rest, its depths known, takes that out
    over rolled, sunk and steered states (the mean of the two only, without the rest depths)."""
    import dataclasses

    from perception.kinematics.fisheye import KinematicStateEstimator

    nominal = dataclasses.replace(rover_model(), rest_sag=0.018, pitch_sag=0.014)
    cam = fisheye(nominal)
    true, true_cam = mounted_off(nominal, cam, [0.4, -0.45, 0.3], (0.003, -0.002, 0.002))
    rng = np.random.default_rng(5)
    rest_depth = nominal.rest_depths(0.0, math.radians(-8.0))  # at rest, nose up 8 degrees
    assert rest_depth[0] > nominal.nominal_depth + 0.0015 > rest_depth[1] + 0.003
    rest = render_markers(true, true_cam, (0.01, -0.02), rest_depth, np.zeros(4), rng=rng)
    states = [((0.08, -0.05), (0.16, 0.14), (0.2, -0.15)), ((-0.06, 0.03), (0.14, 0.155), (-0.2, 0.1))]
    frames = [render_markers(true, true_cam, p, d, true.wheel_angles(*lam), rng=rng) for p, d, lam in states]
    errors, means = {}, {}
    for zero in ("off", "mean", "axles"):
        errs, mean_errs = [], []
        for (_, d, _), img in zip(states, frames, strict=True):
            est = KinematicStateEstimator(cam, nominal)
            if zero != "off":
                offsets = est.zero_depth(rest, rest_depth if zero == "axles" else None)
                assert offsets is not None
                np.testing.assert_allclose(est.depth_zero, offsets)
            s = est.update(img, 0.0)
            assert s.markers_found == len(MARKERS)
            errs.append(np.abs(s.depth - d).max())
            mean_errs.append(abs(np.mean(s.depth - d)))
        errors[zero], means[zero] = max(errs), max(mean_errs)
    assert errors["off"] > 0.002  # the mount error shows as depth
    assert errors["axles"] < min(0.35 * errors["off"], 0.001)
    assert means["mean"] < 0.35 * means["off"]  # the mean only: the axles' common error
    est.reset()
    assert not est.depth_zero.any()
    # a frame far from rest, or without markers, sets no zero
    sunk = render_markers(true, true_cam, (0, 0), (0.175, 0.175), np.zeros(4), rng=rng)
    with caplog.at_level("WARNING"):
        assert est.zero_depth(sunk) is None
        assert est.zero_depth(np.zeros((480, 640, 3), np.uint8)) is None
    assert "at rest" in caplog.text and "markers found" in caplog.text
    assert not est.depth_zero.any()
    with pytest.raises(ValueError, match="rest_depth"):
        est.zero_depth(rest, (0.15, math.nan))


def test_the_rest_depths_follow_the_tilt_and_survive_a_round_trip(tmp_path):
    """Level: the nominal depth; tilted, both axles hang deeper by rest_sag (1 - cos roll cos
    pitch), and nose up moves pitch_sag sin(pitch) from the rear axle's depth to the front's."""
    import dataclasses

    from perception.models.calib_io import CalibrationError

    model = dataclasses.replace(rover_model(), rest_sag=0.0184, pitch_sag=0.0146)
    np.testing.assert_allclose(model.rest_depths(0.0, 0.0), [model.nominal_depth] * 2)
    p = math.radians(-10.0)
    common = model.nominal_depth + 0.0184 * (1 - math.cos(p))
    np.testing.assert_allclose(
        model.rest_depths(0.0, p),
        [common + 0.0146 * math.sin(-p), common - 0.0146 * math.sin(-p)],
        atol=1e-12,
    )
    assert model.rest_depths(0.2, 0.0)[0] == pytest.approx(model.nominal_depth + 0.0184 * (1 - math.cos(0.2)))
    loaded = RoverKinematicModel.load(model.save(tmp_path / "model.yaml"))
    assert (loaded.rest_sag, loaded.pitch_sag) == (0.0184, 0.0146)
    with pytest.raises(CalibrationError, match="pitch_sag"):
        dataclasses.replace(model, pitch_sag=-0.01)
    with pytest.raises(ValueError, match="finite"):
        model.rest_depths(math.nan, 0.0)


@pytest.mark.parametrize("reads", [0.98, 1.015])
def test_the_correction_marker_measures_the_treads_rate_scale(monkeypatch, reads):
    """Treads that read every rotation 2 % short (or 1.5 % long), as a fisheye mount error makes
    them, are scaled back by the rotation the white marker counts between its sightings: whole
    turns. The scale is within 0.2 % after twelve turns, and so are the rates; off, they stay off."""
    import perception.kinematics.fisheye as fk
    from perception.kinematics.wheel_rotation import RotationMeasurement

    model = rover_model()
    cam = fisheye(model)
    img = render_markers(model, cam, (0.0, 0.0), (0.15, 0.15), model.wheel_angles(0.0, 0.0))
    step, dt = 0.45, 1 / 30  # true rotation a frame [rad]: 13.5 rad/s
    measured = RotationMeasurement(step * reads, 0, 0, 0, True)
    monkeypatch.setattr(fk, "measure_pairs", lambda pairs, *a, **k: [measured] * len(pairs))
    results = {}
    for prior in (2 * math.pi, 0.0):
        est = fk.KinematicStateEstimator(cam, model, fk.KinematicsConfig(rate_scale_prior=prior))
        true = [0.0]

        def sighting(img_, strip, true=true):
            """The marker (at wheel angle 0), seen in the first frame of each turn, 0.02 rad off."""
            phase = true[0] % (2 * math.pi)
            return phase + 0.02 if phase < step else None

        monkeypatch.setattr(est, "_marker_may_show", lambda strip, expected: True)
        monkeypatch.setattr(est, "_marker_phase", sighting)
        for k in range(int(12 * 2 * math.pi / step) + 2):
            true[0] = k * step
            s = est.update(img, k * dt)
        results[prior] = (est.rate_scale, s.theta_dot, s.theta)
    scale, rate, theta = results[2 * math.pi]
    np.testing.assert_allclose(scale, 1 / reads, rtol=0.002)
    np.testing.assert_allclose(rate, step / dt, rtol=0.002)
    assert np.abs(theta - true[0]).max() < 0.2  # held by the marker's corrections, as before
    scale, rate, _ = results[0.0]
    np.testing.assert_array_equal(scale, 1.0)
    np.testing.assert_allclose(rate, step * reads / dt, rtol=1e-9)


def test_the_kinematic_model_keeps_its_joint_limits(tmp_path):
    from dataclasses import replace

    from perception.models.calib_io import CalibrationError

    model = replace(rover_model(), joint_limits=(0.35, 0.05, 0.52))
    back = RoverKinematicModel.load(model.save(tmp_path / "rover.yaml"))
    assert back.joint_limits == pytest.approx((0.35, 0.05, 0.52))
    assert RoverKinematicModel.load(rover_model().save(tmp_path / "none.yaml")).joint_limits is None
    with pytest.raises(CalibrationError, match="joint_limits"):
        replace(rover_model(), joint_limits=(0.35, -0.05, 0.52))

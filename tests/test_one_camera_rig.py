"""The one-camera rig: the fisheye alone gives the odometry, joints, wheels and slip."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import rover_env  # noqa: F401  (registers the environments)
from perception.odometry.fisheye import FisheyeOdometry
from perception.odometry.flow import FlowOdometry
from rover_env.config.rig import FISHEYE_ONLY_GROUND_DEG

ACTIONS = [np.array([0.3, 0.12, -0.12], np.float32)] * 45 + [np.array([0.3, 0.0, 0.0], np.float32)] * 30


def _drive(rig, seed=3, imu=None):
    env = gym.make("Rover-v0", rig=rig, imu=imu)
    try:
        obs, info = env.reset(seed=seed)
        poses, est, truth = [], [], []
        for a in ACTIONS:
            obs, _, term, trunc, info = env.step(a)
            poses.append(info["ground_truth"]["pose"].copy())
            truth.append(info["ground_truth"]["twist"].copy())
            est.append(np.asarray(info["estimate"]["twist"], dtype=float).copy())
            assert np.all(np.isfinite(obs))
        u = env.unwrapped
        return np.array(poses), np.array(truth), np.array(est), u.rig, u.pipeline
    finally:
        env.close()


def test_the_fisheye_alone_estimates_the_twist_on_the_same_physics():
    poses1, truth1, est1, rig1, pipe1 = _drive("fisheye_only")
    poses2, truth2, est2, rig2, pipe2 = _drive(None)
    # the rig: one fisheye, which renders the ground for its odometry; no downward camera
    assert list(rig1) == ["fisheye"]
    assert rig1["fisheye"].ground_view_deg == pytest.approx(FISHEYE_ONLY_GROUND_DEG)
    assert isinstance(pipe1.estimator.odometry, FisheyeOdometry)
    assert isinstance(pipe2.estimator.odometry, FlowOdometry)
    assert pipe1.frames["fisheye_windowed"] > 0.8 * len(ACTIONS)  # the kinematics' windows still work
    # the same seed and actions drive the same rover whatever observes it
    assert np.array_equal(poses1, poses2)
    # the fisheye's twist, after the first second (the rover starts from rest)
    err = np.abs(est1[30:] - truth1[30:]).mean(axis=0)
    ref = np.abs(est2[30:] - truth2[30:]).mean(axis=0)
    assert err[0] < 0.02 and err[1] < 0.02 and err[2] < 0.03, err
    assert err[0] < 1.5 * ref[0] + 0.005, (err, ref)


def test_the_one_camera_rig_is_refused_where_it_cannot_be(tmp_path):
    with pytest.raises(ValueError, match="rig='bogus': use one of"):
        gym.make("Rover-v0", rig="bogus")
    with pytest.raises(ValueError, match="use it with obs_source='estimated'"):
        gym.make("Rover-v0", rig="fisheye_only", obs_source="ground_truth")
    path = tmp_path / "declared.yaml"
    path.write_text(
        "name: declared\ncourse: {waypoints: [[2.0, 0.0]]}\nterrain: {kind: flat, size: [12.0, 12.0]}\n"
        "rig:\n  - {name: fisheye, kind: fisheye}\n"
    )
    with pytest.raises(ValueError, match="declares its own rig"):
        gym.make("Rover-v0", scenario=str(path), rig="fisheye_only")


def test_a_declared_rig_without_a_downward_camera_gets_the_fisheyes_odometry(tmp_path):
    path = tmp_path / "one.yaml"
    path.write_text(
        "name: one\ncourse: {waypoints: [[4.0, 0.0]]}\nterrain: {kind: flat, size: [12.0, 12.0]}\n"
        "rig:\n  - {name: fish, kind: fisheye}\n  - {name: imu, kind: imu, imu: bmi088}\n"
    )
    env = gym.make("Rover-v0", scenario=str(path))
    try:
        u = env.unwrapped
        # the ground rendered for it
        assert u.rig["fish"].ground_view_deg == pytest.approx(FISHEYE_ONLY_GROUND_DEG)
        assert u.pipeline.estimator.odometry_camera == "fisheye"
        env.reset(seed=0)
        for _ in range(40):
            _, _, _, _, info = env.step(np.array([0.25, 0.0, 0.0], np.float32))
        vx_true = info["ground_truth"]["twist"][0]
        assert math.isclose(info["estimate"]["twist"][0], vx_true, abs_tol=0.03)
        assert u.pipeline.estimator.last_step.odometry_quality > 0.3
    finally:
        env.close()


def test_a_region_of_interest_in_parts_keeps_its_parts_apart():
    from perception.models.cameras import OmniCamera
    from rover_env.rendering.cubemap import CubemapRemap

    cam = OmniCamera.equidistant((320, 240), math.radians(190.0), 150.0)
    yy, xx = np.mgrid[0:240, 0:320]
    r = np.hypot(xx - 159.5, yy - 119.5)
    disk = r < 70.0  # the ground about the axis
    blob = (np.abs(xx - 240) < 25) & (np.abs(yy - 119.5) < 25)  # a wheel, touching the disk
    merged = CubemapRemap(cam, roi=disk | blob)
    apart = CubemapRemap(cam, roi=(blob, disk))
    # merged, the two are one part too wide for a view, split along the cube's faces; apart, each
    # is a view aimed at it
    assert not all(f.name.startswith("roi") for f in merged.faces)
    assert [f.name[:3] for f in apart.faces] == ["roi", "roi"] and apart.face_region == (0, 1)
    assert np.array_equal(apart.rendered, merged.rendered)  # the same pixels, in two views
    with pytest.raises(ValueError, match="roi: shape"):
        CubemapRemap(cam, roi=(blob, disk[:100]))


def test_settings_for_the_other_camera_are_refused():
    from perception.estimator import EstimatorError
    from perception.odometry.fisheye import FisheyeOdometryConfig
    from perception.odometry.flow import FlowOdometryConfig
    from rover_env.sensors.rig import builtin_estimator

    with pytest.raises(
        EstimatorError, match="fisheye_odometry: this estimator takes its odometry from the downward"
    ):
        gym.make("Rover-v0", estimator=builtin_estimator(fisheye_odometry=FisheyeOdometryConfig()))
    odo = FlowOdometryConfig.for_camera(160, 30.0)
    with pytest.raises(EstimatorError, match="odometry: a FlowOdometryConfig is the downward camera's"):
        gym.make("Rover-v0", rig="fisheye_only", estimator=builtin_estimator(odometry=odo))


def test_the_ground_in_parts_renders_the_same_image_from_fewer_pixels(monkeypatch):
    """rig_speed --floor's leaner views (a 30-degree disc, four sectors) see what the cube's faces see."""
    import dataclasses

    from conftest import flat_scenario
    from scipy.ndimage import maximum_filter, minimum_filter

    import rover_env.sensors.cameras as cams
    from rover_env.config.rig import FISHEYE_ONLY_CAMERA, PERCEPTION_PRESETS
    from rover_env.sim.simulation import RoverSim

    cfg = dataclasses.replace(PERCEPTION_PRESETS["train"].fisheye, **FISHEYE_ONLY_CAMERA)
    sim = RoverSim(flat_scenario(mu=1.0), renderer="gl")
    try:
        sim.reset(2.0, 1.0, 0.4)
        cube = cams.FisheyeCamera(sim, cfg)
        whole = cams._kinematics_roi

        def in_parts(c, g, mount):
            kin, ground = whole(c, g, mount)
            return (kin, *cams.ground_in_parts(c, np.array(mount).reshape(4, 4), ground))

        monkeypatch.setattr(cams, "_kinematics_roi", in_parts)
        parts = cams.FisheyeCamera(sim, cfg)
        assert np.array_equal(parts.remapper.rendered, cube.remapper.rendered)

        def ground_pixels(cam):
            r = cam.remapper
            return sum(f.size[0] * f.size[1] for f, k in zip(r.faces, r.face_region, strict=True) if k > 0)

        assert ground_pixels(parts) < 0.85 * ground_pixels(cube)  # 57,700 against 71,500
        assert parts.remapper.face_region.count(0) == cube.remapper.face_region.count(
            0
        )  # the kinematics' own
        a, b = cube.render_view(), parts.render_view()
        ground = cube.remapper.rendered & (a.segmentation == b.segmentation)
        seg = a.segmentation
        interior = cube.remapper.rendered & (minimum_filter(seg, 3) == maximum_filter(seg, 3))
        assert (a.segmentation == b.segmentation)[interior].mean() > 0.999
        diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int))[ground & interior]
        # the same rays resampled from other views: 0.25 grey levels apart on average, 1 at the p99
        assert diff.mean() < 1.0 and np.percentile(diff, 99) <= 4, (diff.mean(), np.percentile(diff, 99))
    finally:
        sim.close()

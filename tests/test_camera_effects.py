"""Field cameras in the simulation: motion blur along each pixel's actual motion, and the keyword."""

from __future__ import annotations

import math

import cv2
import gymnasium as gym
import numpy as np
import pytest
from conftest import flat_scenario

import rover_env  # noqa: F401
from perception.models.validation import ConfigError
from perception.rig import SensorSpec
from rover_env.config.cameras import DownwardCameraConfig
from rover_env.rendering import focus_on_rover
from rover_env.rendering.base import MotionSpec
from rover_env.rendering.gl import gl_status
from rover_env.sensors.cameras import DownwardCamera, FisheyeCamera
from rover_env.sensors.motion_blur import MotionField, blur
from rover_env.sim.simulation import RoverSim


def pinhole_rays(f: float, size=(64, 48)):
    w, h = size
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    xs, ys = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([(xs - K[0, 2]) / f, (ys - K[1, 2]) / f, np.ones_like(xs)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)

    def project(p):
        return np.stack([f * p[:, 0] / p[:, 2] + K[0, 2], f * p[:, 1] / p[:, 2] + K[1, 2]], -1)

    return rays, project, K


def test_motion_field_of_a_camera_over_a_still_plane_is_the_known_flow():
    f, height = 100.0, 0.8
    rays, project, K = pinhole_rays(f)
    field = MotionField(rays, project)
    points = rays * (height / rays[..., 2])[..., None]  # the plane z = height in the optical frame
    T = np.eye(4)
    # the camera translates along its x at 1.5 m/s and turns about its axis at 0.4 rad/s
    links = {-1: (np.zeros(3), np.array([1.5, 0.0, 0.0]), np.array([0.0, 0.0, 0.4]))}
    vel = field.velocity(points, None, T, links, body_id=99)
    xs, ys = np.meshgrid(np.arange(64.0), np.arange(48.0))
    # translation: the plane moves by -v f / h; rotation w about z: a pixel moves by -w x (x - c)
    u, v = xs - K[0, 2], ys - K[1, 2]
    expected_u = -1.5 * f / height + 0.4 * v
    expected_v = -0.4 * u
    np.testing.assert_allclose(vel[..., 0], expected_u, atol=0.02 * 1.5 * f / height)
    np.testing.assert_allclose(vel[..., 1], expected_v, atol=0.02 * 1.5 * f / height)


def test_blur_of_an_edge_spans_speed_times_exposure_over_the_ground_sample_distance():
    """A rendered step edge moving at the field's velocity: its 0-100 % ramp is v T / GSD long."""
    f, height, speed, exposure = 400.0, 0.8, 2.0, 0.004
    rays, project, _ = pinhole_rays(f, (160, 40))
    field = MotionField(rays, project)
    points = rays * (height / rays[..., 2])[..., None]
    links = {-1: (np.zeros(3), np.array([speed, 0.0, 0.0]), np.zeros(3))}
    vel = field.velocity(points, None, np.eye(4), links, body_id=99)
    image = np.zeros((40, 160, 3), np.uint8)
    image[:, 80:] = 200
    out = blur(image, vel, exposure, samples=32).astype(float)[20, :, 0]
    gsd = height / f  # [m/px] at the image centre
    expected = speed * exposure / gsd  # 4 px
    # the edge's derivative is the blur's box (length L) convolved with the 1 px box of resampling
    # a step: its variance is (L^2 + 1) / 12
    g = np.diff(out)
    x = np.arange(len(g))
    mean = np.sum(g * x) / g.sum()
    var = np.sum(g * (x - mean) ** 2) / g.sum()
    measured = math.sqrt(12 * var - 1)
    assert measured == pytest.approx(expected, rel=0.1), (measured, expected)


def test_a_rolling_shutter_shifts_each_sensor_row_by_its_velocity_times_its_readout_delay():
    """Rows given as the sensor's row fractions: the image's own rows repeat the default; all
    at the last row read (fraction 1) is a global shutter; the first row lags by the readout."""
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 255, (40, 120, 3), dtype=np.uint8), (0, 0), 2.0)
    vel = np.zeros((40, 120, 2), np.float32)
    vel[..., 0] = 400.0  # [px/s]
    exposure, readout = 0.002, 0.01
    own = blur(image, vel, exposure, 8, readout)
    ys = np.repeat((np.arange(40, dtype=np.float32) / 39)[:, None], 120, axis=1)
    np.testing.assert_array_equal(blur(image, vel, exposure, 8, readout, rows=ys), own)
    last = np.ones((40, 120), np.float32)  # (as few samples as the global shutter's path needs)
    np.testing.assert_array_equal(
        blur(image, vel, exposure, 2, readout, rows=last), blur(image, vel, exposure, 2)
    )
    # the first row saw, on average, what is now (400 px/s) x (readout + exposure / 2) = 4.4 px on
    first = np.zeros((40, 120), np.float32)
    out = blur(image, vel, exposure, 8, readout, rows=first).astype(float)[20, :, 0]
    ref = image.astype(float)[20, :, 0]
    shifts = np.arange(0.0, 8.0, 0.05)
    errors = [
        np.abs(np.interp(np.arange(20, 100) + d, np.arange(120), ref) - out[20:100]).mean() for d in shifts
    ]
    assert shifts[int(np.argmin(errors))] == pytest.approx(4.4, abs=0.15)


def test_blur_through_a_lens_samples_each_sensor_pixels_path_in_the_ideal_view_at_once():
    """With a lens's maps, the blur's output is the sensor's grid: at rest exactly the lens's
    remap; in motion the blurred ideal view seen through the lens, one resampling sharper."""
    rng = np.random.default_rng(5)
    image = cv2.GaussianBlur(rng.integers(0, 255, (60, 90, 3), dtype=np.uint8), (0, 0), 1.5)
    ys, xs = np.mgrid[0:40, 0:64].astype(np.float32)
    r2 = ((xs - 32) ** 2 + (ys - 20) ** 2) / 32.0**2
    maps = ((xs - 32) * (1 + 0.2 * r2) + 45, (ys - 20) * (1 + 0.2 * r2) + 30)  # a barrel lens
    lens = cv2.remap(image, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    still = np.zeros((60, 90, 2), np.float32)
    np.testing.assert_array_equal(blur(image, still, 0.004, 8, maps=maps), lens)
    moving = np.zeros((60, 90, 2), np.float32)
    moving[..., 0] = 800.0  # [px/s]: 3.2 px over 4 ms
    once = blur(image, moving, 0.004, 8, maps=maps).astype(float)
    twice = cv2.remap(blur(image, moving, 0.004, 8), *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    inner = np.s_[4:-4, 8:-8]
    assert np.abs(once - twice)[inner].mean() < 1.0
    assert np.abs(once - lens)[inner].mean() > 5.0  # it did blur


def test_an_rgb_images_blur_is_each_of_its_channels_blurred_alone():
    """The blur takes an RGB image through four channels (OpenCV's fast path); the result is the
    same, to the bit, as each channel blurred on its own, with and without a lens's maps."""
    rng = np.random.default_rng(8)
    image = cv2.GaussianBlur(rng.integers(0, 255, (50, 70, 3), dtype=np.uint8), (0, 0), 1.0)
    velocity = np.dstack([np.full((50, 70), 300.0), np.linspace(-500, 500, 50 * 70).reshape(50, 70)])
    velocity = velocity.astype(np.float32)
    ys, xs = np.mgrid[0:40, 0:60].astype(np.float32)
    for maps in (None, (xs * 1.1 + 2.5, ys * 1.05 + 3.25)):
        for exposure in (0.003, 0.012):  # two samples, and several
            out = blur(image, velocity, exposure, 8, maps=maps)
            for c in range(3):
                alone = blur(np.ascontiguousarray(image[..., c : c + 1]), velocity, exposure, 8, maps=maps)
                np.testing.assert_array_equal(out[..., c], alone.reshape(out.shape[:2]))


def test_the_fisheye_atlas_rows_are_the_sensor_rows_of_its_pixels():
    """What a rolling shutter reads on the cube faces: at each fisheye pixel's atlas position,
    the atlas holds that pixel's own row."""
    from rover_env.config.cameras import FisheyeCameraConfig
    from rover_env.rendering.cubemap import CubemapRemap

    model = FisheyeCameraConfig().model(np.eye(4))
    remapper = CubemapRemap(model)
    mx, my = remapper.maps
    assert np.isfinite(remapper.atlas_rows).all()
    rows = cv2.remap(remapper.atlas_rows, mx, my, cv2.INTER_LINEAR)
    w, h = model.image_size
    ys = np.repeat(np.arange(h, dtype=np.float32)[:, None], w, axis=1)
    inside = remapper.face_index >= 0
    assert inside.mean() > 0.5
    err = np.abs(rows - ys)[inside]
    # (at the edge of the field of view, the face margin's rows are their nearest pixel's)
    assert np.percentile(err, 99.9) < 0.1 and err.max() < 1.5


def test_the_downward_cameras_motion_field_follows_the_rovers_true_speed():
    sim = RoverSim(flat_scenario(mu=1.0), renderer="tiny")
    try:
        sim.reset(0.0, 0.0, 0.3)
        g = sim.geometry
        sim.rover.command(np.full(4, 1.2 / g.wheel_radius), 0.0, 0.0)
        sim.step(2.0)
        cam = DownwardCamera(sim, DownwardCameraConfig.preset("train", rate_hz=30.0))
        cam.set_effects(True, seed=1)
        view = cam.render_view()
        vel = cam._motion.velocity(
            cam._points_cam(view), view.segmentation, cam.T_world_cam(), sim.link_motion(), sim.rover.body_id
        )
        lin, _ = sim.base_velocity()
        speed = math.hypot(lin[0], lin[1])
        ground = (view.segmentation & ((1 << 24) - 1)) != sim.rover.body_id
        assert ground.mean() > 0.5
        f = cam.model.K[1, 1]
        # image up is body forward: the ground moves down the image at v f / depth, pixel by pixel
        expected = speed * f / view.depth[ground]
        assert np.median(vel[..., 1][ground] / expected) == pytest.approx(1.0, abs=0.03)
        assert np.median(np.abs(vel[..., 0][ground])) < 0.05 * np.median(expected)
        # the rover's body (its base link) moves with the camera
        body = view.segmentation == sim.rover.body_id
        if body.any():
            assert np.median(np.abs(vel[body])) < 0.05 * np.median(expected)
    finally:
        sim.close()


@pytest.mark.skipif(not gl_status()[0], reason=f"no OpenGL context here: {gl_status()[1]}")
def test_the_gl_velocity_buffer_equals_the_motion_field_of_a_labelled_render():
    """The renderer's velocity buffer (per-link velocities drawn in the colour pass) against the
    field computed from a labelled render's points and bodies, on a turning, steering rover
    (downward camera: 0.009 px/s median; fisheye: 2.0 px/s median, 12 px/s p95 of 271).

    The fisheye's buffer is drawn on its cube faces (atlas pixels per second): it is carried to
    the fisheye's pixels through the remap's Jacobian, d(atlas)/d(fisheye pixel)."""
    env = gym.make("RoverShadows-v0", renderer="gl", camera_effects="field")
    try:
        env.reset(seed=2)
        for _ in range(30):
            env.step(np.array([0.8, 0.4, 0.0], np.float32))
        sim = env.unwrapped.sim
        for cam in env.unwrapped.pipeline.cameras:
            if isinstance(cam, DownwardCamera):
                cam._lens_keep = None  # the whole view (see the lens footprint's own test)
            focus_on_rover(sim, cam.config.ground_range)
            view = cam._render(labels=True)
            links = sim.link_motion()
            T = cam.T_world_cam()
            expected = cam._motion.velocity(
                cam._points_cam(view), view.segmentation, T, links, sim.rover.body_id
            )
            com, v, w = links[-1]
            buffers: list[tuple] = []

            def keep(image, velocity, origin, buffers=buffers):
                buffers.append((origin, velocity.copy()))
                return image

            spec = MotionSpec(sim.rover.body_id, links, v + np.cross(w, T[:3, 3] - com), w, keep)
            cam._render(labels=False, motion=spec)
            if not isinstance(cam, FisheyeCamera):
                ((origin, drawn),) = buffers
                assert origin == (0, 0)
            else:  # a buffer per face, placed in the atlas
                aw, ah = cam.remapper.atlas_size
                drawn = np.zeros((ah, aw, 2), np.float32)
                assert len(buffers) == len(cam.remapper.faces)
                for (x0, y0), buf in buffers:
                    drawn[y0 : y0 + buf.shape[0], x0 : x0 + buf.shape[1]] = buf
                remapper = cam.remapper
                mx, my = remapper.maps
                at = cv2.remap(drawn, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                # the remap's Jacobian by central differences, within one face
                J = np.stack([np.stack(np.gradient(m)[::-1], -1) for m in (mx, my)], -2)  # (H, W, 2, 2)
                face = remapper.face_index
                same = np.ones_like(face, bool)
                for ax in (0, 1):
                    for step in (1, -1):
                        same &= np.roll(face, step, axis=ax) == face
                ok = same & (face >= 0) & (np.abs(np.linalg.det(J)) > 1e-6)
                drawn = np.zeros_like(expected)
                drawn[ok] = np.linalg.solve(J[ok], at[ok][..., None])[..., 0]
                expected = np.where(ok[..., None], expected, 0.0)
            speed = np.linalg.norm(expected, axis=-1)
            err = np.linalg.norm(drawn - expected, axis=-1)[speed > 0]
            rover = ((view.segmentation & ((1 << 24) - 1)) == sim.rover.body_id)[speed > 0]
            print(
                f"{type(cam).__name__}: median speed {np.median(speed[speed > 0]):.0f} px/s, error median "
                f"{np.median(err):.3f}, p95 {np.percentile(err, 95):.2f} px/s; "
                f"on the rover ({rover.sum()} px) {np.median(err[rover]):.3f}"
            )
            # the fisheye's buffer is resampled bilinearly from its cube faces, the labelled points
            # by the nearest face pixel: they differ by a fraction of a pixel's change of motion
            typical = np.median(speed[speed > 0])
            assert np.median(err) < 0.01 * typical
            assert np.percentile(err, 95) < 0.06 * typical  # edges mix two motions
            assert rover.sum() > 100 and np.median(err[rover]) < 0.02 * typical
    finally:
        env.close()


def test_field_cameras_change_the_images_not_the_physics_and_the_seed_repeats_them():
    actions = [np.array([0.6, 0.1 * math.sin(k / 4), 0.0], np.float32) for k in range(25)]

    def run(effects, seed=4):
        env = gym.make("RoverShadows-v0", renderer="tiny", camera_effects=effects)
        try:
            env.reset(seed=seed)
            out = [env.step(a) for a in actions]
            images = {k: v.copy() for k, v in env.unwrapped.pipeline.last_images.items()}
        finally:
            env.close()
        poses = np.array([o[4]["ground_truth"]["pose"] for o in out])
        return poses, np.array([o[0] for o in out]), images

    p_ideal, o_ideal, im_ideal = run("ideal")
    p_field, o_field, im_field = run("field")
    p_again, o_again, im_again = run("field")
    np.testing.assert_array_equal(p_ideal, p_field)  # the physics is the same whatever observes
    np.testing.assert_array_equal(o_field, o_again)
    assert all(np.array_equal(im_field[k], im_again[k]) for k in im_field)
    assert not np.array_equal(o_ideal, o_field)
    assert not np.array_equal(im_ideal["downward"], im_field["downward"])
    # the estimator is given the field cameras' photometric response (their output gamma)
    env = gym.make("RoverShadows-v0", renderer="tiny", camera_effects="field")
    try:
        rig = env.unwrapped.pipeline.rig
        assert [rig[n].gamma for n in ("fisheye", "downward")] == [2.2, 2.2]
        assert [rig[n].bayer for n in ("fisheye", "downward")] == ["RGGB", "RGGB"]
        assert env.unwrapped.pipeline.kinematics.gamma == 2.2
        assert env.unwrapped.pipeline.kinematics.bayer == "RGGB"
        # and its lens's vignetting, which the odometry flat-fields
        assert [rig[n].vignetting for n in ("fisheye", "downward")] == [0.8, 0.8]
        assert env.unwrapped.pipeline.odometry._flat is not None
    finally:
        env.close()
    with pytest.raises(ConfigError, match="gamma"):
        SensorSpec("downward", "pinhole", 30.0, np.eye(4), None, gamma=0.0)
    with pytest.raises(ConfigError, match="bayer"):
        SensorSpec("downward", "pinhole", 30.0, np.eye(4), None, bayer="RGBW")
    for vignetting in (0.0, 1.2, float("nan")):
        with pytest.raises(ConfigError, match="downward.vignetting"):
            SensorSpec("downward", "pinhole", 30.0, np.eye(4), None, vignetting=vignetting)
    with pytest.raises(ValueError, match="camera_effects"):
        gym.make("Rover-v0", camera_effects="vivid")


def test_lens_distortion_matches_the_calibration_the_estimator_is_given():
    """Checkerboard corners through the lens, and in the delivered image, against the calibration."""
    import cv2

    from rover_env.config.image_sensor import ImageSensorConfig
    from rover_env.config.scenario import load_scenario

    scenario = load_scenario("calibration")
    sim = RoverSim(scenario, renderer="gl")
    try:
        sim.reset(0.013, 0.021, 0.3)
        sensor = ImageSensorConfig(read_noise_e=0.0, prnu=0.0, dsnu_e=0.0, vignetting=1.0, blur_samples=1)
        cam = DownwardCamera(sim, DownwardCameraConfig(shadows=False, sensor=sensor))
        cam.set_effects(True, seed=2)
        lensed = cam._lens(cam.capture().image)  # the image the lens forms, before the sensor
        for _ in range(20):  # auto-exposure settles on the board
            delivered = cam.sample()
        pos, quat = sim.client.getBasePositionAndOrientation(sim.rover.body_id)
        R_wb = np.array(sim.client.getMatrixFromQuaternion(quat)).reshape(3, 3)
    finally:
        sim.close()
    model = cam.model
    assert np.allclose(model.distortion, sensor.distortion)
    s = scenario.terrain.checker_square
    i, j = np.meshgrid(np.arange(-40, 41), np.arange(-40, 41))
    world = np.column_stack([i.ravel() * s, j.ravel() * s, np.zeros(i.size)])
    T_cb = np.linalg.inv(model.T_body_cam)
    cam_pts = ((world - pos) @ R_wb) @ T_cb[:3, :3].T + T_cb[:3, 3]
    expected = model.project(cam_pts)
    w, h = model.image_size
    inside = np.isfinite(expected).all(axis=1) & (expected > 12).all(axis=1)
    inside &= (expected[:, 0] < w - 12) & (expected[:, 1] < h - 12)
    assert inside.sum() > 100
    ideal = cam._ideal.project(cam_pts[inside])
    # the image's edges bend: without the distortion the corners would be pixels off there
    assert np.max(np.linalg.norm(ideal - expected[inside], axis=1)) > 5.0
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)

    def corners(image):
        gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        start = expected[inside].astype(np.float32).reshape(-1, 1, 2)
        return cv2.cornerSubPix(gray, start, (7, 7), (-1, -1), crit).reshape(-1, 2)

    # through the lens: undistorted with the calibration, the corners are where an ideal camera
    # sees them
    undist = model.undistort_points(corners(lensed))
    err_u = np.linalg.norm(undist - ideal, axis=1)
    print(f"{inside.sum()} corners through the lens, after undistortion: median {np.median(err_u):.3f} px")
    assert np.median(err_u) <= 0.1
    # in the delivered image (Bayer demosaicing and shot noise added) against the distorted projection
    err = np.linalg.norm(corners(delivered) - expected[inside], axis=1)
    print(f"delivered: median {np.median(err):.3f} px, p95 {np.percentile(err, 95):.3f} px")
    assert np.median(err) <= 0.15 and np.percentile(err, 95) <= 0.3


def test_a_scenario_sets_a_cameras_sensor_figures_and_bad_ones_name_the_key():
    import dataclasses

    from rover_env.config.io import ConfigError
    from rover_env.config.rig import SensorConfig

    scenario = rover_env.load_scenario("flat_patches")
    rig = (
        SensorConfig("fisheye", "fisheye"),
        SensorConfig("downward", "pinhole", camera={"sensor": {"jpeg_quality": 70, "exposure_max_s": 0.008}}),
    )
    env = gym.make("Rover-v0", scenario=dataclasses.replace(scenario, rig=rig), camera_effects="field")
    try:
        sensor = env.unwrapped.pipeline.downward.image_sensor.config
        assert (sensor.jpeg_quality, sensor.exposure_max_s, sensor.full_well_e) == (70, 0.008, 10_400.0)
        assert np.allclose(env.unwrapped.rig["downward"].model.distortion[:2], sensor.distortion[:2])
    finally:
        env.close()
    with pytest.raises(ConfigError, match=r"camera\.sensor\.gamma"):
        SensorConfig("downward", "pinhole", camera={"sensor": {"gamma": 0.0}})
    with pytest.raises(ConfigError, match=r"unknown key 'camera\.sensor\.iso'"):
        SensorConfig("downward", "pinhole", camera={"sensor": {"iso": 100}})
    # (the preset's own 10 ms is capped at a faster camera's frame period; one set otherwise is not)
    long = SensorConfig("downward", "pinhole", rate_hz=120.0, camera={"sensor": {"exposure_max_s": 0.012}})
    with pytest.raises(ConfigError, match="exposure_max_s: 12 ms is longer than the frame period 8.33333 ms"):
        gym.make(
            "Rover-v0", scenario=dataclasses.replace(scenario, rig=(rig[0], long)), camera_effects="field"
        )
    fast = SensorConfig("downward", "pinhole", rate_hz=120.0)
    env = gym.make(
        "Rover-v0", scenario=dataclasses.replace(scenario, rig=(rig[0], fast)), camera_effects="field"
    )
    try:
        env.reset(seed=0)
        assert env.unwrapped.pipeline.downward.image_sensor.config.exposure_max_s == pytest.approx(1 / 120)
    finally:
        env.close()


def test_the_sun_moves_and_clouds_dim_it_and_auto_exposure_follows():
    import dataclasses

    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import SunConfig

    sun = SunConfig(
        azimuth_deg=90.0, elevation_deg=30.0, azimuth_rate_deg_s=2.0, clouds=((1.0, 3.0, 0.2, 0.0),)
    )
    az = math.radians(90.0 + 2.0 * 5.0)
    assert np.allclose(
        sun.direction(5.0)[:2] / np.linalg.norm(sun.direction(5.0)[:2]), [math.cos(az), math.sin(az)]
    )
    assert np.allclose([sun.transmission(t) for t in (0.5, 1.0, 2.0, 3.5)], [1.0, 0.2, 0.2, 1.0])
    ramped = SunConfig(clouds=((1.0, 3.0, 0.2, 0.5),))
    assert ramped.transmission(1.25) == pytest.approx(0.6)
    for bad, key in (
        ((1.0, 0.5, 0.2, 0.0), "end"),
        ((1.0, 2.0, 1.5, 0.0), "transmission"),
        ((0, 1, 0.5), "clouds"),
    ):
        with pytest.raises(ConfigError, match=key):
            SunConfig(clouds=(bad,))
    # the rover stands still; a cloud covers the sun at 1 s: the image darkens, then the
    # auto-exposure brings its mean back to the target within its settling time
    scenario = rover_env.load_scenario(rover_env.MISSIONS["Rover-v0"])
    scenario = dataclasses.replace(
        scenario, sun=dataclasses.replace(scenario.sun, clouds=((1.0, 4.0, 0.15, 0.0),))
    )
    env = gym.make("Rover-v0", scenario=scenario, renderer="tiny", camera_effects="field")
    try:
        env.reset(seed=3)
        cam = env.unwrapped.pipeline.downward
        target, settle = cam.config.sensor.ae_target, cam.config.sensor.ae_settling_s
        levels = []
        for _ in range(int(3.5 * 30)):
            env.step(np.zeros(3, np.float32))
            levels.append((env.unwrapped.sim.t, env.unwrapped.pipeline.last_images["downward"].mean() / 255))
    finally:
        env.close()
    t, level = np.array(levels).T
    assert abs(level[(t > 0.6) & (t < 0.99)].mean() / target - 1) < 0.05
    assert level[(t > 0.99) & (t < 1.05)].min() < 0.8 * target  # the cloud darkens the frame
    back = (t > 1.0 + settle + 2 / 30) & (t < 3.5)
    assert np.all(np.abs(level[back] / target - 1) < 0.05)


@pytest.mark.parametrize("renderer", ["gl", "tiny"])
def test_a_cloud_shadow_sweeps_over_the_ground_with_the_wind(renderer):
    """A cloud's shadow band moving along world x at 2 m/s, its leading edge in the downward view:
    GL dims each pixel by the band's cover at its ground point (image / sunlit image against
    (ambient + D sky) / (ambient + D)); TinyRenderer dims the whole view by its value at the camera."""
    import dataclasses

    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import SunConfig

    if renderer == "gl" and not gl_status()[0]:
        pytest.skip(f"no OpenGL context here: {gl_status()[1]}")
    band = (1.0, 2.0, 0.0, 3.0, 0.2, 0.3)  # t_enter, speed, heading, length, transmission, edge
    sun = SunConfig(azimuth_deg=30.0, elevation_deg=50.0, cloud_shadows=(band,))
    assert sun.shade([[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.5, 0.0, 0.0]], 1.0) == pytest.approx(
        [0.6, 0.2, 1.0]
    )
    sim = RoverSim(dataclasses.replace(flat_scenario(), sun=sun), renderer=renderer)
    try:
        sim.reset(0.0, 0.0, 0.0)
        cam = DownwardCamera(sim)

        def view_at(t):
            sim._steps = int(round(t / sim.dt))  # the light at time t (the rover stands still)
            return cam.render_view()

        lit = view_at(0.0).rgb.astype(np.float64).mean(axis=2)
        a, D = cam.config.ambient, sun.direction(0.0)[2]  # flat ground: cos(i) = the sun's height
        seen = view_at(0.0).points_world
        x0 = float(np.median(seen[..., 0]))
        t = 1.0 + x0 / 2.0  # the leading edge at the middle of the view
        view = view_at(t)
        ratio = view.rgb.astype(np.float64).mean(axis=2) / np.maximum(lit, 1.0)
        ok = ~view.shadow & (lit > 20) & (lit < 250)
        if renderer == "gl":
            expected = (a + D * sun.shade(view.points_world.reshape(-1, 3), t).reshape(ratio.shape)) / (a + D)
            err = np.abs(ratio - expected)[ok]
            print(
                f"gl: ratio {ratio[ok].min():.2f} to {ratio[ok].max():.2f}; error median {np.median(err):.3f}"
            )
            assert ratio[ok].max() - ratio[ok].min() > 0.4  # the edge is in the view
            assert np.median(err) < 0.02 and np.percentile(err, 95) < 0.06
        else:
            shade = float(sun.shade(cam.T_world_cam()[:3, 3][None], t)[0])
            expected = (a + D * shade) / (a + D)
            print(f"tiny: ratio median {np.median(ratio[ok]):.3f} against {expected:.3f}")
            assert np.median(ratio[ok]) == pytest.approx(expected, abs=0.03)
    finally:
        sim.close()
    with pytest.raises(ConfigError, match=r"cloud_shadows\[0\]\.edge"):
        SunConfig(cloud_shadows=((1.0, 2.0, 0.0, 3.0, 0.2, 0.0),))
    with pytest.raises(ConfigError, match="cloud_shadows"):
        SunConfig(cloud_shadows=((1.0, 2.0, 0.0, 3.0),))


def test_a_field_lens_draws_only_the_pixels_it_reads_and_its_frames_do_not_change():
    """With a distorting lens the wider ideal view is drawn only within BLUR_REACH_PX of the
    pixels the lens reads (88 % of it): those are bit-for-bit the full render's, the rest black
    and still; a frame whose blur reaches farther is drawn in full; the delivered frames and the
    observations are the same as with the whole view drawn."""
    actions = [np.array([0.9, 0.5 * math.sin(k / 6), 0.0], np.float32) for k in range(40)]

    def run(mask: bool):
        env = gym.make("RoverShadows-v0", renderer="gl", camera_effects="field", preset="train")
        try:
            env.reset(seed=2)
            (cam,) = [c for c in env.unwrapped.pipeline.cameras if isinstance(c, DownwardCamera)]
            if not mask:
                cam._lens_keep = None
            frames, obs = [], []
            for a in actions:
                obs.append(env.step(a)[0])
                frames.append(env.unwrapped.pipeline.last_images["downward"].copy())
            if mask:  # the footprint against the full render, at this instant
                kept = cam._lens_keep
                assert kept is not None and kept.shape == cam._render_model.image_size[::-1]
                assert 0.8 < kept.mean() < 0.95
                sim = env.unwrapped.sim
                focus_on_rover(sim, cam.config.ground_range)
                links = sim.link_motion()
                T = cam.T_world_cam()
                com, v, w = links[-1]
                spec = MotionSpec(sim.rover.body_id, links, v + np.cross(w, T[:3, 3] - com), w, None)
                renderer = focus_on_rover(sim, cam.config.ground_range)
                args = (cam._render_model, T, cam.lighting)
                full = renderer.render_pinhole(*args, segmentation=False, motion=spec)
                part = renderer.render_pinhole(*args, segmentation=False, motion=spec, keep=kept)
                np.testing.assert_array_equal(part.rgb[kept], full.rgb[kept])
                np.testing.assert_array_equal(part.motion[kept], full.motion[kept])
                assert not part.rgb[~kept].any() and not part.motion[~kept].any()
                assert full.rgb[~kept].mean() > 10  # the ground is there, and was left undrawn
                # the camera's own choice: masked at a short exposure, whole at a long one
                cam.image_sensor.exposure_s = 1e-4
                assert not cam._render(labels=False, motion=spec).motion[~kept].any()
                cam.image_sensor.exposure_s = 0.01
                span = np.abs(full.motion).max()
                assert span * 0.01 > cam.BLUR_REACH_PX
                assert cam._render(labels=False, motion=spec).motion[~kept].any()
        finally:
            env.close()
        return frames, np.array(obs)

    f_mask, o_mask = run(True)
    f_full, o_full = run(False)
    assert all(np.array_equal(a, b) for a, b in zip(f_mask, f_full, strict=True))
    np.testing.assert_array_equal(o_mask, o_full)

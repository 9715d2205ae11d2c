"""Wheel sinkage from the fisheye, on images ray-cast with a known sinkage (no simulator)."""

from __future__ import annotations

import numpy as np
import pytest
from test_markers import fisheye, rover_model

from perception.kinematics.sinkage import SinkageEstimator
from perception.models.drive_geometry import WHEELS

FACE = np.array([96.0, 96.0, 98.0])  # the wheels' inner faces: grey
SAND = np.array([176.0, 164.0, 132.0])  # the soil: a sand colour, textured


def cast(
    model, camera, sinkage: float, soil=SAND, texture: float = 18.0, seed: int = 0, shade: float = 0.0
) -> np.ndarray:
    """The fisheye image of the four wheels' inner faces standing ``sinkage`` [m] deep in level soil.

    Each pixel's ray meets, nearest first, a wheel's inner face (a disc of the wheel's radius,
    seen where it stands above the soil) or the soil's surface; anything else is black. With
    ``shade`` [m], the soil within it of each face is in the wheel's shade, grey grains a quarter
    darker and brighter than the face's grey (their mean the face's).
    """
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(w) + 0.0, np.arange(h) + 0.0)
    rays = camera.cam2world(np.stack([u, v], -1).reshape(-1, 2))
    T = model.T_body_cam
    d = rays @ T[:3, :3].T  # body frame
    o = T[:3, 3]
    frames = model.wheel_frames(np.zeros(2), np.full(2, model.nominal_depth), np.zeros(4))
    ground_z = frames[0][1][2] - model.wheel_radius + sinkage
    best = np.full(len(d), np.inf)
    img = np.zeros((len(d), 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ground = (ground_z - o[2]) / d[:, 2]
        hit = np.isfinite(t_ground) & (t_ground > 0)
        best = np.where(hit, t_ground, best)
        rng = np.random.default_rng(seed)
        p = o + t_ground[:, None] * d
        grain = np.sin(p[:, 0] * 340.0) * np.cos(p[:, 1] * 290.0) + rng.normal(0, 0.3, len(d))
        img = np.where(hit[:, None], soil + texture * grain[:, None], img)
        for k, (_, c) in enumerate(frames):
            side = -1.0 if WHEELS[k][1] == "L" else 1.0
            inward = side * (c[1] + side * 0.5 * model.wheel_width - p[:, 1])
            near = hit & (inward >= 0) & (inward <= shade) & (np.abs(p[:, 0] - c[0]) <= model.wheel_radius)
            img = np.where(near[:, None], FACE * (1.0 + 0.25 * np.sign(grain))[:, None], img)
        for k, (_, c) in enumerate(frames):
            side = -1.0 if WHEELS[k][1] == "L" else 1.0
            y_face = c[1] + side * 0.5 * model.wheel_width
            t = (y_face - o[1]) / d[:, 1]
            q = o + t[:, None] * d
            on = (t > 0) & ((q[:, 0] - c[0]) ** 2 + (q[:, 2] - c[2]) ** 2 <= model.wheel_radius**2)
            on &= q[:, 2] >= ground_z  # below the surface the soil hides it
            nearer = on & (t < best)
            best = np.where(nearer, t, best)
            img = np.where(nearer[:, None], FACE, img)
    img = np.where(np.isfinite(rays[:, :1]), img, 0.0)
    return np.clip(img, 0, 255).reshape(h, w, 3).astype(np.uint8)


@pytest.fixture(scope="module")
def rig():
    model = rover_model()
    return model, fisheye(model)


@pytest.mark.parametrize("sinkage", [0.010, 0.025, 0.045])
def test_a_known_sinkage_is_measured_on_every_wheel(rig, sinkage):
    model, camera = rig
    est = SinkageEstimator(camera, model).measure(
        cast(model, camera, sinkage), np.zeros(2), np.full(2, model.nominal_depth), np.zeros(4)
    )
    np.testing.assert_allclose(est.sinkage, sinkage, atol=0.002)
    assert np.all(est.quality > 0.5)


def test_wheels_on_rigid_ground_read_no_sinkage(rig):
    model, camera = rig
    est = SinkageEstimator(camera, model).measure(
        cast(model, camera, 0.0), np.zeros(2), np.full(2, model.nominal_depth), np.zeros(4)
    )
    np.testing.assert_allclose(est.sinkage, 0.0, atol=0.002)


def test_soil_half_in_the_wheels_shade_is_soil_though_its_mean_is_the_faces_grey(rig):
    """The face's samples as colour features: grey face above 21 mm; below it soil in the wheel's
    shade, grains darker and brighter than the face (their mean near the face's, far from the
    sunlit soil's beside it)."""
    from perception.kinematics.sinkage import SinkageConfig

    model, camera = rig
    face, sunlit = np.array([0.0, 0.0, 296.0]), np.array([1.0, -0.6, 312.0])

    def split(config, depth=0.021, swing=15.0, offset=4.0):
        est = SinkageEstimator(camera, model, config)
        z = est.zeta[est._row]
        grain = offset + np.where(np.arange(len(z)) % 2 == 0, swing, -swing)  # brighter, darker, ...
        x = np.where((z < depth)[:, None], face + np.c_[0.0 * grain, 0.0 * grain, grain], face)
        ground = np.tile(sunlit, (len(est._local[0]) - est._n_face, 1))
        out = est._breaks(x[None], np.ones((1, len(z)), bool), ground[None], np.ones((1, len(ground)), bool))
        return out.sinkage[0], out.quality[0]

    z, q = split(SinkageConfig())
    assert abs(z - 0.0195) <= 0.002 and q >= 0.3  # between the rows at 18 and 21 mm
    # the mean colour alone takes it for the face: rigid ground
    assert split(SinkageConfig(soil_break=1.0))[0] == 0.0
    # low, the mean decides (a pose error of a pixel shows the ground under a rim)
    assert split(SinkageConfig(), depth=0.009)[0] == 0.0


def test_a_wrong_wheel_pose_moves_the_measured_sinkage_by_its_height(rig):
    """The sinkage is read against the wheel's estimated pose: an axle taken 1 cm lower reads 1 cm deeper."""
    model, camera = rig
    img = cast(model, camera, 0.03)
    est = SinkageEstimator(camera, model).measure(
        img, np.zeros(2), np.full(2, model.nominal_depth + 0.01), np.zeros(4)
    )
    np.testing.assert_allclose(est.sinkage, 0.04, atol=0.004)


@pytest.mark.parametrize(
    "image",
    [
        lambda m, c: np.zeros((480, 640, 3), np.uint8),  # a black frame
        lambda m, c: cast(m, c, 0.03, soil=FACE, texture=2.0),  # soil as grey and dark as the face
    ],
)
def test_no_boundary_to_see_is_no_sinkage(rig, image):
    model, camera = rig
    est = SinkageEstimator(camera, model).measure(
        image(model, camera), np.zeros(2), np.full(2, model.nominal_depth), np.zeros(4)
    )
    assert np.all(np.isnan(est.sinkage)) and np.all(est.quality == 0.0)


def test_the_ground_in_view_is_lifted_only_where_most_wheels_report_sinkage():
    from perception.rover_estimator import ground_lift

    nan = float("nan")
    np.testing.assert_allclose(ground_lift([0.020, 0.022, nan, 0.026]), [0.020, 0.022, 0.022, 0.026])
    # one wheel's reading alone (a shadow on rigid ground, more often than soil): no lift
    np.testing.assert_array_equal(ground_lift([0.0, 0.011, 0.0, nan]), np.zeros(4))
    np.testing.assert_array_equal(ground_lift([0.008, 0.011, nan, nan]), np.zeros(4))
    assert ground_lift([nan] * 4) is None  # nothing measured: the last lift holds


def _frame(z, q):
    from perception.kinematics.sinkage import SinkageEstimate

    return SinkageEstimate(np.asarray(z, dtype=float), np.asarray(q, dtype=float))


def test_the_track_outvotes_a_flipped_frame_and_forgets_old_ones():
    from perception.kinematics.sinkage import SinkageTrack

    track = SinkageTrack(window=0.8, min_weight=1.5)
    nan = float("nan")
    # one frame's quality alone is not enough
    out = track.update(0.0, _frame([0.020, 0.020, 0.0, nan], [0.9, 0.9, 0.9, 0.0]))
    assert np.all(np.isnan(out.sinkage)) and np.all(out.quality == 0.0)
    out = track.update(0.1, _frame([0.022, 0.020, 0.0, 0.030], [0.9, 0.9, 0.9, 0.9]))
    np.testing.assert_allclose(out.sinkage[:3], [0.020, 0.020, 0.0])
    np.testing.assert_allclose(out.quality[:3], 0.6)
    assert np.isnan(out.sinkage[3])
    # FL's reading flips to 0 (its soil in the wheel's shade taken for the face); FR's below
    # the reported quality does not count
    out = track.update(0.2, _frame([0.0, 0.060, 0.0, 0.030], [0.5, 0.2, 0.9, 0.9]))
    np.testing.assert_allclose(out.sinkage, [0.020, 0.020, 0.0, 0.030])
    # nothing new for longer than the window: none left
    out = track.update(1.05, None)
    assert np.all(np.isnan(out.sinkage)) and np.all(out.quality == 0.0)
    # a change of ground wins once its frames outweigh the old ones
    for k in range(5):
        track.update(1.1 + 0.1 * k, _frame([0.030] * 4, [0.9] * 4))
    out = track.update(1.6, _frame([0.010] * 4, [0.9] * 4))
    np.testing.assert_allclose(out.sinkage, 0.030)
    for k in range(5):
        out = track.update(1.7 + 0.1 * k, _frame([0.010] * 4, [0.9] * 4))
    np.testing.assert_allclose(out.sinkage, 0.010)
    np.testing.assert_allclose(out.quality, 1.0)
    # time running back (a new log): afresh
    out = track.update(0.0, _frame([0.040] * 4, [0.9] * 4))
    assert np.all(np.isnan(out.sinkage))


@pytest.mark.parametrize("kw", [{"window": 0.0}, {"window": float("nan")}, {"min_weight": -1.0}])
def test_a_track_without_a_window_or_weight_is_refused(kw):
    from perception.kinematics.sinkage import SinkageTrack

    with pytest.raises(ValueError, match="window|min_weight"):
        SinkageTrack(**kw)

"""Heading from a sun sensor: the geometry against known poses, and the filter on synthetic drives.

Perception only: the readings are made here from known attitudes and a known sun.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from perception.fusion.sun_heading import HeadingConfig, HeadingFilter, level_direction, sun_heading, wrap
from perception.models.validation import ConfigError


def sun_dir(az: float, el: float) -> np.ndarray:
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def world_from_body(yaw: float, pitch: float, roll: float) -> np.ndarray:
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_matrix()


def test_sun_heading_recovers_a_known_pose():
    rng = np.random.default_rng(3)
    for _ in range(300):
        yaw, pitch, roll = rng.uniform(-3.1, 3.1), rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4)
        R_bs = Rotation.from_rotvec(rng.uniform(-0.3, 0.3, 3)).as_matrix()
        az, el = rng.uniform(-3.1, 3.1), rng.uniform(0.2, 1.4)
        e = sun_dir(az, el)
        s = (world_from_body(yaw, pitch, roll) @ R_bs).T @ e
        y, el_level = sun_heading(s, R_bs, e, roll, pitch)
        assert abs(wrap(y - yaw)) < 1e-9
        assert el_level == pytest.approx(el, abs=1e-9)


def test_level_direction_undoes_the_tilt():
    s_world = np.array([0.3, -0.4, 0.866])
    roll, pitch = 0.2, -0.15
    tilt = world_from_body(0.0, pitch, roll)
    np.testing.assert_allclose(level_direction(tilt.T @ s_world, roll, pitch), s_world, atol=1e-12)


def test_a_tilt_error_turns_the_azimuth_by_tan_elevation():
    # a roll error across the sun's azimuth moves it by about tan(el) times the error
    el, err = math.radians(60.0), math.radians(0.5)
    e = sun_dir(math.pi / 2, el)  # the sun to the left of a rover heading along x
    s = world_from_body(0.0, 0.0, 0.0).T @ e
    y, _ = sun_heading(s, np.eye(3), e, 0.0, err)  # pitch error: the sun's side direction
    assert abs(y) == pytest.approx(math.tan(el) * err, rel=0.02)


def drive(filt: HeadingFilter, headings, yaw_error, tilt_error, el, az, noise=0.0, seed=0, boresight=0.0):
    """Readings at 5 Hz along ``headings`` [rad], each for 10 s; returns the yaw errors after each leg."""
    rng = np.random.default_rng(seed)
    e = sun_dir(az, el)
    R_bs = Rotation.from_rotvec([0.0, 0.0, boresight]).as_matrix()
    dr_error = yaw_error
    out = []
    for psi in headings:
        for _ in range(50):
            filt.predict(0.2, 1e-9)
            true_roll, true_pitch = 0.02 * math.sin(psi), -0.03
            # the IMU's tilt is off by the body-frame error; the dead reckoning by dr_error
            s = (world_from_body(psi, true_pitch, true_roll) @ R_bs).T @ e
            s = Rotation.from_rotvec(noise * rng.standard_normal(3)).as_matrix() @ s
            c = filt.update(
                psi + dr_error, s, np.eye(3), e, true_roll - tilt_error[0], true_pitch - tilt_error[1]
            )
            if c is not None:
                dr_error += c
        out.append(dr_error)
    return out


def test_filter_finds_heading_and_tilt_errors_as_the_rover_turns():
    # start 1.5 deg off, the IMU tilted 1 deg off on both axes, a 60 deg sun
    filt = HeadingFilter(HeadingConfig(start_std_deg=1.0), accuracy_deg=0.1, noise_deg=0.03, tilt_std=0.02)
    tilt = (math.radians(1.0), math.radians(-1.0))
    errs = drive(filt, [0.0, 0.6, 1.6, 2.5], math.radians(1.5), tilt, math.radians(60.0), 2.0, 5e-4)
    assert abs(math.degrees(errs[-1])) < 0.1
    np.testing.assert_allclose(filt.x[1:], tilt, atol=math.radians(0.1))
    assert filt.yaw_std < math.radians(0.3)  # the tilt error is allowed to wander (tilt_time)
    assert filt.used == 200 and filt.rejected == 0


def test_filter_on_one_heading_keeps_the_start_fix_where_the_sun_cannot_tell():
    # one heading: the tilt across the sun's azimuth stays unknown; with a high sun its 1 deg
    # would put the azimuth 2.7 deg off, and the filter must not follow it
    filt = HeadingFilter(HeadingConfig(start_std_deg=1.0), accuracy_deg=0.1, noise_deg=0.03, tilt_std=0.02)
    tilt = (math.radians(1.0), 0.0)  # a roll error, the sun to the side
    errs = drive(filt, [0.0], 0.0, tilt, math.radians(70.0), math.pi / 2)
    assert abs(math.degrees(errs[-1])) < 0.6
    assert filt.yaw_std > math.radians(0.5)


def test_filter_keeps_the_boresight_error_as_its_floor():
    # a sensor turned 0.3 deg about its boresight reads every azimuth 0.3 deg off: the heading
    # cannot be known better than the prior of that error allows
    cfg = HeadingConfig(start_std_deg=1.0, tilt_time=1e9, tilt_noise_deg=0.01)
    filt = HeadingFilter(cfg, accuracy_deg=0.1, noise_deg=0.03, tilt_std=0.01)
    errs = drive(filt, [0.0, 1.0, 2.0], 0.0, (0.0, 0.0), math.radians(45.0), 0.5, boresight=math.radians(0.3))
    # the prior splits the 0.3 deg: 1 : 0.01 in variance between the start fix and the sensor
    assert abs(math.degrees(errs[-1])) == pytest.approx(0.3 / 1.01, abs=0.02)
    assert filt.yaw_std == pytest.approx(math.radians(0.1) / math.hypot(1.0, 0.1), rel=0.1)


def test_filter_leaves_out_a_zenith_sun_and_an_outlier():
    filt = HeadingFilter()
    e = sun_dir(0.0, math.radians(89.0))
    assert filt.update(0.0, e, np.eye(3), e, 0.0, 0.0) is None
    e = sun_dir(1.0, math.radians(40.0))
    s = world_from_body(0.5, 0.0, 0.0).T @ e  # the dead reckoning 30 deg off: a bad reading
    assert filt.update(0.0, s, np.eye(3), e, 0.0, 0.0) is None
    assert filt.rejected == 1 and filt.used == 0
    nan = np.full(3, np.nan)
    assert filt.update(0.0, nan, np.eye(3), e, 0.0, 0.0) is None


@pytest.mark.parametrize(
    "key, value",
    [("start_std_deg", 0.0), ("gate", -1.0), ("tilt_std_deg", float("nan")), ("max_elevation_deg", 90.0)],
)
def test_heading_config_rejects_impossible_values(key, value):
    with pytest.raises(ConfigError, match=key):
        HeadingConfig(**{key: value})

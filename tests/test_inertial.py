"""Roll, pitch and tilted dead reckoning from IMU samples alone (no simulator)."""

import math

import numpy as np
import pytest

from perception.fusion.inertial import AttitudeFilter, G, tilt_from_gravity, tilted_step


def rot_zyx(roll, pitch, yaw):
    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return Rz @ Ry @ Rx


def test_tilt_at_rest_from_gravity_round_trip():
    for roll, pitch in [(0.0, 0.0), (0.2, -0.1), (-0.35, 0.3)]:
        f = rot_zyx(roll, pitch, 1.0).T @ [0.0, 0.0, G]
        assert tilt_from_gravity(f) == pytest.approx((roll, pitch), abs=1e-12)


def test_attitude_follows_a_known_roll_rate_with_a_calibrated_z_bias():
    """Roll at 0.2 rad/s for 1 s from level, the gyro's z bias calibrated at rest: the gyro carries it."""
    bias = np.array([0.0, 0.0, 0.005])
    a = AttitudeFilter()
    a.calibrate(bias, [0.0, 0.0, G])
    assert a.bias == pytest.approx(bias)
    dt, rate = 1 / 240, 0.2
    for k in range(240):
        roll = rate * (k + 1) * dt
        f = rot_zyx(roll, 0.0, 0.0).T @ [0.0, 0.0, G]
        a.update(bias + [rate, 0.0, 0.0], f, dt)
    assert a.roll == pytest.approx(0.2, abs=1e-3)
    assert a.pitch == pytest.approx(0.0, abs=1e-3)


def test_gravity_corrects_a_wrong_start_and_learns_the_x_y_gyro_biases():
    bias = np.array([0.01, -0.008, 0.0])  # a MEMS gyro's turn-on bias, not calibrated in x, y
    a = AttitudeFilter()
    a.calibrate(np.zeros(3), [0.0, 0.0, G])  # believes it is level
    f = rot_zyx(0.1, -0.15, 0.0).T @ [0.0, 0.0, G]
    for _ in range(240 * 120):  # two minutes at rest, tilted
        a.update(bias, f, 1 / 240)
    assert (a.roll, a.pitch) == pytest.approx((0.1, -0.15), abs=1e-3)
    assert a.bias[:2] == pytest.approx(bias[:2], abs=5e-4)


def test_a_mount_rotated_about_z_reads_in_the_body_frame():
    R_body_imu = rot_zyx(0.0, 0.0, math.pi / 2)  # IMU x along body y
    a = AttitudeFilter(R_body_imu)
    f_body = rot_zyx(0.0, 0.2, 0.0).T @ [0.0, 0.0, G]
    a.calibrate(np.zeros(3), R_body_imu.T @ f_body)
    assert a.pitch == pytest.approx(0.2, abs=1e-9) and a.roll == pytest.approx(0.0, abs=1e-9)


def test_tilted_step_on_a_slope_and_the_heading_rate():
    pitch = math.radians(-10.0)  # nose up a 10 deg slope
    pose, z = np.zeros(3), 0.0
    for _ in range(100):
        pose, z = tilted_step(pose, z, (1.0, 0.0, 0.0), 0.0, pitch, 0.0, 0.01)
    assert pose[0] == pytest.approx(math.cos(pitch), rel=1e-12)
    assert z == pytest.approx(math.sin(-pitch), rel=1e-12)
    a = AttitudeFilter()
    a.calibrate(np.zeros(3), rot_zyx(0.0, 0.3, 0.0).T @ [0.0, 0.0, G])
    assert a.heading_rate(0.5) == pytest.approx(0.5 / math.cos(0.3), rel=1e-9)


def test_bad_inputs():
    with pytest.raises(ValueError, match="R_body_imu"):
        AttitudeFilter(np.ones((3, 3)))
    with pytest.raises(ValueError, match="time_constant"):
        AttitudeFilter(time_constant=0.0)
    with pytest.raises(ValueError, match="at rest"):
        AttitudeFilter().calibrate([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])

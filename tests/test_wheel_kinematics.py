"""Slip definitions of perception.models.wheel_kinematics (perception, no simulator)."""

import numpy as np
import pytest

from perception import slip_angle, slip_ratio, wheel_ground_velocity
from perception.models.wheel_kinematics import rolling_speeds


def test_slip_ratio_values():
    assert slip_ratio(1.0, 1.0) == 0.0
    assert slip_ratio(1.0, 0.6) == pytest.approx(0.4)  # spinning: tread faster than ground
    assert slip_ratio(0.5, 1.0) == pytest.approx(-0.5)  # skidding
    assert slip_ratio(2.0, 0.0) == 1.0
    assert slip_ratio(0.0, 2.0) == -1.0
    assert slip_ratio(0.0, 0.0) == 0.0
    assert slip_ratio(0.004, 0.0) == pytest.approx(0.4)  # eps floor 0.01 m/s
    assert slip_ratio(-1.0, -0.5) == pytest.approx(-0.5)  # reversing and spinning


def test_wheel_velocity_of_a_pure_rotation():
    xy = np.array([[0.4, 0.3], [0.4, -0.3]])
    # yaw rate 1 rad/s about the body centre: wheel velocities are perpendicular to the radius
    vl, vt = wheel_ground_velocity((0.0, 0.0, 1.0), xy, np.arctan2(xy[:, 0], -xy[:, 1]))
    np.testing.assert_allclose(vl, [0.5, 0.5], atol=1e-12)  # |omega| * radius
    np.testing.assert_allclose(vt, [0.0, 0.0], atol=1e-12)
    assert slip_angle(1.0, 1.0) == pytest.approx(np.pi / 4)


def test_rolling_speeds_are_proportional_to_the_distance_from_the_centre_of_rotation():
    xy = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])
    np.testing.assert_allclose(np.abs(rolling_speeds(xy, np.zeros(4))), 1.0)
    # double Ackermann left, front-only Ackermann left (rear axle on the centre's line), right
    for icr in ((0.0, 2.0), (-0.4, 1.5), (0.3, -3.0)):
        rel = xy - np.array(icr)
        steer = np.arctan(-rel[:, 0] / rel[:, 1])  # each wheel heads across its line to the centre
        speeds = rolling_speeds(xy, steer)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        np.testing.assert_allclose(np.abs(speeds), dist / dist.max(), atol=1e-9)
        assert np.all(np.sign(speeds) == np.sign(speeds[0]))  # all roll the same way

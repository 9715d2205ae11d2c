"""Slip definitions of DESIGN.md (perception, no simulator)."""

import numpy as np
import pytest

from perception import slip_angle, slip_ratio, wheel_ground_velocity


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

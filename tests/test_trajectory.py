"""Trajectory tools: the odometry paper's path-segment error on known answers."""

import math

import numpy as np
import pytest

from perception.odometry.trajectory import path_segment_errors


def arc(n=3001, length=30.0, radius=math.inf):
    """Poses along a straight line or an arc of ``radius``, ``length`` metres long."""
    s = np.linspace(0.0, length, n)
    if math.isinf(radius):
        return np.column_stack([s, np.zeros(n), np.zeros(n)])
    a = s / radius
    return np.column_stack([radius * np.sin(a), radius * (1 - np.cos(a)), a])


def test_a_rigidly_moved_estimate_has_no_segment_error():
    truth = arc(radius=8.0)
    yaw, t = 0.7, np.array([3.0, -2.0])
    c, s = math.cos(yaw), math.sin(yaw)
    est = truth.copy()
    est[:, :2] = truth[:, :2] @ np.array([[c, s], [-s, c]]) + t
    est[:, 2] += yaw
    for e in path_segment_errors(truth, est, lengths=(5.0, 10.0)):
        assert e.count > 0
        assert e.mean < 1e-9


def test_a_scale_error_shows_as_its_share_of_the_length():
    truth = arc()
    est = truth.copy()
    est[:, 0] *= 1.05  # 5 % too long
    errs = path_segment_errors(truth, est, lengths=(5.0, 10.0, 20.0, 40.0))
    for e in errs[:3]:
        assert e.count == pytest.approx(30.0 - e.length, abs=1.0)
        assert e.mean_percent == pytest.approx(5.0, abs=0.05)
        assert e.std < 0.01 * e.length
    assert errs[3].count == 0 and math.isnan(errs[3].mean)  # longer than the path


def test_a_yaw_drift_bends_the_segments_by_the_square_of_their_length():
    truth = arc()
    est = arc()
    ang = 0.01 * est[:, 0]  # a yaw drift of 0.01 rad/m bends the estimated path
    est[:, :2] = (
        np.column_stack([np.cumsum(np.r_[0, np.cos(ang[:-1])]), np.cumsum(np.r_[0, np.sin(ang[:-1])])]) * 0.01
    )
    est[:, 2] = ang
    e10 = path_segment_errors(truth, est, lengths=(10.0,))[0]
    # a constant curvature k over L: endpoint off by about k L^2 / 2 = 0.5 m
    assert e10.mean == pytest.approx(0.01 * 10.0**2 / 2, rel=0.05)
    with pytest.raises(ValueError, match="shape"):
        path_segment_errors(truth, est[:-1])

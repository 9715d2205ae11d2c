"""The wheels' tracks carried with the body: heights where the wheels have rolled (no simulator)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from perception.odometry.flow import _rotation
from perception.odometry.wheel_tracks import WheelTracks, wheel_contacts

WHEELS_XY = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])


def ground(wx, wy):
    """A smooth relief (world frame) [m]."""
    return 0.03 * np.sin(2 * math.pi * wx / 1.5) * np.cos(2 * math.pi * wy / 2.0)


def _drive(tracks: WheelTracks, twist, dt: float, steps: int, error=None):
    """Drive a level body at ``twist`` (v_x, v_y, omega) over ``ground``; the tracks carried by the
    true motion (or with ``error(k)`` added to each step's displacement). Returns the final pose."""
    pose = np.zeros(3)  # world (x, y, yaw)
    for k in range(steps):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        wx = pose[0] + c * WHEELS_XY[:, 0] - s * WHEELS_XY[:, 1]
        wy = pose[1] + s * WHEELS_XY[:, 0] + c * WHEELS_XY[:, 1]
        contacts = np.column_stack([WHEELS_XY, -0.265 + ground(wx, wy)])  # body frame, body level
        tracks.add(k * dt, contacts)
        vx, vy, w = twist
        D = np.array([vx * dt, vy * dt, 0.0])
        R = _rotation(np.array([0.0, 0.0, w * dt]))
        moved = D if error is None else D + error(k)
        tracks.move(R, moved)
        pose = pose + np.array([c * D[0] - s * D[1], s * D[0] + c * D[1], w * dt])
    return pose, steps * dt


def _laid_contacts(twist, dt: float, steps: int) -> list[np.ndarray]:
    """World (x, y) of each wheel's contact at every step of :func:`_drive`'s true motion."""
    pose, out = np.zeros(3), [[] for _ in WHEELS_XY]
    for _ in range(steps):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        for i, (x, y) in enumerate(WHEELS_XY):
            out[i].append((pose[0] + c * x - s * y, pose[1] + s * x + c * y))
        vx, vy, w = twist
        pose = pose + np.array([(c * vx - s * vy) * dt, (s * vx + c * vy) * dt, w * dt])
    return [np.array(o) for o in out]


def _world_height(pose, xy):
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return -0.265 + ground(pose[0] + c * xy[:, 0] - s * xy[:, 1], pose[1] + s * xy[:, 0] + c * xy[:, 1])


@pytest.mark.parametrize("twist", [(0.6, 0.0, 0.0), (0.5, 0.0, 0.25)])
def test_the_tracks_give_the_grounds_height_where_the_wheels_rolled(twist):
    tracks = WheelTracks(0.03, max_travel=2.0)
    pose, t = _drive(tracks, twist, 1 / 30, 45)
    # points on the front wheels' tracks now: where the front wheels were 0.2-0.6 s ago
    # every carried contact sits where its ground is, seen from the body now
    c, s_ = math.cos(pose[2]), math.sin(pose[2])
    for side in range(4):
        kept = tracks.tracks(t + 1.0)[side]  # all of them
        assert len(kept) > 10
    world = _laid_contacts(twist, 1 / 30, 45)
    for side in range(4):
        kept = tracks.tracks(t + 1.0)[side]
        dx, dy = world[side][:, 0] - pose[0], world[side][:, 1] - pose[1]
        body = np.column_stack([c * dx + s_ * dy, -s_ * dx + c * dy])  # every contact laid
        gap = np.linalg.norm(kept[:, None, :2] - body[None, :, :], axis=2).min(axis=1)
        assert gap.max() < 1e-9  # (kept every 3 cm: each is one of them, exactly)
    hits, travels = [], []
    for back in (3, 5, 8):  # contacts kept every 3 cm or more of travel
        for side in (0, 1):
            xy = tracks.tracks(t)[side][-back][:2][None, :] + np.array([[0.0, 0.01]])  # 1 cm off the line
            z, on, travel = tracks.heights_at(xy, t)
            assert on.all()
            hits.append(abs(z[0] - _world_height(pose, xy)[0]))
            travels.append(travel[0])
    assert 0.05 < min(travels) and max(travels) < 0.4 and travels[0] < travels[2] < travels[4]
    assert max(hits) < 0.0015  # the relief's change across a centimetre and between contacts
    # off every track: no height
    z, on, _ = tracks.heights_at(np.array([[0.0, 0.0], [0.1, 0.15]]), t)
    assert not on.any() and np.isnan(z).all()


def test_a_wheel_on_an_older_track_takes_out_the_tracks_drift():
    """The carried tracks drift in height with the travel (a motion that errs by 1 cm a metre
    upward); the rear wheels roll over the front wheels' tracks, which closes the loop."""
    err = 0.6 / 30 * 0.01  # per step: 1 cm per metre travelled
    drifting = WheelTracks(0.03, max_travel=2.0)
    pose, t = _drive(drifting, (0.6, 0.0, 0.0), 1 / 30, 60, error=lambda k: np.array([0.0, 0.0, -err]))
    xy = np.array([[-0.2, 0.3], [0.0, -0.3], [0.2, 0.3]])
    z, on, travel = drifting.heights_at(xy, t)
    truth = _world_height(pose, xy)
    assert on.all()
    # without the loop's closure the tracks would stand 1 cm per metre of travel too high
    assert np.abs(z - truth).max() < 0.001
    assert np.abs(z + 0.01 * travel - truth).max() > 0.003


def test_wheel_contacts_lie_one_radius_below_the_centres():
    R = np.eye(3)
    frames = [(R, np.array([x, y, -0.15])) for x, y in WHEELS_XY]
    c = wheel_contacts(frames, 0.115, (0.0, 0.0, -0.265))
    assert c[:, 2] == pytest.approx(-0.265)
    assert c[:, :2] == pytest.approx(WHEELS_XY)
    # a wheel rolled by phi about x (its axle tilted) touches level ground on its rim, r cos(phi) below
    phi = math.radians(12)
    Rx = np.array(
        [[1.0, 0.0, 0.0], [0.0, math.cos(phi), -math.sin(phi)], [0.0, math.sin(phi), math.cos(phi)]]
    )
    c = wheel_contacts([(Rx, np.zeros(3))], 0.115, (0.0, 0.0, -0.265))[0]
    assert c == pytest.approx(0.115 * np.array([0.0, math.sin(phi), -math.cos(phi)]))
    # the lowest point of the rim circle (centre + r (cos a * x' + sin a * z'), x', z' the rim's plane)
    a = np.linspace(0, 2 * math.pi, 3601)
    rim = 0.115 * (np.outer(np.cos(a), Rx[:, 0]) + np.outer(np.sin(a), Rx[:, 2]))
    assert c[2] == pytest.approx(rim[:, 2].min(), abs=1e-6)


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="half_width"):
        WheelTracks(0.0)
    with pytest.raises(ValueError, match="min_age"):
        WheelTracks(0.03, max_age=0.1, min_age=0.2)
    with pytest.raises(ValueError, match="max_travel"):
        WheelTracks(0.03, max_travel=0.0)

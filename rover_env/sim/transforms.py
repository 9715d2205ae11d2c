"""Rotations of the simulation's frames: quaternions (x, y, z, w), Euler angles, matrices.

Numpy only, so that every layer (the simulation, the renderers, the task) shares one definition.
"""

from __future__ import annotations

import math

import numpy as np


def yaw_to_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of intrinsic Z-Y-X (yaw, pitch, roll) Euler angles [rad]."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy,
        ]
    )


def quat_to_yaw(quat_xyzw) -> float:
    """Heading of the body x axis projected on the world x-y plane [rad]."""
    x, y, z, w = quat_xyzw
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def quat_to_matrix(quat_xyzw) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion (x, y, z, w); columns are the frame's axes."""
    x, y, z, w = (float(v) for v in quat_xyzw)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )

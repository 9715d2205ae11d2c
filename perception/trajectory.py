"""Trajectories: planar poses to TUM files (``t x y z qx qy qz qw``, readable by ``evo``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def yaw_to_quat_xyzw(yaw) -> np.ndarray:
    """(..., 4) quaternions (x, y, z, w) of rotations by ``yaw`` [rad] about z."""
    yaw = np.asarray(yaw, dtype=np.float64)
    q = np.zeros(yaw.shape + (4,))
    q[..., 2] = np.sin(yaw / 2)
    q[..., 3] = np.cos(yaw / 2)
    return q


def write_tum(path: str | Path, t, position, quat_xyzw) -> Path:
    """Write a TUM trajectory: one line ``t x y z qx qy qz qw`` per pose.

    Args:
        path: Output file.
        t: (n,) times [s].
        position: (n, 3) positions [m].
        quat_xyzw: (n, 4) orientations.
    """
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    data = np.hstack([t, np.asarray(position, dtype=np.float64), np.asarray(quat_xyzw, dtype=np.float64)])
    if data.shape[1] != 8:
        raise ValueError(f"TUM rows need t, 3 positions and 4 quaternion values; got {data.shape[1]} columns")
    path = Path(path)
    np.savetxt(path, data, fmt="%.6f")
    return path


def write_planar_tum(path: str | Path, t, poses_xy_yaw) -> Path:
    """TUM file of planar poses (x [m], y [m], yaw [rad]) at z = 0."""
    p = np.asarray(poses_xy_yaw, dtype=np.float64).reshape(-1, 3)
    xyz = np.column_stack([p[:, 0], p[:, 1], np.zeros(len(p))])
    return write_tum(path, t, xyz, yaw_to_quat_xyzw(p[:, 2]))

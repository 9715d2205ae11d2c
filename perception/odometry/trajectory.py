"""Trajectories: planar poses to TUM files, and the odometry paper's path-segment error.

TUM lines are ``t x y z qx qy qz qw`` (readable by ``evo``).
"""

from __future__ import annotations

from dataclasses import dataclass
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


def format_planar_tum(t, poses_xy_yaw, z=None) -> str:
    """The text of a TUM file of planar poses (x [m], y [m], yaw [rad]) at height ``z`` [m] (default 0)."""
    import io

    p = np.asarray(poses_xy_yaw, dtype=np.float64).reshape(-1, 3)
    zz = np.zeros(len(p)) if z is None else np.broadcast_to(np.asarray(z, dtype=np.float64), (len(p),))
    t = np.asarray(t, dtype=np.float64).reshape(-1, 1)
    data = np.hstack([t, p[:, :2], zz[:, None], yaw_to_quat_xyzw(p[:, 2])])
    buf = io.StringIO()
    np.savetxt(buf, data, fmt="%.6f")
    return buf.getvalue()


def write_planar_tum(path: str | Path, t, poses_xy_yaw, z=None) -> Path:
    """TUM file of planar poses (x [m], y [m], yaw [rad]) at height ``z`` [m] (default 0)."""
    p = np.asarray(poses_xy_yaw, dtype=np.float64).reshape(-1, 3)
    zz = np.zeros(len(p)) if z is None else np.broadcast_to(np.asarray(z, dtype=np.float64), (len(p),))
    xyz = np.column_stack([p[:, 0], p[:, 1], zz])
    return write_tum(path, t, xyz, yaw_to_quat_xyzw(p[:, 2]))


@dataclass(frozen=True)
class SegmentError:
    """Endpoint position error of odometry path segments of one length (odometry paper, Table I).

    Attributes:
        length: Segment length along the true path [m].
        count: Segments measured.
        mean: Mean endpoint error [m].
        std: Its standard deviation [m].
        mean_percent: ``mean`` as a share of ``length`` [%].
    """

    length: float
    count: int
    mean: float
    std: float
    mean_percent: float


def path_segment_errors(
    true_xy_yaw, est_xy_yaw, lengths=(5.0, 10.0, 20.0), stride: float = 1.0
) -> list[SegmentError]:
    """Position error of the estimate's path segments against the truth's, as in the odometry paper.

    For each segment, the true path from a start pose to the point ``length`` metres further
    along it is taken with the estimate over the same time span. The estimated segment is
    translated and rotated so that its start pose matches the true start pose, and the
    Euclidean distance between the two endpoints is the segment's error. The start then moves
    ``stride`` metres along the true path, up to its end.

    Args:
        true_xy_yaw: (n, 3) true planar poses (x [m], y [m], yaw [rad]), time-aligned with ...
        est_xy_yaw: (n, 3) the estimated poses (dead reckoning).
        lengths: Segment lengths [m].
        stride: Distance between segment starts along the true path [m].

    Returns:
        One :class:`SegmentError` per length; a length longer than the path has count 0 and NaN errors.
    """
    tru = np.asarray(true_xy_yaw, dtype=np.float64).reshape(-1, 3)
    est = np.asarray(est_xy_yaw, dtype=np.float64).reshape(-1, 3)
    if tru.shape != est.shape:
        raise ValueError(f"true and estimated poses differ in shape: {tru.shape} and {est.shape}")
    if not stride > 0:
        raise ValueError(f"stride: {stride!r} m must be > 0")
    along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(tru[:, :2], axis=0), axis=1))])
    starts = np.searchsorted(along, np.arange(0.0, along[-1], stride)) if len(along) else np.zeros(0, int)
    out = []
    for length in lengths:
        ends = np.searchsorted(along, along[starts] + length)
        ok = ends < len(along)
        i, j = starts[ok], ends[ok]
        # the estimate's displacement in its start frame, put into the truth's start frame
        d = est[j, :2] - est[i, :2]
        rot = tru[i, 2] - est[i, 2]
        c, s = np.cos(rot), np.sin(rot)
        moved = tru[i, :2] + np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])
        err = np.linalg.norm(moved - tru[j, :2], axis=1)
        if len(err):
            mean = float(err.mean())
            out.append(SegmentError(float(length), len(err), mean, float(err.std()), 100.0 * mean / length))
        else:
            out.append(SegmentError(float(length), 0, float("nan"), float("nan"), float("nan")))
    return out

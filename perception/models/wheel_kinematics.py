"""Wheel-ground kinematics shared by ground truth and estimators: slip ratio and slip angle.

Definitions (docs/environment.md): for wheel i with spin rate omega_i [rad/s] and radius r [m], and ground
velocity v_i of its centre along its heading (longitudinal) and across it (lateral) [m/s],

    s_i    = (omega_i r - v_i,long) / max(|omega_i r|, |v_i,long|, eps)    in [-1, 1]
    beta_i = atan2(v_i,lat, v_i,long)                                       [rad]

s > 0: the wheel spins faster than it travels (traction loss); s < 0: it skids.
"""

from __future__ import annotations

import numpy as np

SLIP_EPS = 0.01  # [m/s] speed below which slip is not resolvable; keeps s finite at standstill


def slip_ratio(
    tread_speed: np.ndarray | float,
    ground_speed: np.ndarray | float,
    eps: float = SLIP_EPS,
    clip: bool = True,
) -> np.ndarray:
    """Longitudinal slip ratio.

    Args:
        tread_speed: Wheel spin rate times radius, omega * r [m/s].
        ground_speed: Longitudinal ground velocity of the wheel centre [m/s].
        eps: Denominator floor [m/s].
        clip: Clip to [-1, 1] (the definition); False gives the ratio before the clip, which
            passes +-1 where the tread and the ground move in opposite directions.

    Returns:
        Slip ratio (in [-1, 1] when clipped), same shape as the inputs.
    """
    ws = np.asarray(tread_speed, dtype=np.float64)
    v = np.asarray(ground_speed, dtype=np.float64)
    den = np.maximum(np.maximum(np.abs(ws), np.abs(v)), eps)
    ratio = (ws - v) / den
    return np.clip(ratio, -1.0, 1.0) if clip else ratio


def slip_angle(v_long: np.ndarray | float, v_lat: np.ndarray | float) -> np.ndarray:
    """Slip angle atan2(v_lat, v_long) [rad]; 0 for a wheel at rest."""
    return np.arctan2(np.asarray(v_lat, dtype=np.float64), np.asarray(v_long, dtype=np.float64))


def wheel_ground_velocity(
    twist: np.ndarray, wheel_xy: np.ndarray, steering: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Planar body twist transported to wheel centres and rotated into each wheel's heading.

    Args:
        twist: (v_x, v_y, omega) of the body in the body frame [m/s, m/s, rad/s].
        wheel_xy: Wheel centre positions in the body frame, shape (N, 2) [m].
        steering: Per-wheel steering angles, shape (N,) [rad], positive turns left.

    Returns:
        ``(v_long, v_lat)``, each shape (N,) [m/s], along and across each wheel's heading.
    """
    vx, vy, wz = (float(v) for v in twist)
    xy = np.asarray(wheel_xy, dtype=np.float64)
    vwx = vx - wz * xy[:, 1]
    vwy = vy + wz * xy[:, 0]
    c, s = np.cos(steering), np.sin(steering)
    return c * vwx + s * vwy, -s * vwx + c * vwy


def rolling_speeds(wheel_xy: np.ndarray, steering: np.ndarray) -> np.ndarray:
    """Relative wheel speeds of a rigid body whose steered wheels all roll without side slip.

    The body twist (v_x, v_y, omega) that moves every wheel centre along its heading is the
    least-squares null vector of the wheels' lateral-velocity constraints (the instantaneous
    centre of rotation that best fits the steering); each wheel's speed along its heading
    follows (:func:`wheel_ground_velocity`). Their ratios are the ratios of the wheels' spin
    rates when none slips.

    Args:
        wheel_xy: (N, 2) wheel centres in the body frame [m].
        steering: (N,) steering angles [rad], positive left.

    Returns:
        (N,) speeds along each heading, scaled so that the largest magnitude is 1 (the common
        sign is arbitrary).
    """
    xy = np.asarray(wheel_xy, dtype=np.float64)
    c, s = np.cos(steering), np.sin(steering)
    # lateral velocity of wheel i: -s (v_x - omega y_i) + c (v_y + omega x_i) = 0
    A = np.column_stack([-s, c, s * xy[:, 1] + c * xy[:, 0]])
    twist = np.linalg.svd(A)[2][-1]
    v_long = wheel_ground_velocity(twist, xy, steering)[0]
    return v_long / max(float(np.abs(v_long).max()), 1e-12)

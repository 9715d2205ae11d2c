"""Double-Ackermann drive geometry: the one place the steering and wheel-speed maps live.

The simulator (``rover_env``), the estimators (``perception``) and the controllers all use these
maps; this module depends on numpy only. Body frame (REP-103): x forward, y left; wheel order
FL, FR, RL, RR; axle order F, R; steering angles positive counter-clockwise seen from above.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.models.validation import ConfigError, check_range

WHEELS: tuple[str, ...] = ("FL", "FR", "RL", "RR")
AXLES: tuple[str, ...] = ("F", "R")


def ackermann_arms(axle_x: float, track: float, center_x: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per wheel: arm from the turn-centre line along x, and lateral offset y [m] (FL, FR, RL, RR).

    Args:
        axle_x: Axles at x = +axle_x (front) and -axle_x (rear) [m].
        track: Lateral distance between wheel centres [m].
        center_x: x of the turn-centre line the tie rods are designed for [m].
    """
    arm = np.array([axle_x, axle_x, -axle_x, -axle_x], dtype=np.float64) - center_x
    y = np.array([track / 2, -track / 2, track / 2, -track / 2], dtype=np.float64)
    return arm, y


def wheel_steering_angles(
    arms: tuple[np.ndarray, np.ndarray], steer_front: float, steer_rear: float
) -> np.ndarray:
    """Per-wheel steering angles for the axle commands (the tie rods' Ackermann map) [rad].

    The axle command lambda is the angle of a virtual wheel at the axle centre; for wheel i with
    arm a_i to the turn-centre line and lateral offset y_i,
    tan(delta_i) = a_i tan(lambda) / (a_i - y_i tan(lambda)).

    Args:
        arms: :func:`ackermann_arms`.
        steer_front: lambda_F [rad], positive turns left.
        steer_rear: lambda_R [rad].
    """
    arm, y = arms
    out = []
    for k, lam in enumerate((steer_front, steer_front, steer_rear, steer_rear)):
        t = math.tan(lam)
        a = float(arm[k])
        out.append(math.atan(a * t / (a - float(y[k]) * t)))
    return np.array(out)


def axle_steering_angles(arms: tuple[np.ndarray, np.ndarray], wheel_steer) -> np.ndarray:
    """The inverse map: (lambda_F, lambda_R) [rad] from 4 wheel angles, averaged per axle.

    From tan(delta) = a t / (a - y t): t = a tan(delta) / (a + y tan(delta)).
    """
    arm, y = arms
    lam = []
    for a, yy, d in zip(arm.tolist(), y.tolist(), np.asarray(wheel_steer, dtype=np.float64).tolist()):
        td = math.tan(d)
        lam.append(math.atan(a * td / (a + yy * td)))
    return np.array([0.5 * (lam[0] + lam[1]), 0.5 * (lam[2] + lam[3])])


def ackermann_wheel_speeds(
    axle_x: float, track: float, speed: float, steer_front: float, steer_rear: float
) -> np.ndarray:
    """Ground speed of each wheel centre for a body-centre speed and axle steering commands.

    The instantaneous centre of rotation (ICR) is where the normals of the two axles' virtual
    centre wheels meet; each wheel's speed is proportional to its distance from it, so no wheel
    is dragged. Parallel axle angles (straight or crab driving) give equal speeds.

    Args:
        axle_x: Axles at x = +-axle_x [m].
        track: Lateral distance between wheel centres [m].
        speed: Signed speed of the body centre [m/s].
        steer_front: lambda_F [rad].
        steer_rear: lambda_R [rad].

    Returns:
        (4,) wheel-centre speeds [m/s], order FL, FR, RL, RR, with the sign of ``speed``.
    """
    tf, tr = math.tan(steer_front), math.tan(steer_rear)
    if abs(tf - tr) < 1e-9:
        return np.full(4, float(speed))
    yc = 2.0 * axle_x / (tf - tr)
    xc = axle_x - yc * tf
    r_body = math.hypot(xc, yc)
    half = track / 2.0
    ax = axle_x
    r_wheels = [math.hypot(x - xc, y - yc) for x, y in ((ax, half), (ax, -half), (-ax, half), (-ax, -half))]
    return np.array([speed * r / r_body for r in r_wheels])


@dataclass(frozen=True)
class DriveGeometry:
    """What a controller needs of the rover: wheel layout, radius and steering limits.

    Defaults are the simulated rover's (``rover_env.sim.geometry.RoverGeometry.drive`` returns the
    configured rover's).

    Attributes:
        axle_x: Axles at x = +axle_x (front) and -axle_x (rear), body frame [m].
        track: Lateral distance between wheel centres [m].
        wheel_radius: Tread radius [m].
        steer_limit: Axle steering command range +/- [rad].
        ackermann_center_x: x of the turn-centre line the tie rods are designed for [m].
    """

    axle_x: float = 0.40
    track: float = 0.60
    wheel_radius: float = 0.115
    steer_limit: float = math.radians(30.0)
    ackermann_center_x: float = 0.0

    def __post_init__(self) -> None:
        check_range("axle_x", self.axle_x, 0.05, 5.0)
        check_range("track", self.track, 0.1, 5.0)
        check_range("wheel_radius", self.wheel_radius, 0.0, None, lo_open=True)
        check_range("steer_limit", self.steer_limit, 0.0, math.radians(60), lo_open=True)
        if abs(self.ackermann_center_x) >= self.axle_x:
            raise ConfigError("ackermann_center_x: must lie between the axles")

    @property
    def wheelbase(self) -> float:
        """Distance between front and rear axle [m]."""
        return 2.0 * self.axle_x

    @property
    def arms(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`ackermann_arms` of this rover."""
        return ackermann_arms(self.axle_x, self.track, self.ackermann_center_x)

    def wheel_xy(self) -> np.ndarray:
        """Nominal wheel centres in the body x-y plane, (4, 2) [m], order FL, FR, RL, RR."""
        h = self.track / 2.0
        a = self.axle_x
        return np.array([[a, h], [a, -h], [-a, h], [-a, -h]], dtype=np.float64)

    def ackermann_angles(self, steer_front: float, steer_rear: float) -> np.ndarray:
        """Per-wheel steering angles for the axle commands [rad] (:func:`wheel_steering_angles`)."""
        return wheel_steering_angles(self.arms, steer_front, steer_rear)

    def wheel_speeds(self, speed: float, steer_front: float, steer_rear: float) -> np.ndarray:
        """Wheel-centre speeds [m/s] for a body-centre speed (:func:`ackermann_wheel_speeds`)."""
        return ackermann_wheel_speeds(self.axle_x, self.track, speed, steer_front, steer_rear)

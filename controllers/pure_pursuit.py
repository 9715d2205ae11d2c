"""Pure-pursuit waypoint following for a double-Ackermann rover, on observations only."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from perception.observation import OBS_FIELDS


@dataclass(frozen=True)
class PurePursuitConfig:
    """Gains and limits.

    Attributes:
        cruise_speed: Speed on straight segments [m/s].
        min_speed: Speed floor when turning hard or arriving [m/s].
        v_max: Speed that action 1.0 commands in the environment [m/s].
        steer_limit: Steering that action 1.0 commands [rad].
        half_wheelbase: Distance from the body centre to each axle [m].
        min_lookahead: Lower bound of the lookahead distance [m].
        slow_bearing: Bearing at which the speed has dropped to ``min_speed`` [rad].
    """

    cruise_speed: float = 0.8
    min_speed: float = 0.25
    v_max: float = 2.0
    steer_limit: float = math.radians(30.0)
    half_wheelbase: float = 0.40
    min_lookahead: float = 1.0
    slow_bearing: float = math.radians(60.0)


class PurePursuit:
    """Steer along the arc through the next waypoint, with equal-and-opposite axle steering.

    The arc from the body centre to a point at distance L and bearing alpha has curvature
    kappa = 2 sin(alpha) / L. Double-Ackermann steering with lambda_F = -lambda_R = lambda
    turns about a centre on the body's lateral axis with kappa = tan(lambda) / half_wheelbase.

    Args:
        obs_fields: Names of the observation entries (default
            :data:`perception.observation.OBS_FIELDS`); the
            controller reads ``waypoint_distance`` and ``waypoint_bearing``.
        config: Gains and limits.
    """

    def __init__(self, obs_fields: Sequence[str] | None = None, config: PurePursuitConfig | None = None):
        self.cfg = config or PurePursuitConfig()
        fields = list(OBS_FIELDS if obs_fields is None else obs_fields)
        try:
            self._i_dist = fields.index("waypoint_distance")
            self._i_bear = fields.index("waypoint_bearing")
        except ValueError as exc:
            raise ValueError(f"observation lacks a field the controller needs: {exc}") from None

    def reset(self) -> None:
        """Pure pursuit is memoryless."""

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Drive-mode action (speed, lambda_F, lambda_R) scaled to [-1, 1]."""
        c = self.cfg
        dist = float(obs[self._i_dist])
        bearing = float(obs[self._i_bear])
        lookahead = max(dist, c.min_lookahead)
        kappa = 2.0 * math.sin(bearing) / lookahead
        lam = math.atan(kappa * c.half_wheelbase)
        lam = max(-c.steer_limit, min(c.steer_limit, lam))
        turn = min(abs(bearing) / c.slow_bearing, 1.0)
        speed = c.cruise_speed - (c.cruise_speed - c.min_speed) * turn
        speed = min(speed, max(c.min_speed, 0.6 * dist))
        if abs(bearing) > math.pi / 2:  # waypoint behind: turn on the spot's tightest arc
            lam = math.copysign(c.steer_limit, bearing)
            speed = c.min_speed
        return np.array([speed / c.v_max, lam / c.steer_limit, -lam / c.steer_limit], dtype=np.float32)

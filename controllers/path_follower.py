"""Path following for a double-Ackermann rover: curvature from the course errors, and speed.

The follower steers the body centre along the current course segment. In the distance domain
(s, metres driven) a body at cross-track error e (left +) and heading error psi (segment minus
body heading) on a path of curvature kappa_p obeys

    de/ds = -sin(psi),    dpsi/ds = kappa_p - kappa,

where kappa is the body's curvature. The law

    kappa = k1 sin(psi) - k2 e - k3 z,    z = integral of e ds,

places the linearised closed loop's poles at s^3 + k1 s^2 + k2 s + k3 = (s + p)^3 (k1 = 3p,
k2 = 3p^2, k3 = p^3, p = ``bandwidth`` [1/m]): errors decay over about 1/p metres at any speed,
and the integral removes the steady-state offset on a curved path, whose curvature the
observation does not carry. Both axles steer, equal and opposite (lambda_F = -lambda_R), so
that the body centre turns about a point on its lateral line: kappa = tan(lambda) / axle_x.

Speed is scheduled from the course speed: lower in tight turns (a lateral-acceleration
limit), with large heading errors, and while the estimates' quality is low.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from perception.models.validation import check_range
from perception.observation import OBS_FIELDS, field_index


@dataclass(frozen=True)
class PathFollowerConfig:
    """Gains and limits of :class:`PathFollower`.

    Attributes:
        cruise_speed: Speed on straight segments [m/s].
        min_speed: Lowest scheduled speed while driving [m/s].
        v_max: Speed that a speed action of 1.0 commands in the environment [m/s].
        steer_limit: Axle steering that a steering action of 1.0 commands [rad].
        axle_x: Distance from the body centre to each axle [m].
        bandwidth: p, the closed loop's triple pole [1/m].
        integral_curvature: Largest curvature the integral term may command [1/m].
        integrate_within: (|e| [m], |psi| [rad]) within which the error is integrated (outside,
            at a corner or after a disturbance, the integral holds).
        lateral_accel: Speed limit in turns: v^2 |kappa| <= this [m/s^2].
        slow_heading: Heading error at which the speed has dropped to ``min_speed`` [rad].
        min_quality: Below this estimate quality (the lower of odometry and kinematics, 0-1)
            the speed is scaled down in proportion, to ``min_speed`` at quality 0.
        dt: Control period [s].
    """

    cruise_speed: float = 0.8
    min_speed: float = 0.2
    v_max: float = 2.0
    steer_limit: float = math.radians(30.0)
    axle_x: float = 0.40
    bandwidth: float = 0.8
    integral_curvature: float = 0.6
    integrate_within: tuple[float, float] = (0.5, 0.35)
    lateral_accel: float = 0.6
    slow_heading: float = math.radians(70.0)
    min_quality: float = 0.5
    dt: float = 1.0 / 30.0

    def __post_init__(self) -> None:
        check_range("cruise_speed", self.cruise_speed, 0.0, self.v_max, lo_open=True)
        check_range("min_speed", self.min_speed, 0.0, self.cruise_speed)
        check_range("steer_limit", self.steer_limit, 0.0, math.pi / 2, lo_open=True, hi_open=True)
        check_range("axle_x", self.axle_x, 0.0, 10.0, lo_open=True)
        check_range("bandwidth", self.bandwidth, 0.0, 100.0, lo_open=True)
        check_range("integral_curvature", self.integral_curvature, 0.0, 100.0)
        check_range("lateral_accel", self.lateral_accel, 0.0, 100.0, lo_open=True)
        check_range("slow_heading", self.slow_heading, 0.0, math.pi, lo_open=True)
        check_range("min_quality", self.min_quality, 0.0, 1.0)
        check_range("dt", self.dt, 0.0, 10.0, lo_open=True)


def _field_index(fields: Sequence[str], name: str) -> int:
    try:
        return field_index(fields, name)
    except KeyError as exc:
        raise ValueError(
            f"{exc.args[0]}; pass the environment's field names (env.unwrapped.obs_fields)"
        ) from None


def env_field_names(env) -> list[str]:
    """Names of the observation fields of a :class:`~rover_env.envs.RoverEnv` (or a wrapper of one)."""
    return [f.name for f in env.unwrapped.obs_fields]


class PathFollower:
    """Follow the waypoint course on the observation's task features (drive action mode).

    Args:
        obs_fields: Names of the observation's entries (default
            :data:`perception.observation.OBS_FIELDS`, the environments' layout); the follower
            reads ``cross_track``, ``heading_error``, ``v_x`` and the two quality fields.
        config: Gains and limits; :meth:`for_env` fills the rover's from an environment.
    """

    def __init__(
        self, obs_fields: Sequence[str] | None = None, config: PathFollowerConfig | None = None
    ) -> None:
        self.cfg = config or PathFollowerConfig()
        fields = list(OBS_FIELDS if obs_fields is None else obs_fields)
        self._i = {
            name: _field_index(fields, name)
            for name in ("v_x", "cross_track", "heading_error", "odometry_quality", "kinematics_quality")
        }
        p = self.cfg.bandwidth
        self.gains = (3.0 * p, 3.0 * p * p, p**3)
        self.reset()

    @classmethod
    def for_env(cls, env, **overrides) -> PathFollower:
        """A follower for a :class:`~rover_env.envs.RoverEnv` (or a wrapper of one).

        The course speed, ``v_max``, the rover's steering limit and axle position and the
        control period come from the environment; ``overrides`` set any other field.
        """
        base = env.unwrapped
        g = base.geometry
        kw = dict(
            cruise_speed=base.scenario.course.speed,
            v_max=base.v_max,
            steer_limit=g.steer_limit,
            axle_x=g.axle_x,
            dt=base.control_dt,
        )
        kw.update(overrides)
        return cls(env_field_names(env), PathFollowerConfig(**kw))

    def reset(self) -> None:
        """Clear the integral at the start of an episode."""
        self._z = 0.0

    def command(self, obs: np.ndarray) -> tuple[float, float]:
        """(body-centre speed [m/s], curvature [1/m]) for ``obs``; advances the integral."""
        c = self.cfg
        obs = np.asarray(obs, dtype=np.float64)
        e = float(obs[self._i["cross_track"]])
        psi = float(obs[self._i["heading_error"]])
        v = float(obs[self._i["v_x"]])
        k1, k2, k3 = self.gains
        e_in, psi_in = c.integrate_within
        if abs(e) <= e_in and abs(psi) <= psi_in:
            z_max = c.integral_curvature / k3
            self._z = min(max(self._z + e * abs(v) * c.dt, -z_max), z_max)
        if abs(psi) > math.pi / 2:  # facing away from the segment: turn toward it at the limit
            kappa = math.copysign(math.inf, psi)
        else:
            kappa = k1 * math.sin(psi) - k2 * e - k3 * self._z
        kappa_max = math.tan(c.steer_limit) / c.axle_x
        kappa = min(max(kappa, -kappa_max), kappa_max)
        speed = c.cruise_speed
        if kappa != 0.0:
            speed = min(speed, math.sqrt(c.lateral_accel / abs(kappa)))
        turn = min(abs(psi) / c.slow_heading, 1.0)
        speed = min(speed, c.cruise_speed - (c.cruise_speed - c.min_speed) * turn)
        quality = min(float(obs[self._i["odometry_quality"]]), float(obs[self._i["kinematics_quality"]]))
        if c.min_quality > 0 and quality < c.min_quality:
            speed = c.min_speed + (speed - c.min_speed) * max(quality, 0.0) / c.min_quality
        return max(speed, c.min_speed), kappa

    def steering(self, kappa: float) -> float:
        """Axle command lambda = lambda_F = -lambda_R [rad] that turns the body centre at ``kappa``."""
        return math.atan(kappa * self.cfg.axle_x)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Drive-mode action (speed, lambda_F, lambda_R), scaled to [-1, 1]."""
        c = self.cfg
        speed, kappa = self.command(obs)
        lam = self.steering(kappa) / c.steer_limit
        return np.array([speed / c.v_max, lam, -lam], dtype=np.float32)


__all__ = ["PathFollower", "PathFollowerConfig"]

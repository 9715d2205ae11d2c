"""Slip-aware traction control: per-wheel speed limits that hold the slip ratio near a set-point.

The path follower (:class:`~controllers.path_follower.PathFollower`) gives the body speed and
curvature; the double-Ackermann geometry turns them into each wheel's tread-speed command. A
wheel whose tread runs faster than its ground speed by more than the set-point slip only digs
and spends its friction on spinning: with Coulomb friction the force it gets is the same, but
the friction cone it has left across its heading, which holds the rover on its course, shrinks.
So each wheel's command is bounded by the tread speed that gives the set-point slip s* at its
estimated ground speed v (the body twist transported to the wheel, along its heading):

    s = (w - v) / w = s*   =>   w_max = v / (1 - s*)        (driving; at least v + min_slip_speed,
                                                             so that the rover can start)
    s = (w - v) / v = -s*  =>   w_min = v (1 - s*)          (braking: the wheel does not lock)

An integral on the estimated slip's error scales each bound (in log space) and removes the bias
of the ground-speed estimate; it acts only while the bound is active. While the odometry's
quality is below ``min_quality`` the ground speed is not trusted: the wheels get the nominal
commands, and the follower's speed schedule slows the rover down. Before the first trusted
estimate of an episode the rover is at rest (every episode starts so), and its ground speed is
taken as zero: the wheels start within ``min_slip_speed``, so that on loose soil they do not
spin and dig in while the odometry has not yet seen a frame pair.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from controllers.path_follower import PathFollower, PathFollowerConfig, _field_index, env_field_names
from perception.models.drive_geometry import WHEELS, DriveGeometry
from perception.models.validation import check_range
from perception.models.wheel_kinematics import wheel_ground_velocity
from perception.observation import OBS_FIELDS


@dataclass(frozen=True)
class TractionConfig:
    """Parameters of :class:`SlipAwareController`.

    Attributes:
        slip_setpoint: s*, the slip ratio each wheel is held at or below (0-1).
        min_slip_speed: Smallest allowed tread speed over the ground speed [m/s]; from rest the
            set-point alone would allow no motion.
        gain: Integral gain of the bound's log-scale on the slip error [1/s per unit slip].
        correction_range: (lowest, highest) log-scale of a bound.
        min_quality: Odometry quality (0-1) below which no bound is applied.
        feedback_speed: Ground speed [m/s] below which the slip estimate does not feed the
            integral: slip is not resolved there (an estimator reports about 0, see
            :attr:`perception.SlipConfig.event_min_speed`).
    """

    slip_setpoint: float = 0.15
    min_slip_speed: float = 0.05
    gain: float = 2.0
    correction_range: tuple[float, float] = (-1.0, 0.5)
    min_quality: float = 0.2
    feedback_speed: float = 0.15

    def __post_init__(self) -> None:
        check_range("slip_setpoint", self.slip_setpoint, 0.0, 1.0, lo_open=True, hi_open=True)
        check_range("min_slip_speed", self.min_slip_speed, 0.0, 10.0)
        check_range("gain", self.gain, 0.0, 1000.0)
        lo, hi = self.correction_range
        check_range("correction_range[0]", lo, -10.0, 0.0)
        check_range("correction_range[1]", hi, 0.0, 10.0)
        check_range("min_quality", self.min_quality, 0.0, 1.0)
        check_range("feedback_speed", self.feedback_speed, 0.0, 100.0)


class SlipAwareController:
    """Path following with per-wheel traction control (``action_mode="wheels"``).

    Args:
        obs_fields: Names of the observation's entries (default
            :data:`perception.observation.OBS_FIELDS`).
        geometry: The rover's drive geometry (wheel positions, Ackermann steering); a
            ``RoverGeometry`` is accepted for its ``drive``.
        follower: Path-following gains and limits.
        traction: Traction-control parameters.
    """

    def __init__(
        self,
        obs_fields: Sequence[str] | None = None,
        geometry: DriveGeometry | None = None,
        follower: PathFollowerConfig | None = None,
        traction: TractionConfig | None = None,
    ) -> None:
        geometry = getattr(geometry, "drive", geometry)
        self.geometry: DriveGeometry = geometry if geometry is not None else DriveGeometry()
        self.follower = PathFollower(obs_fields, follower)
        self.cfg = traction or TractionConfig()
        fields = list(OBS_FIELDS if obs_fields is None else obs_fields)
        self._i_twist = [_field_index(fields, n) for n in ("v_x", "v_y", "omega")]
        self._i_slip = [_field_index(fields, f"slip_{w}") for w in WHEELS]
        self._i_steer = [_field_index(fields, f"steering_{a}") for a in ("F", "R")]
        self._i_quality = _field_index(fields, "odometry_quality")
        self._wheel_xy = self.geometry.wheel_xy()
        self.reset()

    @classmethod
    def for_env(
        cls, env, traction: TractionConfig | None = None, **follower_overrides
    ) -> SlipAwareController:
        """A controller for a :class:`~rover_env.envs.RoverEnv` in ``action_mode="wheels"``."""
        base = env.unwrapped
        if base.action_mode.value != "wheels":
            raise ValueError(
                f"SlipAwareController commands each wheel: make the environment with "
                f"action_mode='wheels' (it has {base.action_mode.value!r})"
            )
        follower = PathFollower.for_env(env, **follower_overrides).cfg
        return cls(env_field_names(env), base.geometry.drive, follower, traction)

    def reset(self) -> None:
        """Clear the follower's integral and the wheels' bound corrections."""
        self.follower.reset()
        self.correction = np.zeros(4)  # log-scale of each wheel's bound
        self.limited = np.zeros(4, dtype=bool)  # which wheels the bound held back last step
        self._moving = False  # a trusted ground speed was seen since the reset

    def wheel_commands(self, obs: np.ndarray) -> tuple[np.ndarray, float]:
        """(tread-speed commands (4,) [m/s], axle steering lambda [rad]) for ``obs``."""
        speed, kappa = self.follower.command(np.asarray(obs, dtype=np.float64))
        lam = self.follower.steering(kappa)
        return self.limit(obs, speed, lam, -lam), lam

    def limit(self, obs: np.ndarray, speed: float, lam_f: float, lam_r: float) -> np.ndarray:
        """Tread-speed commands (4,) [m/s] for a drive command, within each wheel's slip bounds.

        Args:
            obs: The observation (estimated twist, slip, steering and odometry quality).
            speed: Commanded body-centre speed [m/s], forward +.
            lam_f: Front axle steering command [rad].
            lam_r: Rear axle steering command [rad].

        Advances the bounds' integrals by one control period.
        """
        c, g = self.cfg, self.geometry
        obs = np.asarray(obs, dtype=np.float64)
        nominal = g.wheel_speeds(speed, lam_f, lam_r)
        self.limited[:] = False
        trusted = bool(obs[self._i_quality] >= c.min_quality)
        self._moving |= trusted
        if not self._moving:  # at rest since the start: no ground speed yet
            v_long = np.zeros(4)
        elif not trusted:
            return nominal
        else:
            delta = g.ackermann_angles(*obs[self._i_steer])
            v_long, _ = wheel_ground_velocity(obs[self._i_twist], self._wheel_xy, delta)
        sgn = np.sign(nominal)
        ground = sgn * v_long  # ground speed in the commanded direction
        scale = np.exp(self.correction)
        upper = np.maximum(ground / (1.0 - c.slip_setpoint), ground + c.min_slip_speed) * scale
        lower = np.maximum(ground * (1.0 - c.slip_setpoint), 0.0) / scale
        want = np.abs(nominal)
        cmd = np.minimum(np.maximum(want, lower), np.maximum(upper, 0.0))
        self.limited = (want > upper) | (want < lower)
        # integral on the slip error of the wheels the bound holds (drive slip > 0, skid < 0)
        slip = sgn * obs[self._i_slip]
        err = np.where(
            want > upper, c.slip_setpoint - slip, np.where(want < lower, slip + c.slip_setpoint, 0.0)
        )
        dt = self.follower.cfg.dt
        lo, hi = c.correction_range
        learn = self.limited & (np.abs(ground) >= c.feedback_speed)
        self.correction = np.where(
            learn,
            np.clip(self.correction + c.gain * err * dt, lo, hi),
            np.where(self.limited, self.correction, self.correction * math.exp(-dt)),
        )
        return sgn * cmd

    def action(self, commands: np.ndarray, lam_f: float, lam_r: float) -> np.ndarray:
        """Wheels-mode action for tread speeds (4,) [m/s] and axle angles [rad], scaled to [-1, 1]."""
        f = self.follower.cfg
        act = np.concatenate([np.asarray(commands) / f.v_max, [lam_f / f.steer_limit, lam_r / f.steer_limit]])
        return np.clip(act, -1.0, 1.0).astype(np.float32)

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Wheels-mode action (w_FL, w_FR, w_RL, w_RR, lambda_F, lambda_R), scaled to [-1, 1]."""
        cmd, lam = self.wheel_commands(obs)
        return self.action(cmd, lam, -lam)


__all__ = ["SlipAwareController", "TractionConfig"]

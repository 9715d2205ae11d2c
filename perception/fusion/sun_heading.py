"""Absolute heading from a sun sensor, the IMU's tilt and the ephemeris.

A sun sensor measures the direction toward the sun in its own frame. Turned into the body frame
by its mount and levelled by the body's roll and pitch (from the IMU), its azimuth in the level
frame is the sun's azimuth relative to the rover's heading; the ephemeris gives the sun's azimuth
in the world. Their difference is the heading:

    s_level = Ry(pitch) Rx(roll) R_body_sensor s,     yaw = atan2(e_y, e_x) - atan2(s_level_y, s_level_x)

(world from body = Rz(yaw) Ry(pitch) Rx(roll), as the dead reckoning's). An error of delta in the
sensor's direction or in the tilt moves the azimuth by up to delta / cos(el) and delta tan(el)
(el: the sun's elevation): a high sun gives a poor heading, and none at the zenith.

:class:`HeadingFilter` fuses the readings into the dead-reckoned heading with an error-state
Kalman filter on the sun's azimuth and elevation. Its states are the heading's error (its variance
grows with the gyro's noise and bias), the sensor's fixed error about its boresight (which looks
like a heading error forever, and bounds what the sun can give), and the tilt's error in the body
frame: a MEMS accelerometer's bias of 10 mg tilts the IMU's gravity by 0.6 deg, which no IMU sees
but which moves the sun's azimuth by tan(el) times as much. The sun's elevation measures the tilt's
error toward the sun; as the rover turns the sun moves round the body and shows the rest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.models.rover import rot_x, rot_y, rot_z
from perception.models.validation import ConfigError


def wrap(angle: float) -> float:
    """``angle`` [rad] wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def level_direction(s_body, roll: float, pitch: float) -> np.ndarray:
    """A body-frame direction in the level frame (the body's frame turned back by pitch and roll)."""
    return rot_y(pitch) @ rot_x(roll) @ np.asarray(s_body, dtype=np.float64)


def sun_heading(s_sensor, R_body_sensor, ephemeris, roll: float, pitch: float) -> tuple[float, float]:
    """The rover's heading from one sun reading.

    Args:
        s_sensor: (3,) direction toward the sun measured in the sensor frame.
        R_body_sensor: (3, 3) the sensor's mount rotation (body from sensor).
        ephemeris: (3,) direction toward the sun in the world frame (z up) at the reading's time.
        roll: The body's roll [rad] (world from body = Rz(yaw) Ry(pitch) Rx(roll)).
        pitch: The body's pitch [rad].

    Returns:
        (yaw [rad] in [-pi, pi), the sun's elevation in the level frame [rad]).
    """
    s = level_direction(
        np.asarray(R_body_sensor, dtype=np.float64) @ np.asarray(s_sensor, float), roll, pitch
    )
    e = np.asarray(ephemeris, dtype=np.float64)
    el = math.atan2(s[2], math.hypot(s[0], s[1]))
    return wrap(math.atan2(e[1], e[0]) - math.atan2(s[1], s[0])), el


@dataclass(frozen=True)
class HeadingConfig:
    """Parameters of :class:`HeadingFilter`.

    Attributes:
        start_std_deg: The start fix's heading uncertainty (1 sigma) [deg].
        tilt_noise_deg: The IMU tilt's error that varies from reading to reading (1 sigma) [deg]
            (its constant part is the accelerometer's bias, from the IMU's data sheet).
        tilt_time: Correlation time of the tilt's slowly varying error [s].
        gate: Readings whose residual exceeds this many standard deviations are left out.
        max_turn_rate: Readings while the rover turns faster than this [rad/s] are left out
            (the IMU's tilt errs most while its gravity carries a turn's centripetal force).
        tilt_std_deg: The tilt's slowly varying error (1 sigma) [deg]; None: from the IMU's data
            sheet (the accelerometer's bias and cross-axis coupling, and the gyro's bias over the
            attitude filter's time constant).
        max_elevation_deg: Readings with the sun higher than this are left out (the azimuth
            is undefined at the zenith) [deg].
    """

    start_std_deg: float = 1.0
    tilt_noise_deg: float = 0.2
    tilt_time: float = 60.0
    gate: float = 4.0
    max_turn_rate: float = 0.05
    tilt_std_deg: float | None = None
    max_elevation_deg: float = 85.0

    def __post_init__(self) -> None:
        keys = ("start_std_deg", "tilt_noise_deg", "tilt_time", "gate", "max_turn_rate", "max_elevation_deg")
        for key in keys + (("tilt_std_deg",) if self.tilt_std_deg is not None else ()):
            v = getattr(self, key)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"heading.{key}: {v!r}; give a finite number above 0")
        if self.max_elevation_deg >= 90.0:
            raise ConfigError(f"heading.max_elevation_deg: {self.max_elevation_deg!r}; give it below 90 deg")


class HeadingFilter:
    """The dead-reckoned yaw corrected by sun readings: an error-state Kalman filter.

    States: the yaw's error [rad] (the dead reckoning carries the yaw; :meth:`update` returns the
    correction to add to it), the sensor's fixed error about its boresight [rad], and the tilt's
    error as (roll, pitch) corrections [rad]. Measurements: the sun's azimuth (world) and
    elevation, from a reading through the estimated attitude, against the ephemeris's.

    Args:
        config: Its parameters.
        accuracy_deg: The sun sensor's fixed error per axis (1 sigma) [deg].
        noise_deg: A reading's white noise per axis (1 sigma) [deg].
        tilt_std: The IMU tilt's slowly varying error (1 sigma) [rad] from its data sheet
            (``config.tilt_std_deg``, when given, takes its place); the sensor's fixed error about
            its other two axes is added to it, as it looks the same.
    """

    def __init__(
        self,
        config: HeadingConfig | None = None,
        accuracy_deg: float = 0.1,
        noise_deg: float = 0.03,
        tilt_std: float = 0.01,
    ) -> None:
        self.config = config or HeadingConfig()
        self.accuracy = math.radians(accuracy_deg)
        self.noise = math.radians(noise_deg)
        if self.config.tilt_std_deg is not None:
            tilt_std = math.radians(self.config.tilt_std_deg)
        self.tilt_std = math.hypot(float(tilt_std), self.accuracy)
        self.reset()

    def reset(self) -> None:
        """At the start fix: its heading uncertainty; the sensor's and the tilt's errors as their priors."""
        c = self.config
        self.P = np.diag(
            [math.radians(c.start_std_deg) ** 2, self.accuracy**2, self.tilt_std**2, self.tilt_std**2]
        )
        #: Estimates of the boresight error and the tilt's (roll, pitch) corrections [rad].
        self.x = np.zeros(3)
        #: Readings used and left out (gated) since the reset.
        self.used = 0
        self.rejected = 0

    def predict(self, dt: float, yaw_rate_var: float) -> None:
        """Dead reckoning over ``dt`` [s]: the yaw's variance grows by ``yaw_rate_var`` [rad^2/s] * dt."""
        if dt <= 0:
            return
        self.P[0, 0] += yaw_rate_var * dt
        phi = math.exp(-dt / self.config.tilt_time)
        for k in (2, 3):  # the tilt's error: a first-order Gauss-Markov process
            self.x[k - 1] *= phi
            self.P[k, :] *= phi
            self.P[:, k] *= phi
            self.P[k, k] += self.tilt_std**2 * (1.0 - phi * phi)

    def _measure(self, x, yaw, s_body, roll, pitch) -> np.ndarray:
        """(azimuth [rad] world, elevation [rad]) of the reading with the errors ``x`` (4,) taken out."""
        s = level_direction(rot_z(x[1]) @ s_body, roll + x[2], pitch + x[3])
        return np.array([yaw + x[0] + math.atan2(s[1], s[0]), math.atan2(s[2], math.hypot(s[0], s[1]))])

    def update(
        self, yaw_dr: float, s_sensor, R_body_sensor, ephemeris, roll: float, pitch: float
    ) -> float | None:
        """Fuse one sun reading; the correction [rad] to add to the dead-reckoned yaw (None: not used).

        Args:
            yaw_dr: The dead-reckoned yaw at the reading's time [rad].
            s_sensor: (3,) the measured direction toward the sun, sensor frame.
            R_body_sensor: (3, 3) the sensor's mount rotation.
            ephemeris: (3,) the direction toward the sun from the ephemeris, world frame.
            roll: The IMU's roll [rad].
            pitch: The IMU's pitch [rad].
        """
        s_body = np.asarray(R_body_sensor, dtype=np.float64) @ np.asarray(s_sensor, dtype=np.float64)
        e = np.asarray(ephemeris, dtype=np.float64)
        el_sun = math.atan2(e[2], math.hypot(e[0], e[1]))
        if not np.all(np.isfinite(s_body)) or not 0.0 < el_sun < math.radians(self.config.max_elevation_deg):
            return None
        x0 = np.concatenate([[0.0], self.x])
        h0 = self._measure(x0, yaw_dr, s_body, roll, pitch)
        H = np.empty((2, 4))
        eps = 1e-6
        for k in range(4):
            dx = x0.copy()
            dx[k] += eps
            d = self._measure(dx, yaw_dr, s_body, roll, pitch) - h0
            d[0] = wrap(d[0])
            H[:, k] = d / eps
        r = np.array([wrap(math.atan2(e[1], e[0]) - h0[0]), el_sun - h0[1]])
        tilt = math.radians(self.config.tilt_noise_deg)
        ce, te = math.cos(el_sun), math.tan(el_sun)
        R = np.diag([(self.noise / ce) ** 2 + (tilt * te) ** 2, self.noise**2 + tilt**2])
        S = H @ self.P @ H.T + R
        if float(r @ np.linalg.solve(S, r)) > self.config.gate**2:
            self.rejected += 1
            return None
        K = self.P @ H.T @ np.linalg.inv(S)
        dx = K @ r
        I_KH = np.eye(4) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T  # Joseph form
        self.x += dx[1:]
        self.used += 1
        return float(dx[0])

    @property
    def yaw_std(self) -> float:
        """Standard deviation of the yaw's error [rad]."""
        return math.sqrt(max(self.P[0, 0], 0.0))

"""A 6-axis IMU on the rover body: exact specific force and angular rate, then a noise model.

The simulation samples the sensor like a camera (:meth:`rover_env.sim.simulation.RoverSim.attach_sensor`).
Each sample is what an integrating MEMS part delivers over its sample period T:

* angular rate: the rotation of the mount frame from the last sample to this one, divided by T
  (the body's instantaneous rate at the first sample after a reset);
* specific force: the mount point's velocity change over T, less gravity, in the mount frame
  (gravity alone, -g, at the first sample after a reset). A level body at rest reads
  (0, 0, +9.81) m/s^2.

Then, per axis, with constants drawn once per episode from the seed:

    y = Q(sat((I + S + M) x + b0 + n_white + b_flicker + b_walk))

S: scale-factor errors (diagonal), M: axis misalignment (off-diagonal), b0: turn-on bias,
n_white: white noise of density N, b_flicker: bias instability B (a sum of first-order Gauss-Markov
processes whose time constants span 1 ms to 10^4 s, scaled so that the Allan curve's floor is
0.664 B), b_walk: bias random walk of density K; sat: range saturation, Q: quantisation to the
resolution. Frames: the mount frame is the body frame (x forward, y left, z up) turned by the
mount's roll, pitch and yaw; units rad/s and m/s^2.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from rover_env.config.imu import G, ImuConfig
from rover_env.config.io import ConfigError

#: Time constants of the bias-instability processes [s]: two per decade from 1 ms to 10^4 s.
FLICKER_TAUS = 0.001 * 10.0 ** (np.arange(15) / 2.0)


def _gm_avar(tau: np.ndarray, tc: np.ndarray) -> np.ndarray:
    """Allan variance of unit-variance first-order Gauss-Markov processes (time constants ``tc``)."""
    x = np.asarray(tau, dtype=np.float64)[:, None] / tc[None, :]
    return (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x)) / (x * x)


def _flicker_variance() -> float:
    """Variance of each Gauss-Markov term per unit B^2: the sum's Allan floor is (2 ln 2 / pi) B^2.

    The floor is the geometric mean of the sum's Allan variance over tau = 1 ... 1000 s (its
    ripple there is within +-3 %).
    """
    taus = np.logspace(0, 3, 61)
    total = _gm_avar(taus, FLICKER_TAUS).sum(axis=1)
    return (2 * math.log(2) / math.pi) / float(np.exp(np.mean(np.log(total))))


_FLICKER_VAR = _flicker_variance()


def _log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of a rotation matrix whose angle is below pi (a sample's increment)."""
    vee = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    s = float(np.linalg.norm(vee))  # sin(angle)
    c = 0.5 * (float(np.trace(R)) - 1.0)  # cos(angle)
    angle = math.atan2(s, c)
    return vee * (angle / s) if s > 1e-12 else vee


class ImuNoise:
    """The error model of :class:`ImuConfig` for one episode, as a stream of samples.

    Args:
        config: The IMU.
        seed: Seeds the episode's constants (turn-on biases, scale factors, misalignment) and
            the noise streams.
    """

    def __init__(self, config: ImuConfig, seed: int | None = None) -> None:
        self.config = config
        self.dt = 1.0 / float(config.rate_hz)
        rng = np.random.default_rng(seed)
        self._rng = rng
        triads = (config.gyro, config.accel)
        # per-episode constants: (6,) turn-on bias, two (3, 3) error matrices I + S + M
        self.turn_on = np.concatenate([t.turn_on_bias * rng.standard_normal(3) for t in triads])
        self.matrices = []
        for t in triads:
            E = np.eye(3) + np.diag(t.scale_factor * rng.standard_normal(3))
            off = ~np.eye(3, dtype=bool)
            E[off] += t.misalignment * rng.standard_normal(6)
            self.matrices.append(E)
        col = np.repeat([0, 1], 3)
        self._white = np.array([triads[c].noise_density for c in col]) / math.sqrt(self.dt)
        self._walk = np.array([triads[c].bias_random_walk for c in col]) * math.sqrt(self.dt)
        self._gm_sd = np.array([triads[c].bias_instability for c in col]) * math.sqrt(_FLICKER_VAR)
        self._phi = np.exp(-self.dt / FLICKER_TAUS)  # (terms,)
        # stationary start of each Gauss-Markov term; the walk starts at 0 (b0 holds the offset)
        self._gm = self._gm_sd[None, :] * rng.standard_normal((len(FLICKER_TAUS), 6))
        self._walk_state = np.zeros(6)
        self._range = np.array([triads[c].range for c in col])
        self._res = np.array([triads[c].resolution for c in col])
        self._buffer = np.zeros((0, 6))
        self._next = 0

    def errors(self, n: int) -> np.ndarray:
        """The next ``n`` samples of additive error (bias + noise), (n, 6): gyro xyz, accel xyz."""
        if n < 0:
            raise ValueError(f"n: {n}; give a count >= 0")
        rng = self._rng
        out = self.turn_on + self._white * rng.standard_normal((n, 6))
        steps = self._walk * rng.standard_normal((n, 6))
        walk = self._walk_state + np.cumsum(steps, axis=0)
        if n:
            self._walk_state = walk[-1].copy()
        out += walk
        for i, phi in enumerate(self._phi):
            drive = self._gm_sd * math.sqrt(1.0 - phi * phi) * rng.standard_normal((n, 6))
            if n:
                y, zf = lfilter([1.0], [1.0, -phi], drive, axis=0, zi=phi * self._gm[i][None, :])
                self._gm[i] = y[-1]
                out += y
        return out

    def measure(self, gyro: np.ndarray, accel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured samples of true rates and specific forces, each (n, 3) or (3,).

        Returns:
            (samples (n, 6) or (6,): gyro [rad/s] then accel [m/s^2], saturated (n, 6) or (6,) bool).
        """
        g = np.asarray(gyro, dtype=np.float64)
        a = np.asarray(accel, dtype=np.float64)
        single = g.ndim == 1
        g, a = g.reshape(-1, 3), a.reshape(-1, 3)
        n = len(g)
        if len(self._buffer) - self._next < n:  # errors are drawn a second's worth at a time
            rest = self._buffer[self._next :]
            self._buffer = np.vstack([rest, self.errors(max(n, int(round(1.0 / self.dt))))])
            self._next = 0
        err = self._buffer[self._next : self._next + n]
        self._next += n
        true = np.hstack([g @ self.matrices[0].T, a @ self.matrices[1].T])
        y = true + err
        sat = np.abs(y) >= self._range
        y = np.clip(y, -self._range, self._range)
        quant = self._res > 0
        if np.any(quant):
            r = np.where(quant, self._res, 1.0)
            y = np.where(quant, np.clip(np.rint(y / r) * r, -self._range, self._range), y)
        return (y[0], sat[0]) if single else (y, sat)


class Imu:
    """The IMU as a sensor of a :class:`rover_env.sim.simulation.RoverSim` (attach it with ``attach_sensor``).

    :meth:`sample` returns (7,) float64: gyro xyz [rad/s], accel xyz [m/s^2] in the mount frame,
    then a saturation flag (1.0 when any axis hit its range). :meth:`reset` draws a new episode's
    errors. The simulation samples it also while the rover settles before t = 0 (``preroll``).

    Args:
        sim: The simulation.
        config: The IMU (default: the BMI088 preset).
        seed: Seed of the first episode's errors.
    """

    #: Sampled while the rover settles at rest before t = 0 (see ``RoverSim.attach_sensor``).
    preroll = True

    def __init__(self, sim, config: ImuConfig | None = None, seed: int | None = None) -> None:
        self.sim = sim
        self.config = config or ImuConfig.preset("bmi088")
        steps = self.period / sim.dt
        if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
            raise ConfigError(
                f"imu.rate_hz: {self.config.rate_hz:g} Hz does not divide the physics rate "
                f"{1 / sim.dt:g} Hz; use 240, 120, 80 or 60 Hz"
            )
        self.R_body_imu = Rotation.from_euler("xyz", self.config.rpy).as_matrix()
        self.r_body = np.asarray(self.config.position, dtype=np.float64)
        self.noise = ImuNoise(self.config, seed)
        self._last: tuple[int, np.ndarray, np.ndarray] | None = None  # (step, R_world_imu, v_mount)

    @property
    def period(self) -> float:
        """Time between samples [s]."""
        return 1.0 / float(self.config.rate_hz)

    def reset(self, seed: int | None = None, config: ImuConfig | None = None) -> None:
        """A new episode: new turn-on biases, scale factors, misalignment and noise streams.

        ``config``: this episode's unit (its own figures, as domain randomisation draws them),
        while :attr:`config` stays the data sheet; None: the data sheet's figures.
        """
        self.noise = ImuNoise(self.config if config is None else config, seed)
        self._last = None

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """(angular rate [rad/s], specific force [m/s^2]) at the mount now, mount frame, no errors."""
        sim = self.sim
        lin, ang = sim.base_velocity()
        R_wb = sim.base_matrix()[:3, :3]
        R_wi = R_wb @ self.R_body_imu
        w = np.asarray(ang, dtype=np.float64)
        r = R_wb @ self.r_body
        wx, wy, wz = ang
        v = np.array(lin) + (wy * r[2] - wz * r[1], wz * r[0] - wx * r[2], wx * r[1] - wy * r[0])
        step = sim.steps
        last = self._last
        gravity = np.array([0.0, 0.0, -G])
        if last is None or step <= last[0]:
            rate = R_wi.T @ w
            force = R_wi.T @ (-gravity)
        else:
            dt = (step - last[0]) * sim.dt
            rate = _log_so3(last[1].T @ R_wi) / dt
            force = R_wi.T @ ((v - last[2]) / dt - gravity)
        self._last = (step, R_wi, v)
        return rate, force

    def sample(self) -> np.ndarray:
        """The IMU's output now: (7,) gyro [rad/s], accel [m/s^2], saturated flag."""
        rate, force = self.truth()
        y, sat = self.noise.measure(rate, force)
        return np.concatenate([y, [1.0 if sat.any() else 0.0]])

"""A 6-axis IMU on the rover body: exact specific force and angular rate, then a noise model.

The simulation samples the sensor like a camera (:meth:`rover_env.sim.RoverSim.attach_sensor`).
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
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from rover_env.config_io import ConfigError, check_range, from_dict, real_number, to_dict

#: Gravity of the simulation [m/s^2] (``RoverSim`` sets (0, 0, -9.81)).
G = 9.81
_DEG = math.pi / 180.0

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


@dataclass(frozen=True)
class TriadNoise:
    """Error model of three like axes (a gyro or an accelerometer), the same for each axis.

    Units: ``u`` is rad/s for a gyro, m/s^2 for an accelerometer.

    Attributes:
        noise_density: White noise N [u/sqrt(Hz)] (angle / velocity random walk).
        bias_instability: B [u]: the Allan deviation's floor is 0.664 B.
        bias_random_walk: K [u/s/sqrt(Hz)] (rate / acceleration random walk).
        turn_on_bias: Standard deviation of the constant bias drawn per episode [u].
        scale_factor: Standard deviation of each axis's scale-factor error [-].
        misalignment: Standard deviation of each cross-axis coupling [rad].
        range: Largest magnitude the axis reports; beyond it the output saturates [u] (inf: none).
        resolution: Output step [u] (0: not quantised).
    """

    noise_density: float = 0.0
    bias_instability: float = 0.0
    bias_random_walk: float = 0.0
    turn_on_bias: float = 0.0
    scale_factor: float = 0.0
    misalignment: float = 0.0
    range: float = field(default=math.inf, metadata={"allow_inf": True})
    resolution: float = 0.0

    def check(self, prefix: str) -> None:
        """Raise :class:`ConfigError` naming ``prefix.key`` for a non-number or a bad value."""
        for key, value in asdict(self).items():
            name = f"{prefix}.{key}"
            v = real_number(name, value, allow_inf=key == "range")
            if key == "range":
                if not v > 0:
                    raise ConfigError(f"{name}: {value!r}; give a positive full-scale value (.inf: none)")
            else:
                check_range(name, v, 0.0)


@dataclass(frozen=True)
class ImuConfig:
    """An IMU: its rate, where it sits on the body, and the error model of its two triads.

    Attributes:
        name: Preset name (or "custom").
        rate_hz: Sample rate [Hz]; must divide the physics rate (240 Hz: 240, 120, 80, 60 ...).
        position: Mount position in the body frame [m].
        rpy: Mount orientation, roll-pitch-yaw of the mount frame in the body frame [rad].
        gyro: Gyroscope errors [rad/s].
        accel: Accelerometer errors [m/s^2].
    """

    name: str = "bmi088"
    rate_hz: float = 240.0
    position: tuple[float, float, float] = (0.0, 0.0, 0.05)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gyro: TriadNoise = field(default_factory=TriadNoise)
    accel: TriadNoise = field(default_factory=TriadNoise)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ConfigError(f"imu.name: {self.name!r}; give a name")
        check_range("imu.rate_hz", self.rate_hz, 0.0, lo_open=True)
        for key in ("position", "rpy"):
            v = getattr(self, key)
            if not isinstance(v, list | tuple | np.ndarray) or len(v) != 3:
                raise ConfigError(f"imu.{key}: {v!r}; give three numbers")
            for i, x in enumerate(v):
                real_number(f"imu.{key}[{i}]", x)
        self.gyro.check("imu.gyro")
        self.accel.check("imu.accel")

    @classmethod
    def preset(cls, name: str, **overrides) -> ImuConfig:
        """A named part: ``"bmi088"`` (MEMS, the default), ``"tactical"`` or ``"ideal"`` (no errors)."""
        if name not in IMU_PRESETS:
            raise ConfigError(f"imu preset {name!r}: choose one of {sorted(IMU_PRESETS)}")
        return replace(IMU_PRESETS[name], **overrides)

    @classmethod
    def from_dict(cls, d: dict) -> ImuConfig:
        """From a scenario or preset mapping: ``preset`` (optional) and overrides, triads as mappings.

        Every value is checked by the one path of scenario files
        (:func:`rover_env.config_io.from_dict`): numbers must be numbers (not text, not
        true/false), unknown keys are named.
        """
        if not isinstance(d, dict):
            raise ConfigError(f"imu: {d!r}; give a mapping (preset, rate_hz, position, rpy, gyro, accel)")
        d = dict(d)
        name = d.pop("preset", "bmi088")
        if not isinstance(name, str):
            raise ConfigError(f"imu.preset: {name!r}; choose one of {sorted(IMU_PRESETS)}")
        base = cls.preset(name)
        known = {"rate_hz", "position", "rpy", "gyro", "accel"}
        unknown = sorted(set(d) - known, key=str)
        if unknown:
            raise ConfigError(f"imu: unknown keys {unknown}; allowed: preset, {', '.join(sorted(known))}")
        merged = to_dict(base)
        for key in ("gyro", "accel"):
            if key in d:
                sub = d.pop(key)
                if not isinstance(sub, dict):
                    fields = sorted(asdict(getattr(base, key)))
                    raise ConfigError(f"imu.{key}: {sub!r}; give a mapping of {fields}")
                merged[key] = {**merged[key], **sub}
        overridden = bool(d) or merged != to_dict(base)
        merged.update(d)
        merged["name"] = "custom" if overridden else base.name
        return from_dict(cls, merged, "imu")


# Bosch BMI088 (data sheet BST-BMI088-DS001): gyro output noise 0.014 deg/s/sqrt(Hz), bias
# stability 2 deg/h, zero-rate offset +-1 deg/s (taken as 2 sigma), 16-bit output (here at the
# +-500 deg/s range); accelerometer noise density 175 ug/sqrt(Hz), zero-g offset +-20 mg (2 sigma),
# 16-bit at +-6 g; sensitivity and cross-axis tolerances of about 1 % (2 sigma). The data sheet
# gives no random walks of the biases and no accelerometer bias stability: those three are
# typical of the class and marked as assumptions in docs/imu.md.
_BMI088 = ImuConfig(
    name="bmi088",
    gyro=TriadNoise(
        noise_density=0.014 * _DEG,
        bias_instability=2.0 * _DEG / 3600.0,
        bias_random_walk=2.0e-7,
        turn_on_bias=0.5 * _DEG,
        scale_factor=0.005,
        misalignment=0.005,
        range=500.0 * _DEG,
        resolution=1000.0 * _DEG / 65536.0,
    ),
    accel=TriadNoise(
        noise_density=175e-6 * G,
        bias_instability=50e-6 * G,
        bias_random_walk=3.0e-5,
        turn_on_bias=10e-3 * G,
        scale_factor=0.005,
        misalignment=0.005,
        range=6.0 * G,
        resolution=12.0 * G / 65536.0,
    ),
)

# A tactical-grade unit (fibre-optic or high-end MEMS, HG1700 class): angle random walk
# 0.1 deg/sqrt(h), bias instability 1 deg/h, velocity random walk 0.05 m/s/sqrt(h), accelerometer
# bias instability 50 ug, 100 ppm scale factor, 0.1 mrad misalignment.
_TACTICAL = ImuConfig(
    name="tactical",
    gyro=TriadNoise(
        noise_density=0.1 * _DEG / 60.0,
        bias_instability=1.0 * _DEG / 3600.0,
        bias_random_walk=3.0e-8,
        turn_on_bias=3.0 * _DEG / 3600.0,
        scale_factor=1e-4,
        misalignment=1e-4,
        range=1000.0 * _DEG,
        resolution=1e-7,
    ),
    accel=TriadNoise(
        noise_density=0.05 / 60.0,
        bias_instability=50e-6 * G,
        bias_random_walk=1.0e-5,
        turn_on_bias=1e-3 * G,
        scale_factor=1e-4,
        misalignment=1e-4,
        range=20.0 * G,
        resolution=1e-5,
    ),
)

IMU_PRESETS: dict[str, ImuConfig] = {
    "bmi088": _BMI088,
    "tactical": _TACTICAL,
    "ideal": ImuConfig(name="ideal"),
}


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
    """The IMU as a sensor of a :class:`rover_env.sim.RoverSim` (attach it with ``attach_sensor``).

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

    def reset(self, seed: int | None = None) -> None:
        """A new episode: new turn-on biases, scale factors, misalignment and noise streams."""
        self.noise = ImuNoise(self.config, seed)
        self._last = None

    def truth(self) -> tuple[np.ndarray, np.ndarray]:
        """(angular rate [rad/s], specific force [m/s^2]) at the mount now, mount frame, no errors."""
        sim = self.sim
        c = sim.client
        body = sim.rover.body_id
        pos, quat = c.getBasePositionAndOrientation(body)
        lin, ang = c.getBaseVelocity(body)
        R_wb = np.array(c.getMatrixFromQuaternion(quat)).reshape(3, 3)
        R_wi = R_wb @ self.R_body_imu
        w = np.asarray(ang, dtype=np.float64)
        r = R_wb @ self.r_body
        wx, wy, wz = ang
        v = np.array(lin) + (wy * r[2] - wz * r[1], wz * r[0] - wx * r[2], wx * r[1] - wy * r[0])
        step = sim._steps
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

"""The IMU's configuration: its rate, mount and data-sheet error figures, and the named parts.

The sensor itself (its error model sampled at the simulation's substeps) is
:class:`rover_env.sensors.imu.Imu`. Units: rad/s for a gyro, m/s^2 for an accelerometer.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from rover_env.config.io import ConfigError, check_range, from_dict, real_number, to_dict

#: Gravity of the simulation [m/s^2] (``RoverSim`` sets (0, 0, -9.81)).
G = 9.81
_DEG = math.pi / 180.0


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
        (:func:`rover_env.config.io.from_dict`): numbers must be numbers (not text, not
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

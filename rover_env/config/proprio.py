"""The proprioceptive sensors' configurations: wheel encoders, motor currents, the command.

A rig's ``wheel_encoders`` report each wheel's angle as a quantised counter, its
``motor_current`` each drive motor's current, its ``command`` the wheel rates and steering the
rover was told to hold (the sensors themselves: :mod:`rover_env.sensors.proprio`). The figures
and where they come from are in ``docs/own_estimator.md`` ("Proprioceptive sensors").
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from rover_env.config.io import ConfigError, check_range, from_dict, to_dict


@dataclass(frozen=True)
class EncoderConfig:
    """Incremental wheel encoders, one per wheel, read as a wrapping counter.

    Attributes:
        name: The part (``"custom"`` once a figure is changed).
        rate_hz: Readings per second [Hz]; must divide the physics rate.
        counts_per_rev: Counts per wheel revolution (after quadrature decoding and any gear
            between the disc and the wheel) [-].
        counter_bits: Width of the counter the counts accumulate in; it wraps at
            ``2 ** counter_bits`` (a 16-bit timer counter: every 16 revolutions at 4096 counts).
    """

    name: str = "as5047p"
    rate_hz: float = 120.0
    counts_per_rev: int = 4096
    counter_bits: int = 16

    def __post_init__(self) -> None:
        check_range("wheel_encoders.rate_hz", self.rate_hz, 0.0, 10000.0, lo_open=True)
        check_range("wheel_encoders.counts_per_rev", self.counts_per_rev, 4, 2**24)
        check_range("wheel_encoders.counter_bits", self.counter_bits, 8, 32)
        if 2**self.counter_bits < 4 * self.counts_per_rev:
            raise ConfigError(
                f"wheel_encoders.counter_bits: {self.counter_bits}; the counter must hold at least 4 "
                f"revolutions ({4 * self.counts_per_rev} counts) to be unwrapped between readings"
            )


@dataclass(frozen=True)
class MotorCurrentConfig:
    """Each drive motor's current sense: the wheel torque through the gearhead and the motor.

    The current is ``I = tau_m / k_t + I_0 tanh(omega_m / omega_0) + I_off + n``, with
    ``tau_m = tau_wheel / (N eta)`` while the motor drives its wheel and ``tau_wheel eta / N``
    while the wheel drives the motor back (braking); then quantised to ``lsb`` and clipped at
    ``range``.

    Attributes:
        name: The part (``"custom"`` once a figure is changed).
        rate_hz: Readings per second [Hz]; must divide the physics rate.
        gear_ratio: N, motor turns per wheel turn [-].
        torque_constant: k_t [N m/A].
        efficiency: eta, the gearhead's efficiency at load, (0, 1] [-].
        no_load_current: I_0, the current the motor and gearhead's friction take turning
            without load [A].
        friction_speed: omega_0, the motor speed over which that friction builds up from rest
            [rad/s] (a smooth Coulomb friction).
        offset_std: Spread of the current sense's offset I_off, drawn once per episode [A].
        noise_std: Each reading's white noise [A].
        lsb: Resolution of the current sense's converter [A] (0: none).
        range: Full scale [A]; a reading beyond is clipped to it.
    """

    name: str = "dcx26"
    rate_hz: float = 120.0
    gear_ratio: float = 100.0
    torque_constant: float = 0.0283
    efficiency: float = 0.75
    no_load_current: float = 0.06
    friction_speed: float = 5.0
    offset_std: float = 0.01
    noise_std: float = 0.02
    lsb: float = 0.002
    range: float = 10.0

    def __post_init__(self) -> None:
        check_range("motor_current.rate_hz", self.rate_hz, 0.0, 10000.0, lo_open=True)
        check_range("motor_current.gear_ratio", self.gear_ratio, 0.0, 1e4, lo_open=True)
        check_range("motor_current.torque_constant", self.torque_constant, 0.0, 10.0, lo_open=True)
        check_range("motor_current.efficiency", self.efficiency, 0.0, 1.0, lo_open=True)
        check_range("motor_current.no_load_current", self.no_load_current, 0.0, 100.0)
        check_range("motor_current.friction_speed", self.friction_speed, 0.0, 1e4, lo_open=True)
        check_range("motor_current.offset_std", self.offset_std, 0.0, 10.0)
        check_range("motor_current.noise_std", self.noise_std, 0.0, 10.0)
        check_range("motor_current.lsb", self.lsb, 0.0, 1.0)
        check_range("motor_current.range", self.range, 0.0, 1e3, lo_open=True)


@dataclass(frozen=True)
class CommandConfig:
    """The command the rover holds: each wheel's rate target and each axle's steering.

    Attributes:
        rate_hz: Readings per second [Hz]; None: the environment's control rate.
    """

    rate_hz: float | None = None

    def __post_init__(self) -> None:
        if self.rate_hz is not None:
            check_range("command.rate_hz", self.rate_hz, 0.0, 10000.0, lo_open=True)


# A magnetic rotary encoder on each wheel's axle of the AS5047P's class (ams OSRAM): its
# incremental (ABI) output at 1024 pulses, 4096 steps a revolution after quadrature, read by a
# 16-bit timer counter (an STM32 timer in encoder mode), which wraps. Its integral
# non-linearity (a fraction of a degree) is left out: the quantisation is the error modelled.
ENCODER_PRESETS: dict[str, EncoderConfig] = {"as5047p": EncoderConfig()}

# A 26 mm graphite-brush DC motor with a 100:1 three-stage planetary gearhead. The figures are
# of that class (maxon's DCX 26 L and GPX 26 catalogue pages: a torque constant of a few tens
# of mN m/A at 24 V, tens of mA without load, 70-80 % gearhead efficiency at load), rounded and
# assumed, not one part's data sheet: give your motor's. With them the rover's 8 N m wheel
# torque limit takes 3.8 A. The current sense's offset (10 mA), noise (20 mA) and resolution
# (2 mA) are assumed, typical of a motor driver's shunt amplifier and 12-14-bit converter.
MOTOR_PRESETS: dict[str, MotorCurrentConfig] = {"dcx26": MotorCurrentConfig()}


def _from(cls, presets: dict, key: str, d: Any):
    """A configuration from a preset name, a mapping (``preset`` and overrides) or itself."""
    if isinstance(d, cls):
        return d
    if d is None:
        d = next(iter(presets))
    if isinstance(d, str):
        if d not in presets:
            raise ConfigError(f"{key}: {d!r}; choose one of {sorted(presets)}")
        return presets[d]
    if not isinstance(d, dict):
        raise ConfigError(f"{key}: {d!r}; give a preset name or a mapping (preset and figures)")
    d = dict(d)
    name = d.pop("preset", next(iter(presets)))
    base = _from(cls, presets, f"{key}.preset", name)
    known = set(cls.__dataclass_fields__) - {"name"}
    unknown = sorted(set(d) - known, key=str)
    if unknown:
        raise ConfigError(f"{key}: unknown key {unknown[0]!r}; allowed: preset, {', '.join(sorted(known))}")
    merged = to_dict(base) | d
    if d:
        merged["name"] = "custom"
    return from_dict(cls, merged, key)


def encoder_config(d: Any = None) -> EncoderConfig:
    """An :class:`EncoderConfig` from a preset name, a mapping (``preset`` and overrides), itself or None."""
    return _from(EncoderConfig, ENCODER_PRESETS, "wheel_encoders", d)


def motor_config(d: Any = None) -> MotorCurrentConfig:
    """A :class:`MotorCurrentConfig` from a preset name, a mapping (preset and overrides), itself or None."""
    return _from(MotorCurrentConfig, MOTOR_PRESETS, "motor_current", d)


def with_rate(config, rate_hz: float | None):
    """``config`` at ``rate_hz`` (None: as it is)."""
    return config if rate_hz is None else replace(config, rate_hz=rate_hz)

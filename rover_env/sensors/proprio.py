"""Proprioceptive sensors: wheel encoders, drive-motor currents and the command in force.

Each is sampled by the simulation like a camera (:meth:`rover_env.sim.simulation.RoverSim.attach_sensor`)
and reads the rover's joints at the substep of its sample; its message carries what the part
delivers, with the error model of its configuration (:mod:`rover_env.config.proprio`). Wheel
order FL, FR, RL, RR.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np

from rover_env.config.proprio import CommandConfig, EncoderConfig, MotorCurrentConfig


class _WheelSensor(ABC):
    """What the encoders and current senses share: the rover they read, their part, their rate."""

    def __init__(self, sim, config, seed: int | None) -> None:
        self.sim = sim
        self.config = config
        self._rover = sim.rover
        self.reset(seed)

    @property
    def period(self) -> float:
        """Time between readings [s]."""
        return 1.0 / float(self.config.rate_hz)

    @abstractmethod
    def reset(self, seed: int | None = None) -> None:
        """A new episode: the part's per-episode state, drawn from ``seed``."""


class WheelEncoders(_WheelSensor):
    """Each wheel's angle as an incremental encoder's wrapping counter.

    :meth:`sample` returns (4,) float64 counts, whole numbers in [0, 2 ** counter_bits): the
    wheel's unwrapped angle since the rover was built, floor(angle / 2 pi * counts_per_rev),
    modulo the counter's range (it starts at an arbitrary count drawn per episode, as a counter
    does at power-up). Rolling forward counts up.
    """

    def __init__(self, sim, config: EncoderConfig | None = None, seed: int | None = None) -> None:
        super().__init__(sim, config or EncoderConfig(), seed)

    def reset(self, seed: int | None = None) -> None:
        """A new episode: the counters' power-up values."""
        rng = np.random.default_rng(seed)
        self._start = rng.integers(0, 2**self.config.counter_bits, size=4).astype(np.float64)

    def sample(self) -> np.ndarray:
        """The counters now: (4,) counts."""
        c = self.config
        angle = np.array([s[0] for s in self._rover._read_wheel_joints()])
        counts = np.floor(angle * (c.counts_per_rev / (2.0 * math.pi)))
        return np.mod(counts + self._start, float(2**c.counter_bits))


class MotorCurrents(_WheelSensor):
    """Each drive motor's current [A], from its wheel's true torque (see :class:`MotorCurrentConfig`).

    :meth:`sample` returns (4,) float64 currents [A], positive driving the wheel forward.
    """

    def __init__(self, sim, config: MotorCurrentConfig | None = None, seed: int | None = None) -> None:
        super().__init__(sim, config or MotorCurrentConfig(), seed)

    def reset(self, seed: int | None = None) -> None:
        """A new episode: the current sense's offsets and noise stream."""
        self._rng = np.random.default_rng(seed)
        self._offset = self.config.offset_std * self._rng.standard_normal(4)

    def current(self, torque, rate) -> np.ndarray:
        """The noise-free current [A] of wheel torques [N m] at wheel rates [rad/s] (no offset)."""
        c = self.config
        tau = np.asarray(torque, dtype=np.float64)
        w_m = np.asarray(rate, dtype=np.float64) * c.gear_ratio
        driving = tau * w_m >= 0.0  # the motor drives its wheel (or the wheel stands)
        tau_m = np.where(driving, tau / (c.gear_ratio * c.efficiency), tau * c.efficiency / c.gear_ratio)
        return tau_m / c.torque_constant + c.no_load_current * np.tanh(w_m / c.friction_speed)

    def sample(self) -> np.ndarray:
        """The currents now: (4,) [A]."""
        c = self.config
        states = self._rover._read_wheel_joints()
        i = self.current([s[3] for s in states], [s[1] for s in states])
        i = i + self._offset + c.noise_std * self._rng.standard_normal(4)
        if c.lsb > 0.0:
            i = np.round(i / c.lsb) * c.lsb
        return np.clip(i, -c.range, c.range)


class CommandSensor:
    """The command the rover holds: (6,) wheel-rate targets FL, FR, RL, RR [rad/s], lambda_F, lambda_R [rad].

    What the drive electronics were last told (after the rover's limits), not what the wheels
    do. Its rate is the configuration's, or ``control_hz`` when that gives none.
    """

    def __init__(self, sim, config: CommandConfig | None = None, control_hz: float = 30.0) -> None:
        self.sim = sim
        self.config = config or CommandConfig()
        self.rate_hz = float(self.config.rate_hz if self.config.rate_hz is not None else control_hz)
        self._rover = sim.rover

    @property
    def period(self) -> float:
        """Time between readings [s]."""
        return 1.0 / self.rate_hz

    def sample(self) -> np.ndarray:
        """The command in force now: (6,)."""
        rv = self._rover
        return np.concatenate([rv.wheel_rate_cmd, rv.steer_cmd]).astype(np.float64)

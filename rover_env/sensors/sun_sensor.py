"""A two-axis fine sun sensor on the rover: the sun's direction in its frame, and the ephemeris's.

Each reading is the true direction toward the sun (the scenario's sun at that time, world frame)
seen from the sensor's frame, turned by the episode's fixed error (a small rotation, per-axis
standard deviation ``accuracy_deg``) and by each reading's white noise (``noise_deg``). The
sensor reads only while the sun lies within its field of view and at least ``min_sunlight`` of
the direct sunlight reaches it (the haze, a cloud in front of the sun, a cloud's shadow over
the rover). Beside the reading the message carries the sun's direction from the ephemeris at
that time, world frame: what a rover's flight software computes from its clock and its site,
known before the mission (clouds are not in it).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from rover_env.config.sun_sensor import SunSensorConfig


class SunSensor:
    """The sun sensor as a sensor of a :class:`~rover_env.sim.simulation.RoverSim` (see ``attach_sensor``).

    :meth:`sample` returns (7,) float64: the measured unit vector toward the sun in the sensor
    frame (z: its boresight), the ephemeris's unit vector toward the sun in the world frame
    (z up; the azimuth counter-clockwise from world x, as the scenario's), and a flag:
    0 a reading, 1 no sun (out of view or too dim; the first three are then NaN).

    Args:
        sim: The simulation (its rover's pose, its scenario's sun, its haze).
        config: The part (default: the NFSS-411).
        T_body_sensor: (4, 4) body-from-sensor mount; None: :meth:`standard_mount`.
        seed: Seed of the first episode's fixed error and noise.
    """

    def __init__(
        self, sim, config: SunSensorConfig | None = None, T_body_sensor=None, seed: int | None = None
    ) -> None:
        self.sim = sim
        self.config = config or SunSensorConfig()
        T = self.standard_mount(sim.geometry) if T_body_sensor is None else np.asarray(T_body_sensor, float)
        self.T_body_sensor = T
        self.reset(seed)

    @staticmethod
    def standard_mount(g) -> np.ndarray:
        """(4, 4) body-from-sensor pose on top of the mast's post, boresight up (body z)."""
        T = np.eye(4)
        T[:3, 3] = (g.mast_x, 0.0, g.mast_camera_position[2] + 0.5 * g.mast_thickness + 0.01)
        return T

    @property
    def period(self) -> float:
        """Time between readings [s]."""
        return 1.0 / float(self.config.rate_hz)

    def reset(self, seed: int | None = None) -> None:
        """A new episode: a new fixed error and noise stream."""
        self._rng = np.random.default_rng(seed)
        fixed = math.radians(self.config.accuracy_deg) * self._rng.standard_normal(3)
        self.R_error = Rotation.from_rotvec(fixed).as_matrix()

    def sunlight(self) -> float:
        """Share of the full direct sunlight at the sensor now [0..1]."""
        sim = self.sim
        sun = sim.scenario.sun
        t = sim.t
        p = (sim.base_matrix() @ self.T_body_sensor)[:3, 3]
        return float(sim.haze * sun.transmission(t) * sun.shade(p[None, :], t)[0])

    def truth(self) -> np.ndarray:
        """The exact unit vector toward the sun in the sensor frame now."""
        sim = self.sim
        R_ws = sim.base_matrix()[:3, :3] @ self.T_body_sensor[:3, :3]
        return R_ws.T @ sim.scenario.sun.direction(sim.t)

    def sample(self) -> np.ndarray:
        """The reading now: (7,) measured direction (sensor frame), ephemeris direction (world), flag."""
        cfg = self.config
        ephemeris = self.sim.scenario.sun.direction(self.sim.t)
        noise = Rotation.from_rotvec(math.radians(cfg.noise_deg) * self._rng.standard_normal(3)).as_matrix()
        s = noise @ self.R_error @ self.truth()
        seen = s[2] >= math.cos(math.radians(cfg.fov_deg)) and self.sunlight() >= cfg.min_sunlight
        if not seen:
            return np.concatenate([np.full(3, np.nan), ephemeris, [1.0]])
        return np.concatenate([s / np.linalg.norm(s), ephemeris, [0.0]])

"""Domain randomisation: the ranges from which each episode's world is drawn.

With randomisation on, every reset draws, from the episode's seed, a sun, sky light, ground look,
camera mounts and sensor figures and a friction factor, each uniformly within its range below;
the same seed gives the same world. The estimator keeps the nominal calibration (the cameras'
mounts, the IMU's data sheet), so the errors it meets are real. ``"off"`` keeps the scenario's
world as it is.

A range is ``(min, max)``; ``min == max`` fixes the value. Keys and their defaults:

=========================  ===============  ==================================================
key                        default          what is drawn
=========================  ===============  ==================================================
``sun_elevation_deg``      (20, 75)         the sun's height at t = 0 [deg] (rates and clouds stay)
``sun_azimuth_deg``        (-180, 180)      its direction at t = 0 [deg]
``sun_transmission``       (0.6, 1.0)       haze: factor on the direct sunlight
``ambient``                (0.15, 0.4)      sky light: share of the albedo seen in full shadow
``textures``               4 presets        the ground texture, one of these presets
``albedo``                 (0.75, 1.25)     factor on the ground's reflectance
``contrast``               (0.7, 1.3)       factor on the texture's deviation from its mean
``mount_rotation_deg``     (-0.5, 0.5)      each camera's mount error about each axis [deg]
``mount_offset_m``         (-0.003, 0.003)  each camera's mount error along each axis [m]
``read_noise``             (0.85, 1.15)     factor on each image sensor's read noise
``full_well``              (0.9, 1.1)       factor on its full-well capacity
``fixed_pattern``          (0.5, 1.5)       factor on its PRNU, DSNU and dark current
``imu_noise``              (0.8, 1.2)       factor on the IMU's noise densities, bias
                                            instability and random walk
``friction``               (0.85, 1.15)     factor on every friction coefficient of the map
=========================  ===============  ==================================================

The sensor spreads are assumed: a data sheet gives typical figures, and units of one model
differ from them by about these shares (read noise and full well by +-10-15 %, fixed-pattern
noise and dark current by up to 2x between units and with temperature).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from rover_env.config.io import ConfigError, from_dict, real_number
from rover_env.config.textures import TEXTURE_PRESETS

#: Ground textures drawn from by default (procedural presets of :mod:`rover_env.sim.textures`).
TEXTURE_BANK: tuple[str, ...] = ("regolith", "sand", "gravel", "concrete")

# each range key: (lowest allowed min, highest allowed max)
_LIMITS: dict[str, tuple[float, float]] = {
    "sun_elevation_deg": (1.0, 90.0),
    "sun_azimuth_deg": (-360.0, 360.0),
    "sun_transmission": (0.0, 1.0),
    "ambient": (0.0, 1.0),
    "albedo": (0.05, 3.0),
    "contrast": (0.0, 3.0),
    "mount_rotation_deg": (-10.0, 10.0),
    "mount_offset_m": (-0.1, 0.1),
    "read_noise": (0.0, 10.0),
    "full_well": (0.05, 10.0),
    "fixed_pattern": (0.0, 10.0),
    "imu_noise": (0.0, 10.0),
    "friction": (0.05, 5.0),
}


@dataclass(frozen=True)
class RandomizeConfig:
    """The ranges of domain randomisation (see the module's table). Each range is (min, max)."""

    sun_elevation_deg: tuple[float, float] = (20.0, 75.0)
    sun_azimuth_deg: tuple[float, float] = (-180.0, 180.0)
    sun_transmission: tuple[float, float] = (0.6, 1.0)
    ambient: tuple[float, float] = (0.15, 0.4)
    textures: tuple[str, ...] = TEXTURE_BANK
    albedo: tuple[float, float] = (0.75, 1.25)
    contrast: tuple[float, float] = (0.7, 1.3)
    mount_rotation_deg: tuple[float, float] = (-0.5, 0.5)
    mount_offset_m: tuple[float, float] = (-0.003, 0.003)
    read_noise: tuple[float, float] = (0.85, 1.15)
    full_well: tuple[float, float] = (0.9, 1.1)
    fixed_pattern: tuple[float, float] = (0.5, 1.5)
    imu_noise: tuple[float, float] = (0.8, 1.2)
    friction: tuple[float, float] = (0.85, 1.15)

    def __post_init__(self) -> None:
        for key, (lo_ok, hi_ok) in _LIMITS.items():
            rng = getattr(self, key)
            if isinstance(rng, (str, bytes)) or not hasattr(rng, "__len__") or len(rng) != 2:
                raise ConfigError(f"randomize.{key}: {rng!r}; give a range (min, max)")
            lo = real_number(f"randomize.{key}[0]", rng[0])
            hi = real_number(f"randomize.{key}[1]", rng[1])
            if lo > hi:
                raise ConfigError(f"randomize.{key}: ({lo:g}, {hi:g}) has its minimum above its maximum")
            if lo < lo_ok or hi > hi_ok:
                raise ConfigError(f"randomize.{key}: ({lo:g}, {hi:g}) is outside [{lo_ok:g}, {hi_ok:g}]")
        if not self.textures:
            raise ConfigError("randomize.textures: empty; name at least one texture preset")
        for i, name in enumerate(self.textures):
            if name not in TEXTURE_PRESETS:
                raise ConfigError(
                    f"randomize.textures[{i}]: {name!r}; use presets of {list(TEXTURE_PRESETS)}"
                )


def randomize_config(value: Any, key: str = "randomize") -> RandomizeConfig | None:
    """The ranges ``value`` asks for, or None (off).

    ``"off"`` (or None, False): None; ``"on"`` (or True): the defaults; a mapping: its ranges over
    the defaults. Anything else: :class:`ConfigError` naming ``key``.
    """
    if value is None or value is False or value == "off":
        return None
    if value is True or value == "on":
        return RandomizeConfig()
    if isinstance(value, RandomizeConfig):
        return value
    if isinstance(value, Mapping):
        return from_dict(RandomizeConfig, dict(value), key)
    raise ConfigError(f"{key}: {value!r}; use 'off', 'on' or a mapping of ranges (min, max)")


def range_keys() -> tuple[str, ...]:
    """The range keys of :class:`RandomizeConfig` (all but ``textures``)."""
    return tuple(f.name for f in fields(RandomizeConfig) if f.name != "textures")


def _draw(rng, r: tuple[float, float]) -> float:
    lo, hi = float(r[0]), float(r[1])
    return lo if lo == hi else float(rng.uniform(lo, hi))


@dataclass(frozen=True)
class WorldDraw:
    """One episode's draw (see :class:`RandomizeConfig`).

    The sun's angles are in degrees; each camera's mount error is (rotation vector [rad],
    offset [m]) in its optical frame.
    """

    sun_elevation_deg: float
    sun_azimuth_deg: float
    sun_transmission: float
    ambient: float
    texture: str
    albedo: float
    contrast: float
    mounts: tuple[tuple[float, ...], ...]  # per camera: (rx, ry, rz [rad], dx, dy, dz [m])
    read_noise: tuple[float, ...]  # per camera
    full_well: tuple[float, ...]
    fixed_pattern: tuple[float, ...]
    imu_noise: float
    friction: float

    @staticmethod
    def draw(cfg: RandomizeConfig, rng, cameras: int) -> WorldDraw:
        """Draw a world for a rover with ``cameras`` cameras from generator ``rng``.

        The draws are made in a fixed order, the per-camera ones last, so that the world and its
        physics (the friction factor) do not depend on how many cameras observe it.
        """
        d = {k: _draw(rng, getattr(cfg, k)) for k in ("sun_elevation_deg", "sun_azimuth_deg")}
        d["sun_transmission"] = _draw(rng, cfg.sun_transmission)
        d["ambient"] = _draw(rng, cfg.ambient)
        texture = cfg.textures[int(rng.integers(len(cfg.textures)))]
        d["albedo"] = _draw(rng, cfg.albedo)
        d["contrast"] = _draw(rng, cfg.contrast)
        d["imu_noise"] = _draw(rng, cfg.imu_noise)
        d["friction"] = _draw(rng, cfg.friction)
        mounts = tuple(
            tuple(math.radians(_draw(rng, cfg.mount_rotation_deg)) for _ in range(3))
            + tuple(_draw(rng, cfg.mount_offset_m) for _ in range(3))
            for _ in range(cameras)
        )

        def per_camera(r: tuple[float, float]) -> tuple[float, ...]:
            return tuple(_draw(rng, r) for _ in range(cameras))

        return WorldDraw(
            texture=texture,
            mounts=mounts,
            read_noise=per_camera(cfg.read_noise),
            full_well=per_camera(cfg.full_well),
            fixed_pattern=per_camera(cfg.fixed_pattern),
            **d,
        )

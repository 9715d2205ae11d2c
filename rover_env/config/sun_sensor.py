"""The sun sensor's configuration: its rate, field of view, error figures, and the named parts.

A two-axis fine sun sensor on the mast's top, looking up, measures the direction of the sun in
its own frame. With the tilt from the IMU and the sun's direction from the ephemeris (the
mission's clock and site) that gives the rover's heading absolutely, as Sojourner's sun sensor
and the MER rovers' sun-finding did. The sensor itself is :class:`rover_env.sensors.sun_sensor.SunSensor`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from rover_env.config.io import ConfigError, check_range, from_dict, to_dict


@dataclass(frozen=True)
class SunSensorConfig:
    """A fine sun sensor's figures.

    Attributes:
        name: The part's name (``"custom"`` once a figure is changed).
        rate_hz: Readings per second [Hz]; must divide the physics rate.
        fov_deg: Half-angle of its field of view about its boresight (its z axis) [deg].
        accuracy_deg: Standard deviation of its fixed error per axis [deg]: calibration residual
            and alignment to the body, drawn once per episode (about the boresight too, which
            turns the measured azimuth directly).
        noise_deg: Standard deviation of each reading's white noise per axis [deg].
        min_sunlight: The share of the full direct sunlight it needs to read [0..1]; below it
            (a cloud, a cloud's shadow, haze) it reports no sun.
    """

    name: str = "nfss411"
    rate_hz: float = 5.0
    fov_deg: float = 70.0
    accuracy_deg: float = 0.1
    noise_deg: float = 0.03
    min_sunlight: float = 0.5

    def __post_init__(self) -> None:
        check_range("sun.rate_hz", self.rate_hz, 0.0, 1000.0, lo_open=True)
        check_range("sun.fov_deg", self.fov_deg, 0.0, 90.0, lo_open=True)
        check_range("sun.accuracy_deg", self.accuracy_deg, 0.0, 30.0)
        check_range("sun.noise_deg", self.noise_deg, 0.0, 30.0)
        check_range("sun.min_sunlight", self.min_sunlight, 0.0, 1.0, lo_open=True)

    @classmethod
    def preset(cls, name: str, **overrides) -> SunSensorConfig:
        """A named part: ``"nfss411"`` (the default) or ``"ideal"`` (no errors)."""
        if name not in SUN_SENSOR_PRESETS:
            raise ConfigError(f"sun preset {name!r}: choose one of {sorted(SUN_SENSOR_PRESETS)}")
        return replace(SUN_SENSOR_PRESETS[name], **overrides)

    @classmethod
    def from_dict(cls, d) -> SunSensorConfig:
        """From a preset name, or a mapping: ``preset`` (optional) and overrides (checked, named)."""
        if isinstance(d, SunSensorConfig):
            return d
        if isinstance(d, str):
            return cls.preset(d)
        if not isinstance(d, dict):
            raise ConfigError(f"sun: {d!r}; give a preset name or a mapping (preset and figures)")
        d = dict(d)
        name = d.pop("preset", "nfss411")
        if not isinstance(name, str):
            raise ConfigError(f"sun.preset: {name!r}; choose one of {sorted(SUN_SENSOR_PRESETS)}")
        base = cls.preset(name)
        known = {"rate_hz", "fov_deg", "accuracy_deg", "noise_deg", "min_sunlight"}
        unknown = sorted(set(d) - known, key=str)
        if unknown:
            raise ConfigError(f"sun: unknown keys {unknown}; allowed: preset, {', '.join(sorted(known))}")
        merged = to_dict(base) | d
        if d:
            merged["name"] = "custom"
        return from_dict(cls, merged, "sun")


# NewSpace Systems NFSS-411 fine sun sensor (data sheet, via CubeSatShop): field of view 140 deg
# (70 deg half-angle), accuracy < 0.1 deg RMS over the field of view, 5 Hz update rate. The
# split of that accuracy into a fixed error (0.1 deg per axis, kept whole) and a white noise
# (0.03 deg), and the 50 % of direct sunlight it needs, are assumptions (the sheet gives neither).
SUN_SENSOR_PRESETS: dict[str, SunSensorConfig] = {
    "nfss411": SunSensorConfig(),
    "ideal": SunSensorConfig(name="ideal", accuracy_deg=0.0, noise_deg=0.0),
}

"""Scenarios: terrain, friction map, sun, course, start pose and duration, loaded from YAML.

A scenario is a frozen :class:`ScenarioConfig`. Shipped presets live in ``rover_env/config/scenarios``
as YAML files; :func:`load_scenario` takes a preset name or a path. Angles that people write by
hand (sun, start yaw, slope) are given in degrees under keys that end in ``_deg``; properties
without the suffix return radians, which is what the code uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np

from perception.models.validation import read_yaml
from rover_env.config.io import ConfigError, check_range, from_dict, load_yaml_dataclass, replace
from rover_env.config.randomize import randomize_config
from rover_env.config.rig import SensorConfig, check_rig, imu_config, standard_rig
from rover_env.config.textures import TEXTURE_PRESETS

#: Most heightfield points a rough terrain may have (the memory budget): 1001 x 1001, e.g.
#: 100 m x 100 m at 0.1 m or 20 m x 20 m at 0.02 m. A simulation holds about 1.3 kB a point
#: (collision shape, heights, visual mesh): 1.4 GB at this budget, 5.3 GB at 2001 x 2001
#: (measured, peak RSS with the GL renderer); PyBullet's heightfield crashes the process
#: (SIGSEGV) between 9 and 16 million points.
MAX_HEIGHTFIELD_POINTS = 1001 * 1001


#: Squares along one edge of the checkerboard texture tile.
CHECKER_SQUARES_PER_TILE = 8


@dataclass(frozen=True)
class TerrainConfig:
    """Ground shape and appearance. The terrain is centred on the world origin.

    Attributes:
        kind: ``"flat"`` (an exact plane, possibly inclined) or ``"rough"`` (a heightfield).
        size: Extent of the terrain along world x and y [m].
        cell: Heightfield grid spacing [m] (rough terrain only).
        roughness: RMS height of the random relief [m] (rough terrain only).
        wavelength: Dominant wavelength of the relief [m]; shorter bumps are attenuated.
        slope_deg: Inclination of the mean ground plane [deg].
        slope_azimuth_deg: Direction of steepest ascent, counter-clockwise from world x [deg].
        seed: Seed of the random relief and of procedural textures.
        texture: A preset (``regolith``, ``sand``, ``gravel``, ``concrete``, ``checkerboard``)
            or the path of an image file (relative paths are relative to the scenario file).
        texture_tile: Ground size covered by one repetition of the texture [m].
        texture_px: Pixels along one edge of a procedural texture tile; with ``texture_tile``
            this sets the detail (default 2 m / 1024 px, about 2 mm per pixel).
    """

    kind: Literal["flat", "rough"] = "flat"
    size: tuple[float, float] = (40.0, 40.0)
    cell: float = 0.1
    roughness: float = 0.0
    wavelength: float = 1.5
    slope_deg: float = 0.0
    slope_azimuth_deg: float = 0.0
    seed: int = 0
    texture: str = "regolith"
    texture_tile: float = 2.0
    texture_px: int = 1024

    @property
    def checker_square(self) -> float | None:
        """Edge of one square of the ``checkerboard`` texture [m], else None.

        On flat ground without slope the board's corners lie exactly at integer multiples of
        this length in world x and y, at z = 0.
        """
        if self.texture != "checkerboard":
            return None
        return self.texture_tile / CHECKER_SQUARES_PER_TILE

    def __post_init__(self) -> None:
        for i, v in enumerate(self.size):
            check_range(f"size[{i}]", v, 2.0, 500.0)
        check_range("cell", self.cell, 0.02, 1.0)
        check_range("roughness", self.roughness, 0.0, 0.5)
        check_range("wavelength", self.wavelength, 2 * self.cell, 100.0)
        check_range("slope_deg", self.slope_deg, 0.0, 35.0)
        check_range("slope_azimuth_deg", self.slope_azimuth_deg, -360.0, 360.0)
        check_range("texture_tile", self.texture_tile, 0.1, 100.0)
        check_range("texture_px", self.texture_px, 16, 8192)
        if self.kind == "rough":
            points = self.grid_points
            if points > MAX_HEIGHTFIELD_POINTS:
                raise ConfigError(
                    f"size {list(self.size)} m at cell {self.cell} m is a heightfield of {points:,} points; "
                    f"at most {MAX_HEIGHTFIELD_POINTS:,} fit the memory budget "
                    "(docs/rover_and_scenarios.md): use a larger cell or a smaller terrain"
                )
        if self.kind == "flat" and self.roughness > 0:
            raise ConfigError("roughness: must be 0 for kind 'flat' (use kind 'rough')")
        if self.kind == "rough" and self.roughness == 0:
            raise ConfigError("roughness: must be > 0 for kind 'rough'")
        if not self.texture:
            raise ConfigError("texture: must name a preset or an image file")

    @property
    def grid_points(self) -> int:
        """Points of the rough terrain's heightfield grid (its rows times its columns)."""
        nx, ny = (int(math.ceil(s / self.cell)) + 1 for s in self.size)
        return nx * ny

    @property
    def slope(self) -> float:
        """Inclination [rad]."""
        return math.radians(self.slope_deg)

    @property
    def slope_azimuth(self) -> float:
        """Direction of steepest ascent [rad]."""
        return math.radians(self.slope_azimuth_deg)


@dataclass(frozen=True)
class FrictionPatch:
    """A region of the ground with its own friction coefficient.

    Attributes:
        mu: Coulomb friction coefficient in the region, 0.05 to 1.5.
        center: Region centre in the world x-y plane [m].
        shape: ``"rect"`` or ``"circle"``.
        size: Rectangle extent along its own x and y before rotation [m].
        yaw_deg: Rectangle rotation about world z [deg].
        radius: Circle radius [m].
        slip_loss: Loose soil: the share of ``mu`` a wheel loses by digging in when it spins
            (or skids) fully (0: firm ground). See :class:`FrictionMapConfig`.
        soil: Deformable soil in the region: a soil preset (``toyoura``, ``lunar_regolith``,
            ``mars_simulant``, ``dry_sand``, ...), a YAML file or a mapping
            (:class:`rover_env.config.soil.SoilConfig`). Wheels there sink and shear the soil
            (:mod:`rover_env.sim.terramechanics`) instead of touching the rigid ground; ``mu``
            and ``slip_loss`` do not apply to them. None: rigid ground.
    """

    mu: float
    center: tuple[float, float]
    shape: Literal["rect", "circle"] = "rect"
    size: tuple[float, float] = (2.0, 2.0)
    yaw_deg: float = 0.0
    radius: float = 1.0
    slip_loss: float = 0.0
    soil: Any = None

    def __post_init__(self) -> None:
        check_range("mu", self.mu, 0.05, 1.5)
        check_range("slip_loss", self.slip_loss, 0.0, 0.9)
        if self.soil is not None:
            from rover_env.config.soil import SoilConfig

            object.__setattr__(self, "soil", SoilConfig.from_dict(self.soil))
        for i, v in enumerate(self.size):
            check_range(f"size[{i}]", v, 0.0, 1000.0, lo_open=True)
        check_range("radius", self.radius, 0.0, 1000.0, lo_open=True)


@dataclass(frozen=True)
class FrictionMapConfig:
    """Friction over the ground: a default and patches; later patches override earlier ones.

    On a loose-soil patch (``slip_loss`` > 0) a wheel that spins or skids digs in and loses grip,
    as sand shears under it (slip sinkage): its friction is mu (1 - slip_loss * dig) with

        dig = clip((|s| - critical_slip) / (1 - critical_slip), 0, 1) * clip(u / dig_speed, 0, 1),

    s the wheel's slip ratio and u = |omega r - v_long| its slip speed, updated at every control
    step from the simulator's state. Up to ``critical_slip`` the soil holds, and a wheel that
    creeps (u small) does not dig, so a rover can start from rest.

    Attributes:
        default_mu: Friction outside the patches.
        patches: Regions of other friction.
        critical_slip: Slip ratio up to which loose soil keeps its grip.
        dig_speed: Slip speed [m/s] at and above which a wheel past ``critical_slip`` digs fully.
    """

    default_mu: float = 0.9
    patches: tuple[FrictionPatch, ...] = ()
    critical_slip: float = 0.2
    dig_speed: float = 0.2

    def __post_init__(self) -> None:
        check_range("default_mu", self.default_mu, 0.05, 1.5)
        check_range("critical_slip", self.critical_slip, 0.0, 1.0, hi_open=True)
        check_range("dig_speed", self.dig_speed, 0.0, 10.0, lo_open=True)


def cloud_shade(bands, sun, points) -> np.ndarray:
    """Factor (N,) on the direct sunlight at world ``points`` (N, 3) [m] under cloud-shadow ``bands``.

    ``bands``: :meth:`SunConfig.cloud_bands`; ``sun``: unit vector toward the sun. A point's place
    in a band is that of where its ray to the sun meets the ground plane z = 0; the band's cover
    rises linearly over its ``edge`` at both ends.
    """
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    out = np.ones(len(p))
    if not bands:
        return out
    s = np.asarray(sun, dtype=np.float64)
    q = p[:, :2] - p[:, 2:3] * (s[:2] / max(float(s[2]), 1e-6))[None]
    for dx, dy, lead, length, trans, edge in bands:
        u = q[:, 0] * dx + q[:, 1] * dy - lead
        cover = np.clip(0.5 - u / edge, 0.0, 1.0) * np.clip(0.5 + (u + length) / edge, 0.0, 1.0)
        out *= 1.0 - cover * (1.0 - trans)
    return out


#: Cloud shadows a scenario may hold (:attr:`SunConfig.cloud_shadows`; the GL renderer's limit).
MAX_CLOUD_SHADOWS = 4


@dataclass(frozen=True)
class SunConfig:
    """Directional sunlight, which may move and be dimmed during a mission.

    Attributes:
        azimuth_deg: Direction toward the sun in the ground plane, counter-clockwise from
            world x [deg], at t = 0.
        elevation_deg: Sun height above the horizon [deg], at t = 0.
        azimuth_rate_deg_s: The sun's azimuth change per second of mission time [deg/s].
        elevation_rate_deg_s: The sun's elevation change per second [deg/s]; the elevation is
            held within 1..90 deg.
        clouds: Clouds passing in front of the sun: (start [s], end [s], transmission [0..1],
            ramp [s]) each. Between start and end the direct sunlight is multiplied by the
            transmission (the sky light stays), reached over ``ramp`` seconds at both ends (0: a
            step). Where clouds overlap their transmissions multiply.
        cloud_shadows: Clouds' shadows that sweep over the ground with the wind: (t_enter [s],
            speed [m/s], heading_deg, length [m], transmission [0..1], edge [m]) each. The
            shadow is a band ``length`` metres deep along the wind (unbounded across it), moving toward
            ``heading_deg`` (counter-clockwise from world x) at ``speed``; its leading edge
            crosses the world origin at ``t_enter``; inside it the direct sunlight is multiplied
            by ``transmission``, reached over an ``edge`` metres wide penumbra. The band lies in
            the cloud layer and falls along the sun's rays (a point's place in it is that of
            where its ray to the sun meets the ground plane z = 0). The GL renderer draws it per
            pixel; TinyRenderer dims the whole view by its value at the camera.
    """

    azimuth_deg: float = 180.0
    elevation_deg: float = 45.0
    azimuth_rate_deg_s: float = 0.0
    elevation_rate_deg_s: float = 0.0
    clouds: tuple[tuple[float, float, float, float], ...] = ()
    cloud_shadows: tuple[tuple[float, float, float, float, float, float], ...] = ()

    def __post_init__(self) -> None:
        check_range("azimuth_deg", self.azimuth_deg, -360.0, 360.0)
        check_range("elevation_deg", self.elevation_deg, 1.0, 90.0)
        check_range("azimuth_rate_deg_s", self.azimuth_rate_deg_s, -90.0, 90.0)
        check_range("elevation_rate_deg_s", self.elevation_rate_deg_s, -90.0, 90.0)
        for i, cloud in enumerate(self.clouds):
            key = f"clouds[{i}]"
            if len(cloud) != 4:
                raise ConfigError(f"{key}: {cloud!r}; give (start [s], end [s], transmission, ramp [s])")
            start, end, transmission, ramp = cloud
            check_range(f"{key}.start", start, 0.0, 1e6)
            check_range(f"{key}.end", end, start, 1e6, lo_open=True)
            check_range(f"{key}.transmission", transmission, 0.0, 1.0)
            check_range(f"{key}.ramp", ramp, 0.0, 0.5 * (end - start))
        if len(self.cloud_shadows) > MAX_CLOUD_SHADOWS:
            raise ConfigError(
                f"cloud_shadows: {len(self.cloud_shadows)} given; at most {MAX_CLOUD_SHADOWS} are drawn"
            )
        for i, band in enumerate(self.cloud_shadows):
            key = f"cloud_shadows[{i}]"
            if len(band) != 6:
                raise ConfigError(
                    f"{key}: {band!r}; give (t_enter [s], speed [m/s], heading_deg, length [m], "
                    "transmission, edge [m])"
                )
            t_enter, speed, heading, length, transmission, edge = band
            check_range(f"{key}.t_enter", t_enter, -1e6, 1e6)
            check_range(f"{key}.speed", speed, 0.0, 100.0)
            check_range(f"{key}.heading_deg", heading, -360.0, 360.0)
            check_range(f"{key}.length", length, 0.0, 1e5, lo_open=True)
            check_range(f"{key}.transmission", transmission, 0.0, 1.0)
            check_range(f"{key}.edge", edge, 0.0, 1e3, lo_open=True)

    def direction(self, t: float = 0.0) -> np.ndarray:
        """Unit vector from the ground toward the sun at mission time ``t`` [s], world frame."""
        az = math.radians(self.azimuth_deg + self.azimuth_rate_deg_s * t)
        el = math.radians(min(max(self.elevation_deg + self.elevation_rate_deg_s * t, 1.0), 90.0))
        return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])

    def cloud_bands(self, t: float) -> tuple[tuple[float, ...], ...]:
        """The cloud shadows at mission time ``t`` [s].

        Each is (d_x, d_y, lead [m], length [m], transmission, edge [m]): ``d`` the unit wind
        direction and ``lead`` the leading edge's place along it, from the world origin.
        """
        out = []
        for t_enter, speed, heading, length, trans, edge in self.cloud_shadows:
            h = math.radians(heading)
            out.append((math.cos(h), math.sin(h), speed * (t - t_enter), length, trans, edge))
        return tuple(out)

    def shade(self, points, t: float) -> np.ndarray:
        """Factor (N,) on the direct sunlight at world ``points`` (N, 3) [m] from the cloud shadows."""
        return cloud_shade(self.cloud_bands(t), self.direction(t), points)

    def transmission(self, t: float) -> float:
        """Share of the direct sunlight that reaches the ground at mission time ``t`` [s] (1: no cloud)."""
        out = 1.0
        for start, end, trans, ramp in self.clouds:
            if start <= t <= end:
                edge = min(t - start, end - t)
                k = 1.0 if ramp <= 0 else min(edge / ramp, 1.0)
                out *= 1.0 - k * (1.0 - trans)
        return out


@dataclass(frozen=True)
class CourseConfig:
    """The waypoint course of the driving task.

    Attributes:
        waypoints: Waypoints in the world x-y plane [m], driven in order from the start.
        tolerance: Distance at which a waypoint counts as reached [m]. The last one is reached
            when the rover is within it *and* has passed the goal (crossed the line through it
            square to the last segment), so that it drives to the goal instead of stopping at
            the edge of the circle; the judge counts a success when the true position is within
            it then.
        speed: Nominal cruise speed for controllers [m/s].
    """

    waypoints: tuple[tuple[float, float], ...]
    tolerance: float = 0.5
    speed: float = 0.8

    def __post_init__(self) -> None:
        if len(self.waypoints) < 1:
            raise ConfigError("waypoints: need at least one waypoint")
        check_range("tolerance", self.tolerance, 0.05, 10.0)
        check_range("speed", self.speed, 0.0, 5.0, lo_open=True)


@dataclass(frozen=True)
class StartConfig:
    """Start pose of the rover and its random variation at reset.

    Attributes:
        position: Body centre start position in the world x-y plane [m].
        yaw_deg: Start heading, counter-clockwise from world x [deg].
        jitter_position: Radius of a uniform random offset added at reset [m].
        jitter_yaw_deg: Half-width of a uniform random heading offset at reset [deg].
        fix_std: Standard deviations of the start fix with estimated observations: (position
            per axis [m], yaw [deg]). Dead reckoning starts from the true start pose plus
            Gaussian noise of these deviations, drawn from the episode's seeded generator: what
            a rover's localisation gives before a traverse. (0, 0) starts it at the exact true
            pose, an oracle no real rover has.
    """

    position: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    jitter_position: float = 0.0
    jitter_yaw_deg: float = 0.0
    fix_std: tuple[float, float] = (0.05, 1.0)

    def __post_init__(self) -> None:
        check_range("yaw_deg", self.yaw_deg, -360.0, 360.0)
        check_range("jitter_position", self.jitter_position, 0.0, 5.0)
        check_range("jitter_yaw_deg", self.jitter_yaw_deg, 0.0, 180.0)
        if len(self.fix_std) != 2:
            raise ConfigError(
                f"fix_std: give [position std in m, yaw std in deg], got {list(self.fix_std)!r}"
            )
        check_range("fix_std[0]", self.fix_std[0], 0.0, 10.0)
        check_range("fix_std[1]", self.fix_std[1], 0.0, 180.0)

    @property
    def yaw(self) -> float:
        """Start heading [rad]."""
        return math.radians(self.yaw_deg)


@dataclass(frozen=True)
class ScenarioConfig:
    """A complete driving scenario. See the shipped YAML presets for examples.

    Attributes:
        name: Short identifier.
        course: The waypoint course.
        description: One line for listings.
        terrain: Ground shape and texture.
        friction: Friction map.
        sun: Sun direction.
        start: Start pose.
        duration: Episode time limit [s].
        imu: The rover's IMU for estimated observations: a preset name or a mapping (``preset``
            and overrides; see :meth:`rover_env.config.imu.ImuConfig.from_dict`), or None (no
            IMU). The environment's ``imu`` keyword, when given, takes its place. With a ``rig``,
            the IMU is declared in the rig instead.
        rig: The rover's sensors in sampling order (:class:`~rover_env.config.rig.SensorConfig`);
            None: the standard rig (:func:`~rover_env.config.rig.standard_rig`: the fisheye,
            the downward camera and the ``imu`` if any).
        randomize: Domain randomisation of each episode's world: ``"off"`` (or absent), ``"on"``
            (the default ranges) or a mapping of ranges (:mod:`rover_env.config.randomize`).
        stuck_after: The judge ends an episode as ``"stuck"`` when, over this many seconds, the
            rover's body moved less than 0.1 m while its treads turned through 0.5 m or more
            [s]; None (the default): never.
    """

    name: str
    course: CourseConfig
    description: str = ""
    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    friction: FrictionMapConfig = field(default_factory=FrictionMapConfig)
    sun: SunConfig = field(default_factory=SunConfig)
    start: StartConfig = field(default_factory=StartConfig)
    duration: float = 60.0
    imu: Any = None
    rig: tuple[SensorConfig, ...] | None = None
    randomize: Any = None
    stuck_after: float | None = None

    def __post_init__(self) -> None:
        check_range("duration", self.duration, 0.1, 36000.0)
        if self.stuck_after is not None:
            check_range("stuck_after", self.stuck_after, 0.5, 3600.0)
        randomize_config(self.randomize)  # ConfigError naming the key
        if self.imu is not None:
            # validated here (ConfigError naming the key): a preset name or a mapping
            imu_config(self.imu)
        if self.rig is not None:
            if self.imu is not None:
                raise ConfigError("imu: this scenario declares a rig; declare its IMU there (kind: imu)")
            check_rig(self.rig)
        hx, hy = self.terrain.size[0] / 2 - 1.0, self.terrain.size[1] / 2 - 1.0
        points = [("start.position", self.start.position)] + [
            (f"course.waypoints[{i}]", w) for i, w in enumerate(self.course.waypoints)
        ]
        for key, (x, y) in points:
            if abs(x) > hx or abs(y) > hy:
                raise ConfigError(
                    f"{key}: ({x:g}, {y:g}) is outside the terrain (|x| <= {hx:g}, |y| <= {hy:g}"
                    " m, 1 m from the edge); enlarge terrain.size or move the point"
                )


def scenario_rig(scenario: ScenarioConfig) -> tuple[SensorConfig, ...]:
    """The sensors ``scenario``'s rover carries: its ``rig``, or the standard rig."""
    return scenario.rig if scenario.rig is not None else standard_rig(scenario.imu)


def _preset_dir() -> resources.abc.Traversable:
    return resources.files("rover_env.config") / "scenarios"


def preset_path(name: str) -> resources.abc.Traversable:
    """Where the shipped scenario preset ``name`` is (a YAML file in the installed package)."""
    return _preset_dir() / f"{name}.yaml"


def list_scenarios() -> list[str]:
    """Names of the shipped scenario presets."""
    return sorted(p.name[: -len(".yaml")] for p in _preset_dir().iterdir() if p.name.endswith(".yaml"))


def load_scenario(scenario: str | Path | ScenarioConfig) -> ScenarioConfig:
    """Load a scenario from a preset name, a YAML path, or pass a config through.

    A YAML file may start from a shipped preset: ``base: NAME`` takes the preset's keys, and
    the file's other top-level keys replace the preset's whole (``base: flat_patches`` with a
    ``rig:`` is that mission with other sensors).

    Args:
        scenario: A name from :func:`list_scenarios`, a path to a YAML file, or a
            :class:`ScenarioConfig`.

    Returns:
        The validated scenario, with a relative texture path resolved against the YAML file.

    Raises:
        ConfigError: Unknown preset, missing file, or invalid content (naming file and key).
    """
    if isinstance(scenario, ScenarioConfig):
        return scenario
    text = str(scenario)
    if isinstance(scenario, str) and not text.endswith((".yaml", ".yml")) and "/" not in text:
        names = list_scenarios()
        if text not in names:
            raise ConfigError(
                f"unknown scenario preset {text!r}; presets: {', '.join(names)} "
                "(or pass the path of a YAML file)"
            )
        with resources.as_file(_preset_dir() / f"{text}.yaml") as path:
            return load_yaml_dataclass(ScenarioConfig, path)
    path = Path(scenario)
    data = read_yaml(path)
    if isinstance(data, dict) and "base" in data:
        base = data["base"]
        if not isinstance(base, str) or base not in list_scenarios():
            raise ConfigError(
                f"{path}: base: {base!r}; name a shipped scenario preset ({', '.join(list_scenarios())})"
            )
        with resources.as_file(preset_path(base)) as base_path:
            merged = dict(read_yaml(base_path)) | {k: v for k, v in data.items() if k != "base"}
        try:
            cfg = from_dict(ScenarioConfig, merged)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    else:
        cfg = load_yaml_dataclass(ScenarioConfig, path)
    tex = cfg.terrain.texture
    if tex not in TEXTURE_PRESETS:
        tex_path = Path(tex)
        if not tex_path.is_absolute():
            tex_path = (path.parent / tex_path).resolve()
        if not tex_path.is_file():
            raise ConfigError(
                f"{path}: terrain.texture: {tex!r} is neither a preset "
                f"({', '.join(TEXTURE_PRESETS)}) nor an existing image file"
            )
        cfg = replace(cfg, terrain=replace(cfg.terrain, texture=str(tex_path)))
    return cfg

"""The sensor rig a scenario declares, and the camera presets of the estimator in the loop.

A scenario's ``rig`` lists the rover's sensors in the order the simulation samples them; each
has a name (the ``sensor`` of its messages), a kind, and optionally a rate, a mount and the
settings of its kind. Without a ``rig`` a rover carries the standard one
(:func:`standard_rig`): the fisheye, the downward camera and, if the scenario names an IMU,
the IMU and a sun sensor. Example (the downward camera 10 cm ahead of its standard mount,
x = 0.95 m on the mast, at 60 Hz; an IMU at 120 Hz and a sun sensor)::

    rig:
      - {name: fisheye, kind: fisheye}
      - {name: downward, kind: pinhole, rate_hz: 60, mount: {position: [1.05, 0.0, 0.535]}}
      - {name: imu, kind: imu, rate_hz: 120, imu: bmi088}
      - {name: sun, kind: sun, sun: nfss411}

The built-in estimator takes one fisheye and at most one pinhole camera (and an IMU and a sun
sensor if there are): without the pinhole camera it is the one-camera rig
(:func:`fisheye_only_rig`), the fisheye giving the odometry too; a rig with other sensors or
more of them needs an estimator of your own that takes it.

Frames: a mount is the sensor's frame in the body frame (x forward, y left, z up), "body from
sensor", as a 4 x 4 matrix or as ``position`` [m] and ``rpy`` [rad] (roll, pitch, yaw about the
body's fixed x, y, z axes, applied in that order). A camera's frame is its optical frame (z along
the optical axis, x along image rows, y down the image).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal, get_args

import numpy as np

from perception.models.calib_io import check_rigid
from rover_env.config.cameras import CameraConfig, DownwardCameraConfig, FisheyeCameraConfig
from rover_env.config.imu import ImuConfig
from rover_env.config.io import ConfigError, check_range, from_dict
from rover_env.config.proprio import encoder_config, motor_config
from rover_env.config.sun_sensor import SunSensorConfig

#: The kinds of sensor a rig may hold: a downward pinhole camera, a downward fisheye, an IMU, a
#: sun sensor, wheel encoders, the drive motors' currents, the command in force.
SensorKind = Literal["pinhole", "fisheye", "imu", "sun", "wheel_encoders", "motor_current", "command"]
SENSOR_KIND_NAMES: tuple[str, ...] = get_args(SensorKind)

#: The estimator-in-the-loop presets (:data:`PERCEPTION_PRESETS`).
PresetName = Literal["eval", "train"]

#: The standard mounts' orientations as ``rpy`` [rad] (body from sensor): the downward camera's
#: image up is body forward; the fisheye's image x is body forward; both look down. (An IMU's
#: standard mount is where its settings put it.)
STANDARD_RPY: dict[str, tuple[float, float, float]] = {
    "pinhole": (math.pi, 0.0, -math.pi / 2),
    "fisheye": (math.pi, 0.0, 0.0),
    "imu": (0.0, 0.0, 0.0),
    "sun": (0.0, 0.0, 0.0),
    "wheel_encoders": (0.0, 0.0, 0.0),
    "motor_current": (0.0, 0.0, 0.0),
    "command": (0.0, 0.0, 0.0),
}

#: The proprioceptive kinds: they read the rover's joints, so have no mount of their own.
PROPRIO_KINDS: tuple[str, ...] = ("wheel_encoders", "motor_current", "command")


def mount_matrix(position, rpy) -> np.ndarray:
    """The (4, 4) body-from-sensor pose of a sensor at ``position`` [m] turned by ``rpy`` [rad]."""
    T = np.eye(4)
    from scipy.spatial.transform import Rotation  # here: the command line starts without SciPy

    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = position
    return T


def _mount(value: Any) -> Any:
    """A scenario's mount, checked: None, ``{position, rpy}`` (either optional) or a 4 x 4 rigid matrix.

    Returned in its own form (a mapping of tuples, or 4 x 4 rows), so that a configuration
    written out (:func:`rover_env.config.io.to_dict`) reads back the same.
    """
    if value is None:
        return None
    if isinstance(value, dict):
        unknown = sorted(set(value) - {"position", "rpy"}, key=str)
        if unknown:
            raise ConfigError(f"mount: unknown key {unknown[0]!r}; give position [m] and/or rpy [rad]")
        pose = from_dict(_MountPose, value, "mount")
        return {k: v for k, v in (("position", pose.position), ("rpy", pose.rpy)) if v is not None}
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f"mount: {value!r}; give a 4 x 4 matrix or position and rpy") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ConfigError(f"mount: {value!r}; give a 4 x 4 matrix of finite numbers (body from sensor)")
    try:
        check_rigid(T, "mount")
    except ConfigError as exc:
        raise ConfigError(f"{exc}; a mount is a rigid transform (rotation and translation)") from None
    return tuple(tuple(float(v) for v in row) for row in T)


@dataclass(frozen=True)
class _MountPose:
    position: tuple[float, float, float] | None = None
    rpy: tuple[float, float, float] | None = None


_CAMERA_CONFIGS: dict[str, type[CameraConfig]] = {
    "pinhole": DownwardCameraConfig,
    "fisheye": FisheyeCameraConfig,
}


#: Each kind's settings key in a rig entry (None: it takes none).
_SETTINGS_KEY: dict[str, str | None] = {
    "pinhole": "camera",
    "fisheye": "camera",
    "imu": "imu",
    "sun": "sun",
    "wheel_encoders": "encoder",
    "motor_current": "motor",
    "command": None,
}


@dataclass(frozen=True)
class SensorConfig:
    """One sensor of a scenario's rig.

    Attributes:
        name: Its name: the ``sensor`` of its messages, the key in ``env.unwrapped.rig``.
        kind: ``"pinhole"``, ``"fisheye"``, ``"imu"``, ``"sun"`` (a sun sensor),
            ``"wheel_encoders"``, ``"motor_current"`` or ``"command"`` (:data:`PROPRIO_KINDS`).
        rate_hz: Samples per second [Hz]; must divide the physics rate (240 Hz: 240, 120, 80,
            60, 48, 40, 30, ...). None: the preset's (cameras), the part's own, or for a
            command the environment's control rate.
        mount: Body from sensor: a 4 x 4 rigid transform, or ``{position: [x, y, z], rpy: [r,
            p, y]}`` [m, rad], either of which may be left out and is then the standard
            mount's. None: the standard mount (the downward camera on the mast, the fisheye
            under the body, looking down as :data:`STANDARD_RPY` says; the IMU where its
            settings put it; the sun sensor on top of the mast, looking up).
        camera: A camera's settings that differ from the preset's: fields of
            :class:`~rover_env.config.cameras.DownwardCameraConfig` (pinhole) or
            :class:`~rover_env.config.cameras.FisheyeCameraConfig` (fisheye), except ``rate_hz``.
        imu: An IMU's settings: a preset name or a mapping (``preset`` and overrides, see
            :meth:`rover_env.config.imu.ImuConfig.from_dict`); None: ``bmi088``. Its
            ``rate_hz`` and mount above, when given, take the place of the settings'.
        sun: A sun sensor's settings: a preset name or a mapping (``preset`` and overrides, see
            :meth:`rover_env.config.sun_sensor.SunSensorConfig.from_dict`); None: ``nfss411``.
        encoder: Wheel encoders' settings: a preset name or a mapping (``preset`` and fields of
            :class:`~rover_env.config.proprio.EncoderConfig`); None: ``as5047p``.
        motor: Motor currents' settings: a preset name or a mapping (``preset`` and fields of
            :class:`~rover_env.config.proprio.MotorCurrentConfig`); None: ``dcx26``.
    """

    name: str
    kind: SensorKind
    rate_hz: float | None = None
    mount: Any = None
    camera: Any = None
    imu: Any = None
    sun: Any = None
    encoder: Any = None
    motor: Any = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise ConfigError(f"name: {self.name!r}; give each sensor a non-empty name")
        if self.kind not in SENSOR_KIND_NAMES:
            raise ConfigError(
                f"kind: {self.kind!r} (sensor {self.name!r}); use one of {list(SENSOR_KIND_NAMES)}"
            )
        if self.rate_hz is not None:
            check_range("rate_hz", self.rate_hz, 0.0, 10000.0, lo_open=True)
        object.__setattr__(self, "mount", _mount(self.mount))
        if self.mount is not None and self.kind in PROPRIO_KINDS:
            raise ConfigError(
                f"mount: sensor {self.name!r} is {self.kind}, which reads the joints; leave mount out"
            )
        settings = _SETTINGS_KEY[self.kind]
        for key in ("camera", "imu", "sun", "encoder", "motor"):
            if getattr(self, key) is not None and key != settings:
                how = f"give its settings as {settings}" if settings else "it takes only rate_hz"
                raise ConfigError(f"{key}: sensor {self.name!r} is of kind {self.kind}; {how}")
        if self.encoder is not None:
            encoder_config(self.encoder)  # validated here
        if self.motor is not None:
            motor_config(self.motor)  # validated here
        if self.camera is not None:
            if not isinstance(self.camera, dict):
                raise ConfigError(f"camera: {self.camera!r}; give a mapping of camera settings")
            if "rate_hz" in self.camera:
                raise ConfigError(f"camera.rate_hz: give sensor {self.name!r}'s rate as its rate_hz")
            from_dict(_CAMERA_CONFIGS[self.kind], self.camera, "camera")  # validated here
        if self.imu is not None:
            imu_config(self.imu)  # validated here
        if self.sun is not None:
            SunSensorConfig.from_dict(self.sun)  # validated here

    def mount_or(self, standard: np.ndarray) -> np.ndarray:
        """The (4, 4) mount; ``standard`` (the sensor's mount without one) fills what it leaves out."""
        T = np.array(standard, dtype=np.float64)
        if isinstance(self.mount, dict):
            if "position" in self.mount:
                T[:3, 3] = self.mount["position"]
            if "rpy" in self.mount:
                T[:3, :3] = mount_matrix((0.0, 0.0, 0.0), self.mount["rpy"])[:3, :3]
        elif self.mount is not None:
            T = np.array(self.mount, dtype=np.float64)
        return T

    def camera_config(self, preset: CameraConfig) -> CameraConfig:
        """This camera's configuration: ``preset`` with this sensor's rate and settings."""
        changes = dict(self.camera or {})
        if self.rate_hz is not None:
            changes["rate_hz"] = self.rate_hz
        if isinstance(changes.get("sensor"), dict):  # figures over the preset camera's sensor
            merged = dataclasses.asdict(preset.sensor) | changes["sensor"]
            changes["sensor"] = from_dict(type(preset.sensor), merged, "camera.sensor")
        return dataclasses.replace(preset, **changes) if changes else preset


def imu_config(imu: Any) -> ImuConfig:
    """An :class:`~rover_env.config.imu.ImuConfig` from a preset name, a mapping or itself."""
    if isinstance(imu, ImuConfig):
        return imu
    return ImuConfig.from_dict({"preset": imu} if isinstance(imu, str) else imu)


def check_rig(rig: tuple[SensorConfig, ...]) -> None:
    """Reject a rig with two sensors of one name (:class:`ConfigError` naming the key)."""
    seen: dict[str, int] = {}
    for i, s in enumerate(rig):
        if s.name == "fisheye_windowed":  # the pipeline's count of windowed fisheye frames
            raise ConfigError(f"rig[{i}].name: 'fisheye_windowed' is reserved; give the sensor another name")
        if s.name in seen:
            raise ConfigError(
                f"rig[{i}].name: {s.name!r} is also rig[{seen[s.name]}]'s; give each sensor its own name"
            )
        seen[s.name] = i


def with_imu(rig: tuple[SensorConfig, ...], imu: Any) -> tuple[SensorConfig, ...]:
    """``rig`` with ``imu`` (settings, as in :attr:`SensorConfig.imu`) as its IMU.

    The rig's IMU is replaced in its place (keeping its name, rate and mount); a rig without
    one gets the sensor ``"imu"`` last.

    Raises:
        ConfigError: The rig has several IMUs (say which one in the scenario instead).
    """
    found = [i for i, s in enumerate(rig) if s.kind == "imu"]
    if len(found) > 1:
        names = [rig[i].name for i in found]
        raise ConfigError(f"imu: the rig has IMUs {names}; give each one's settings in the scenario's rig")
    if not found:
        return rig + (SensorConfig("imu", "imu", imu=imu),)
    i = found[0]
    return rig[:i] + (dataclasses.replace(rig[i], imu=imu),) + rig[i + 1 :]


def standard_rig(imu: Any = None) -> tuple[SensorConfig, ...]:
    """The rig of a scenario that declares none: the fisheye, the downward camera, ``imu`` and a sun sensor.

    The IMU and the sun sensor (``"sun"``, an NFSS-411 on the mast) come together: the sun
    sensor gives the heading only with the tilt the IMU measures. Declare a ``rig`` for one
    without the other.

    Args:
        imu: The scenario's IMU (a preset name or a mapping), or None for neither.
    """
    rig = (SensorConfig("fisheye", "fisheye"), SensorConfig("downward", "pinhole"))
    if imu is None:
        return rig
    return rig + (SensorConfig("imu", "imu", imu=imu), SensorConfig("sun", "sun"))


#: The rigs the environment's ``rig`` keyword names (:func:`named_rig`).
RIG_NAMES: tuple[str, ...] = ("standard", "fisheye_only", "full")

#: The one-camera rig's fisheye also renders the ground its odometry tracks: the rays within
#: this angle of the body's -z [deg] (split into the cube's faces). Its odometry fits the motion
#: to the ground within 60 degrees (:data:`perception.odometry.fisheye.TRACK_FREE_DEG`; 0.25 m
#: of the camera's foot) and finds the wheels' tracks in the ring beyond, to 70 degrees: the
#: ground there has the height of the wheels' contacts, which sets its scale on rough ground.
FISHEYE_ONLY_GROUND_DEG = 75.0

#: The one-camera rig's fisheye settings (:class:`rover_env.config.cameras.FisheyeCameraConfig`
#: fields): the ground view above, rendered at the same resolution as the kinematics' parts.
FISHEYE_ONLY_CAMERA: dict[str, float] = {"roi_ground_deg": FISHEYE_ONLY_GROUND_DEG, "ground_oversample": 1.0}


def fisheye_only_rig(imu: Any = None) -> tuple[SensorConfig, ...]:
    """The one-camera rig: the fisheye alone (its odometry, kinematics and wheels), ``imu`` and a sun sensor.

    The fisheye renders the ground its odometry tracks as well as the parts the kinematics reads
    (``roi_ground_deg``). With ``imu`` None, neither an IMU nor a sun sensor.
    """
    rig: tuple[SensorConfig, ...] = (SensorConfig("fisheye", "fisheye", camera=dict(FISHEYE_ONLY_CAMERA)),)
    if imu is None:
        return rig
    return rig + (SensorConfig("imu", "imu", imu=imu), SensorConfig("sun", "sun"))


def full_rig(imu: Any = None) -> tuple[SensorConfig, ...]:
    """The standard rig with an IMU (``imu``, None: the BMI088), a sun sensor and proprioception.

    The proprioceptive sensors are the wheel encoders (``"encoders"``), the drive motors'
    currents (``"currents"``) and the command in force (``"command"``).
    """
    return standard_rig("bmi088" if imu is None else imu) + (
        SensorConfig("encoders", "wheel_encoders"),
        SensorConfig("currents", "motor_current"),
        SensorConfig("command", "command"),
    )


def named_rig(name: str, imu: Any = None) -> tuple[SensorConfig, ...]:
    """The rig called ``name`` (:data:`RIG_NAMES`) with ``imu`` (and then a sun sensor), or ConfigError.

    ``"full"`` always has an IMU (the BMI088 if ``imu`` is None).
    """
    if name == "standard":
        return standard_rig(imu)
    if name == "fisheye_only":
        return fisheye_only_rig(imu)
    if name == "full":
        return full_rig(imu)
    raise ConfigError(
        f"rig: {name!r}; use one of {list(RIG_NAMES)} (or declare the sensors in the scenario's rig)"
    )


@dataclass(frozen=True)
class PerceptionPreset:
    """Camera configurations of the estimator in the loop.

    Attributes:
        name: Preset name.
        downward: The downward camera (its rate is the odometry's).
        fisheye: The fisheye (its rate is the kinematics').
        odometry: Odometry parameters that differ from
            :meth:`FlowOdometryConfig.for_camera` of the downward camera.
        fisheye_window: (axle roll [rad/s], axle travel [m/s], wheel steering [rad/s]): while
            the kinematics estimator tracks every marker and joint, the fisheye renders only the
            windows that hold the wheels, arms and markers over the joint states these rates
            reach in one frame from its last estimate
            (:func:`~perception.models.rover_parts.joint_window_parts`),
            as a sensor's tracker-driven windowed readout; otherwise, and with None, its whole
            image (or region of interest). The steering rate is raised to 1.25 times the
            rover's ``steer_max_rate`` if it is below (an inner wheel turns faster than its axle).
    """

    name: str
    downward: DownwardCameraConfig
    fisheye: FisheyeCameraConfig
    odometry: dict = field(default_factory=dict, hash=False)
    fisheye_window: tuple[float, float, float] | None = None


def _presets() -> dict[str, PerceptionPreset]:
    return {
        # the papers' resolutions and rates. The downward camera sees no ground beyond 2 m, so only
        # that is drawn for it. The fisheye reads out what the kinematics estimator can use, as
        # the train preset does: its region of interest, and while it tracks every joint only
        # the windows about them (the pixels the estimator reads, along the same rays, see the
        # tests); this cuts its rendering time by 40 % at 640 x 480 (benchmarks/ablations.py
        # fisheye_readout)
        "eval": PerceptionPreset(
            "eval",
            DownwardCameraConfig.preset("full", rate_hz=60.0, ground_range=2.0),
            FisheyeCameraConfig.preset("full", roi=True, ground_range=2.0),
            fisheye_window=(1.8, 0.3, 0.0),
        ),
        # the lowest resolutions at which the estimators hold up: below 320x240 the fisheye's
        # tread texture is too coarse for the wheel rates, and below 30 Hz the wheels turn too
        # far between frames at 2 m/s; the fisheye renders only its region of interest, and
        # both cameras draw only the exact ground within 2 m. At 160 px a feature's track is
        # noisy, and the yaw rate rests on how far apart the features lie: twice the paper's
        # 40-50 features, out to 8 px from the border (a 2 m/s frame step), lower its error
        # by a tenth (benchmarks/ablations.py features)
        # The downward camera stays at 30 Hz too: at 15 Hz (half its rendering and odometry time)
        # slip while slipping was 0.44 MAE against 0.025 over the four missions, 0.62 against
        # 0.021 on loose slope, and slip-event F1 0.90 against 0.99 (benchmarks/slip_accuracy.py
        # --preset train, seeds 201-203, GL)
        "train": PerceptionPreset(
            "train",
            DownwardCameraConfig.preset("train", rate_hz=30.0, ground_range=2.0),
            FisheyeCameraConfig.preset("half", rate_hz=30.0, roi=True, ground_range=2.0),
            odometry={"roi_margin": 0.05, "max_features": 100},
            # windows: roll and travel at 1.8 rad/s and 0.3 m/s (the 99th percentiles of their
            # frame-to-frame changes on rough ground are half that), steering at the rover's limit
            fisheye_window=(1.8, 0.3, 0.0),
        ),
    }


#: The presets by name (:data:`PresetName`).
PERCEPTION_PRESETS: dict[str, PerceptionPreset] = _presets()

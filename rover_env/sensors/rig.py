"""The estimator in the loop: the rover's sensors sampled by the simulation, an estimator on their messages.

:class:`PerceptionPipeline` builds the rig of one :class:`RoverSim` (the downward camera, the
fisheye and, if fitted, the IMU, attached as sensors that the simulation samples at their exact
times while it steps), describes it as a :class:`perception.rig.Rig`, and runs an estimator on
the sensor messages (:mod:`perception.estimator`): the built-in :class:`perception.RoverEstimator`
by default, or any other made by a factory from the rig. The estimator sees the messages, the
rig's calibrations and the start fix only, never the simulator; a sensor that takes requests
from it (the fisheye's windowed readout) gets them through :meth:`PerceptionPipeline.update`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from perception.estimator import EstimatorError, check_estimate, estimator_name
from perception.fusion.slip import SlipConfig
from perception.kinematics.fisheye import KinematicsConfig
from perception.odometry.fisheye import FisheyeOdometryConfig
from perception.odometry.flow import FlowOdometryConfig
from perception.rig import (
    EncoderModel,
    ImuModel,
    MotorModel,
    Rig,
    SensorMessage,
    SensorSpec,
    SunSensorModel,
    TriadFigures,
    read_only,
)
from perception.rover_estimator import IMU_CALIBRATION_S, STEP_KEYS, RoverEstimator, StepEstimate
from rover_env.config.imu import ImuConfig
from rover_env.config.io import ConfigError
from rover_env.config.proprio import CommandConfig, encoder_config, motor_config, with_rate
from rover_env.config.rig import (
    FISHEYE_ONLY_CAMERA,
    PERCEPTION_PRESETS,
    PROPRIO_KINDS,
    PerceptionPreset,
    PresetName,
    SensorConfig,
    check_rig,
    imu_config,
    mount_matrix,
    standard_rig,
)
from rover_env.config.sun_sensor import SunSensorConfig
from rover_env.sensors.cameras import DownwardCamera, FisheyeCamera
from rover_env.sensors.image_sensor import BAYER
from rover_env.sensors.imu import Imu
from rover_env.sensors.proprio import CommandSensor, MotorCurrents, WheelEncoders
from rover_env.sensors.sun_sensor import SunSensor
from rover_env.sim.simulation import RoverSim

log = logging.getLogger(__name__)

__all__ = [
    "IMU_CALIBRATION_S",
    "PERCEPTION_PRESETS",
    "STEP_KEYS",
    "PerceptionPipeline",
    "PerceptionPreset",
    "StepEstimate",
    "builtin_estimator",
    "rig_of",
]


def _figures(triad) -> TriadFigures:
    return TriadFigures(
        noise_density=triad.noise_density,
        bias_instability=triad.bias_instability,
        bias_random_walk=triad.bias_random_walk,
        turn_on_bias=triad.turn_on_bias,
        range=triad.range,
        misalignment=triad.misalignment,
    )


#: A simulated sensor: a camera, an IMU, a sun sensor or a proprioceptive one that the simulation samples.
SimSensor = DownwardCamera | FisheyeCamera | Imu | SunSensor | WheelEncoders | MotorCurrents | CommandSensor

#: A proprioceptive kind's settings key in a scenario's rig entry, for error messages.
_SETTINGS_NAME = {"wheel_encoders": "encoder", "motor_current": "motor"}


def build_sensor(
    sim: RoverSim,
    config: SensorConfig,
    preset: PerceptionPreset,
    key: str,
    declared: bool = True,
    control_hz: float = 30.0,
) -> SimSensor:
    """The simulated sensor ``config`` declares, on ``sim``'s rover (not yet attached).

    Args:
        sim: The simulation (its rover, sun and physics rate).
        config: The sensor's declaration.
        preset: The cameras' settings where ``config`` gives none.
        key: Its key in the scenario, for error messages: ``"rig[2]"`` in a declared rig, or
            the sensor's name in the standard rig (``"imu"``: the scenario's ``imu`` key).
        declared: It is an entry of the scenario's ``rig`` (its IMU settings under ``imu``).
        control_hz: The environment's control rate [Hz]: a command sensor's without its own.

    Raises:
        ConfigError: Its rate does not divide the physics rate (naming the key that set it).
    """
    if config.kind in PROPRIO_KINDS:
        part: Any
        if config.kind == "wheel_encoders":
            part = with_rate(encoder_config(config.encoder), config.rate_hz)
        elif config.kind == "motor_current":
            part = with_rate(motor_config(config.motor), config.rate_hz)
        else:
            part = CommandConfig(config.rate_hz)
        rate = part.rate_hz if part.rate_hz is not None else control_hz
        if config.kind == "command":  # its rate is its own or the control rate, which divides
            settings = key
        else:
            settings = f"{key}.{_SETTINGS_NAME[config.kind]}" if declared else key
    elif config.kind == "imu":
        imu = imu_config(config.imu if config.imu is not None else "bmi088")
        changes: dict[str, Any] = {}
        if config.rate_hz is not None:
            changes["rate_hz"] = config.rate_hz
        if config.mount is not None:
            T = config.mount_or(mount_matrix(imu.position, imu.rpy))
            changes["position"] = tuple(float(v) for v in T[:3, 3])
            changes["rpy"] = tuple(float(v) for v in Rotation.from_matrix(T[:3, :3]).as_euler("xyz"))
        imu = dataclasses.replace(imu, **changes) if changes else imu
        rate = imu.rate_hz
        settings = f"{key}.imu" if declared else key
    elif config.kind == "sun":
        sun = SunSensorConfig.from_dict(config.sun if config.sun is not None else "nfss411")
        if config.rate_hz is not None:
            sun = dataclasses.replace(sun, rate_hz=config.rate_hz)
        rate = sun.rate_hz
        settings = f"{key}.sun" if declared else key
    else:
        base = preset.downward if config.kind == "pinhole" else preset.fisheye
        try:
            cam_cfg = config.camera_config(base)
        except ConfigError as exc:
            raise ConfigError(f"{key}.{exc}") from None
        rate = cam_cfg.rate_hz
        settings = f"the preset {preset.name!r}'s {config.kind} camera"
    steps = (1.0 / sim.dt) / rate
    if abs(steps - round(steps)) > 1e-6 or round(steps) < 1:
        where = f"{key}.rate_hz" if config.rate_hz is not None else f"{settings}.rate_hz"
        raise ConfigError(
            f"{where}: {rate:g} Hz (sensor {config.name!r}) does not divide the physics rate "
            f"{1 / sim.dt:g} Hz; use a whole fraction of it (240, 120, 80, 60, 48, 40, 30 ... at 240 Hz)"
        )
    if config.kind == "wheel_encoders":
        return WheelEncoders(sim, part)
    if config.kind == "motor_current":
        return MotorCurrents(sim, part)
    if config.kind == "command":
        return CommandSensor(sim, part, control_hz)
    if config.kind == "imu":
        return Imu(sim, imu)
    if config.kind == "sun":
        return SunSensor(sim, sun, config.mount_or(SunSensor.standard_mount(sim.geometry)))
    if config.kind == "pinhole":
        standard = DownwardCamera.standard_mount(sim.geometry)
        return DownwardCamera(sim, cam_cfg, config.mount_or(standard))  # type: ignore[arg-type]
    if config.kind == "fisheye":
        standard = FisheyeCamera.standard_mount(sim.geometry)
        return FisheyeCamera(sim, cam_cfg, config.mount_or(standard))  # type: ignore[arg-type]
    raise ConfigError(f"{key}.kind: {config.kind!r}; no simulated sensor of this kind")


def _photometry(camera) -> dict[str, Any]:
    """A simulated camera's photometry, :class:`SensorSpec` keywords (none for rendered images).

    Its image sensor's output gamma, colour-filter array and lens vignetting.
    """
    if camera.image_sensor is None:
        return {}
    return {
        "gamma": float(camera.image_sensor.config.gamma),
        "bayer": BAYER,
        "vignetting": float(camera.image_sensor.config.vignetting),
    }


def rig_of(sim: RoverSim, sensors: Mapping[str, SimSensor]) -> Rig:
    """The :class:`perception.rig.Rig` of a simulated rover's sensors: what an estimator is given.

    The cameras' calibrations are their exact models (the simulation renders through them) and
    their image sensors' output gamma, vignetting and colour-filter array; the
    IMU's is its data sheet (its errors are drawn per episode, and not given away). The rover's
    kinematic model sees the markers through the rig's first fisheye (or where the standard
    fisheye would be).
    """
    g = sim.geometry
    specs = []
    for name, sensor in sensors.items():
        if isinstance(sensor, Imu):
            T = np.eye(4)
            T[:3, :3] = sensor.R_body_imu
            T[:3, 3] = sensor.r_body
            model = ImuModel(gyro=_figures(sensor.config.gyro), accel=_figures(sensor.config.accel))
            specs.append(SensorSpec(name, "imu", sensor.config.rate_hz, T, model))
        elif isinstance(sensor, SunSensor):
            c = sensor.config
            sun = SunSensorModel(c.fov_deg, c.accuracy_deg, c.noise_deg)
            specs.append(SensorSpec(name, "sun", c.rate_hz, sensor.T_body_sensor, sun))
        elif isinstance(sensor, WheelEncoders):
            ec = sensor.config
            encoders = EncoderModel(ec.counts_per_rev, ec.counter_bits)
            specs.append(SensorSpec(name, "wheel_encoders", ec.rate_hz, np.eye(4), encoders))
        elif isinstance(sensor, MotorCurrents):
            mc = sensor.config
            motor = MotorModel(**{k: getattr(mc, k) for k in MotorModel.__dataclass_fields__})
            specs.append(SensorSpec(name, "motor_current", mc.rate_hz, np.eye(4), motor))
        elif isinstance(sensor, CommandSensor):
            specs.append(SensorSpec(name, "command", sensor.rate_hz, np.eye(4), None))
        elif isinstance(sensor, FisheyeCamera):
            c = sensor.config
            rate, T = c.rate_hz, sensor.T_body_cam
            kw = _photometry(sensor)
            if c.roi and c.roi_ground_deg > 0.0:  # it reads out the ground within this angle
                kw["ground_view_deg"] = float(c.roi_ground_deg)
            specs.append(SensorSpec(name, "fisheye", rate, T, sensor.model, True, **kw))
        elif isinstance(sensor, DownwardCamera):
            rate, T = sensor.config.rate_hz, sensor.T_body_cam
            specs.append(SensorSpec(name, "pinhole", rate, T, sensor.model, **_photometry(sensor)))
        else:
            raise TypeError(
                f"sensor {name!r}: {type(sensor).__name__} has no rig spec; add its kind to rig_of"
            )
    fisheyes = [s for s in sensors.values() if isinstance(s, FisheyeCamera)]
    T_fish = fisheyes[0].T_body_cam if fisheyes else FisheyeCamera.standard_mount(g)
    return Rig(specs, vehicle=g.kinematic_model(T_fish), steer_max_rate=g.steer_max_rate)


#: A factory of estimators: called once per environment with its rig.
EstimatorFactory = Callable[[Rig], Any]


def builtin_estimator(
    preset: PresetName | PerceptionPreset = "train",
    *,
    odometry: FlowOdometryConfig | None = None,
    kinematics: KinematicsConfig | None = None,
    slip: SlipConfig | None = None,
    odometry_gyro: bool = True,
    odometry_overrides: Mapping[str, Any] | None = None,
    fisheye_window: tuple[float, float, float] | None | Literal["preset"] = "preset",
    fisheye_odometry: FisheyeOdometryConfig | None = None,
) -> EstimatorFactory:
    """A factory of the built-in :class:`perception.RoverEstimator` as ``preset`` sets it up, with changes.

    With no changes it builds what an environment builds without ``estimator=``; pass it as
    ``gym.make(ID, estimator=builtin_estimator("train", slip=SlipConfig(grip_std=0.0)))`` to
    run the built-in estimator with other parameters (an ablation).

    Args:
        preset: The preset whose odometry settings and fisheye windows are used.
        odometry: The odometry's whole configuration; None: :meth:`FlowOdometryConfig.for_camera`
            of the downward camera with the preset's settings and ``odometry_overrides``.
        kinematics: Fisheye-kinematics parameters (None: the defaults).
        slip: Slip-filter parameters (None: the defaults).
        odometry_gyro: Give the odometry's 3-D fit the gyro's roll and pitch rates (with an IMU).
        odometry_overrides: :class:`FlowOdometryConfig` fields set over the preset's: the
            downward camera's odometry. An unknown field is refused here; on a rig without a
            downward camera (the one-camera rig) any is refused when the estimator is built
            (give ``fisheye_odometry`` there).
        fisheye_window: The fisheye's windowed readout (see :class:`PerceptionPreset`):
            ``"preset"``, None (whole frames) or (roll [rad/s], travel [m/s], steering [rad/s]).
        fisheye_odometry: The fisheye odometry's parameters on a rig without a downward camera
            (None: :meth:`FisheyeOdometryConfig.for_ground_view` of the fisheye's ground view).
    """
    if isinstance(preset, str):
        if preset not in PERCEPTION_PRESETS:
            raise ConfigError(f"preset: {preset!r}; use one of {sorted(PERCEPTION_PRESETS)}")
        preset = PERCEPTION_PRESETS[preset]
    given = dict(odometry_overrides or {})
    unknown = sorted(set(given) - set(FlowOdometryConfig.__dataclass_fields__), key=str)
    if unknown:
        raise ConfigError(
            f"odometry_overrides: {unknown[0]!r} is not a FlowOdometryConfig field; use one of "
            f"{sorted(FlowOdometryConfig.__dataclass_fields__)}"
        )
    if odometry is not None and given:
        raise ConfigError(
            "odometry_overrides: give them in odometry= (a whole FlowOdometryConfig) or here, not both"
        )
    # the simulated camera is noise-free and renders each frame anew: a repeat is a standstill
    overrides = {"repeated_frames": "still"} | preset.odometry | given
    window = preset.fisheye_window if fisheye_window == "preset" else fisheye_window

    def factory(rig: Rig) -> RoverEstimator:
        if given and not rig.of_kind("pinhole"):
            raise ConfigError(
                f"odometry_overrides {sorted(given)}: this rig has no downward camera ({rig!r}), and its "
                "odometry is the fisheye's; give fisheye_odometry=FisheyeOdometryConfig(...) instead"
            )
        # a simulated mission starts at rest, steering centred: the fisheye's first frame zeroes it
        return RoverEstimator(
            rig,
            odometry,
            kinematics,
            slip,
            overrides,
            window,
            odometry_gyro,
            zero_steering_at_start=True,
            fisheye_odometry=fisheye_odometry,
        )

    factory.__qualname__ = f"builtin_estimator({preset.name!r})"
    return factory


class PerceptionPipeline:
    """The simulated sensors of one rover and the estimator that consumes their messages.

    The rig's sensors are attached to the simulation in the rig's order (by default
    ``"fisheye"``, ``"downward"``, then ``"imu"`` if fitted); the simulation samples them while
    it steps. The pipeline never
    steps the physics; its estimator reads no simulator state.

    Args:
        sim: The simulation the sensors are attached to (one per environment).
        preset: A :data:`PERCEPTION_PRESETS` name or a :class:`PerceptionPreset`.
        odometry: Odometry parameters of the built-in estimator.
        kinematics: Fisheye-kinematics parameters of the built-in estimator.
        slip: Slip-filter parameters of the built-in estimator.
        imu: With the standard rig, an IMU on the body (the sensor ``"imu"``). None: no IMU.
        odometry_gyro: The built-in estimator gives the odometry's 3-D fit the gyro's roll and
            pitch rates (with an IMU; default).
        estimator: A factory (a class or callable) called once with the :class:`Rig`; None: the
            built-in :class:`perception.RoverEstimator` with the preset's parameters.
        rig: The sensors to build and attach, in sampling order (a scenario's ``rig``, see
            :mod:`rover_env.config.rig`); None: the standard rig (fisheye, downward camera,
            ``imu``). Cameras take the preset's settings where their declaration gives none.
        declared: ``rig`` is the scenario's ``rig`` key (errors name ``rig[i]``), not the
            standard rig (errors name the sensor: ``imu.rate_hz``).
        camera_effects: Deliver the cameras' images through their image sensors and lenses
            (``camera_effects="field"``); the rig's calibrations then hold the lenses' distortion.
        control_hz: The environment's control rate [Hz] (a command sensor's rate without its own).
    """

    def __init__(
        self,
        sim: RoverSim,
        preset: PresetName | PerceptionPreset = "train",
        odometry: FlowOdometryConfig | None = None,
        kinematics: KinematicsConfig | None = None,
        slip: SlipConfig | None = None,
        imu: ImuConfig | None = None,
        odometry_gyro: bool = True,
        estimator: EstimatorFactory | None = None,
        rig: tuple[SensorConfig, ...] | None = None,
        declared: bool = False,
        camera_effects: bool = False,
        control_hz: float = 30.0,
    ) -> None:
        if isinstance(preset, str):
            if preset not in PERCEPTION_PRESETS:
                raise ConfigError(f"preset: {preset!r}; use one of {sorted(PERCEPTION_PRESETS)}")
            preset = PERCEPTION_PRESETS[preset]
        self.preset = preset
        if rig is None:
            rig = standard_rig(imu)
        elif imu is not None:
            raise ValueError("imu: this pipeline is given a rig; declare the IMU in it (kind: imu)")
        check_rig(rig)
        if estimator is None and not any(c.kind == "pinhole" for c in rig):
            # a rig without a downward camera: the built-in estimator takes its odometry from the
            # fisheye, which renders the ground for it unless the declaration says otherwise (an
            # estimator of your own gets what its rig declares: camera: {roi_ground_deg: 75})
            rig = tuple(
                dataclasses.replace(c, camera=dict(FISHEYE_ONLY_CAMERA) | dict(c.camera or {}))
                if c.kind == "fisheye"
                else c
                for c in rig
            )
        #: The simulated sensors by name, in the order the simulation samples them.
        self.sensors: dict[str, SimSensor] = {}
        for i, config in enumerate(rig):
            key = f"rig[{i}]" if declared else config.name
            sensor = build_sensor(sim, config, preset, key, declared, control_hz)
            sim.attach_sensor(config.name, sensor)
            self.sensors[config.name] = sensor
        cameras = {n: s for n, s in self.sensors.items() if isinstance(s, DownwardCamera | FisheyeCamera)}
        self.cameras = list(cameras.values())
        self.imus = [s for s in self.sensors.values() if isinstance(s, Imu)]
        self.sun_sensors = [s for s in self.sensors.values() if isinstance(s, SunSensor)]
        #: The encoders and current senses (their per-episode draws: ``reset(seed)``).
        self.proprio = [s for s in self.sensors.values() if isinstance(s, WheelEncoders | MotorCurrents)]
        # the first of each kind, as a user reaches them (None if the rig has none)
        self.downward = next((s for s in self.cameras if isinstance(s, DownwardCamera)), None)
        self.fisheye = next((s for s in self.cameras if isinstance(s, FisheyeCamera)), None)
        self.imu = self.imus[0] if self.imus else None
        for cam in self.cameras:  # before the rig is described: a field lens is in the calibration
            cam.set_effects(camera_effects)
        #: What the estimator is given: the rig's own copy, its arrays read-only (the sensors
        #: keep theirs, so nothing done to it changes what they deliver).
        self.rig = read_only(rig_of(sim, self.sensors))
        if estimator is None:
            self.estimator: Any = builtin_estimator(
                preset, odometry=odometry, kinematics=kinematics, slip=slip, odometry_gyro=odometry_gyro
            )(self.rig)
        else:
            try:
                self.estimator = estimator(self.rig)
            except (Exception, SystemExit) as exc:  # the user's code: any error, named
                who = getattr(estimator, "__qualname__", type(estimator).__name__)
                raise EstimatorError(
                    f"estimator factory {who}({self.rig!r}): {type(exc).__name__}: {exc}"
                ) from exc
            for method in ("reset", "update"):
                if not callable(getattr(self.estimator, method, None)):
                    raise TypeError(
                        f"estimator {estimator_name(self.estimator)} has no {method}() method; an estimator "
                        "has reset(start_fix) and update(messages, t) (see perception.estimator)"
                    )
        self.name = estimator_name(self.estimator)
        self.builtin = isinstance(self.estimator, RoverEstimator)
        camera_names = list(cameras)
        #: Each camera's latest image given to the estimator (None before the first).
        self.last_images: dict[str, np.ndarray | None] = dict.fromkeys(camera_names)
        self._sim_timing = sim.timing
        self._perception_s = 0.0
        self._step = 0
        #: Frames given to the estimator so far: downward, fisheye, and fisheye frames rendered in windows.
        self.frames = dict.fromkeys(camera_names, 0) | {"fisheye_windowed": 0}
        self._listeners: list[Callable[[Sequence[SensorMessage]], None]] = []

    def add_listener(self, listener: Callable[[Sequence[SensorMessage]], None]) -> None:
        """Call ``listener(messages)`` with every control step's messages before the estimator sees them.

        A recorder's hook (``rover record``): it reads the messages, it cannot change them (their
        arrays are read-only) nor the estimate.
        """
        self._listeners.append(listener)

    @property
    def timing(self) -> dict[str, float]:
        """Wall-clock seconds spent so far: physics, rendering (sensor sampling), perception."""
        readout = self.estimator.timing["readout"] if self.builtin else 0.0
        return {
            "physics": self._sim_timing["physics"],
            "rendering": self._sim_timing["sensors"] + readout,
            "perception": self._perception_s,
        }

    # the built-in estimator's parts, for benchmarks and tests
    @property
    def odometry(self):
        """The built-in estimator's odometry (on the one-camera rig, the fisheye's)."""
        return self._builtin().odometry

    @property
    def kinematics(self):
        """The built-in estimator's :class:`perception.KinematicStateEstimator`."""
        return self._builtin().kinematics

    @property
    def slip(self):
        """The built-in estimator's :class:`perception.SlipEstimator`."""
        return self._builtin().slip

    def _builtin(self) -> RoverEstimator:
        if not self.builtin:
            raise TypeError(f"the estimator is {self.name}, not the built-in RoverEstimator")
        return self.estimator

    def start(self, start_fix, messages: Sequence[SensorMessage], t: float) -> dict[str, Any]:
        """Start after the simulation's reset: the estimator's ``reset``, then the reset's messages.

        Returns:
            The estimate (checked, :func:`perception.estimator.check_estimate`).
        """
        fix = np.asarray(start_fix, dtype=np.float64)
        if fix.shape != (3,) or not np.all(np.isfinite(fix)):
            raise ValueError(f"start_fix={fix.tolist()}: give a finite (x, y, yaw) [m, rad]")
        self._step = 0
        self.last_images = dict.fromkeys(self.last_images)
        for cam in self.cameras:
            if isinstance(cam, FisheyeCamera):
                cam.request_window(0.0, None)
        try:
            self.estimator.reset(fix.copy())
        except (Exception, SystemExit) as exc:  # the user's code: any error (an exit too), named
            raise EstimatorError(f"estimator {self.name}, reset: {type(exc).__name__}: {exc}") from exc
        return self.update(messages, t)

    def update(self, messages: Sequence[SensorMessage], t: float) -> dict[str, Any]:
        """One control step's messages to the estimator; the checked estimate at ``t`` [s]."""
        t0 = time.perf_counter()
        for m in messages:
            if isinstance(m.data, np.ndarray):  # the estimator reads the samples; it cannot change them
                m.data.flags.writeable = False
            if m.sensor in self.last_images:
                self.last_images[m.sensor] = m.data
                self.frames[m.sensor] += 1
        for listener in self._listeners:
            listener(messages)
        try:
            values = self.estimator.update(list(messages), t)
        except (Exception, SystemExit) as exc:
            raise EstimatorError(
                f"estimator {self.name}, step {self._step}: {type(exc).__name__}: {exc}"
            ) from exc
        out = check_estimate(values, self.name, self._step)
        request = getattr(self.estimator, "readout_request", None)
        if request is not None:
            for name, sensor in self.sensors.items():
                if not self.rig[name].readout_window:
                    continue
                req = request(name)
                accept = getattr(sensor, "request_window", None)
                if req is not None and accept is not None:
                    accept(float(req[0]), req[1])
        self.frames["fisheye_windowed"] = sum(
            c.sampled["windowed"] for c in self.cameras if isinstance(c, FisheyeCamera)
        )
        self._step += 1
        self._perception_s += time.perf_counter() - t0
        return out

    # the built-in estimator's full output, as before the estimator interface
    def reset(self, pose0, messages: Sequence[SensorMessage], t: float = 0.0) -> StepEstimate:
        """:meth:`start`, returning the built-in estimator's full :class:`StepEstimate`."""
        self._builtin()
        self.start(pose0, messages, t)
        return self.estimator.last_step

    def process(self, messages: Sequence[SensorMessage], t: float) -> StepEstimate:
        """:meth:`update`, returning the built-in estimator's full :class:`StepEstimate`."""
        self._builtin()
        self.update(messages, t)
        return self.estimator.last_step

    def estimate(self) -> StepEstimate:
        """The built-in estimator's full estimate at the last processed time."""
        return self._builtin().step_estimate()

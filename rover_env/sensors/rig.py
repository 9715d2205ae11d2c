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

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perception.estimator import EstimatorError, check_estimate, estimator_name
from perception.fisheye_kinematics import KinematicsConfig
from perception.odometry import FlowOdometryConfig
from perception.rig import ImuModel, Rig, SensorMessage, SensorSpec, TriadFigures
from perception.rover_estimator import IMU_CALIBRATION_S, STEP_KEYS, RoverEstimator, StepEstimate
from perception.slip import SlipConfig
from rover_env.config.cameras import DownwardCameraConfig, FisheyeCameraConfig
from rover_env.config.imu import ImuConfig
from rover_env.config.io import ConfigError
from rover_env.sensors.cameras import DownwardCamera, FisheyeCamera
from rover_env.sensors.imu import Imu
from rover_env.sim.simulation import RoverSim

log = logging.getLogger(__name__)

__all__ = [
    "IMU_CALIBRATION_S",
    "PERCEPTION_PRESETS",
    "STEP_KEYS",
    "PerceptionPipeline",
    "PerceptionPreset",
    "StepEstimate",
    "rig_of",
]


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
            reach in one frame from its last estimate (:func:`~perception.rover_parts.joint_window_parts`),
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
        # the windows about them (pixels the estimator reads are unchanged, see the tests); this
        # halves its rendering time at 640 x 480 (benchmarks/env_speed.py)
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
        # 40-50 features, out to 8 px from the border (a 2 m/s frame step), halve its error.
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


PERCEPTION_PRESETS: dict[str, PerceptionPreset] = _presets()


def _figures(triad) -> TriadFigures:
    return TriadFigures(
        noise_density=triad.noise_density,
        bias_instability=triad.bias_instability,
        bias_random_walk=triad.bias_random_walk,
        turn_on_bias=triad.turn_on_bias,
        range=triad.range,
    )


def rig_of(sim: RoverSim, downward: DownwardCamera, fisheye: FisheyeCamera, imu: Imu | None = None) -> Rig:
    """The :class:`perception.rig.Rig` of a simulated rover's sensors: what an estimator is given.

    The cameras' calibrations are their exact models (the simulation renders through them); the
    IMU's is its data sheet (its errors are drawn per episode, and not given away).
    """
    g = sim.geometry
    specs = [
        SensorSpec("fisheye", "fisheye", fisheye.config.rate_hz, fisheye.T_body_cam, fisheye.model, True),
        SensorSpec("downward", "pinhole", downward.config.rate_hz, downward.T_body_cam, downward.model),
    ]
    if imu is not None:
        T = np.eye(4)
        T[:3, :3] = imu.R_body_imu
        T[:3, 3] = imu.r_body
        model = ImuModel(gyro=_figures(imu.config.gyro), accel=_figures(imu.config.accel))
        specs.append(SensorSpec("imu", "imu", imu.config.rate_hz, T, model))
    return Rig(specs, vehicle=g.kinematic_model(fisheye.T_body_cam), steer_max_rate=g.steer_max_rate)


#: A factory of estimators: called once per environment with its rig.
EstimatorFactory = Callable[[Rig], Any]


class PerceptionPipeline:
    """The simulated sensors of one rover and the estimator that consumes their messages.

    The cameras are attached to the simulation as sensors (``"fisheye"`` then ``"downward"``,
    then ``"imu"`` if fitted); the simulation samples them while it steps. The pipeline never
    steps the physics; its estimator reads no simulator state.

    Args:
        sim: The simulation the sensors are attached to (one per environment).
        preset: A :data:`PERCEPTION_PRESETS` name or a :class:`PerceptionPreset`.
        odometry: Odometry parameters of the built-in estimator.
        kinematics: Fisheye-kinematics parameters of the built-in estimator.
        slip: Slip-filter parameters of the built-in estimator.
        imu: An IMU on the body (attached as the sensor ``"imu"``). None (default): no IMU.
        odometry_gyro: The built-in estimator gives the odometry's 3-D fit the gyro's roll and
            pitch rates (with an IMU; default).
        estimator: A factory (a class or callable) called once with the :class:`Rig`; None: the
            built-in :class:`perception.RoverEstimator` with the preset's parameters.
    """

    def __init__(
        self,
        sim: RoverSim,
        preset: str | PerceptionPreset = "train",
        odometry: FlowOdometryConfig | None = None,
        kinematics: KinematicsConfig | None = None,
        slip: SlipConfig | None = None,
        imu: ImuConfig | None = None,
        odometry_gyro: bool = True,
        estimator: EstimatorFactory | None = None,
    ) -> None:
        if isinstance(preset, str):
            if preset not in PERCEPTION_PRESETS:
                raise ConfigError(f"preset: {preset!r}; use one of {sorted(PERCEPTION_PRESETS)}")
            preset = PERCEPTION_PRESETS[preset]
        self.preset = preset
        self.downward = DownwardCamera(sim, preset.downward)
        self.fisheye = FisheyeCamera(sim, preset.fisheye)
        sim.attach_sensor("fisheye", self.fisheye)
        sim.attach_sensor("downward", self.downward)
        self.imu: Imu | None = None
        if imu is not None:
            self.imu = Imu(sim, imu)
            sim.attach_sensor("imu", self.imu)
        self.rig = rig_of(sim, self.downward, self.fisheye, self.imu)
        self._sensors: dict[str, DownwardCamera | FisheyeCamera | Imu] = {
            "fisheye": self.fisheye,
            "downward": self.downward,
        }
        if self.imu is not None:
            self._sensors["imu"] = self.imu
        if estimator is None:
            # the simulated camera is noise-free and renders each frame anew: a repeat is a standstill
            overrides = {"repeated_frames": "still"} | preset.odometry
            self.estimator: Any = RoverEstimator(
                self.rig, odometry, kinematics, slip, overrides, preset.fisheye_window, odometry_gyro
            )
        else:
            self.estimator = estimator(self.rig)
            for method in ("reset", "update"):
                if not callable(getattr(self.estimator, method, None)):
                    raise TypeError(
                        f"estimator {estimator_name(self.estimator)} has no {method}() method; an estimator "
                        "has reset(start_fix) and update(messages, t) (see perception.estimator)"
                    )
        self.name = estimator_name(self.estimator)
        self.builtin = isinstance(self.estimator, RoverEstimator)
        self.last_images: dict[str, np.ndarray | None] = {"downward": None, "fisheye": None}
        self._sim_timing = sim.timing
        self._perception_s = 0.0
        self._step = 0
        #: Frames given to the estimator so far: downward, fisheye, and fisheye frames rendered in windows.
        self.frames = {"downward": 0, "fisheye": 0, "fisheye_windowed": 0}

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
        """The built-in estimator's :class:`perception.FlowOdometry`."""
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
        self.last_images = {"downward": None, "fisheye": None}
        self.fisheye.request_window(0.0, None)
        try:
            self.estimator.reset(fix.copy())
        except Exception as exc:
            raise EstimatorError(f"estimator {self.name}, reset: {type(exc).__name__}: {exc}") from exc
        return self.update(messages, t)

    def update(self, messages: Sequence[SensorMessage], t: float) -> dict[str, Any]:
        """One control step's messages to the estimator; the checked estimate at ``t`` [s]."""
        t0 = time.perf_counter()
        for m in messages:
            if m.sensor in self.last_images:
                self.last_images[m.sensor] = m.data
                self.frames[m.sensor] += 1
        try:
            values = self.estimator.update(list(messages), t)
        except Exception as exc:
            raise EstimatorError(
                f"estimator {self.name}, step {self._step}: {type(exc).__name__}: {exc}"
            ) from exc
        out = check_estimate(values, self.name, self._step)
        request = getattr(self.estimator, "readout_request", None)
        if request is not None:
            for name, sensor in self._sensors.items():
                if not self.rig[name].readout_window:
                    continue
                req = request(name)
                accept = getattr(sensor, "request_window", None)
                if req is not None and accept is not None:
                    accept(float(req[0]), req[1])
        self.frames["fisheye_windowed"] = self.fisheye.sampled["windowed"]
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

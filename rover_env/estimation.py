"""The estimator in the loop: the rover's cameras rendered at their rates, perception on the images.

:class:`PerceptionPipeline` owns the two simulated cameras of one :class:`RoverSim` and the
estimators that turn their images into the state (``perception`` sees images, camera models and
times only, never the simulator):

- the downward camera (chained frame pairs) -> :class:`perception.FlowOdometry` -> body twist,
  with the ground plane from the fisheye's latest axle roll, height and steering;
- the fisheye -> :class:`perception.KinematicStateEstimator` -> psi, d, lambda, theta, theta_dot;
- both -> :class:`perception.SlipEstimator` -> fused twist and wheel rates, slip ratio and angle;
- the fused twist integrated from the start pose -> the dead-reckoned planar pose.

The simulation samples the cameras at their exact times while it steps; the pipeline consumes
the timestamped images and never steps the physics.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from perception.fisheye_kinematics import KinematicsConfig, KinematicState, KinematicStateEstimator
from perception.inertial import AttitudeFilter, G, tilted_step
from perception.kinematics import AXLES, MARKERS
from perception.odometry import (
    FlowOdometry,
    FlowOdometryConfig,
    OdometryEstimate,
    arc_step,
    ground_plane_from_wheels,
)
from perception.rover_parts import joint_window_parts
from perception.slip import SlipConfig, SlipEstimate, SlipEstimator
from rover_env.cameras import DownwardCamera, DownwardCameraConfig, FisheyeCamera
from rover_env.config_io import ConfigError
from rover_env.fisheye import FisheyeCameraConfig
from rover_env.ground_truth import GROUND_TRUTH_KEYS
from rover_env.imu import Imu, ImuConfig
from rover_env.sim import RoverSim, SensorMessage

log = logging.getLogger(__name__)

#: Keys of ``info["estimate"]``: the ground truth's keys without ``pose``, plus the
#: dead-reckoned ``odometry_pose`` (x, y, yaw) and the estimates' quality.
ESTIMATE_KEYS: tuple[str, ...] = (
    ("odometry_pose",) + tuple(k for k in GROUND_TRUTH_KEYS if k != "pose") + ("quality",)
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

#: The gyro's bias is calibrated on its samples over this long before t = 0 [s], the second half
#: of the simulation's settling: the rover is then at rest on its wheels.
IMU_CALIBRATION_S = 0.25
#: The rate of the fused velocity that the attitude filter takes out of the specific force is a
#: difference over at least this long [s] (shorter: the odometry's frame-to-frame noise).
VELOCITY_RATE_S = 0.25


@dataclass
class StepEstimate:
    """The estimate after one control period.

    Attributes:
        values: ``ESTIMATE_KEYS`` -> float arrays (wheel order FL, FR, RL, RR; axles F, R).
        odometry_quality: Quality of the last odometry estimate (0 when it was invalid).
        kinematics_quality: Share of the fisheye's 10 degrees of freedom measured in its last frame.
        attitude_quality: Share of the control period's IMU samples that were in range, once the
            attitude was initialised at a standstill or has settled on gravity (three of its time
            constants); 0 before that, and without an IMU (``values["tilt"]`` then reads 0: unknown,
            not level).
        slip: The slip filter's full output.
        odometry: The last odometry estimate (None before the first pair).
        kinematics: The last kinematic state.
        imu_saturated: IMU samples since the last estimate that hit a range and were left out.
        gyro_bias: The gyro's estimated yaw-rate bias and its standard deviation [rad/s]
            (None without an IMU).
        tilt: (roll, pitch) of the body from the IMU [rad] (None without one).
        height: Dead-reckoned height change since the start [m] (0 without an IMU).
    """

    values: dict[str, np.ndarray]
    odometry_quality: float
    kinematics_quality: float
    attitude_quality: float
    slip: SlipEstimate
    odometry: OdometryEstimate | None = field(default=None, repr=False)
    kinematics: KinematicState | None = field(default=None, repr=False)
    imu_saturated: int = 0
    gyro_bias: tuple[float, float] | None = None
    tilt: tuple[float, float] | None = None
    height: float = 0.0


class PerceptionPipeline:
    """The cameras of one simulated rover and the estimators that consume their images.

    The cameras are attached to the simulation as sensors (``"fisheye"`` then ``"downward"``);
    the simulation samples them while it steps. The pipeline never steps the physics and reads
    no simulator state: it gets the sensor messages and the time the step ended
    (:meth:`process`), and the start fix at :meth:`reset`. What a camera fault does reaches it
    only as the images the camera delivers.

    Args:
        sim: The simulation the cameras are attached to (one per environment).
        preset: A :data:`PERCEPTION_PRESETS` name or a :class:`PerceptionPreset`.
        odometry: Odometry parameters.
        kinematics: Fisheye-kinematics parameters.
        slip: Slip-filter parameters.
        imu: An IMU on the body (attached as the sensor ``"imu"``, after the cameras): its gyro's
            body-z rate, averaged between camera frames, goes into the slip filter with a bias
            that the filter learns from the odometry. None (default): no IMU, as before.
        odometry_gyro: With an IMU, give the odometry's 3-D fit the gyro's mean roll and pitch
            rates over each frame pair (``FlowOdometry.update(rate_xy=...)``; default). False:
            the odometry's velocities are vision only (the odometry paper's method).
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
        self.odometry_gyro = bool(odometry_gyro)
        if imu is not None:
            self.imu = Imu(sim, imu)
            sim.attach_sensor("imu", self.imu)
            # the calibration the estimator is given: the mount and the data sheet's noise
            self._imu_z = self.imu.R_body_imu[2]  # body-z component of a mount-frame rate
            self._gyro_density = imu.gyro.noise_density
            self.attitude = AttitudeFilter(self.imu.R_body_imu)
        self._z = 0.0  # dead-reckoned height change [m] (with an IMU)
        self._twist = np.zeros(3)  # the twist of the last dead-reckoning step
        self._twist_hist: list[tuple[float, float, float]] = []  # (t, v_x, v_y) for the velocity's rate
        self._imu_batch: list[np.ndarray] = []  # samples since the last flush, and the last one's time
        self._imu_t = 0.0
        self._gyro_xy: list[np.ndarray] = []  # gyro samples (IMU frame) since the last downward frame
        self.last_images: dict[str, np.ndarray | None] = {"downward": None, "fisheye": None}
        self._imu_saturated = 0
        self._imu_used = 0  # in-range samples this control period
        self._attitude_s = 0.0  # IMU time the attitude has run on since the reset [s]
        self._attitude_ready = False  # initialised from a standstill, or settled on gravity
        self._attitude_q = 0.0  # the attitude quality of the last processed step
        self._sim_timing = sim.timing
        g = sim.geometry
        self._steer_max_rate = g.steer_max_rate
        self.model = g.kinematic_model(self.fisheye.T_body_cam)
        down = preset.downward
        self.odometry = FlowOdometry(
            self.downward.model,
            # the simulated camera is noise-free and renders each frame anew: a repeat is a standstill
            odometry
            or FlowOdometryConfig.for_camera(
                down.width, down.rate_hz, **({"repeated_frames": "still"} | preset.odometry)
            ),
        )
        self.kinematics = KinematicStateEstimator(self.fisheye.model, self.model, kinematics)
        nominal = self.model.wheel_frames(np.zeros(2), np.full(2, self.model.nominal_depth), np.zeros(4))
        slip = slip or SlipConfig()
        if imu is not None:
            # the gyro's bias prior from its data sheet: the turn-on spread, and a drift of the
            # bias instability over about 100 s on top of the random walk
            slip = dataclasses.replace(
                slip,
                gyro_bias_std=max(imu.gyro.turn_on_bias, 1e-6),
                gyro_bias_rw=imu.gyro.bias_random_walk + imu.gyro.bias_instability / 10.0,
            )
        self.slip = SlipEstimator(np.array([c[:2] for _, c in nominal]), g.wheel_radius, slip)
        self._pose = np.zeros(3)
        self._t_pose = 0.0
        self._t = 0.0
        self._last_odom: OdometryEstimate | None = None
        self._perception_s = 0.0
        self._window_s = 0.0
        #: Frames processed so far: downward, fisheye, and fisheye frames rendered in windows.
        self.frames = {"downward": 0, "fisheye": 0, "fisheye_windowed": 0}

    @property
    def timing(self) -> dict[str, float]:
        """Wall-clock seconds spent so far: physics, rendering (sensor sampling), perception."""
        return {
            "physics": self._sim_timing["physics"],
            "rendering": self._sim_timing["sensors"] + self._window_s,
            "perception": self._perception_s,
        }

    def reset(self, pose0, messages: list[SensorMessage], t: float = 0.0) -> StepEstimate:
        """Start again after the simulation's reset, from the start fix (x, y, yaw) [m, rad].

        Args:
            pose0: Where the rover believes it starts (world frame); dead reckoning starts there.
            messages: The sensor messages of the reset (each camera's first frame).
            t: Simulation time of the reset [s].

        Returns:
            The estimate after the first frames.
        """
        pose0 = np.asarray(pose0, dtype=np.float64)
        if pose0.shape != (3,) or not np.all(np.isfinite(pose0)):
            raise ValueError(f"pose0={pose0.tolist()}: give a finite (x, y, yaw) [m, rad]")
        self.odometry.reset()
        self.kinematics.reset()
        self.slip.reset()
        self._pose = pose0.copy()
        self._t_pose = float(t)
        self._t = float(t)
        self._last_odom = None
        self._imu_batch = []
        self._gyro_xy = []
        self.last_images = {"downward": None, "fisheye": None}  # the latest images given to perception
        self._imu_saturated = 0
        self._imu_used = 0
        self._attitude_s = 0.0
        self._attitude_ready = False
        self._attitude_q = 0.0
        self._z = 0.0
        self._twist = np.zeros(3)
        self._twist_hist = []
        if self.imu is not None:
            self.attitude.reset()
        self.fisheye.request_window(0.0, None)
        standstill = [m for m in messages if m.t < t - 1e-9]
        if standstill and self.imu is not None:
            self._calibrate_gyro(standstill, t)
        return self.process([m for m in messages if m.t >= t - 1e-9], t)

    def _calibrate_gyro(self, messages: list[SensorMessage], t: float) -> None:
        """The gyro's bias from its samples while the rover stood settled, the last ``IMU_CALIBRATION_S``."""
        still = np.array(
            [
                m.data[:6]
                for m in messages
                if m.sensor == "imu" and m.t >= t - IMU_CALIBRATION_S - 1e-9 and m.data[6] == 0
            ]
        ).reshape(-1, 6)
        if len(still):
            mean = still.mean(axis=0)
            window = len(still) * self.imu.period
            self.slip.calibrate_gyro(float(self._imu_z @ mean[:3]), self._gyro_density / np.sqrt(window))
            self.attitude.calibrate(mean[:3], mean[3:])
            self._attitude_ready = True

    def _window_parts(self) -> np.ndarray | None:
        """What the fisheye's next frame must show (see ``PerceptionPreset.fisheye_window``)."""
        rates = self.preset.fisheye_window
        s = self.kinematics.state
        if rates is None or s.markers_found < len(MARKERS):
            return None
        if not all(s.valid[f"{dof}_{a}"] for dof in ("psi", "d", "lam") for a in AXLES):
            return None
        roll, travel, steer = rates
        steer = max(steer, 1.25 * self._steer_max_rate)
        period = self.fisheye.period
        return joint_window_parts(
            self.model, s.psi, s.depth, s.delta, (roll * period, travel * period, steer * period)
        )

    def _on_fisheye(self, img: np.ndarray, t: float) -> None:
        self.last_images["fisheye"] = img
        state = self.kinematics.update(img, t)
        self.frames["fisheye"] += 1
        self.frames["fisheye_windowed"] = self.fisheye.sampled["windowed"]
        self.slip.add_wheels(
            t,
            state.theta_dot,
            self.fisheye.period,
            [state.valid[f"theta_{w}"] for w in ("FL", "FR", "RL", "RR")],
            state.delta,
        )
        t0 = time.perf_counter()
        self.fisheye.request_window(t + self.fisheye.period, self._window_parts())
        self._window_s += time.perf_counter() - t0

    def _on_downward(self, img: np.ndarray, t: float) -> None:
        self.last_images["downward"] = img
        self.frames["downward"] += 1
        s = self.kinematics.state
        centres = np.array([c for _, c in self.model.wheel_frames(s.psi, s.depth, s.delta)])
        plane = ground_plane_from_wheels(centres, self.model.wheel_radius)
        est = self.odometry.update(img, t, ground_plane=plane, rate_xy=self._frame_rate_xy())
        if est is not None:
            self._last_odom = est
            if est.valid:
                self.slip.add_odometry(t, est.twist, est.dt, est.quality, cov=est.twist_cov)

    def _velocity_rate(self) -> tuple[float, float]:
        """d(v_x, v_y)/dt of the fused twist over the last ``VELOCITY_RATE_S`` or more [m/s^2].

        The fused velocity rests on the odometry at every frame, whatever the attitude's error
        (the slip filter's accelerometer bias state takes up the gravity that leaks through it).
        """
        t, (vx, vy, _) = self._t_pose, self._twist
        hist = self._twist_hist
        if not hist or t > hist[-1][0]:
            hist.append((t, vx, vy))
        while len(hist) > 2 and t - hist[1][0] >= VELOCITY_RATE_S:
            hist.pop(0)
        t0, vx0, vy0 = hist[0]
        if t - t0 < VELOCITY_RATE_S:
            return 0.0, 0.0
        return (vx - vx0) / (t - t0), (vy - vy0) / (t - t0)

    def _frame_rate_xy(self) -> np.ndarray | None:
        """The gyro's mean body roll and pitch rates since the last downward frame (None: no gyro)."""
        if self.imu is None or not self.odometry_gyro or not self._gyro_xy:
            self._gyro_xy = []
            return None
        w = self.imu.R_body_imu[:2] @ np.mean(self._gyro_xy, axis=0) - self.attitude.bias[:2]
        self._gyro_xy = []
        return w

    def _on_imu(self, data: np.ndarray, t: float) -> None:
        if data[6] > 0 or not np.all(np.isfinite(data[:6])):
            self._imu_saturated += 1  # a clipped rate is not a rate: left out, and counted
            return
        self._gyro_xy.append(data[:3])
        self._imu_batch.append(data[:6])
        self._imu_used += 1
        self._imu_t = t

    def _flush_imu(self) -> None:
        """The IMU samples since the last flush: the attitude; the mean body-z rate to the slip filter."""
        batch = self._imu_batch
        if not batch:
            return
        n = len(batch)
        mean = np.mean(batch, axis=0) if n > 1 else batch[0]
        window = n * self.imu.period  # each sample integrates the period before it
        vx, vy, w = self._twist
        # neither the centripetal acceleration omega x v of a turn nor the rate of the body's
        # velocity (a rover speeding up, or sliding down a slope) is gravity
        dvx, dvy = self._velocity_rate()
        self.attitude.update(mean[:3], mean[3:], window, (dvx - w * vy, dvy + w * vx, 0.0))
        self._attitude_s += window
        # without a standstill to start from, three time constants of gravity settle the tilt
        self._attitude_ready |= self._attitude_s >= 3.0 * self.attitude.time_constant
        std = self._gyro_density / np.sqrt(window)
        rate = float(self._imu_z @ mean[:3])
        self.slip.add_gyro(self._imu_t, rate, window, std)
        # the body's acceleration: the specific force less gravity through the attitude, plus the
        # transport terms of a turning frame, is the rate of the body-frame velocity (v_x, v_y)
        a = self.imu.R_body_imu @ mean[3:] - G * self.attitude.R[2]
        wz = rate - self.slip.gyro_bias[0]
        self.slip.add_accel(self._imu_t, (a[0] + wz * vy, a[1] - wz * vx), window)
        self._imu_batch = []

    def process(self, messages: list[SensorMessage], t: float) -> StepEstimate:
        """Consume the sensor messages of one step, in time order, and estimate the state at ``t``.

        Args:
            messages: Messages of the attached cameras (others are ignored), sampled at or before
                ``t`` and after the previous call's time.
            t: The time the step ended [s].
        """
        t0 = time.perf_counter()
        handlers = {"fisheye": self._on_fisheye, "downward": self._on_downward}
        if self.imu is not None:
            handlers["imu"] = self._on_imu
        for msg in messages:
            handler = handlers.get(msg.sensor)
            if handler is None:
                continue
            if msg.t < self._t_pose - 1e-9 or msg.t > t + 1e-9:
                raise ValueError(
                    f"{msg.sensor} message at t={msg.t} s is outside this step ({self._t_pose} to {t} s); "
                    "pass each step's messages once, in time order"
                )
            if msg.sensor == "imu":  # buffered; used at the next frame or the step's end
                handler(msg.data, msg.t)
                continue
            if self.imu is not None:
                self._flush_imu()
            self._integrate(msg.t)
            handler(msg.data, msg.t)
        if self.imu is not None:
            self._flush_imu()
        self._integrate(t)
        self._t = float(t)
        n = self._imu_used + self._imu_saturated
        self._attitude_q = self._imu_used / n if self._attitude_ready and n else 0.0
        out = self.estimate()
        self._imu_saturated = 0
        self._imu_used = 0
        self._perception_s += time.perf_counter() - t0
        return out

    def _integrate(self, t1: float) -> None:
        """Dead reckoning to ``t1``: the slip filter's twist after the last frame held as an arc.

        That twist is the visual odometry fused with the wheels' rates where they grip (on rough
        ground the odometry's planar model errs by 0.05-0.07 m/s); with no new measurement (a
        blackout) it is the last one.
        """
        if t1 > self._t_pose:
            twist = self.slip.twist_at(self._t_pose)
            self._twist = twist
            dt = t1 - self._t_pose
            if self.imu is None:
                self._pose = arc_step(self._pose, twist, dt)
            else:  # on the tilted ground plane, turning at the world heading's rate
                a = self.attitude
                rate = a.heading_rate(float(twist[2]))
                self._pose, self._z = tilted_step(self._pose, self._z, twist, a.roll, a.pitch, rate, dt)
            self._t_pose = t1

    def estimate(self) -> StepEstimate:
        """The estimate at the last processed time (after :meth:`reset` or :meth:`process`)."""
        t = self._t
        sl = self.slip.estimate(t)
        ks = self.kinematics.state
        odo = self._last_odom
        q_odo = float(odo.quality) if odo is not None and odo.valid else 0.0
        q_kin = float(ks.quality)
        values = {
            "odometry_pose": self._pose.copy(),
            "twist": sl.twist.copy(),
            "wheel_rate": sl.wheel_rate.copy(),
            "wheel_angle": ks.theta.copy(),
            "slip_ratio": sl.slip_ratio.copy(),
            "slip_angle": sl.slip_angle.copy(),
            "axle_roll": ks.psi.copy(),
            "axle_height": ks.depth.copy(),
            "steering": ks.lam.copy(),
            "tilt": np.zeros(2),  # unknown without an IMU: attitude quality 0 says so
            "quality": np.array([q_odo, q_kin, 0.0]),
        }
        if self.imu is None:
            return StepEstimate(values, q_odo, q_kin, 0.0, sl, odo, ks)
        tilt = (self.attitude.roll, self.attitude.pitch)
        q_att = self._attitude_q
        values["tilt"] = np.array(tilt)
        values["quality"][2] = q_att
        bias = self.slip.gyro_bias
        return StepEstimate(
            values, q_odo, q_kin, q_att, sl, odo, ks, self._imu_saturated, bias, tilt, self._z
        )

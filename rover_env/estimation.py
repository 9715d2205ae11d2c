"""The estimator in the loop: the rover's cameras rendered at their rates, perception on the images.

:class:`PerceptionPipeline` owns the two simulated cameras of one :class:`RoverSim` and the
estimators that turn their images into the state (``perception`` sees images, camera models and
times only, never the simulator):

- the downward camera (chained frame pairs) -> :class:`perception.FlowOdometry` -> body twist,
  with the ground plane from the fisheye's latest axle roll, height and steering;
- the fisheye -> :class:`perception.KinematicStateEstimator` -> psi, d, lambda, theta, theta_dot;
- both -> :class:`perception.SlipEstimator` -> fused twist and wheel rates, slip ratio and angle;
- the fused twist integrated from the start pose -> the dead-reckoned planar pose.

It advances the physics itself, one camera tick at a time, so that every frame is taken at its
camera's exact time.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from perception.fisheye_kinematics import KinematicsConfig, KinematicState, KinematicStateEstimator
from perception.kinematics import AXLES, MARKERS
from perception.odometry import (
    FlowOdometry,
    FlowOdometryConfig,
    OdometryEstimate,
    arc_step,
    ground_plane_from_wheels,
)
from perception.slip import SlipConfig, SlipEstimate, SlipEstimator
from rover_env.cameras import DownwardCamera, DownwardCameraConfig, FisheyeCamera
from rover_env.config_io import ConfigError
from rover_env.fisheye import FisheyeCameraConfig, joint_window_parts
from rover_env.ground_truth import GROUND_TRUTH_KEYS
from rover_env.sim import RoverSim

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
            reach in one frame from its last estimate (:func:`~rover_env.fisheye.joint_window_parts`),
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
        # the papers' resolutions and rates; the downward camera sees no ground beyond 2 m, so only
        # that is drawn for it (the full fisheye sees the horizon)
        "eval": PerceptionPreset(
            "eval",
            DownwardCameraConfig.preset("full", rate_hz=60.0, ground_range=2.0),
            FisheyeCameraConfig.preset("full"),
        ),
        # the lowest resolutions at which the estimators hold up: below 320x240 the fisheye's
        # tread texture is too coarse for the wheel rates, and below 30 Hz the wheels turn too
        # far between frames at 2 m/s; the fisheye renders only its region of interest, and
        # both cameras draw only the exact ground within 2 m. At 160 px a feature's track is
        # noisy, and the yaw rate rests on how far apart the features lie: twice the paper's
        # 40-50 features, out to 8 px from the border (a 2 m/s frame step), halve its error.
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


@dataclass
class StepEstimate:
    """The estimate after one control period.

    Attributes:
        values: ``ESTIMATE_KEYS`` -> float arrays (wheel order FL, FR, RL, RR; axles F, R).
        odometry_quality: Quality of the last odometry estimate (0 when it was invalid).
        kinematics_quality: Share of the fisheye's 10 degrees of freedom measured in its last frame.
        slip: The slip filter's full output.
        odometry: The last odometry estimate (None before the first pair).
        kinematics: The last kinematic state.
    """

    values: dict[str, np.ndarray]
    odometry_quality: float
    kinematics_quality: float
    slip: SlipEstimate
    odometry: OdometryEstimate | None = field(default=None, repr=False)
    kinematics: KinematicState | None = field(default=None, repr=False)


class PerceptionPipeline:
    """The cameras and estimators of one simulated rover.

    Args:
        sim: The simulation (one per environment).
        preset: A :data:`PERCEPTION_PRESETS` name or a :class:`PerceptionPreset`.
        odometry: Odometry parameters.
        kinematics: Fisheye-kinematics parameters.
        slip: Slip-filter parameters.
    """

    def __init__(
        self,
        sim: RoverSim,
        preset: str | PerceptionPreset = "train",
        odometry: FlowOdometryConfig | None = None,
        kinematics: KinematicsConfig | None = None,
        slip: SlipConfig | None = None,
    ) -> None:
        if isinstance(preset, str):
            if preset not in PERCEPTION_PRESETS:
                raise ConfigError(f"preset: {preset!r}; use one of {sorted(PERCEPTION_PRESETS)}")
            preset = PERCEPTION_PRESETS[preset]
        self.preset = preset
        self.sim = sim
        self.downward = DownwardCamera(sim, preset.downward)
        self.fisheye = FisheyeCamera(sim, preset.fisheye)
        g = sim.geometry
        self.model = g.kinematic_model(self.fisheye.T_body_cam)
        down = preset.downward
        self.odometry = FlowOdometry(
            self.downward.model,
            odometry or FlowOdometryConfig.for_camera(down.width, down.rate_hz, **preset.odometry),
        )
        self.kinematics = KinematicStateEstimator(self.fisheye.model, self.model, kinematics)
        nominal = self.model.wheel_frames(np.zeros(2), np.full(2, self.model.nominal_depth), np.zeros(4))
        self.slip = SlipEstimator(np.array([c[:2] for _, c in nominal]), g.wheel_radius, slip)
        # physics steps per frame of each camera; the pipeline ticks at their greatest common divisor
        steps = [round(c.period / sim.dt) for c in (self.downward, self.fisheye)]
        self._tick = math.gcd(*steps)
        self._every = [n // self._tick for n in steps]
        self._blackout: list[tuple[float, float]] = []
        self._pose = np.zeros(3)
        self._last_odom: OdometryEstimate | None = None
        self._count = 0
        #: Wall-clock seconds spent so far in each part: physics, rendering, perception.
        self.timing = {"physics": 0.0, "rendering": 0.0, "perception": 0.0}
        #: Frames rendered so far: downward, fisheye, and fisheye frames rendered in windows.
        self.frames = {"downward": 0, "fisheye": 0, "fisheye_windowed": 0}

    def reset(self, pose0, blackout=()) -> None:
        """Start again after the simulation's reset, at the known start pose (x, y, yaw) [m, rad].

        Call it after every :meth:`RoverSim.reset`: it takes the first frame of each camera.

        Args:
            pose0: The start pose in the world (dead reckoning starts there).
            blackout: (t0, t1) windows of episode time [s] in which both cameras deliver black
                frames (a camera fault, for robustness tests).
        """
        self.odometry.reset()
        self.kinematics.reset()
        self.slip.reset()
        self._pose = np.array(pose0, dtype=np.float64)
        self._last_odom: OdometryEstimate | None = None
        self._count = 0
        windows = []
        for w in blackout:
            t0, t1 = (float(v) for v in w)
            if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
                raise ValueError(f"blackout window {w!r}: give (t0, t1) with t0 < t1 [s]")
            windows.append((t0, t1))
        self._blackout = windows
        self._capture(downward=True, fisheye=True)

    def _dark(self, t: float) -> bool:
        return any(t0 <= t < t1 for t0, t1 in self._blackout)

    def _frame(self, camera, **options) -> np.ndarray:
        """Render ``camera`` now (black during a blackout); the rendering clock runs meanwhile."""
        t0 = time.perf_counter()
        img = camera.capture(**options).image
        self.timing["rendering"] += time.perf_counter() - t0
        return np.zeros_like(img) if self._dark(self.sim.t) else img

    def _window_parts(self) -> np.ndarray | None:
        """What the fisheye's next frame must show (see ``PerceptionPreset.fisheye_window``)."""
        rates = self.preset.fisheye_window
        s = self.kinematics.state
        if rates is None or s.markers_found < len(MARKERS):
            return None
        if not all(s.valid[f"{dof}_{a}"] for dof in ("psi", "d", "lam") for a in AXLES):
            return None
        roll, travel, steer = rates
        steer = max(steer, 1.25 * self.sim.geometry.steer_max_rate)
        spread = (roll * self.fisheye.period, travel * self.fisheye.period, steer * self.fisheye.period)
        return joint_window_parts(self.model, s.psi, s.depth, s.delta, spread)

    def _capture(self, downward: bool, fisheye: bool) -> None:
        t = self.sim.t
        if fisheye:
            t0 = time.perf_counter()
            parts = self._window_parts()
            self.timing["rendering"] += time.perf_counter() - t0
            img = self._frame(self.fisheye, parts=parts)
            self.frames["fisheye"] += 1
            self.frames["fisheye_windowed"] += parts is not None
            t0 = time.perf_counter()
            state = self.kinematics.update(img, t)
            self.slip.add_wheels(
                t,
                state.theta_dot,
                self.fisheye.period,
                [state.valid[f"theta_{w}"] for w in ("FL", "FR", "RL", "RR")],
                state.delta,
            )
            self.timing["perception"] += time.perf_counter() - t0
        if downward:
            img = self._frame(self.downward)
            self.frames["downward"] += 1
            t0 = time.perf_counter()
            s = self.kinematics.state
            centres = np.array([c for _, c in self.model.wheel_frames(s.psi, s.depth, s.delta)])
            plane = ground_plane_from_wheels(centres, self.model.wheel_radius)
            est = self.odometry.update(img, t, ground_plane=plane)
            if est is not None:
                self._last_odom = est
                if est.valid:
                    self.slip.add_odometry(t, est.twist, est.dt, est.quality, cov=est.twist_cov)
            self.timing["perception"] += time.perf_counter() - t0

    @property
    def tick(self) -> float:
        """The pipeline's time step [s]: the greatest common divisor of the camera periods."""
        return self.sim.dt * self._tick

    def advance(self, duration: float) -> None:
        """Run the physics for ``duration`` [s], capturing and processing every camera frame."""
        dt = self.tick
        n = round(duration / dt)
        if abs(n * dt - duration) > 1e-9:
            raise ValueError(f"duration {duration} s is not a whole number of camera ticks ({dt} s)")
        for _ in range(n):
            t_prev = self.sim.t
            t0 = time.perf_counter()
            self.sim.step(dt)
            self.timing["physics"] += time.perf_counter() - t0
            self._count += 1
            self._integrate(t_prev, self.sim.t)
            self._capture(
                downward=self._count % self._every[0] == 0, fisheye=self._count % self._every[1] == 0
            )

    def _integrate(self, t0: float, t1: float) -> None:
        """Dead reckoning: the slip filter's twist at the tick's start held over the tick, as an arc.

        That twist is the visual odometry fused with the wheels' rates where they grip (on rough
        ground the odometry's planar model errs by 0.05-0.07 m/s); with no new measurement (a
        blackout) it is the last one.
        """
        self._pose = arc_step(self._pose, self.slip.twist_at(t0), t1 - t0)

    def estimate(self) -> StepEstimate:
        """The estimate now (after :meth:`reset` or :meth:`advance`)."""
        t = self.sim.t
        sl = self.slip.estimate(t)
        ks = self.kinematics.state
        odo = self._last_odom
        q_odo = float(odo.quality) if odo is not None and odo.valid and not self._dark(t) else 0.0
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
            "quality": np.array([q_odo, q_kin, sl.quality]),
        }
        return StepEstimate(values, q_odo, q_kin, sl, odo, ks)

"""The built-in estimator: visual odometry, fisheye kinematics, slip filter, IMU fusion, dead reckoning.

:class:`RoverEstimator` implements the estimator interface (:mod:`perception.estimator`) on a
rig (:class:`perception.rig.Rig`) of one downward pinhole camera, one downward fisheye and,
optionally, one IMU:

- the downward camera (chained frame pairs) -> :class:`perception.FlowOdometry` -> body twist,
  with the ground plane from the fisheye's latest axle roll, height and steering; on a rig with
  no downward camera (the one-camera rig) the fisheye's own frames ->
  :class:`perception.odometry.fisheye.FisheyeOdometry` -> body twist, on the same plane;
- the fisheye -> :class:`perception.KinematicStateEstimator` -> psi, d, lambda, theta, theta_dot;
- both (and the gyro and accelerometer) -> :class:`perception.SlipEstimator` -> fused twist and
  wheel rates, slip ratio and angle; the IMU -> :class:`perception.fusion.inertial.AttitudeFilter`;
- the fused twist integrated from the start fix -> the dead-reckoned pose; with a sun sensor and
  an IMU its heading is corrected by the sun's (:mod:`perception.fusion.sun_heading`).

It sees sensor messages, the rig's calibrations and the start fix only.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from perception.fusion.encoders import EncoderRates
from perception.fusion.inertial import AttitudeFilter, G, tilted_step
from perception.fusion.slip import SlipConfig, SlipEstimate, SlipEstimator
from perception.fusion.soil import SoilIdConfig, SoilIdentifier
from perception.fusion.sun_heading import HeadingConfig, HeadingFilter
from perception.kinematics.fisheye import KinematicsConfig, KinematicState, KinematicStateEstimator
from perception.kinematics.sinkage import SinkageConfig, SinkageEstimate, SinkageEstimator, SinkageTrack
from perception.models.drive_geometry import AXLES, WHEELS
from perception.models.rover import MARKERS
from perception.models.rover_parts import joint_window_parts, kinematics_roi
from perception.models.validation import ConfigError
from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig
from perception.odometry.flow import (
    FlowOdometry,
    FlowOdometryConfig,
    OdometryEstimate,
    arc_step,
    ground_plane_from_wheels,
)
from perception.odometry.wheel_tracks import wheel_contacts
from perception.rig import Rig, SensorMessage

#: The rover's state under the names the simulator's ground truth uses too (besides its pose).
STATE_KEYS: tuple[str, ...] = (
    "twist",
    "wheel_rate",
    "wheel_angle",
    "slip_ratio",
    "slip_angle",
    "axle_roll",
    "axle_height",
    "steering",
    "tilt",
)
#: Keys of ``StepEstimate.values``: the dead-reckoned ``odometry_pose`` (x, y, yaw) and the
#: state keys; the qualities are the StepEstimate's own fields.
STEP_KEYS: tuple[str, ...] = ("odometry_pose", *STATE_KEYS)
#: The gyro's bias is calibrated on its samples over this long before the start [s]: the
#: rover is then at rest on its wheels (a simulated rover stands 2 s, settled after 0.5 s).
#: The bias's error falls as one over its square root: 0.5 mrad/s over 0.25 s, 0.2 over 1.5 s
#: (BMI088), 0.02 and 0.008 rad of heading over a 40 s mission.
IMU_CALIBRATION_S = 1.5
#: The fisheye's frames are measured for sinkage at most this often [Hz] (it changes over
#: decimetres of travel; about 0.8 ms a train-preset frame, benchmarks/soil_estimation.py).
SINKAGE_RATE_HZ = 10.0
#: The odometry's ground plane is raised by the wheels' measured sinkages for at most this long
#: after they were measured [s]; then it falls back to the wheels' lowest points.
GROUND_LIFT_HOLD_S = 2.0
#: ... where at least three wheels report at least this sinkage [m] (one wheel's reading alone
#: is more often a shadow on rigid ground than soil).
GROUND_LIFT_MIN_SINKAGE = 0.005
#: Below half this much ground a frame [m], the downward odometry is also measured over as many
#: frames as cover it (at most its ``history_frames``), for the slip over a window of travel:
#: on the soft-sand mission (0.09 m/s, train preset) the speed read 0.963 of the truth frame to
#: frame, 1.019 over 12 mm (four frames) and 0.996 over 25 mm.
WINDOW_TRAVEL = 0.025
#: The rate of the fused velocity that the attitude filter takes out of the specific force is a
#: difference over at least this long [s] (shorter: the odometry's frame-to-frame noise).
VELOCITY_RATE_S = 0.25
#: The dead-reckoned yaw's variance grows as a random walk whose variance matches, after this long
#: [s], that of the gyro's bias error integrated (which grows as the square of time).
YAW_WALK_MATCH_S = 40.0


@dataclass
class StepEstimate:
    """The built-in estimator's full state after one control period.

    Attributes:
        values: :data:`STEP_KEYS` -> float arrays (wheel order FL, FR, RL, RR; axles F, R), and
            ``sinkage`` (NaN: not measured), ``sinkage_quality`` (1,), with motor currents
            ``wheel_torque``, and once the soil's pull curve is identified ``pull_ratio`` (4,)
            (NaN: a wheel's slip unknown, braking or above 0.95) and ``soil_curve`` (3,): the slips of the
            largest pull and efficiency, and the identification's quality.
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
        heading_std: The heading's standard deviation [rad] from the sun-heading filter (None
            without a sun sensor and an IMU).
        sun_readings: Sun readings fused since the start (0 without a sun sensor).
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
    heading_std: float | None = None
    sun_readings: int = 0

    def fields(self) -> dict[str, object]:
        """The estimate under the names of :data:`perception.estimator.ESTIMATE_FIELDS` (unknown: out)."""
        v = self.values
        out: dict[str, object] = {"pose": np.array(v["odometry_pose"], dtype=np.float64)}
        out["v_x"], out["v_y"], out["omega"] = (float(x) for x in v["twist"])
        for key, prefix, labels in (
            ("wheel_rate", "wheel_rate_", WHEELS),
            ("wheel_angle", "wheel_angle_", WHEELS),
            ("slip_ratio", "slip_", WHEELS),
            ("slip_angle", "slip_angle_", WHEELS),
            ("axle_roll", "axle_roll_", AXLES),
            ("axle_height", "axle_height_", AXLES),
            ("steering", "steering_", AXLES),
        ):
            for label, x in zip(labels, v[key], strict=True):
                out[prefix + label] = float(x)
        out["roll"], out["pitch"] = (float(x) for x in v["tilt"])
        out["odometry_quality"] = float(self.odometry_quality)
        out["kinematics_quality"] = float(self.kinematics_quality)
        out["attitude_quality"] = float(self.attitude_quality)
        out["height"] = float(self.height)
        sl = self.slip
        for k, w in enumerate(WHEELS):
            out[f"slip_std_{w}"] = float(sl.slip_ratio_std[k])
            out[f"slip_valid_{w}"] = float(bool(sl.valid[k]))
            out[f"slip_event_{w}"] = float(bool(sl.events[k]))
        out["slip_quality"] = float(sl.quality)
        for label, x in zip(WHEELS, v["sinkage"], strict=True):
            out[f"sinkage_{label}"] = float(x)
        out["sinkage_quality"] = float(v["sinkage_quality"][0])
        if "pull_ratio" in v:  # the soil's pull curve identified
            for label, x in zip(WHEELS, v["pull_ratio"], strict=True):
                out[f"pull_ratio_{label}"] = float(x)
            out["slip_best_pull"], out["slip_best_efficiency"], out["soil_quality"] = (
                float(x) for x in v["soil_curve"]
            )
        if "wheel_torque" in v:  # a rig with motor currents
            for label, x in zip(WHEELS, v["wheel_torque"], strict=True):
                out[f"wheel_torque_{label}"] = float(x)
        return {
            k: v for k, v in out.items() if k == "pose" or not (isinstance(v, float) and math.isnan(v))
        }  # unknown: left out


def ground_lift(sinkage) -> np.ndarray | None:
    """How far the ground in view lies above each wheel's lowest point [m], from their sinkages.

    Args:
        sinkage: (4,) the wheels' reported sinkages [m] (NaN: not reported).

    Returns:
        Each wheel's sinkage (a wheel not reported: the others' median) where at least three
        wheels report ``GROUND_LIFT_MIN_SINKAGE`` or more; zeros where fewer do (rigid ground,
        or one wheel's reading alone, more often a shadow than soil); None where no wheel is
        reported.
    """
    z = np.asarray(sinkage, dtype=np.float64)
    if not np.isfinite(z).any():
        return None
    if np.count_nonzero(z >= GROUND_LIFT_MIN_SINKAGE) >= 3:  # NaN compares False
        return np.where(np.isfinite(z), z, np.nanmedian(z))
    return np.zeros_like(z)


class RoverEstimator:
    """The built-in estimator of a rig with a downward camera, a fisheye and (optionally) an IMU.

    Implements :class:`perception.estimator.Estimator`; :meth:`update` returns the names of
    :data:`perception.estimator.ESTIMATE_FIELDS` and :meth:`step_estimate` the full state.

    Args:
        rig: The sensors (one ``"fisheye"``, at most one ``"pinhole"``, one ``"imu"``, one
            ``"sun"`` sensor and one ``"wheel_encoders"``: their rates join the fisheye's in the
            slip filter) and the rover's kinematic model. Without a pinhole camera the
            fisheye gives the odometry too (the one-camera rig). A sun sensor is used only with
            an IMU (the sun's direction is levelled by its tilt).
        odometry: Odometry parameters (default: :meth:`FlowOdometryConfig.for_camera` of the
            downward camera, with ``odometry_overrides``).
        kinematics: Fisheye-kinematics parameters.
        slip: Slip-filter parameters (with an IMU, its gyro-bias prior from the data sheet).
        odometry_overrides: Odometry parameters that differ from ``for_camera``'s.
        fisheye_window: (axle roll [rad/s], axle travel [m/s], wheel steering [rad/s]): while the
            kinematics tracks every marker and joint, the fisheye is asked to render only the
            windows that hold the parts over the joint states these rates reach in one frame
            (:func:`perception.models.rover_parts.joint_window_parts`); None: never. The steering rate is
            raised to 1.25 times the rover's ``steer_max_rate`` if below (an inner wheel turns
            faster than its axle).
        odometry_gyro: With an IMU, give the odometry's 3-D fit the gyro's mean roll and pitch
            rates over each frame pair (default). False: vision only (the odometry paper's method).
        zero_steering_at_start: The rover stands at rest on its wheels with its steering centred
            when the time line starts (a simulated mission does): the fisheye frame taken then
            sets the steering's zero (:meth:`KinematicStateEstimator.zero_steering`) and the axle
            depths' (:meth:`KinematicStateEstimator.zero_depth`: the rest depths of the model's
            :meth:`~perception.models.rover.RoverKinematicModel.rest_depths` at the IMU's tilt,
            or without an IMU only the two axles' mean), which takes out most of a fisheye mount
            error's effect on the steering, and on the downward odometry's scale through the
            ground plane. False (default): the calibrated mount is trusted (a log may start
            anywhere).
        heading: The sun-heading filter's parameters (:class:`perception.fusion.sun_heading.HeadingConfig`;
            its ``start_std_deg`` is the start fix's heading uncertainty).
        odometry_camera: ``"auto"`` (the downward camera if the rig has one, else the fisheye),
            ``"downward"`` or ``"fisheye"`` (the fisheye's odometry even beside a downward
            camera, which is then not used).
        fisheye_odometry: The fisheye odometry's parameters (when it is the odometry). None: the
            defaults, or for a fisheye that reads out only the ground near its axis
            (``SensorSpec.ground_view_deg``) features 5 degrees inside that view.
        sinkage: The fisheye's sinkage measurement's parameters (None: the defaults); a
            wheel's sinkage is reported where its quality reaches
            :data:`perception.kinematics.sinkage.MIN_QUALITY`.

    Raises:
        ConfigError: The rig lacks a fisheye, or the downward camera ``odometry_camera`` asks
            for, or has two of a kind.
    """

    def __init__(
        self,
        rig: Rig,
        odometry: FlowOdometryConfig | None = None,
        kinematics: KinematicsConfig | None = None,
        slip: SlipConfig | None = None,
        odometry_overrides: dict | None = None,
        fisheye_window: tuple[float, float, float] | None = None,
        odometry_gyro: bool = True,
        zero_steering_at_start: bool = False,
        heading: HeadingConfig | None = None,
        odometry_camera: str = "auto",
        fisheye_odometry: FisheyeOdometryConfig | None = None,
        sinkage: SinkageConfig | None = None,
        soil: SoilIdConfig | None = None,
    ) -> None:
        down, fish, imu, sun = (
            rig.one("pinhole", "RoverEstimator"),
            rig.one("fisheye", "RoverEstimator"),
            rig.one("imu", "RoverEstimator"),
            rig.one("sun", "RoverEstimator"),
        )
        if odometry_camera not in ("auto", "downward", "fisheye"):
            raise ConfigError(f"odometry_camera: {odometry_camera!r}; use 'auto', 'downward' or 'fisheye'")
        if fish is None:
            raise ConfigError(
                f"rig: RoverEstimator needs a 'fisheye' sensor (and a 'pinhole' one, or the fisheye "
                f"gives the odometry too); this rig has {rig!r}"
            )
        if odometry_camera == "downward" and down is None:
            raise ConfigError(f"odometry_camera='downward': this rig has no 'pinhole' sensor ({rig!r})")
        if odometry_camera == "fisheye" or down is None:
            down = None  # the one-camera rig: the fisheye's odometry
            if odometry is not None:
                raise ConfigError(
                    "odometry: a FlowOdometryConfig is the downward camera's, and this estimator takes its "
                    "odometry from the fisheye; give fisheye_odometry= instead"
                )
        elif fisheye_odometry is not None:
            raise ConfigError(
                "fisheye_odometry: this estimator takes its odometry from the downward camera "
                f"{down.name!r}; give odometry_camera='fisheye' to use the fisheye's"
            )
        if rig.vehicle is None:
            raise ConfigError("rig: RoverEstimator needs the rover's kinematic model (Rig.vehicle)")
        self.rig = rig
        self.down, self.fish, self.imu = down, fish, imu
        self.model = rig.vehicle
        self.fisheye_window = fisheye_window
        self.odometry_gyro = bool(odometry_gyro)
        self.zero_steering_at_start = bool(zero_steering_at_start)
        self._zero_at: float | None = None  # the start's time, until its fisheye frame is seen
        self._steer_max_rate = rig.steer_max_rate
        nominal = self.model.wheel_frames(np.zeros(2), np.full(2, self.model.nominal_depth), np.zeros(4))
        self.odometry: FlowOdometry | FisheyeOdometry
        if down is not None:
            width = down.model.image_size[0]
            odo = odometry or FlowOdometryConfig.for_camera(width, down.rate_hz, **(odometry_overrides or {}))
            if odo.plane_anchor is None:  # the ground in view keeps its height at the front axle
                front = max(c[0] for _, c in nominal)
                ys = [c[1] for _, c in nominal if c[0] > front - 1e-6]
                odo = dataclasses.replace(odo, plane_anchor=(float(front), float(np.mean(ys))))
            self.odometry = FlowOdometry(down.model, odo, vignetting=down.vignetting, gamma=down.gamma)
        else:
            # the rover's parts over their joint range are left out (learned if the range is unknown)
            lim = self.model.joint_limits
            mask = None if lim is None else ~kinematics_roi(fish.model, self.model, *lim)
            fo = fisheye_odometry or FisheyeOdometryConfig.for_ground_view(
                fish.ground_view_deg, fish.model.image_size[0]
            )
            self.odometry = FisheyeOdometry(fish.model, fo, mask=mask)
        #: Which camera gives the odometry: ``"downward"`` or ``"fisheye"``.
        self.odometry_camera = "downward" if down is not None else "fisheye"
        self.kinematics = KinematicStateEstimator(
            fish.model, self.model, kinematics, gamma=fish.gamma, bayer=fish.bayer
        )
        #: Each wheel's sinkage from the fisheye (:mod:`perception.kinematics.sinkage`).
        self.sinkage = SinkageEstimator(fish.model, self.model, sinkage)
        #: The sinkages over the last frames' measurements (a frame's reading can flip).
        self.sinkage_track = SinkageTrack()
        self._sinkage = SinkageEstimate.none()
        self._sinkage_next = -math.inf
        # the ground above each wheel's lowest point [m], and when it was measured [s]
        self._lift = (np.zeros(4), -math.inf)
        slip = slip or SlipConfig()
        if imu is not None:
            R = imu.mount[:3, :3]
            self.R_body_imu = R
            self._imu_z = R[2]  # body-z component of a mount-frame rate
            self._gyro_density = imu.model.gyro.noise_density
            self.attitude = AttitudeFilter(R)
            # the gyro's bias prior from its data sheet: the turn-on spread, and a drift of the
            # bias instability over about 100 s on top of the random walk
            slip = dataclasses.replace(
                slip,
                gyro_bias_std=max(imu.model.gyro.turn_on_bias, 1e-6),
                gyro_bias_rw=imu.model.gyro.bias_random_walk + imu.model.gyro.bias_instability / 10.0,
            )
        self.slip = SlipEstimator(np.array([c[:2] for _, c in nominal]), self.model.wheel_radius, slip)
        #: The motor-current sensor (None without one): each step's median currents give the
        #: wheels' torques through its data sheet.
        self.currents = rig.one("motor_current", "RoverEstimator")
        self._current_batch: list[np.ndarray] = []
        self._torque: np.ndarray | None = None
        enc = rig.one("wheel_encoders", "RoverEstimator")
        #: The wheel encoders' rates (None without encoders), averaged over a fisheye frame.
        self.encoders = (
            None
            if enc is None
            else EncoderRates(
                enc.name, enc.model.counts_per_rev, enc.model.counter_bits, enc.period, fish.period
            )
        )
        #: The soil's pull curve, identified from the torques, slips, sinkages and the
        #: accelerometer (None without motor currents, an IMU or the rover's mass).
        self.soil: SoilIdentifier | None = None
        if self.currents is not None and imu is not None and self.model.mass > 0:
            m = self.model
            # the body's height over the ground, from the load a pitch moves between the axles
            h = m.axle_x * m.pitch_sag / m.rest_sag if m.rest_sag > 0 else 0.0
            if soil is None:  # the accelerometer's bias from its data sheet: offset and cross-axis g
                acc = imu.model.accel
                soil = SoilIdConfig(accel_bias_std=math.hypot(acc.turn_on_bias, acc.misalignment * G))
            self.soil = SoilIdentifier(m.wheel_radius, m.mass, m.axle_x, h, soil)
            self._wheel_xy = np.array([c[:2] for _, c in nominal])  # the wheels' centres, body x-y [m]
        # sensors whose samples are gathered, not acted on one by one (no dead reckoning up to each)
        self._batched = {s.name for s in (imu, enc, self.currents) if s is not None}
        #: The sun sensor (None without one, or without an IMU to level it) and its heading filter.
        self.sun = sun if imu is not None else None
        self.heading: HeadingFilter | None = None
        if self.sun is not None:
            m = self.sun.model
            assert imu is not None
            # the accelerometer's bias and its cross-axis coupling tilt its gravity; the gyro's x-y
            # bias, until the attitude filter has learnt it, tilts it by bias * time constant
            tilt = math.hypot(
                imu.model.accel.turn_on_bias / G,
                imu.model.accel.misalignment,
                imu.model.gyro.turn_on_bias * self.attitude.time_constant,
            )
            self.heading = HeadingFilter(heading, m.accuracy_deg, m.noise_deg, tilt)
        self._pose = np.zeros(3)
        self._fix = np.zeros(3)
        self._started = False
        self._t_pose = 0.0
        self._t = 0.0
        self._request: tuple[float, np.ndarray | None] | None = None
        #: Wall-clock seconds spent: estimating, and choosing readout windows.
        self.timing = {"perception": 0.0, "readout": 0.0, "sinkage": 0.0, "soil": 0.0}
        self._clear()

    def _clear(self) -> None:
        self._last_odom: OdometryEstimate | None = None
        self._imu_batch: list[np.ndarray] = []
        self._imu_t = 0.0
        self._gyro_xy: list[np.ndarray] = []
        self._imu_saturated = 0
        self._imu_used = 0
        self._attitude_s = 0.0
        self._attitude_ready = False
        self._attitude_q = 0.0
        self._z = 0.0
        self._twist = np.zeros(3)
        self._twist_hist: list[tuple[float, float, float]] = []
        self._force_sum = np.zeros(3)  # the step's specific force samples, body frame, summed
        self._force_n = 0
        self._soil_t: float | None = None

    # ------------------------------------------------------------------ the interface
    def reset(self, start_fix: Sequence[float]) -> None:
        """Start again from the start fix (x, y, yaw) [m, rad] (world frame).

        The next :meth:`update` starts the time line: its messages before its ``t`` are the
        settling before the start (an IMU's standstill, which calibrates the gyro).
        """
        fix = np.asarray(start_fix, dtype=np.float64)
        if fix.shape != (3,) or not np.all(np.isfinite(fix)):
            raise ValueError(f"start_fix={fix.tolist()}: give a finite (x, y, yaw) [m, rad]")
        self.odometry.reset()
        self.kinematics.reset()
        self.slip.reset()
        self._sinkage_next = -math.inf
        self._sinkage = SinkageEstimate.none()
        self.sinkage_track.reset()
        # the ground above each wheel's lowest point [m], and when it was measured [s]
        self._lift = (np.zeros(4), -math.inf)
        if self.encoders is not None:
            self.encoders.reset()
        self._current_batch = []
        self._torque = None
        if self.soil is not None:
            self.soil.reset()
        self._fix = fix.copy()
        self._pose = fix.copy()
        self._started = False
        self._request = (0.0, None)  # the fisheye renders whole until the kinematics tracks it
        self._clear()
        if self.imu is not None:
            self.attitude.reset()
        if self.heading is not None:
            self.heading.reset()

    def update(self, messages: Sequence[SensorMessage], t: float) -> dict[str, object]:
        """Consume the messages since the last call, in time order; the estimate at ``t`` [s].

        Returns the names of :data:`perception.estimator.ESTIMATE_FIELDS`.
        """
        if not self._started:
            self._started = True
            self._t_pose = self._t = float(t)
            self._zero_at = float(t) if self.zero_steering_at_start else None
            standstill = [m for m in messages if m.t < t - 1e-9]
            if standstill and self.imu is not None:
                self._calibrate_gyro(standstill, t)
            messages = [m for m in messages if m.t >= t - 1e-9]
        return self.process(messages, t).fields()

    def readout_request(self, sensor: str) -> tuple[float, np.ndarray | None] | None:
        """The fisheye's next readout window (once), as (t [s], body-frame points or None: whole)."""
        if sensor != self.fish.name or self._request is None:
            return None
        req, self._request = self._request, None
        return req

    # ------------------------------------------------------------------ the work
    def _calibrate_gyro(self, messages: Sequence[SensorMessage], t: float) -> None:
        """The gyro's bias from its samples while the rover stood settled, the last ``IMU_CALIBRATION_S``."""
        assert self.imu is not None
        still = np.array(
            [
                m.data[:6]
                for m in messages
                if m.sensor == self.imu.name and m.t >= t - IMU_CALIBRATION_S - 1e-9 and m.data[6] == 0
            ]
        ).reshape(-1, 6)
        if len(still):
            mean = still.mean(axis=0)
            window = len(still) * self.imu.period
            self.slip.calibrate_gyro(float(self._imu_z @ mean[:3]), self._gyro_density / np.sqrt(window))
            self.attitude.calibrate(mean[:3], mean[3:])
            self._attitude_ready = True

    def _window_parts(self) -> np.ndarray | None:
        """What the fisheye's next frame must show (see ``fisheye_window``)."""
        rates = self.fisheye_window
        s = self.kinematics.state
        if rates is None or s.markers_found < len(MARKERS):
            return None
        if not all(s.valid[f"{dof}_{a}"] for dof in ("psi", "d", "lam") for a in AXLES):
            return None
        roll, travel, steer = rates
        steer = max(steer, 1.25 * self._steer_max_rate)
        period = self.fish.period
        parts = joint_window_parts(
            self.model, s.psi, s.depth, s.delta, (roll * period, travel * period, steer * period)
        )
        return parts

    def _on_fisheye(self, img: np.ndarray, t: float) -> None:
        if self._zero_at is not None:
            if abs(t - self._zero_at) <= 1e-9:  # taken at rest, steering centred
                self.kinematics.zero_steering(img)
                rest = None
                if self.imu is not None and self._attitude_ready:
                    rest = self.model.rest_depths(self.attitude.roll, self.attitude.pitch)
                self.kinematics.zero_depth(img, rest)
            self._zero_at = None
        state = self.kinematics.update(img, t)
        self._measure_sinkage(img, state, t)
        if self.down is None:  # the one-camera rig: the fisheye's odometry on the wheels' plane now
            self._odometry_frame(img, t)
        if self.encoders is not None:  # a counter that stands while its wheel is seen turning
            self.encoders.check_stuck(state.theta_dot, [state.valid[f"theta_{w}"] for w in WHEELS], t)
        self.slip.add_wheels(
            t,
            state.theta_dot,
            self.fish.period,
            [state.valid[f"theta_{w}"] for w in WHEELS],
            state.delta,
            state.theta_dot_std,
        )
        t0 = time.perf_counter()
        self._request = (t + self.fish.period, self._window_parts())
        self.timing["readout"] += time.perf_counter() - t0

    def _measure_sinkage(self, img: np.ndarray, state: KinematicState, t: float) -> None:
        """Each wheel's sinkage in this fisheye frame, at the joints the kinematics measured in it."""
        if t < self._sinkage_next - 1e-9:
            return  # measured at SINKAGE_RATE_HZ; the last measurement stands until the next
        t0 = time.perf_counter()
        self._sinkage_next = t + 1.0 / SINKAGE_RATE_HZ
        measured = None
        if state.axles_valid:
            # the wheels stand where the image shows them: at the depths with their rest offset
            depth = state.depth + self.kinematics.depth_zero
            measured = self.sinkage.measure(img, state.psi, depth, state.delta)
        self._sinkage = self.sinkage_track.update(t, measured)
        lift = ground_lift(self._sinkage.reported()[0])
        if lift is not None:
            self._lift = (lift, t)
        self.timing["sinkage"] += time.perf_counter() - t0

    def wheel_ground_plane(self) -> tuple[float, float, float]:
        """The ground under the wheels of the kinematics' latest state, z = a x + b y + c (body) [-, -, m].

        The plane through the wheels' lowest points, each raised by its sinkage where at least
        three wheels report ``GROUND_LIFT_MIN_SINKAGE`` (a wheel whose sinkage was not reported
        by the median of the others'; held for ``GROUND_LIFT_HOLD_S``): on soil the ground in
        view is the soil's surface, not the rims' lowest points below it.
        """
        s = self.kinematics.state
        centres = np.array([c for _, c in self.model.wheel_frames(s.psi, s.depth, s.delta)])
        lift, t_lift = self._lift
        if self._t - t_lift <= GROUND_LIFT_HOLD_S:
            centres[:, 2] += lift
        return ground_plane_from_wheels(centres, self.model.wheel_radius)

    def _on_downward(self, img: np.ndarray, t: float) -> None:
        self._odometry_frame(img, t)

    def _odometry_frame(self, img: np.ndarray, t: float) -> None:
        """One frame of the odometry's camera: its estimate to the slip filter."""
        plane = self.wheel_ground_plane()
        if isinstance(self.odometry, FisheyeOdometry):  # the wheels' tracks anchor its scale
            s = self.kinematics.state
            frames = self.model.wheel_frames(s.psi, s.depth, s.delta)
            contacts = wheel_contacts(frames, self.model.wheel_radius, plane)
            est = self.odometry.update(
                img, t, ground_plane=plane, rate_xy=self._frame_rate_xy(), contacts=contacts
            )
        else:
            est = self.odometry.update(img, t, ground_plane=plane, rate_xy=self._frame_rate_xy())
        if est is not None:
            self._last_odom = est
            if est.valid:
                self.slip.add_odometry(t, est.twist, est.dt, est.quality, cov=est.twist_cov)
                if isinstance(self.odometry, FlowOdometry):
                    self._window_odometry(est, t)

    def _window_odometry(self, est: OdometryEstimate, t: float) -> None:
        """At a crawl, the odometry over the last ``WINDOW_TRAVEL`` of ground to the slip filter.

        The slip over a window of travel (:meth:`perception.fusion.slip.SlipEstimator.window_slip`)
        rests on it: frame to frame, a crawl reads a few per cent slow
        (:meth:`perception.odometry.flow.FlowOdometry.track_back`).
        """
        assert isinstance(self.odometry, FlowOdometry)
        window = self.slip.config.window_max
        step = math.hypot(est.twist[0], est.twist[1]) * est.dt  # ground a frame [m]
        if window <= 0 or step >= 0.5 * WINDOW_TRAVEL:
            return
        n = min(
            math.ceil(WINDOW_TRAVEL / max(step, 1e-9)),
            self.odometry.config.history_frames,
            int(window / est.dt),
        )
        w = self.odometry.track_back(n) if n >= 2 else None
        if w is not None and w.valid:
            self.slip.add_window_odometry(t - w.dt, t, w.twist, w.twist_cov, w.quality)

    def _velocity_rate(self) -> tuple[float, float]:
        """d(v_x, v_y)/dt of the fused twist over the last ``VELOCITY_RATE_S`` or more [m/s^2].

        The fused velocity rests on the odometry at every frame, whatever the attitude's error
        (the slip filter's accelerometer bias state takes up the gravity that leaks through it).
        In an odometry outage (:meth:`perception.fusion.slip.SlipEstimator.in_outage`) it does not, and
        its rate would feed the attitude's error back into the velocity: none is given then.
        """
        t, (vx, vy, _) = self._t_pose, self._twist
        hist = self._twist_hist
        if self.slip.in_outage(t):
            hist.clear()
            return 0.0, 0.0
        if not hist or t > hist[-1][0]:
            hist.append((t, vx, vy))
        while len(hist) > 2 and t - hist[1][0] >= VELOCITY_RATE_S:
            hist.pop(0)
        t0, vx0, vy0 = hist[0]
        if t - t0 < VELOCITY_RATE_S:
            return 0.0, 0.0
        return (vx - vx0) / (t - t0), (vy - vy0) / (t - t0)

    def _frame_rate_xy(self) -> np.ndarray | None:
        """The gyro's mean body roll and pitch rates since the odometry's last frame (None: no gyro)."""
        if self.imu is None or not self.odometry_gyro or not self._gyro_xy:
            self._gyro_xy = []
            return None
        w = self.R_body_imu[:2] @ np.mean(self._gyro_xy, axis=0) - self.attitude.bias[:2]
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
        assert self.imu is not None
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
        f = self.R_body_imu @ mean[3:]
        if self.soil is not None:
            self._force_sum += f * n
            self._force_n += n
        a = f - G * self.attitude.R[2]
        wz = rate - self.slip.gyro_bias[0]
        self.slip.add_accel(self._imu_t, (a[0] + wz * vy, a[1] - wz * vx), window)
        self._imu_batch = []

    def _on_encoders(self, data: np.ndarray, t: float) -> None:
        """A wheel-encoder reading: a window's rates to the slip filter when one is complete."""
        assert self.encoders is not None
        w = self.encoders.add(data, t)
        if w is not None and w.valid.any():
            self.slip.add_wheels(w.t, w.rate, w.dt, w.valid, noise=w.std)

    def _on_currents(self, data: np.ndarray, t: float) -> None:
        """A motor-current reading: kept for the step's torques (:meth:`MotorModel.step_torque`)."""
        assert self.currents is not None
        i = np.asarray(data, dtype=np.float64).reshape(-1)
        if i.shape != (4,):
            raise ValueError(
                f"{self.currents.name}: a motor-current sample is (4,) currents FL, FR, RL, RR [A]; "
                f"got shape {i.shape}"
            )
        self._current_batch.append(i)

    def _wheel_torque(self, wheel_rate: np.ndarray) -> None:
        """The step's wheel torques [N m] from the median of its currents (a spike is outvoted)."""
        batch, self._current_batch = self._current_batch, []
        if not batch:
            self._torque = None  # no reading this step: unknown, not the last one
            return
        assert self.currents is not None
        self._torque = self.currents.model.step_torque(np.array(batch), wheel_rate)

    def _soil_step(self, t: float, sl: SlipEstimate) -> None:
        """The step's torques, slips (``sl``), sinkages and specific force to the soil identification."""
        assert self.soil is not None
        t0 = time.perf_counter()
        force = self._force_sum / self._force_n if self._force_n else None
        self._force_sum, self._force_n = np.zeros(3), 0
        dt = 0.0 if self._soil_t is None else t - self._soil_t
        self._soil_t = t
        v = sl.twist[:2]
        centres = self._wheel_xy  # the kingpins: a steered wheel turns about its own
        x, y, yaw = self._pose
        cy, sy = math.cos(yaw), math.sin(yaw)
        xy = centres @ np.array([[cy, sy], [-sy, cy]]) + (x, y)
        sink = self._sinkage.reported()[0]
        distance = float(np.hypot(*v)) * dt
        if not math.isfinite(distance):
            distance = 0.0  # no velocity: no travel counted
        self.soil.add(distance, sl.slip_ratio, sl.valid, self._torque, sink, force, v, xy)
        self.soil.estimate(sl.slip_ratio, sl.valid)
        self.timing["soil"] += time.perf_counter() - t0

    def _on_sun(self, data: np.ndarray, t: float) -> None:
        """A sun reading: the heading it gives, fused into the dead-reckoned yaw."""
        assert self.sun is not None and self.heading is not None
        if data[6] > 0 or not np.all(np.isfinite(data[:6])) or not self._attitude_ready:
            return
        if abs(float(self._twist[2])) > self.heading.config.max_turn_rate:
            return
        a = self.attitude
        correction = self.heading.update(
            float(self._pose[2]), data[:3], self.sun.mount[:3, :3], data[3:6], a.roll, a.pitch
        )
        if correction is not None:
            self._pose[2] += correction

    def process(self, messages: Sequence[SensorMessage], t: float) -> StepEstimate:
        """Consume the messages of one step, in time order, and estimate the state at ``t``.

        Args:
            messages: Messages of the rig's sensors (others are ignored), sampled at or before
                ``t`` and after the previous call's time.
            t: The time the step ended [s].
        """
        t0 = time.perf_counter()
        handlers: dict[str, Callable[[np.ndarray, float], None]] = {self.fish.name: self._on_fisheye}
        if self.down is not None:
            handlers[self.down.name] = self._on_downward
        if self.imu is not None:
            handlers[self.imu.name] = self._on_imu
        if self.sun is not None:
            handlers[self.sun.name] = self._on_sun
        if self.encoders is not None:
            handlers[self.encoders.name] = self._on_encoders
        if self.currents is not None:
            handlers[self.currents.name] = self._on_currents
        for msg in messages:
            handler = handlers.get(msg.sensor)
            if handler is None:
                continue
            if msg.t < self._t_pose - 1e-9 or msg.t > t + 1e-9:
                raise ValueError(
                    f"{msg.sensor} message at t={msg.t} s is outside this step ({self._t_pose} to {t} s); "
                    "pass each step's messages once, in time order"
                )
            if msg.sensor in self._batched:  # IMU, encoders, currents: used at the next frame or the end
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
        sl = self.slip.estimate(self._t)
        if self.currents is not None:
            self._wheel_torque(sl.wheel_rate)
        if self.soil is not None:
            self._soil_step(t, sl)
        n = self._imu_used + self._imu_saturated
        self._attitude_q = self._imu_used / n if self._attitude_ready and n else 0.0
        out = self.step_estimate(sl)
        self.last_step = out
        self._imu_saturated = 0
        self._imu_used = 0
        self.timing["perception"] += time.perf_counter() - t0
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
            if self.heading is not None:
                std = self.slip.gyro_bias[1]
                self.heading.predict(dt, self._gyro_density**2 + std * std * YAW_WALK_MATCH_S)
            if self.imu is None:
                self._pose = arc_step(self._pose, twist, dt)
            else:  # on the tilted ground plane, turning at the world heading's rate
                a = self.attitude
                rate = a.heading_rate(float(twist[2]))
                self._pose, self._z = tilted_step(self._pose, self._z, twist, a.roll, a.pitch, rate, dt)
            self._t_pose = t1

    def step_estimate(self, sl: SlipEstimate | None = None) -> StepEstimate:
        """The full estimate at the last processed time (``sl``: the slip filter's then, if known)."""
        t = self._t
        if sl is None:
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
        }
        if self._torque is not None:
            values["wheel_torque"] = self._torque.copy()
        if self.soil is not None and self.soil.last.identified:
            cur = self.soil.last
            values["pull_ratio"] = cur.wheel_pull_ratio.copy()
            values["soil_curve"] = np.array([cur.slip_best_pull, cur.slip_best_efficiency, cur.quality])
        sink, q_sink = self._sinkage.reported()
        values["sinkage"] = sink
        values["sinkage_quality"] = np.array([q_sink])
        if self.imu is None:
            return StepEstimate(values, q_odo, q_kin, 0.0, sl, odo, ks)
        tilt = (self.attitude.roll, self.attitude.pitch)
        q_att = self._attitude_q
        values["tilt"] = np.array(tilt)
        bias = self.slip.gyro_bias
        h = self.heading
        return StepEstimate(
            values,
            q_odo,
            q_kin,
            q_att,
            sl,
            odo,
            ks,
            self._imu_saturated,
            bias,
            tilt,
            self._z,
            None if h is None else h.yaw_std,
            0 if h is None else h.used,
        )

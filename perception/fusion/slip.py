"""Per-wheel slip from vision: ground velocity (visual odometry) against wheel spin (fisheye).

The odometry gives the body twist (v_x, v_y, omega) over each frame pair of its camera (the
downward camera, or on the one-camera rig the fisheye itself); the
fisheye gives each wheel's spin rate theta_dot over each fisheye frame interval and the wheels'
steering angles. A Kalman filter over x = (v_x, v_y, omega, theta_dot_FL, ..., theta_dot_RR)
with a random-walk (constant-velocity) model fuses both streams in time order; each measurement
is an average over its frame interval, so it is applied at the interval's middle. With an IMU,
a gyro's yaw rate (:meth:`SlipEstimator.add_gyro`) comes in with its bias, and an accelerometer's
horizontal acceleration (:meth:`SlipEstimator.add_accel`) drives the velocity's prediction, its
bias estimated, while the wheel rates then integrate angular accelerations: both sides of the
slip ratio are carried from the middle of the last frame to the query time, so a wheel that
spins up while the body does not reads as slip at once. Slip follows from the filtered state:

    v_i = R(-delta_i) (v_body + omega x p_i)                   ground velocity of wheel centre i
    s_i = (theta_dot_i r - v_i,long) / max(|theta_dot_i r|, |v_i,long|, eps)
    beta_i = atan2(v_i,lat, v_i,long)

with its standard deviation from the filter's covariance (first order, then through the clip to
[-1, 1] as a censored normal).

Wheels mostly grip, so each measured wheel rate also brings a pseudo-measurement of zero slip,
s_i ~ N(0, grip_std^2), i.e. v_i,long = theta_dot_i r with a deviation of grip_std times the
wheel's speed: the wheel odometry that rovers fuse with visual odometry. It is gated: a wheel whose
innovation exceeds ``grip_gate`` standard deviations slips and adds nothing, so slip well above the
odometry's noise is measured as before, while the noise of the visual odometry on rough ground
(its planar model leaves out pitch and relief) no longer reads as slip. It is used only where the
measurements alone resolve the slip (the filter's deviation of v_i,long - theta_dot_i r is at most
``max_slip_std`` times the wheel's speed): under poor odometry a wheel that spins with all the
others is not taken for a gripping one. Slip events switch on
when |s| reaches ``event_on`` and off when it falls below ``event_off`` (hysteresis).

Frames: body frame x forward, y left, z up; wheel order FL, FR, RL, RR.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.special import ndtr

from perception.models.drive_geometry import WHEELS
from perception.models.wheel_kinematics import slip_angle, slip_ratio, wheel_ground_velocity

log = logging.getLogger(__name__)

N_WHEELS = 4
#: |slip ratio| at which a wheel slips: a true slip event is slip above it for two frames in a
#: row (between 0.15 and it, neither an event nor a false alarm), and the filter's events switch on there.
SLIP_EVENT = 0.2
#: Readings beyond these magnitudes are no rover's: they are left out, counted and logged
#: (speed [m/s], yaw rate [rad/s], wheel rate [rad/s], acceleration [m/s^2]).
MAX_SPEED, MAX_YAW_RATE, MAX_WHEEL_RATE, MAX_ACCEL = 50.0, 50.0, 500.0, 1000.0
_BIAS = 3 + N_WHEELS  # index of the gyro's yaw-rate bias in the state
_ODOM_BIAS = _BIAS + 1  # index of the odometry's yaw-rate bias (estimated only with a gyro)
_ACC_BIAS = _ODOM_BIAS + 1  # the accelerometer's x and y bias (estimated only with one)
_WHEEL_ACC = _ACC_BIAS + 2  # the wheels' angular accelerations
_N_STATE = _WHEEL_ACC + N_WHEELS


@dataclass(frozen=True)
class SlipConfig:
    """Parameters of :class:`SlipEstimator`.

    Attributes:
        velocity_rw: Process noise: random walk of v_x and v_y [m/s per sqrt(s)]; their
            variance grows by velocity_rw^2 per second between measurements.
        yaw_rate_rw: The same for omega [rad/s per sqrt(s)].
        wheel_rate_rw: The same for each wheel rate [rad/s per sqrt(s)]: a wheel that loses
            traction spins up far faster than the body accelerates.
        odom_std: Odometry noise (v_x, v_y, omega) at quality 1 [m/s, m/s, rad/s]; divided by
            the quality (at least ``min_quality``).
        min_quality: Floor of the quality used to scale ``odom_std``.
        rate_std: Wheel-rate noise: (floor [rad/s], share of |rate|).
        rate_std_own: With a rate's own deviation (:meth:`SlipEstimator.add_wheels` ``std``),
            its noise is the larger of ``rate_std`` and this share of that deviation (0: the
            deviations are ignored). At 1 (the deviation as fitted) a face-on wheel's rates
            weigh less than with ``rate_std`` alone, and the filter follows a wheel that brakes
            within a frame (a turn's inner wheels) a frame later. Replayed on closed-loop drives
            with field cameras (``benchmarks/slip_replay.py record --closed-loop ...
            --camera-effects field``, seeds 100-104, no IMU): the slip-unaware follower's skids
            on flat and rough ground were caught 27 times of 28 at 0.5, 23 at 1; the slip-aware
            drives of the loose slope made 1 false event at 0.5, 2 at 1 and 20 at 0. Measured
            again with the local-plane odometry and the events' hold (``rover eval``, seeds
            100-104) those drives made 1.8 false events a run at 0.5, single-frame misreads of
            a wheel at 0.2-0.3 m/s; at 0.75, as with an IMU, replays gave (0.5 -> 0.75) on the
            loose slope's drives of seeds 105-107 1 -> 0 false events, on the slip-unaware
            follower's of seeds 100-102 the same 17 of 18 skids caught, and on the scripted
            drives' seed sets (train 421, 521, 541, 551, 561, 571; eval 541, 551, 571) false
            events 9, 12, 4, 9, 4, 9; 1, 11, 2 -> 9, 8, 3, 6, 4, 9; 1, 11, 2, none missed more.
        init_std: Prior standard deviation of the state before any measurement
            (v [m/s], omega [rad/s], wheel rate [rad/s]).
        min_speed: Slip is reported as resolved only when the wheel's tread or ground speed
            reaches this [m/s]; below it the ratio is noise over noise.
        max_slip_std: Slip with a larger standard deviation is not valid.
        max_age: A wheel's slip is not valid when the last odometry or its last rate is older
            than this [s]. The default lets two 30 Hz frames go missing, not three: the rates'
            angular accelerations carry a wheel through them, and the slip's deviation grows
            with the gap. The fisheye misses a spinning wheel's treads for a frame or two, 10 to
            17 % of the time in the shadow mission; allowing two took its slip events' F1 from
            0.830 to 0.868 in the replays named under ``wheel_accel_rw`` (seed set 241).
        event_on: |s| at which a slip event starts ...
        event_hold: ... once it has stayed there this long [s] (0: at once; the default, just
            under one 30 Hz frame, asks for two frames in a row and ignores one-frame spikes).
        event_confirm: An event also needs a second measurement of the wheel's rate while it
            lasts (the rate that raised |s| to ``event_on`` and a newer one), or a third
            estimate above ``event_on`` (2 ``event_hold``). A wrong tread alignment is a single
            frame's, so without this one outlier carried through a missed frame makes an event;
            a wheel that the fisheye misses for two frames as it spins up is carried by its
            angular acceleration, and its third estimate above confirms it. Only with an
            ``event_hold`` above 0 (0 starts an event at once).
        event_sure: An event also starts in its first estimate above ``event_on`` where |s| stands
            this many of its standard deviations above it and was at least ``event_off`` in the
            estimate before (the last query at an earlier time; 0: off). The estimates are frame
            means: a wheel that brakes within a frame reads half-way in that frame and fully a
            frame late, so a true event of two frames above 0.2 shows as one frame near 0.15,
            one well above 0.2 and one near it. One outlying rate from steady rolling (|s| near
            0 before it) still needs a second frame. In the replays named under
            ``rate_std_own`` it caught 9 of 10 skids on flat ground and 18 of 18 on rough ground,
            against 5 and 16 without it, with 1 and 1 more false events (7 and 5 in all); on the
            loose slope it changed nothing. An estimate before that was too wide to be valid
            (``max_slip_std``) counts at its lower bound |s| - std where that reaches
            ``event_off`` (and the wheel is at ``event_min_speed``): a wheel driving off from
            reverse at 0.15-0.3 m/s of tread reads so for a frame or two, then its first valid
            estimate starts the event (on the six seed sets of the field-camera slip drives: 4
            more of 885 onsets within two frames, 6 more false events, 47 in all).
        event_sure_gap: ... and where |s| stands this many of its deviations above ``event_on``
            after an estimate that resolved no slip (a wheel through zero speed as it reverses,
            or missed for longer than ``max_age``): such an estimate says nothing of low slip,
            but a first estimate after it is more often an outlier.
        event_off: |s| below which it ends. Estimates that resolve no slip (not valid: too wide,
            or inputs older than ``max_age``) on a wheel at ``event_min_speed`` hold an event
            for ``max_age`` after its last resolved estimate: ended at once, an event split in
            two around such an estimate, and its second half, after the truth's, was a false
            one (scripted slip drives replayed by ``benchmarks/slip_replay.py``, field cameras,
            train preset: false events 12 to 9 on seed set 421 and 6 to 4 on set 541, no event
            missed).
        event_min_speed: Events hold only while the wheel's tread or ground speed reaches this
            [m/s]. Below it a ratio of ``event_on`` is a speed difference of under 0.03 m/s, the
            size of the odometry's noise at the training resolution, and every reversal of a
            wheel sends the ratio through +-1 for a frame or two as its speed passes zero.
        eps: Denominator floor of the slip ratio [m/s] (the ground truth's).
        grip_std: Slip standard deviation of a gripping wheel, the zero-slip pseudo-measurement
            that each measured wheel rate brings (0: none; the filter then rests on the visual
            odometry alone). Applied while the wheel's speed reaches ``event_min_speed``, at
            most once in three quarters of a rate measurement's window: the wheel encoders'
            rates of a frame, beside the fisheye's, do not double the prior.
        grip_gate: The pseudo-measurement is left out for a wheel whose new rate measurement,
            or the filter's rate after it, puts its slip this many standard deviations from
            zero (that wheel slips). It is also left out where the measurements alone do not
            resolve the wheel's slip to ``max_slip_std``. Gating on the filtered rate alone let
            the pseudo-measurements of earlier frames hold a wheel that spins up slowly at grip:
            in the shadow mission's drives a front wheel read no slip for ten frames of true
            slip 0.2-0.35.
        gyro_bias_std: Prior standard deviation of a gyro's yaw-rate bias [rad/s] (its turn-on
            bias); the bias is estimated only when :meth:`SlipEstimator.add_gyro` is used.
        gyro_bias_rw: Random walk of that bias [rad/s per sqrt(s)] (its drift).
        odom_yaw_bias_std: With a gyro, the odometry's yaw rate is given a slowly varying bias
            of this prior standard deviation [rad/s]: on rough ground its planar model turns
            the relief under the camera into a yaw rate of the order of 0.01 rad/s, which would
            otherwise pass into the gyro's bias.
        odom_yaw_bias_rw: Random walk of that bias [rad/s per sqrt(s)].
        accel_velocity_rw: With an accelerometer (:meth:`SlipEstimator.add_accel`), the body's
            velocity is predicted with its measured acceleration up to the query time, and only
            this is left of the velocity's random walk [m/s per sqrt(s)] (vibration, the lever
            arm, the planar model).
        accel_bias_std: Prior deviation of the accelerometer's horizontal bias [m/s^2]: its
            own, and gravity leaking through the attitude's error.
        accel_bias_rw: Random walk of that bias [m/s^2 per sqrt(s)] (the attitude filter takes
            a lasting acceleration partly for tilt, so the leak changes within seconds).
        accel_wheel_rate_rw: With an accelerometer, the wheel rates' random walk [rad/s per
            sqrt(s)] in place of ``wheel_rate_rw``.
        wheel_accel_std: Prior deviation of each wheel's angular acceleration [rad/s^2]: each
            wheel's rate integrates an angular acceleration (a random walk itself), so that the
            rates follow a wheel that spins up or brakes between the frames and through a
            missed one. With rates held as random walks, a wheel spinning up at 26 rad/s^2
            (0.9 rad/s a frame) read 2-3 rad/s behind its measurements, 0.2 in slip.
        wheel_accel_rw: ... and its random walk [rad/s^2 per sqrt(s)]. At 10 the shadow
            mission's slip onsets came within two frames 91-95 % of the time in the replays of
            ``benchmarks/slip_replay.py`` (scripted drives, train preset, field cameras, seed
            sets 221, 231 and 241), at 20 95-100 %.
        outage_after: After this long without a valid odometry twist [s] (a textureless,
            dark or blurred ground), each wheel-rate measurement also brings the rolling
            wheels' kinematics as a loose pseudo-measurement: the wheels' mean longitudinal
            speed is their mean tread speed and their mean lateral speed is zero, each to
            ``outage_slip_std`` of the speed. Without it the velocity was held (no
            accelerometer) or integrated the accelerometer's bias and the gravity leaking
            through the attitude's error for as long as the outage lasted: 7 s on a
            textureless, randomised loose slope took v_x to -2.4 m/s at a true +0.4 and the
            dead-reckoned goal 12 m off. A slip is never valid in an outage (``max_age``), so the
            assumed rolling never reads as a measured zero slip. ``math.inf``: off.
        outage_slip_std: The deviation of that pseudo-measurement, a share of the wheels' speed
            (at least ``event_min_speed``): a slip of this size is allowed for.
        accel_rate_std_own: With an accelerometer, ``rate_std_own`` in its place. The velocity
            is then known far better than the wheel rates, so the rates' own errors (their
            tails: a wheel seen obliquely on the loose slope reads 3-4 deviations off for two
            or three frames) decide the false events. Replayed on closed-loop drives with the
            BMI088 (field cameras, seeds 100-104): at 0.75 the slip-unaware follower's skids on
            flat and rough ground were caught 29 times of 29 with 1 false event, and the
            slip-aware drives of the loose slope made 3; at 0.5, 29 with 3, and 8.

        window_max: A wheel whose slip one frame does not resolve (``max_slip_std``: a wheel
            crawling, where 0.01 m/s of speed is a slip of 0.1) is given its slip over a window
            of travel instead: its mean tread speed from the rate measurements and its mean
            ground speed from the odometry twists over the same time, 1 - ground / tread. The
            window runs back from the wheel's latest rate, over whole frames, until the ratio's
            deviation is within ``window_std``, at most this long [s]; a window whose deviation
            stays above ``max_slip_std`` gives nothing. Measurements, not filtered states: their
            errors are independent from frame to frame and average out over the window. Where
            the odometry over a longer baseline is given (:meth:`SlipEstimator.add_window_odometry`:
            frame to frame, a crawl reads a few per cent slow), its latest window is used. Only
            twists of quality ``window_min_quality`` or more are taken: a poor odometry's errors
            need not average out. On the soil missions' slip-aware drives (BMI088, field cameras,
            seed 0) on ``RoverSoftSand-v0`` the slip while slipping erred by 0.37 with 15 % of those frames
            resolved (the others read 0); with the windows, by 0.028 with all resolved, and on
            ``RoverSlopeLoose-v1`` by 0.027.
        window_std: The deviation at which the window stops growing.
        window_scale_std: The odometry's scale error, a share of its speed, in the window's
            deviation: it does not average out (the ground plane under the wheels on soil: 1-3 %).
        window_min_speed: A window's mean tread or ground speed must reach this [m/s].
        window_min_quality: Smallest odometry quality taken into a window.

    The slip is that of the state at the wheels' latest rates (the middle of the fisheye's last
    frame), held to the query time with the variance growth of ``velocity_rw``,
    ``yaw_rate_rw`` and ``wheel_rate_rw``. Extrapolating the wheels' angular accelerations to
    the query time instead doubled the rates' deviation: short skids of a turn's inner wheels
    read as unresolved, and the slip-unaware follower's skids on flat and rough ground were
    caught 11 times of 29 in replays with the BMI088. Without an accelerometer that state
    includes the odometry of the same frame pair, which comes after the rates: taken before it,
    the velocity was a frame old and a rover braking at 3 m/s^2 read a slip of -0.3 with its
    wheels gripping (in the replays named under ``wheel_accel_rw``, 48-89 false events a seed
    set against 11-16). With one, the accelerometer has carried the velocity to the rates'
    time, and the odometry taken in as well made 7 false events in 15 closed-loop runs of the
    slip-aware follower (seeds 100-104) against 4. A wheel's rate, driven by its motor,
    steps early in a frame when the rover speeds up, so the frame's mean rate is close to its
    rate at the frame's end, while the body's speed rises smoothly. Without an accelerometer
    v_x is therefore carried to the query time at the rate of change of the last two odometry
    twists while the rover speeds up (with one, the accelerometer has carried it to the rates'
    time). Without that a rover speeding up at 4 m/s^2 read a slip of +0.3 with true slip
    +0.1. A wheel that skids as the rover brakes slows through the frame instead, and carrying
    v_x there too missed a recorded skid (``tests/data/skid_rover_v0_seed100_bmi088.npz``).
    The motors brake the wheels early in a frame too (at a reversal), and a slip read against
    the frame-old speed stands at 0.2-0.4 for a frame with the wheels gripping; growing v_x's
    variance by the square of the change not carried removed a third of those false events
    in the scripted drives, but made the slip-unaware follower's braking skids in closed loop
    unresolved (caught 14 of 18 times instead of 17 in replays of seeds 100-102, field
    cameras), so it is not done.

    In the replays of the scripted slip drives (see ``wheel_accel_rw``), these choices (the
    wheels' angular accelerations, the grip gate on the measurement, the state of the rates'
    time with that time's odometry, v_x carried while speeding up, two missed frames, and the
    event rules above) took the slip onsets within two frames from 92.4 / 94.5 / 93.5 % to
    98.2 / 100 / 98.6 % of the events, with F1 0.966 / 0.962 / 0.959 before and 0.955 /
    0.955 / 0.956 after.
    """

    velocity_rw: float = 0.15
    yaw_rate_rw: float = 0.3
    wheel_rate_rw: float = 1.0
    odom_std: tuple[float, float, float] = (0.01, 0.01, 0.02)
    min_quality: float = 0.05
    rate_std: tuple[float, float] = (0.05, 0.01)
    rate_std_own: float = 0.75
    init_std: tuple[float, float, float] = (2.0, 2.0, 20.0)
    min_speed: float = 0.05
    max_slip_std: float = 0.1
    max_age: float = 0.07
    event_on: float = SLIP_EVENT
    event_hold: float = 0.03
    event_confirm: bool = True
    event_sure: float = 1.0
    event_sure_gap: float = 4.0
    event_off: float = 0.1
    event_min_speed: float = 0.15
    eps: float = 0.01
    grip_std: float = 0.03
    grip_gate: float = 2.5
    gyro_bias_std: float = 0.02
    gyro_bias_rw: float = 1e-4
    odom_yaw_bias_std: float = 0.01
    odom_yaw_bias_rw: float = 1e-3
    accel_velocity_rw: float = 0.05
    accel_bias_std: float = 0.2
    accel_bias_rw: float = 0.1
    accel_wheel_rate_rw: float = 2.0
    wheel_accel_std: float = 10.0
    wheel_accel_rw: float = 20.0
    accel_rate_std_own: float = 0.75
    outage_after: float = 0.5
    outage_slip_std: float = 0.25
    window_max: float = 1.0
    window_std: float = 0.03
    window_scale_std: float = 0.02
    window_min_speed: float = 0.02
    window_min_quality: float = 0.5

    def __post_init__(self) -> None:
        for name in ("velocity_rw", "yaw_rate_rw", "wheel_rate_rw", "min_quality", "min_speed", "max_age"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SlipConfig.{name}: {getattr(self, name)!r} must be > 0")
        if not (math.isfinite(self.rate_std_own) and self.rate_std_own >= 0):
            raise ValueError(f"SlipConfig.rate_std_own: {self.rate_std_own!r} must be finite and >= 0")
        if len(self.odom_std) != 3 or min(self.odom_std) <= 0:
            raise ValueError(f"SlipConfig.odom_std: {self.odom_std!r}; give three values > 0")
        if len(self.rate_std) != 2 or self.rate_std[0] <= 0 or self.rate_std[1] < 0:
            raise ValueError(f"SlipConfig.rate_std: {self.rate_std!r}; give (floor > 0, share >= 0)")
        if not (self.grip_std >= 0 and self.grip_gate > 0):
            raise ValueError(
                f"SlipConfig: grip_std={self.grip_std!r} must be >= 0 and grip_gate={self.grip_gate!r} > 0"
            )
        if not (self.odom_yaw_bias_std > 0 and self.odom_yaw_bias_rw >= 0):
            raise ValueError(
                f"SlipConfig: odom_yaw_bias_std={self.odom_yaw_bias_std!r} must be > 0 and "
                f"odom_yaw_bias_rw={self.odom_yaw_bias_rw!r} >= 0"
            )
        if not (self.gyro_bias_std > 0 and self.gyro_bias_rw >= 0):
            raise ValueError(
                f"SlipConfig: gyro_bias_std={self.gyro_bias_std!r} must be > 0 and "
                f"gyro_bias_rw={self.gyro_bias_rw!r} >= 0"
            )
        for name in (
            "accel_velocity_rw", "accel_bias_std", "accel_bias_rw", "accel_wheel_rate_rw", "wheel_accel_std",
            "wheel_accel_rw", "accel_rate_std_own",
        ):  # fmt: skip
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"SlipConfig.{name}: {v!r} must be finite and >= 0")
        if not (self.outage_after > 0 and math.isfinite(self.outage_slip_std) and self.outage_slip_std > 0):
            raise ValueError(
                f"SlipConfig: outage_after={self.outage_after!r} s must be > 0 (inf: off) and "
                f"outage_slip_std={self.outage_slip_std!r} finite and > 0"
            )
        for name in ("event_sure", "event_sure_gap"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(
                    f"SlipConfig.{name}: {getattr(self, name)!r} must be finite and >= 0 (0: off)"
                )
        if not (
            self.window_max >= 0
            and self.window_std > 0
            and self.window_scale_std >= 0
            and self.window_min_speed > 0
        ):
            raise ValueError(
                f"SlipConfig: window_max={self.window_max!r} s must be >= 0 (0: off), window_std="
                f"{self.window_std!r} > 0, window_scale_std={self.window_scale_std!r} >= 0, "
                f"window_min_speed={self.window_min_speed!r} m/s > 0, window_min_quality="
                f"{self.window_min_quality!r} in [0, 1]"
            )
        if not self.event_hold >= 0:
            raise ValueError(f"SlipConfig.event_hold: {self.event_hold!r} s must be >= 0")
        if not 0 < self.event_off < self.event_on <= 1:
            raise ValueError(
                f"SlipConfig: event_off={self.event_off}, event_on={self.event_on}; "
                "need 0 < event_off < event_on <= 1"
            )


@dataclass
class SlipEstimate:
    """Filtered state and slip at one time. Wheel order FL, FR, RL, RR.

    Attributes:
        t: Time [s].
        twist: (v_x, v_y, omega) body frame [m/s, m/s, rad/s].
        twist_std: Their standard deviations.
        wheel_rate: Wheel spin rates [rad/s].
        wheel_rate_std: Their standard deviations.
        v_long: Ground velocity of each wheel centre along its heading [m/s].
        v_lat: Across it, left + [m/s].
        slip_ratio: Longitudinal slip ratio in [-1, 1] (0 where not valid: ``info`` and
            ``valid`` tell such a 0 from a measured one).
        slip_ratio_std: Its standard deviation (first order, through the clip; inf where not
            valid).
        slip_angle: Slip angle [rad] (0 where not valid).
        valid: Whether each wheel's slip is resolved: moving (``min_speed``), fresh data of both
            streams (``max_age``) and a standard deviation of at most ``max_slip_std``. Events
            hold only while it is.
        events: Whether each wheel is in a slip event (hysteresis on |slip_ratio|).
        quality: Share of the wheels whose slip is valid (0-1).
    """

    t: float
    twist: np.ndarray
    twist_std: np.ndarray
    wheel_rate: np.ndarray
    wheel_rate_std: np.ndarray
    v_long: np.ndarray
    v_lat: np.ndarray
    slip_ratio: np.ndarray
    slip_ratio_std: np.ndarray
    slip_angle: np.ndarray
    valid: np.ndarray
    events: np.ndarray
    quality: float = field(default=0.0)


def slip_events(
    slip: np.ndarray,
    on: float = SLIP_EVENT,
    off: float = 0.1,
    min_frames: int = 1,
    speed: np.ndarray | None = None,
    min_speed: float = 0.15,
) -> np.ndarray:
    """Slip events along a sequence by hysteresis: on when |s| >= ``on``, off when |s| < ``off``.

    The rule :class:`SlipEstimator` applies, for labelling a slip sequence sampled once per frame.

    Args:
        slip: (T, ...) slip ratios over time (NaN: no event).
        on: |s| at which an event starts ...
        off: |s| below which it ends.
        min_frames: ... at the ``min_frames``-th sample in a row with |s| >= ``on``.
        speed: (T, ...) the wheels' speeds, max(|tread speed|, |ground speed|) [m/s]; with it,
            samples below ``min_speed`` are no event (``SlipConfig.event_min_speed``).
        min_speed: [m/s].

    Returns:
        (T, ...) bool.
    """
    if min_frames < 1:
        raise ValueError(f"min_frames: {min_frames!r}; use >= 1")
    s = np.abs(np.asarray(slip, dtype=np.float64))
    if speed is not None:
        v = np.asarray(speed, dtype=np.float64)
        if v.shape != s.shape:
            raise ValueError(f"speed: shape {v.shape}; expected the slip's {s.shape}")
        s = np.where(v >= min_speed, s, 0.0)
    out = np.zeros(s.shape, bool)
    state = np.zeros(s.shape[1:], bool)
    run = np.zeros(s.shape[1:], int)
    for k in range(len(s)):
        with np.errstate(invalid="ignore"):
            above = s[k] >= on
            run = np.where(above, run + 1, 0)
            state = np.where(state, s[k] >= off, run >= min_frames)
        out[k] = state
    return out


class SlipEstimator:
    """Per-wheel slip ratio and slip angle from the odometry twist and the optical wheel rates.

    Feed measurements with :meth:`add_odometry` and :meth:`add_wheels` (or :meth:`update` with
    the estimators' result objects) and read the filtered slip with :meth:`estimate`. Within
    one call of :meth:`estimate`, measurements are applied in the order of their times, so the
    two streams may arrive in any order up to the query time; one older than what the filter has
    already applied is applied at the filter's time.

    Args:
        wheel_xy: (4, 2) wheel-centre positions in the body frame [m].
        wheel_radius: [m].
        config: Parameters.
    """

    def __init__(self, wheel_xy, wheel_radius: float, config: SlipConfig | None = None) -> None:
        xy = np.asarray(wheel_xy, dtype=np.float64)
        if xy.shape != (N_WHEELS, 2) or not np.all(np.isfinite(xy)):
            raise ValueError(f"wheel_xy: shape {xy.shape}; expected finite (4, 2) body-frame positions [m]")
        if not (math.isfinite(wheel_radius) and wheel_radius > 0):
            raise ValueError(f"wheel_radius: {wheel_radius!r}; expected a positive length [m]")
        self.wheel_xy = xy
        self.wheel_radius = float(wheel_radius)
        self.config = config or SlipConfig()
        self.reset()

    def reset(self) -> None:
        """Forget every measurement (a new episode or log)."""
        c = self.config
        # twist, wheel rates, gyro and odometry yaw-rate biases, accelerometer bias, wheel accelerations
        self._x = np.zeros(_N_STATE)
        v0, w0, r0 = c.init_std
        biases = [c.gyro_bias_std**2, c.odom_yaw_bias_std**2] + [c.accel_bias_std**2] * 2
        biases += [c.wheel_accel_std**2] * N_WHEELS
        self._P = np.diag([v0**2, v0**2, w0**2] + [r0**2] * N_WHEELS + biases)
        self._gyro_used = False
        self._accel_used = False
        self._inputs: list[tuple[float, float, float, float]] = []  # (t0, t1, a_x, a_y) [s, m/s^2]
        self._t: float | None = None
        # (time [s], sequence, state indices or None, z, R, H or None)
        self._pending: list[tuple[float, int, Any, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._steer = np.zeros(N_WHEELS)
        self._t_odom = -math.inf
        self._t_first = math.inf  # the first measurement's time [s]
        self._t_rate = np.full(N_WHEELS, -math.inf)
        self._t_grip = np.full(N_WHEELS, -math.inf)  # each wheel's last zero-slip pseudo-measurement [s]
        self._rate_dt = 0.0  # the latest rate measurement's window [s]
        self._events = np.zeros(N_WHEELS, bool)
        self._event_seen = np.full(N_WHEELS, -math.inf)  # an event's last resolved estimate [s]
        self._above_since = np.full(N_WHEELS, math.nan)  # when |s| last rose to event_on [s]
        self._above_rate = np.full(N_WHEELS, math.nan)  # the wheel's last rate measurement then [s]
        self._last_t = -math.inf  # time of the last estimate [s] ...
        # ... and its |s| (NaN where not resolved or slow; where resolved too widely to be valid,
        # the lower bound |s| - std if that is at least event_off)
        self._last_mag = np.zeros(N_WHEELS)
        self._mag_before = np.zeros(N_WHEELS)  # |s| at the estimate before that time
        self._at_rates: tuple[float, np.ndarray, np.ndarray] | None = None  # (t, x, P) after the last rates
        self._seq = 0
        # the last two odometry v_x: (time [s], v_x [m/s], its variance [m^2/s^2])
        self._odom_v: list[tuple[float, float, float]] = []
        self.rejected = 0  # readings left out as impossible (see MAX_SPEED and the others)
        # the window's measurements (window_max): odometry (t0, t1, each wheel's v_long and its
        # variance) and rates (t0, t1, which wheels, tread speeds, their variances) [s, m/s, m^2/s^2]
        self._odo_win: list[tuple[float, float, np.ndarray, np.ndarray]] = []
        self._rate_win: list[tuple[float, float, np.ndarray, np.ndarray, np.ndarray]] = []
        self._odo_long: list[tuple[float, float, np.ndarray, np.ndarray]] = []  # add_window_odometry's

    # ------------------------------------------------------------------ inputs
    def add_odometry(self, t: float, twist, dt: float, quality: float = 1.0, cov=None) -> None:
        """A body-twist measurement from the downward camera.

        Args:
            t: Time of the later frame of the pair [s].
            twist: (v_x, v_y, omega), the average over the pair [m/s, m/s, rad/s].
            dt: Time between the pair's frames [s]; the measurement applies at t - dt/2.
            quality: The odometry's quality in (0, 1] (ValueError above 1); without ``cov`` it
                scales the noise ``odom_std`` by 1/quality; 0 or NaN: invalid, left out.
            cov: (3, 3) covariance of the twist (the odometry's ``twist_cov``), if known; the
                noise is then ``cov`` plus ``odom_std`` squared on the diagonal (a floor).
                ValueError unless finite, symmetric and positive semi-definite.

        A twist beyond ``MAX_SPEED`` or ``MAX_YAW_RATE`` is left out and counted (``rejected``).
        """
        z = np.asarray(twist, dtype=np.float64).reshape(-1)
        if quality > 1:
            raise ValueError(f"quality: {quality!r}; the odometry's quality is a share in (0, 1]")
        if z.shape != (3,) or not np.all(np.isfinite(z)) or not (quality > 0):
            return  # an invalid estimate carries no information
        if max(abs(z[0]), abs(z[1])) > MAX_SPEED or abs(z[2]) > MAX_YAW_RATE:
            self._reject(f"odometry twist {z.tolist()} at t={t}")
            return
        floor = np.asarray(self.config.odom_std)
        if cov is not None:
            C = np.asarray(cov, dtype=np.float64)
            if C.shape != (3, 3) or not np.all(np.isfinite(C)):
                raise ValueError(
                    f"cov: shape {C.shape}; give a finite (3, 3) covariance of (v_x, v_y, omega)"
                )
            if (
                not np.allclose(C, C.T, rtol=1e-6, atol=1e-12)
                or np.linalg.eigvalsh(0.5 * (C + C.T)).min() < -1e-12
            ):
                raise ValueError(f"cov: {C.tolist()} is not a covariance (symmetric, positive semi-definite)")
            R = 0.5 * (C + C.T) + np.diag(floor**2)
        else:
            q = max(float(quality), self.config.min_quality)
            R = np.diag((floor / q) ** 2)
        H = None
        if self._gyro_used:  # its yaw rate then carries a bias of its own
            H = np.zeros((3, len(self._x)))
            H[[0, 1, 2], [0, 1, 2]] = 1.0
            H[2, _ODOM_BIAS] = 1.0
        self._queue(t - 0.5 * max(dt, 0.0), np.arange(3), z, R, H)
        self._t_odom = max(self._t_odom, t)
        if self.config.window_max > 0 and dt > 0 and quality >= self.config.window_min_quality:
            self._odo_win.append((t - dt, t, *self._wheels_long(z, R[:3, :3])))
            self._odo_win = [m for m in self._odo_win if m[1] > t - 2 * self.config.window_max]
        # the two latest by time, whatever the order they come in
        latest = self._odom_v + [(t - 0.5 * max(dt, 0.0), float(z[0]), float(R[0, 0]))]
        self._odom_v = sorted(latest, key=lambda m: m[0])[-2:]

    def add_wheels(
        self, t: float, wheel_rate, dt: float, valid=None, steering=None, std=None, noise=None
    ) -> None:
        """Wheel-rate measurements (and steering) from the fisheye, or wheel encoders.

        Args:
            t: Time of the frame [s].
            wheel_rate: (4,) spin rates, the average over the frame interval [rad/s].
            dt: The frame interval [s]; the rates apply at t - dt/2.
            valid: (4,) which rates were measured (default: the finite ones).
            steering: (4,) wheel steering angles [rad], positive left; kept until the next.
            std: (4,) each rate's own standard deviation [rad/s] (inf or NaN: none); the rate's
                noise is the larger of ``rate_std`` and ``rate_std_own`` times this (the
                fisheye's :attr:`~perception.kinematics.fisheye.KinematicState.theta_dot_std`:
                a wheel seen obliquely, on few cells, is measured far less well).
            noise: (4,) the rates' standard deviation [rad/s] in place of ``rate_std`` and
                ``std``: a sensor that knows its own (a wheel encoder's quantisation over the
                interval).
        """
        z = np.asarray(wheel_rate, dtype=np.float64).reshape(-1)
        if z.shape != (N_WHEELS,):
            raise ValueError(f"wheel_rate: shape {z.shape}; expected (4,) rates FL, FR, RL, RR [rad/s]")
        ok = np.isfinite(z) if valid is None else np.asarray(valid, bool) & np.isfinite(z)
        wild = ok & (np.abs(np.where(ok, z, 0.0)) > MAX_WHEEL_RATE)
        if wild.any():
            self._reject(f"wheel rates {z.tolist()} at t={t}")
            ok &= ~wild
        if steering is not None:
            d = np.asarray(steering, dtype=np.float64).reshape(-1)
            if d.shape != (N_WHEELS,):
                raise ValueError(f"steering: shape {d.shape}; expected (4,) wheel angles [rad]")
            self._steer = np.where(np.isfinite(d), d, self._steer)
        if not ok.any():
            return
        floor, share = self.config.rate_std
        sd_z = floor + share * np.abs(z[ok])
        if noise is not None:
            sd_z = np.asarray(noise, dtype=np.float64).reshape(-1)[ok]
            if not np.all(np.isfinite(sd_z) & (sd_z > 0)):
                raise ValueError(f"noise: {np.asarray(noise).tolist()}; give finite deviations > 0 [rad/s]")
        elif std is not None:
            sd = np.asarray(std, dtype=np.float64).reshape(-1)
            if sd.shape != (N_WHEELS,):
                raise ValueError(f"std: shape {sd.shape}; expected (4,) rate deviations [rad/s]")
            own = sd[ok]
            own = np.where(np.isfinite(own) & (own >= 0), own, 0.0)
            share_own = self.config.accel_rate_std_own if self._accel_used else self.config.rate_std_own
            sd_z = np.maximum(sd_z, share_own * own)
        R = np.diag(sd_z**2)
        self._rate_dt = max(dt, 0.0)
        self._queue(t - 0.5 * max(dt, 0.0), 3 + np.flatnonzero(ok), z[ok], R)
        self._t_rate[ok] = np.maximum(self._t_rate[ok], t)
        if self.config.window_max > 0 and dt > 0:
            r = self.wheel_radius
            a, var = np.zeros(N_WHEELS), np.zeros(N_WHEELS)
            a[ok], var[ok] = z[ok] * r, (sd_z * r) ** 2
            self._rate_win.append((t - dt, t, ok.copy(), a, var))
            self._rate_win = [m for m in self._rate_win if m[1] > t - 2 * self.config.window_max]

    def add_gyro(self, t: float, rate: float, dt: float, std: float) -> None:
        """A gyro's body-z rate, the mean over ``dt`` seconds up to ``t``, which carries a bias.

        The filter estimates the bias with the twist. From the first gyro measurement on, the
        odometry's yaw rate is given a slowly varying bias too (``odom_yaw_bias_std``): the two
        biases are told apart by their priors (the gyro's from its data sheet), so a gyro with a
        small turn-on bias carries the heading, and the odometry's rough-ground yaw error does
        not pass into it.

        Args:
            t: End of the averaging window [s]; the measurement applies at t - dt/2.
            rate: Mean angular rate about body z [rad/s].
            dt: Averaging window [s].
            std: Standard deviation of that mean [rad/s] (noise density / sqrt(dt)).
        """
        if not (math.isfinite(rate) and std > 0 and math.isfinite(std)):
            return
        if abs(rate) > MAX_YAW_RATE:
            self._reject(f"gyro rate {rate!r} at t={t}")
            return
        self._gyro_used = True
        H = np.zeros((1, len(self._x)))
        H[0, 2] = H[0, _BIAS] = 1.0
        self._queue(t - 0.5 * max(dt, 0.0), None, np.array([rate]), np.array([[std * std]]), H)

    def add_accel(self, t: float, accel_xy, dt: float) -> None:
        """The body's horizontal acceleration, the mean over ``dt`` seconds up to ``t``.

        ``accel_xy``: (a_x, a_y) [m/s^2] in the body frame: the specific force less gravity
        (through the attitude), plus the transport terms (omega v_y, -omega v_x), so that it is
        the rate of the body-frame velocity (v_x, v_y). From the first call on, the velocity is
        predicted with it and its bias estimated (``accel_velocity_rw`` and the parameters after
        it). Non-finite values are left out.
        """
        a = np.asarray(accel_xy, dtype=np.float64).reshape(-1)
        if a.shape != (2,):
            raise ValueError(f"accel_xy: shape {a.shape}; expected (a_x, a_y) [m/s^2]")
        if not (np.all(np.isfinite(a)) and math.isfinite(t) and dt > 0 and math.isfinite(dt)):
            return
        if np.abs(a).max() > MAX_ACCEL:
            self._reject(f"acceleration {a.tolist()} at t={t}")
            return
        self._accel_used = True
        self._inputs.append((float(t) - float(dt), float(t), float(a[0]), float(a[1])))

    def _reject(self, what: str) -> None:
        """Leave out an impossible reading: count it and say so."""
        self.rejected += 1
        log.warning("slip filter: left out %s (beyond any rover's range)", what)

    def _velocity_change(self, t0: float, t1: float) -> np.ndarray:
        """The integral of the measured acceleration from ``t0`` to ``t1`` [m/s] (none where no input)."""
        dvx = dvy = 0.0
        for a0, a1, ax, ay in self._inputs:
            overlap = min(a1, t1) - max(a0, t0)
            if overlap > 0:
                dvx += overlap * ax
                dvy += overlap * ay
        return np.array([dvx, dvy])

    def calibrate_gyro(self, rate: float, std: float) -> None:
        """A gyro's mean body-z rate [rad/s] while the body stood still: a direct bias measurement.

        ``std``: standard deviation of that mean [rad/s]. Applied at once (call it before the
        first measurements of an episode).
        """
        if not (math.isfinite(rate) and std > 0 and math.isfinite(std)):
            return
        H = np.zeros((1, len(self._x)))
        H[0, _BIAS] = 1.0
        self._update(H, np.array([rate]), np.array([[std * std]]))

    @property
    def gyro_bias(self) -> tuple[float, float]:
        """The gyro's estimated yaw-rate bias and its standard deviation [rad/s]."""
        return float(self._x[_BIAS]), float(math.sqrt(self._P[_BIAS, _BIAS]))

    def update(
        self, t: float, odometry=None, kinematics=None, fisheye_dt: float | None = None
    ) -> SlipEstimate:
        """Add the estimators' latest results (either may be None) and return the estimate at ``t``.

        Args:
            t: Query time [s].
            odometry: A :class:`~perception.odometry.flow.OdometryEstimate` (used when valid).
            kinematics: A :class:`~perception.kinematics.fisheye.KinematicState`.
            fisheye_dt: The fisheye's frame interval [s] (the rates' averaging window).
        """
        if odometry is not None and odometry.valid:
            t_o = t if odometry.t is None else odometry.t
            self.add_odometry(t_o, odometry.twist, odometry.dt, odometry.quality)
        if kinematics is not None:
            valid = [kinematics.valid.get(f"theta_{w}", False) for w in WHEELS]
            self.add_wheels(
                kinematics.t,
                kinematics.theta_dot,
                fisheye_dt or 0.0,
                valid,
                kinematics.delta,
                getattr(kinematics, "theta_dot_std", None),
            )
        return self.estimate(t)

    # ------------------------------------------------------------------ filter
    def _queue(self, t: float, idx, z: np.ndarray, R: np.ndarray, H: np.ndarray | None = None) -> None:
        """Queue z = x[idx] + noise (or z = H x + noise when ``H`` is given) at time ``t``."""
        if not math.isfinite(t):
            raise ValueError(f"measurement time {t!r} is not finite")
        self._seq += 1
        self._pending.append((float(t), self._seq, idx, z, R, H))

    def _predict(self, x: np.ndarray, P: np.ndarray, t0: float, t1: float) -> tuple[np.ndarray, np.ndarray]:
        """The state and covariance at ``t1`` from those at ``t0`` [s]."""
        c = self.config
        dt = t1 - t0
        if not self._accel_used:  # random walks: the twist is held, its variance grows
            rw = [c.velocity_rw**2] * 2 + [c.yaw_rate_rw**2] + [c.wheel_rate_rw**2] * N_WHEELS
            q = np.array(rw + [c.gyro_bias_rw**2, c.odom_yaw_bias_rw**2] + [0.0] * (2 + N_WHEELS))
            F = np.eye(_N_STATE)  # and each wheel rate integrates its angular acceleration
            rates, accs = np.arange(3, _BIAS), np.arange(_WHEEL_ACC, _N_STATE)
            F[rates, accs] = dt
            Q = np.diag(q * dt)
            j = c.wheel_accel_rw**2
            Q[rates, rates] += j * dt**3 / 3.0
            Q[rates, accs] = Q[accs, rates] = j * dt**2 / 2.0
            Q[accs, accs] = j * dt
            return F @ x, F @ P @ F.T + Q
        # the velocity integrates the measured acceleration less its bias; each wheel rate its
        # angular acceleration, an integrated random walk
        F = np.eye(_N_STATE)
        F[[0, 1], [_ACC_BIAS, _ACC_BIAS + 1]] = -dt
        rates, accs = np.arange(3, _BIAS), np.arange(_WHEEL_ACC, _N_STATE)
        F[rates, accs] = dt
        x = F @ x
        x[:2] += self._velocity_change(t0, t1)
        rw = [c.accel_velocity_rw**2] * 2 + [c.yaw_rate_rw**2] + [c.accel_wheel_rate_rw**2] * N_WHEELS
        rw += [c.gyro_bias_rw**2, c.odom_yaw_bias_rw**2] + [c.accel_bias_rw**2] * 2 + [0.0] * N_WHEELS
        Q = np.diag(np.array(rw) * dt)
        j = c.wheel_accel_rw**2
        Q[rates, rates] += j * dt**3 / 3.0
        Q[rates, accs] = Q[accs, rates] = j * dt**2 / 2.0
        Q[accs, accs] = j * dt
        return x, F @ P @ F.T + Q

    def _apply(self, upto: float) -> None:
        """Apply the pending measurements up to time ``upto`` in time order."""
        due = sorted((m for m in self._pending if m[0] <= upto), key=lambda m: (m[0], m[1]))
        self._pending = [m for m in self._pending if m[0] > upto]
        for t, _, idx, z, R, H in due:
            if self._t is not None and t > self._t:
                self._x, self._P = self._predict(self._x, self._P, self._t, t)
            if self._t is None or t > self._t:
                self._t = t
            self._t_first = min(self._t_first, t)
            if H is None:  # rows that pick state entries
                H = np.zeros((len(idx), len(self._x)))
                H[np.arange(len(idx)), idx] = 1.0
            rates = idx is not None and idx[0] >= 3
            gripping = None
            if rates and self.config.grip_std > 0:
                # the wheels whose new rate alone does not show them slipping (gated before the update)
                gripping = (idx - 3)[~self._slipping(idx - 3, z, R)]
            self._update(H, z, R)
            if gripping is not None:
                self._grip(gripping)
            if rates and self.in_outage(t):
                self._roll(idx - 3, z)
            same_time = self._at_rates is not None and abs(self._at_rates[0] - self._t) < 1e-6
            if rates or (same_time and not self._accel_used):
                # the slip's state: after the latest rates (and, without an accelerometer, every
                # measurement of their time: the same frame pair's odometry)
                self._at_rates = (self._t, self._x.copy(), self._P.copy())
        if self._inputs and self._t is not None:  # inputs a second older than the filter are done
            self._inputs = [u for u in self._inputs if u[1] > self._t - 1.0]

    def _update(self, H: np.ndarray, z: np.ndarray, R: np.ndarray) -> None:
        """Kalman update with measurements z = H x + noise of covariance R."""
        S = H @ self._P @ H.T + R
        K = np.linalg.solve(S, H @ self._P).T
        self._x = self._x + K @ (z - H @ self._x)
        IKH = np.eye(len(self._x)) - K @ H
        self._P = IKH @ self._P @ IKH.T + K @ R @ K.T  # Joseph form: stays symmetric PSD

    def _slipping(self, wheels: np.ndarray, z: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Which of ``wheels`` a new rate measurement ``z`` [rad/s] (noise ``R``) shows slipping.

        Its slip in speed, v_i,long - z_i r against the filter's prior twist, beyond ``grip_gate``
        deviations (the twist's, the rate's and the grip's own): the gate of the zero-slip
        pseudo-measurement taken on the measurement itself, before the filter's rate has been
        drawn to grip by the pseudo-measurements of the frames before.
        """
        c = self.config
        x, P = self._x, self._P
        J = _long_jacobian(self.wheel_xy, self._steer)[wheels]
        r = self.wheel_radius
        v = J @ x[:3]
        d = v - z * r
        speed = np.maximum(np.abs(z * r), np.abs(v))
        S = np.einsum("ij,jk,ik->i", J, P[:3, :3], J) + r**2 * np.diag(R) + (c.grip_std * speed) ** 2
        return d**2 > c.grip_gate**2 * S

    def _grip(self, wheels: np.ndarray) -> None:
        """Zero-slip pseudo-measurements v_i,long - theta_dot_i r = 0 of the gripping ``wheels``."""
        c = self.config
        x, P = self._x, self._P
        J = _long_jacobian(self.wheel_xy, self._steer)  # v_long = J @ twist
        speed = np.maximum(np.abs(x[3:_BIAS] * self.wheel_radius), np.abs(J @ x[:3]))
        w = wheels[speed[wheels] >= c.event_min_speed]
        # once a frame: a second rate source (encoders) measuring the same frame does not add a
        # second prior of grip
        assert self._t is not None
        w = w[self._t - self._t_grip[w] >= 0.75 * self._rate_dt]
        if not len(w):
            return
        H = np.zeros((len(w), len(x)))
        H[:, :3] = J[w]
        H[np.arange(len(w)), 3 + w] = -self.wheel_radius
        var = (c.grip_std * speed[w]) ** 2
        S = np.einsum("ij,jk,ik->i", H, P, H) + var
        innov = -(H @ x)
        # only where the measurements alone resolve the slip to max_slip_std
        grip = (innov**2 <= c.grip_gate**2 * S) & (S - var <= (c.max_slip_std * speed[w]) ** 2)
        if grip.any():
            self._update(H[grip], np.zeros(int(grip.sum())), np.diag(var[grip]))
            self._t_grip[w[grip]] = self._t

    def in_outage(self, t: float) -> bool:
        """Whether no valid odometry twist has come for ``outage_after`` seconds up to ``t`` [s]."""
        return t - max(self._t_odom, self._t_first) > self.config.outage_after

    def _roll(self, wheels: np.ndarray, rates: np.ndarray) -> None:
        """In an odometry outage: the measured ``wheels`` roll, to ``outage_slip_std`` of their speed.

        Two rows: their mean longitudinal speed less their mean tread speed, and their mean
        lateral speed, both zero.
        """
        c = self.config
        r = self.wheel_radius
        steer = self._steer[wheels]
        x_i, y_i = self.wheel_xy[wheels, 0], self.wheel_xy[wheels, 1]
        cos, sin = np.cos(steer), np.sin(steer)
        H = np.zeros((2, len(self._x)))
        H[0, :3] = _long_jacobian(self.wheel_xy[wheels], steer).mean(axis=0)
        H[0, 3 + wheels] = -r / len(wheels)
        # across each wheel: the contact point's (v_x - omega y_i, v_y + omega x_i)
        H[1, :3] = np.mean(np.stack([-sin, cos, cos * x_i + sin * y_i], axis=1), axis=0)
        speed = max(float(np.mean(np.abs(rates))) * r, c.event_min_speed)
        self._update(H, np.zeros(2), np.eye(2) * (c.outage_slip_std * speed) ** 2)

    def add_window_odometry(self, t0: float, t1: float, twist, cov=None, quality: float = 1.0) -> None:
        """The body twist averaged from ``t0`` to ``t1`` [s]: the odometry over a longer baseline.

        For the slip over a window of travel only (``window_max``), not fused in the filter: it
        overlaps the frames' twists. ``twist`` (v_x, v_y, omega) [m/s, m/s, rad/s], body frame;
        ``cov`` its (3, 3) covariance (None: ``odom_std`` squared), ``quality`` the odometry's.
        Invalid ones, and those under ``window_min_quality``, are left out.
        """
        z = np.asarray(twist, dtype=np.float64).reshape(-1)
        c = self.config
        if c.window_max <= 0 or z.shape != (3,) or not np.all(np.isfinite(z)) or not t1 > t0:
            return
        if not quality >= c.window_min_quality:
            return
        C = (
            np.diag(np.asarray(self.config.odom_std) ** 2)
            if cov is None
            else np.asarray(cov, dtype=np.float64)
        )
        if C.shape != (3, 3) or not np.all(np.isfinite(C)):
            return
        self._odo_long = [*self._odo_long[-3:], (t0, t1, *self._wheels_long(z, C))]

    def _wheels_long(self, twist: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each wheel's ground speed along its heading [m/s] of an odometry twist, and its variance.

        With a gyro, less the odometry's yaw-rate bias the filter holds now; at the steering now.
        """
        z = twist
        if self._gyro_used:
            z = z.copy()
            z[2] -= self._x[_ODOM_BIAS]
        J = _long_jacobian(self.wheel_xy, self._steer)
        return J @ z, np.einsum("ij,jk,ik->i", J, cov, J)

    def window_slip(self) -> tuple[np.ndarray, np.ndarray]:
        """Each wheel's slip ratio over a window of travel and its deviation (``window_max``).

        NaN and inf for a wheel without a window that resolves it. The window is that of the
        latest twist over a longer baseline (:meth:`add_window_odometry`) if it ends within
        ``max_age`` of the wheel's latest rate, else it runs back from that rate over the frames'
        twists.
        """
        c = self.config
        s_out, sd_out = np.full(N_WHEELS, math.nan), np.full(N_WHEELS, math.inf)
        if c.window_max <= 0 or not self._rate_win:
            return s_out, sd_out

        def ratio(tread, var_t, ground, var_g, span, t_cov, g_cov):
            with np.errstate(invalid="ignore", divide="ignore"):
                var_g = var_g + (c.window_scale_std * ground) ** 2
                sd = np.sqrt(var_g / tread**2 + ground**2 * var_t / tread**4)
                ok = (
                    (t_cov >= 0.8 * span) & (g_cov >= 0.8 * span) & np.isfinite(sd)
                    & (np.maximum(np.abs(tread), np.abs(ground)) >= c.window_min_speed)
                    & (tread * ground >= 0) & (np.abs(tread) >= np.abs(ground))
                )  # fmt: skip
                return 1.0 - ground / tread, sd, ok

        R0, R1 = (np.array([m[k] for m in self._rate_win]) for k in (0, 1))
        measured, A, VA = (np.array([m[k] for m in self._rate_win]) for k in (2, 3, 4))
        if self._odo_win:
            o0, o1 = (np.array([m[k] for m in self._odo_win]) for k in (0, 1))
            OV, OVAR = (np.array([m[k] for m in self._odo_win]) for k in (2, 3))
        for i in range(N_WHEELS):
            rows = measured[:, i]
            if not rows.any():
                continue
            r0, r1, a, va = R0[rows], R1[rows], A[rows, i], VA[rows, i]
            end = float(r1.max())
            if self._odo_long and self._odo_long[-1][1] >= end - c.max_age:
                t0, t1, v_long, var = self._odo_long[-1]
                ov = np.clip(np.minimum(r1, t1) - np.maximum(r0, t0), 0.0, None)
                cov_t = float(ov.sum())
                with np.errstate(invalid="ignore", divide="ignore"):
                    tread, var_t = (ov @ a) / cov_t, (ov**2 @ va) / cov_t**2
                s_, sd, ok = ratio(tread, var_t, v_long[i], var[i], t1 - t0, cov_t, t1 - t0)
                if ok and sd <= c.max_slip_std:
                    s_out[i], sd_out[i] = float(s_), float(sd)
                    continue
            if not self._odo_win:
                continue
            new = np.argsort(-r1)  # newest first
            r0, r1, a, va = r0[new], r1[new], a[new], va[new]
            keep = r0 >= end - c.window_max - 1e-9
            if not keep.any():
                continue
            r0, r1, a, va = r0[keep], r1[keep], a[keep], va[keep]
            d = r1 - r0
            t_cov, a_sum, va_sum = np.cumsum(d), np.cumsum(a * d), np.cumsum(va * d * d)
            start = r0  # window k: from the start of the k-th newest frame to the end
            ov = np.clip(np.minimum(o1[None], end) - np.maximum(o0[None], start[:, None]), 0.0, None)
            g_cov = ov.sum(axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                tread, var_t = a_sum / t_cov, va_sum / t_cov**2
                ground, var_g = (ov @ OV[:, i]) / g_cov, (ov**2 @ OVAR[:, i]) / g_cov**2
            rat, sd, ok = ratio(tread, var_t, ground, var_g, end - start, t_cov, g_cov)
            if not ok.any():
                continue
            good = ok & (sd <= c.window_std)
            k = int(np.argmax(good)) if good.any() else int(np.flatnonzero(ok)[np.argmin(sd[ok])])
            if sd[k] <= c.max_slip_std:
                s_out[i], sd_out[i] = float(rat[k]), float(sd[k])
        return s_out, sd_out

    def twist_at(self, t: float) -> np.ndarray:
        """The filtered body twist (v_x, v_y, omega) at ``t`` [s] [m/s, m/s, rad/s], body frame.

        Applies the measurements up to ``t`` like :meth:`estimate`, without advancing the slip
        events; for dead reckoning between estimates.
        """
        if not math.isfinite(t):
            raise ValueError(f"t={t!r}: the query time must be finite")
        self._apply(t)
        return self._state_at(t)[0][:3].copy()

    def _state_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The state and covariance predicted from the last measurement to ``t`` [s] (not kept)."""
        if self._t is None or t <= self._t:
            return self._x, self._P
        return self._predict(self._x, self._P, self._t, t)

    def estimate(self, t: float) -> SlipEstimate:
        """The filtered state and slip at time ``t`` [s] (measurements up to ``t`` applied)."""
        if not math.isfinite(t):
            raise ValueError(f"t={t!r}: the query time must be finite")
        self._apply(t)
        c = self.config
        x, P = self._state_at(t)
        twist, twist_std = x[:3].copy(), np.sqrt(np.diag(P)[:3])
        if self._at_rates is not None:
            # the slip of the latest rates' time (mid-frame), held since with the random walk's
            # growth: the wheels' acceleration states are not extrapolated (see SlipConfig)
            t_r, x, P = self._at_rates
            q = np.zeros(len(x))
            q[:2], q[2], q[3:_BIAS] = c.velocity_rw**2, c.yaw_rate_rw**2, c.wheel_rate_rw**2
            P = P + np.diag(q * max(t - t_r, 0.0))
            x = x.copy()
            if not self._accel_used and len(self._odom_v) == 2:
                # v_x carried to the query time at the odometry's last change while the rover
                # speeds up, shrunk by its noise (a (1 - 4 var_a / a^2): 0 within two deviations)
                (t0, v0, r0), (t1, v1, r1) = self._odom_v
                if 1e-6 < t1 - t0 <= 2 * c.max_age and t - t1 <= c.max_age:
                    acc = (v1 - v0) / (t1 - t0)
                    var = (r0 + r1) / (t1 - t0) ** 2
                    if acc * x[0] > 0 and acc * acc > 4.0 * var:
                        x[0] += acc * (1.0 - 4.0 * var / (acc * acc)) * max(t - t_r, 0.0)
        else:
            x = x.copy()
        rates = x[3:_BIAS]
        v_long, v_lat = wheel_ground_velocity(x[:3], self.wheel_xy, self._steer)
        a = rates * self.wheel_radius
        raw = slip_ratio(a, v_long, c.eps, clip=False)
        clipped = np.clip(raw, -1.0, 1.0)
        # first-order standard deviation: ds/da and ds/dv_long on the side of the larger speed
        big_a = np.abs(a) >= np.abs(v_long)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            ds_da = np.where(big_a, v_long / a**2, 1.0 / v_long)
            ds_dv = np.where(big_a, -1.0 / a, -a / v_long**2)
        J = np.zeros((N_WHEELS, len(x)))  # d s / d (v_x, v_y, omega), then d s / d rate
        with np.errstate(invalid="ignore"):
            J[:, :3] = _long_jacobian(self.wheel_xy, self._steer) * ds_dv[:, None]
            J[np.arange(N_WHEELS), 3 + np.arange(N_WHEELS)] = ds_da * self.wheel_radius
            var = np.einsum("ij,jk,ik->i", J, P, J)
        s_std = np.sqrt(np.where(np.isfinite(var), np.maximum(var, 0.0), np.inf))
        # the ratio is clipped to [-1, 1]: where the tread and the ground move apart (opposite
        # signs, or one at rest) it sits at +-1 however uncertain the speeds, so its deviation
        # is that of the clipped normal, not the first-order one of the unclipped ratio
        s_std = clipped_normal_std(raw, s_std)
        fresh = (t - self._t_odom <= c.max_age) & (t - self._t_rate <= c.max_age)
        speed = np.maximum(np.abs(a), np.abs(v_long))  # tread or ground [m/s]
        moving = speed >= c.min_speed
        valid = fresh & moving & (s_std <= c.max_slip_std)
        if not valid.all() and c.window_max > 0:
            # not resolved in a frame: over a window of travel (driving; the frame's estimate
            # stands for a wheel braking or reversing)
            s_w, sd_w = self.window_slip()
            use = fresh & ~valid & np.isfinite(s_w)
            clipped, s_std = np.where(use, s_w, clipped), np.where(use, sd_w, s_std)
            valid |= use
        s = np.where(valid, clipped, 0.0)
        beta = np.where(valid, slip_angle(v_long, v_lat), 0.0)
        mag = np.abs(s)
        fast = speed >= c.event_min_speed
        above = valid & fast & (mag >= c.event_on)
        rising = above & np.isnan(self._above_since)
        self._above_since = np.where(above, np.where(rising, t, self._above_since), math.nan)
        self._above_rate = np.where(above, np.where(rising, self._t_rate, self._above_rate), math.nan)
        with np.errstate(invalid="ignore"):
            start = above & (t - self._above_since >= c.event_hold - 1e-9)
            if c.event_confirm and c.event_hold > 0:
                # a newer rate of the wheel says so too: one outlying rate, held while the
                # next frame misses the wheel, is not an event
                # (or it stays above for a third estimate: the rates' accelerations carry a wheel
                # that the fisheye misses for a frame or two)
                start &= (self._t_rate > self._above_rate) | (
                    t - self._above_since >= 2 * c.event_hold - 1e-9
                )
            if c.event_sure > 0:
                if t > self._last_t:
                    self._mag_before = self._last_mag
                # in its first estimate above event_on, surely so, from at least event_off in the
                # estimate before (a held outlier's second frame is not a first one), or more
                # surely so after an estimate that resolved no slip
                first = above & (self._above_since == t)
                with np.errstate(invalid="ignore"):
                    sure = (mag - c.event_sure * s_std >= c.event_on) & (self._mag_before >= c.event_off)
                    gap = np.isnan(self._mag_before) & (mag - c.event_sure_gap * s_std >= c.event_on)
                start |= first & (sure | gap)
        if t >= self._last_t:  # a query back in time does not move the reference
            # an estimate too wide to be valid that still surely shows slip of event_off or
            # more (a wheel reversing at low speed) is no steady rolling before a sure rise
            with np.errstate(invalid="ignore"):
                low = np.abs(clipped) - s_std
                wide = fresh & moving & fast & ~valid & (low >= c.event_off)
            self._last_t, self._last_mag = t, np.where(valid & fast, mag, np.where(wide, low, np.nan))
        # an event ends at a resolved |s| below event_off, or when its wheel slows below
        # event_min_speed; an estimate that resolves no slip holds it for max_age
        resolved = valid & fast
        held = self._events & fast & ~valid & (t - self._event_seen <= c.max_age + 1e-9)
        self._events = np.where(resolved, np.where(self._events, mag >= c.event_off, start), held)
        self._event_seen = np.where(resolved & self._events, t, self._event_seen)
        return SlipEstimate(
            t=float(t),
            twist=twist,
            twist_std=twist_std,
            wheel_rate=rates,
            wheel_rate_std=np.sqrt(np.diag(P)[3:_BIAS]),
            v_long=v_long,
            v_lat=v_lat,
            slip_ratio=s,
            slip_ratio_std=np.where(valid, s_std, np.inf),
            slip_angle=beta,
            valid=valid,
            events=self._events.copy(),
            quality=float(valid.mean()),
        )


def _long_jacobian(wheel_xy: np.ndarray, steering: np.ndarray) -> np.ndarray:
    """(4, 3) d v_long / d (v_x, v_y, omega) of the wheel centres at ``wheel_xy`` [m], ``steering`` [rad]."""
    cos, sin = np.cos(steering), np.sin(steering)
    return np.stack([cos, sin, -cos * wheel_xy[:, 1] + sin * wheel_xy[:, 0]], axis=1)


def clipped_normal_std(mean, std) -> np.ndarray:
    """Standard deviation of clip(X, -1, 1) for X ~ N(mean, std^2) (a normal censored at +-1).

    Args:
        mean: Means (any shape).
        std: Standard deviations (same shape; inf and NaN pass through, 0 gives 0).
    """
    m = np.asarray(mean, dtype=np.float64)
    out = np.array(std, dtype=np.float64, copy=True)
    ok = np.isfinite(m) & np.isfinite(out) & (out > 0)
    if not ok.any():
        return out
    mu, sd = m[ok], out[ok]
    lo, hi = (-1.0 - mu) / sd, (1.0 - mu) / sd
    p_lo, p_hi = ndtr(lo), ndtr(hi)
    f_lo, f_hi = np.exp(-0.5 * lo**2) / math.sqrt(2 * math.pi), np.exp(-0.5 * hi**2) / math.sqrt(2 * math.pi)
    inside = p_hi - p_lo
    # E[Y] and E[Y^2]: the mass beyond each bound sits at it; inside, the truncated moments
    e1 = -p_lo + (1.0 - p_hi) + mu * inside + sd * (f_lo - f_hi)
    e2 = (
        p_lo
        + (1.0 - p_hi)
        + (mu * mu + sd * sd) * inside
        + 2 * mu * sd * (f_lo - f_hi)
        + sd * sd * (lo * f_lo - hi * f_hi)
    )
    out[ok] = np.sqrt(np.maximum(e2 - e1 * e1, 0.0))
    return out

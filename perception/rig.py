"""A rover's sensor rig as an estimator sees it: what each sensor is, where, how often, its model.

The simulation samples the sensors a scenario declares; a robot's log holds the same sensors'
messages. Either way an estimator is built from a :class:`Rig` (a mapping from sensor name to
:class:`SensorSpec`, plus the rover's kinematic model) and fed :class:`SensorMessage` samples;
nothing here needs the simulator.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from perception.models.calib_io import check_rigid
from perception.models.photometry import CFA_PATTERNS
from perception.models.validation import ConfigError, real_number

#: The kinds of sensor a rig may hold, and what ``SensorSpec.model`` is for each.
SENSOR_KINDS: dict[str, str] = {
    "pinhole": "perception.PinholeCamera (a downward camera: its calibration, mount and ground plane)",
    "fisheye": "perception.OmniCamera (a downward fisheye: its calibration)",
    "imu": "perception.rig.ImuModel (the data sheet's figures)",
    "sun": "perception.rig.SunSensorModel (a sun sensor's data-sheet figures)",
    "wheel_encoders": "perception.rig.EncoderModel (counts per revolution, the counter's width)",
    "motor_current": "perception.rig.MotorModel (gear ratio, torque constant, efficiency, friction, noise)",
    "command": "None (the commanded wheel rates and steering need no model)",
}


@dataclass(frozen=True)
class SensorMessage:
    """One sample of a sensor.

    Attributes:
        sensor: The sensor's name in the rig.
        t: Time of the sample [s] (simulation time, or a log's time line).
        data: The sample: a camera's (H, W, 3) uint8 RGB image; an IMU's (7,) gyro xyz [rad/s],
            accelerometer xyz [m/s^2] in its mount frame, and a saturation flag (> 0: a reading
            was clipped at the range); a sun sensor's (7,) unit vector toward the sun in its
            frame, the ephemeris's unit vector toward the sun in the world frame (z up) at that
            time, and a flag (> 0: no sun seen; the first three are then NaN); wheel encoders'
            (4,) counters FL, FR, RL, RR, whole numbers in [0, 2 ** counter_bits) that wrap
            (rolling forward counts up); motor currents' (4,) currents [A] (positive driving
            the wheel forward); a command's (6,) wheel-rate targets FL, FR, RL, RR [rad/s] and
            axle steering lambda_F, lambda_R [rad] in force at ``t``.
    """

    sensor: str
    t: float
    data: Any


@dataclass(frozen=True)
class TriadFigures:
    """Data-sheet figures of three like axes (units: rad/s for a gyro, m/s^2 for an accelerometer).

    Attributes:
        noise_density: White noise [u/sqrt(Hz)].
        bias_instability: Bias instability [u].
        bias_random_walk: Bias random walk [u/s/sqrt(Hz)].
        turn_on_bias: Spread of the bias at turn-on (1 sigma) [u].
        range: Full scale [u] (inf: none).
        misalignment: Spread of each cross-axis coupling (1 sigma) [rad].
    """

    noise_density: float = 0.0
    bias_instability: float = 0.0
    bias_random_walk: float = 0.0
    turn_on_bias: float = 0.0
    range: float = float("inf")
    misalignment: float = 0.0


@dataclass(frozen=True)
class ImuModel:
    """What an estimator knows of an IMU: its data sheet.

    Attributes:
        gyro: The gyro's figures [rad/s].
        accel: The accelerometer's figures [m/s^2].
    """

    gyro: TriadFigures = field(default_factory=TriadFigures)
    accel: TriadFigures = field(default_factory=TriadFigures)


@dataclass(frozen=True)
class SunSensorModel:
    """What an estimator knows of a sun sensor: its data sheet.

    Attributes:
        fov_deg: Half-angle of its field of view about its boresight (its z axis) [deg].
        accuracy_deg: Standard deviation of its fixed error per axis [deg].
        noise_deg: Standard deviation of a reading's white noise per axis [deg].
    """

    fov_deg: float = 70.0
    accuracy_deg: float = 0.1
    noise_deg: float = 0.03


@dataclass(frozen=True)
class EncoderModel:
    """What an estimator knows of wheel encoders.

    Attributes:
        counts_per_rev: Counts per wheel revolution [-].
        counter_bits: The counter wraps at ``2 ** counter_bits`` counts.
    """

    counts_per_rev: int = 4096
    counter_bits: int = 16

    def __post_init__(self) -> None:
        cpr, bits = (
            real_number("counts_per_rev", self.counts_per_rev),
            real_number("counter_bits", self.counter_bits),
        )
        if cpr < 4 or cpr != int(cpr) or not 8 <= bits <= 32 or bits != int(bits) or 2**bits < 4 * cpr:
            raise ConfigError(
                f"wheel encoders: counts_per_rev {self.counts_per_rev!r}, "
                f"counter_bits {self.counter_bits!r}; give whole numbers, at least 4 counts a "
                "revolution and an 8- to 32-bit counter that holds 4 revolutions"
            )

    @property
    def wrap(self) -> float:
        """The counter's range [counts]."""
        return float(2 ** int(self.counter_bits))


@dataclass(frozen=True)
class MotorModel:
    """What an estimator knows of the drive motors' current sense: their data sheet.

    The current is ``I = tau_m / k_t + I_0 tanh(omega_m / omega_0) + offset + noise``, with the
    motor torque ``tau_m = tau_wheel / (N eta)`` while the motor drives the wheel and
    ``tau_wheel eta / N`` while the wheel drives it back; ``omega_m = N omega_wheel``.

    Attributes:
        gear_ratio: N [-]. torque_constant: k_t [N m/A]. efficiency: eta [-].
        no_load_current: I_0 [A]. friction_speed: omega_0 [rad/s, motor side].
        offset_std: Spread of the offset per start [A]. noise_std: White noise [A].
        range: Full scale [A]: a reading at it may be clipped.
    """

    gear_ratio: float = 100.0
    torque_constant: float = 0.0283
    efficiency: float = 0.75
    no_load_current: float = 0.06
    friction_speed: float = 5.0
    offset_std: float = 0.01
    noise_std: float = 0.02
    range: float = 10.0

    def __post_init__(self) -> None:
        for key in ("gear_ratio", "torque_constant", "friction_speed", "range"):
            if not real_number(key, getattr(self, key)) > 0.0:
                raise ConfigError(f"motor_current.{key}: {getattr(self, key)!r}; give a value above 0")
        if not 0.0 < real_number("efficiency", self.efficiency) <= 1.0:
            raise ConfigError(f"motor_current.efficiency: {self.efficiency!r}; give a value in (0, 1]")
        for key in ("no_load_current", "offset_std", "noise_std"):
            if not real_number(key, getattr(self, key)) >= 0.0:
                raise ConfigError(f"motor_current.{key}: {getattr(self, key)!r}; give a value >= 0")

    def step_torque(self, currents, wheel_rate) -> np.ndarray:
        """The wheel torques [N m] of a batch of readings: (n, 4) currents [A] at (4,) wheel rates [rad/s].

        Per wheel the median of its readings, so that a spike is outvoted; a reading that is not
        finite or at full scale (``range``: clipped) is not one, and a wheel with readings for
        no more than half of the batch gets NaN (unknown).
        """
        c = np.asarray(currents, dtype=np.float64).reshape(-1, 4)
        ok = np.isfinite(c) & (np.abs(c) < self.range)
        enough = 2 * ok.sum(axis=0) > len(c)
        med = np.zeros(4)
        for w in np.flatnonzero(enough):
            med[w] = np.median(c[ok[:, w], w])
        return np.where(enough, self.wheel_torque(med, wheel_rate), np.nan)

    def wheel_torque(self, current, wheel_rate) -> np.ndarray:
        """The wheel torques [N m] that draw ``current`` [A] at ``wheel_rate`` [rad/s].

        The inverse of the current model above: the friction's current is taken off, then the
        gearhead's ratio and efficiency applied in the direction the power flows. The current
        sense's offset (``offset_std``, unknown per start) stays in.
        """
        i = np.asarray(current, dtype=np.float64)
        w_m = np.asarray(wheel_rate, dtype=np.float64) * self.gear_ratio
        tau_m = (i - self.no_load_current * np.tanh(w_m / self.friction_speed)) * self.torque_constant
        driving = tau_m * w_m >= 0.0
        return np.where(
            driving, tau_m * self.gear_ratio * self.efficiency, tau_m * self.gear_ratio / self.efficiency
        )


@dataclass(frozen=True)
class SensorSpec:
    """One sensor of a rig.

    Attributes:
        name: Its name (the ``sensor`` of its messages).
        kind: ``"pinhole"``, ``"fisheye"``, ``"imu"``, ``"sun"``, ``"wheel_encoders"``,
            ``"motor_current"`` or ``"command"`` (:data:`SENSOR_KINDS`).
        rate_hz: Samples per second [Hz].
        mount: (4, 4) pose of the sensor's frame in the body frame (body from sensor) [m].
        model: The calibration an estimator uses (see :data:`SENSOR_KINDS`).
        readout_window: The sensor can render only the windows an estimator asks for (a
            tracker-driven windowed readout, see :meth:`perception.estimator.Estimator`).
        gamma: A camera's photometric response: an 8-bit value ``v`` of its images encodes the
            relative irradiance ``(v / 255) ** gamma`` (1: linear; 2.2: a camera's usual output
            gamma). Estimators that compare light levels (shadow ratios, paint against tread)
            linearise with it. Ignored for an IMU.
        bayer: A colour camera's colour-filter array when its images are demosaiced from one
            colour per pixel (``"RGGB"``, ``"BGGR"``, ``"GRBG"``, ``"GBRG"``;
            :data:`perception.models.photometry.CFA_PATTERNS`), or None (full colour, or unknown).
            The fisheye kinematics then reads the treads from each pixel's own sample.
        vignetting: A camera's relative illumination at its image corners (1: none, or not
            calibrated), of the radial model of
            :func:`perception.models.photometry.relative_illumination`. The downward camera's odometry
            flat-fields its frames with it (the fisheye's does not: it tracks features, which a
            smooth shading does not move).
        ground_view_deg: A fisheye that reads out a region of interest: the ground it delivers
            lies within this angle of the body's -z [deg] (beyond, only the parts the
            kinematics reads); None: all it sees. Its own odometry selects features inside it.
    """

    name: str
    kind: str
    rate_hz: float
    mount: np.ndarray
    model: Any
    readout_window: bool = False
    gamma: float = 1.0
    bayer: str | None = None
    vignetting: float = 1.0
    ground_view_deg: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in SENSOR_KINDS:
            raise ConfigError(f"{self.name}.kind: {self.kind!r}; use one of {sorted(SENSOR_KINDS)}")
        gamma = real_number(f"{self.name}.gamma", self.gamma)
        if not 0.0 < gamma <= 5.0:
            raise ConfigError(
                f"{self.name}.gamma: {self.gamma!r}; give the camera's response exponent in (0, 5] "
                "(1: linear images, 2.2: the usual output gamma)"
            )
        vig = real_number(f"{self.name}.vignetting", self.vignetting)
        if not 0.0 < vig <= 1.0:
            raise ConfigError(
                f"{self.name}.vignetting: {self.vignetting!r}; give the lens's relative illumination at "
                "the image corner in (0, 1] (1: no vignetting)"
            )
        if self.bayer is not None and self.bayer not in CFA_PATTERNS:
            raise ConfigError(
                f"{self.name}.bayer: {self.bayer!r}; use one of {sorted(CFA_PATTERNS)} or None (full colour)"
            )
        if self.ground_view_deg is not None:
            g = real_number(f"{self.name}.ground_view_deg", self.ground_view_deg)
            if self.kind != "fisheye" or not 10.0 <= g <= 180.0:
                raise ConfigError(
                    f"{self.name}.ground_view_deg: {self.ground_view_deg!r}; a fisheye's ground view is an "
                    "angle in [10, 180] deg from the body's -z, or None"
                )
        rate = real_number(f"{self.name}.rate_hz", self.rate_hz)
        if not rate > 0:
            raise ConfigError(f"{self.name}.rate_hz: {self.rate_hz!r}; give a rate above 0 [Hz]")
        object.__setattr__(
            self, "mount", check_rigid(np.asarray(self.mount, dtype=np.float64), f"{self.name}.mount")
        )

    @property
    def period(self) -> float:
        """Time between samples [s]."""
        return 1.0 / self.rate_hz


class Rig(Mapping[str, SensorSpec]):
    """A rover's sensors by name, and the rover's kinematic model.

    Args:
        sensors: The sensors (their names must differ).
        vehicle: The rover's :class:`perception.models.rover.RoverKinematicModel` (wheels,
            suspension, markers; its ``T_body_cam`` is the fisheye's mount).
        steer_max_rate: Fastest steering rate of the rover's axles [rad/s].
    """

    def __init__(self, sensors, vehicle=None, steer_max_rate: float = float("inf")) -> None:
        self._sensors: dict[str, SensorSpec] = {}
        for spec in sensors:
            if spec.name in self._sensors:
                raise ConfigError(f"rig: two sensors named {spec.name!r}")
            self._sensors[spec.name] = spec
        self.vehicle = vehicle
        self.steer_max_rate = float(steer_max_rate)

    def __getitem__(self, name: str) -> SensorSpec:
        return self._sensors[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._sensors)

    def __len__(self) -> int:
        return len(self._sensors)

    def of_kind(self, kind: str) -> list[SensorSpec]:
        """The sensors of ``kind``, in the rig's order."""
        return [s for s in self._sensors.values() if s.kind == kind]

    def one(self, kind: str, who: str = "the estimator") -> SensorSpec | None:
        """The rig's only sensor of ``kind``, or None; :class:`ConfigError` if there are several."""
        found = self.of_kind(kind)
        if len(found) > 1:
            names = [s.name for s in found]
            raise ConfigError(f"rig: {who} takes one {kind} sensor; this rig has {names}")
        return found[0] if found else None

    def __repr__(self) -> str:
        inner = ", ".join(f"{s.name}: {s.kind} at {s.rate_hz:g} Hz" for s in self._sensors.values())
        return f"Rig({inner})"


def read_only(rig: Rig) -> Rig:
    """A copy of ``rig`` to give an estimator: its own objects, every array in it read-only.

    An estimator that writes into a calibration it was given (``rig["downward"].model.K[0, 0] =
    ...``, a mount) gets a ``ValueError: assignment destination is read-only`` instead of
    changing the sensors that feed it (in the simulation, the cameras that render its images).
    """
    import copy

    clone = copy.deepcopy(rig)
    _freeze(clone, set())
    return clone


def _freeze(obj: Any, seen: set[int]) -> None:
    """Make every numpy array reachable from ``obj`` read-only."""
    if id(obj) in seen or isinstance(obj, str | bytes | int | float | type(None)):
        return
    seen.add(id(obj))
    if isinstance(obj, np.ndarray):
        obj.flags.writeable = False
    elif isinstance(obj, dict):
        for v in obj.values():
            _freeze(v, seen)
    elif isinstance(obj, list | tuple | set | frozenset):
        for v in obj:
            _freeze(v, seen)
    elif hasattr(obj, "__dict__"):
        for v in vars(obj).values():
            _freeze(v, seen)

"""Replay a robot log through any estimator: the same object that drives in the simulation.

A *rig file* (YAML) says what the log's sensors are, as :class:`perception.rig.Rig` does in
the simulation, and where their messages are (the topic mapping lives here)::

    rover: rover.yaml            # optional: RoverKinematicModel.save (the built-in estimator needs it)
    steer_max_rate: 1.2          # optional [rad/s]
    starts_at_rest: true         # optional: the rover stands still, steering centred, at the log's start
    builtin_estimator:           # optional: the built-in estimator's settings for this log
      odometry: {max_features: 100}   # FlowOdometryConfig fields over the defaults
    sensors:
      - name: fisheye            # the ``sensor`` of its messages
        kind: fisheye            # pinhole | fisheye | imu | sun
        rate_hz: 30
        calibration: fisheye.yaml   # OmniCamera.save (fisheye) or PinholeCamera.save (pinhole)
        topic: /fisheye/image_raw   # optional: the log's only topic of the kind's message type
      - name: imu
        kind: imu
        rate_hz: 200
        mount: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]  # body from IMU
        gyro: {noise_density: 3.0e-4}       # optional data-sheet figures (TriadFigures)
        accel: {noise_density: 2.0e-3}
        saturation: covariance   # optional: -1 at a covariance's start marks a saturated sample
      - name: sun
        kind: sun
        rate_hz: 10
        mount: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.9], [0, 0, 0, 1]]  # body from sensor
        fov_deg: 70                          # optional data-sheet figures (SunSensorModel)
        topic: /sun/direction                # geometry_msgs/Vector3Stamped, sensor frame (NaN: no sun)
        ephemeris_topic: /sun/ephemeris      # geometry_msgs/Vector3Stamped, world frame

Paths are relative to the rig file. :func:`save_rig` writes one for a rig (the simulation's
``env.unwrapped.rig``, for example).

:func:`replay` reads the log's messages (each image and IMU sample placed on the log's time
line by :func:`perception.logs.log_time.place`, damaged messages left out with a warning), gives
them to the estimator in time order as :class:`~perception.rig.SensorMessage` (images as
(H, W, 3) uint8 RGB, IMU samples as gyro xyz [rad/s], accel xyz [m/s^2] and a saturation flag,
sun readings as the sensor's and the ephemeris's unit vectors and a no-sun flag) and calls its
``update`` at every control tick, as the simulation does: ``reset(start_fix)``, then
``update(messages up to t, t)`` at t = 0, 1/control_hz, ... [s] from the first camera frame, up
to the cameras' last frame.

Before any message is given, the log is checked against the rig: each sensor's measured rate
must be its declared ``rate_hz`` within 10 %, and the sensors' time spans must overlap (an IMU
stamped on another clock is an error naming every topic's span, with the ``--time-offset`` that
would put it on the cameras' clock where one is clear).
"""

from __future__ import annotations

import heapq
import logging
import math
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from perception.estimator import ESTIMATE_FIELDS, EstimatorError, check_estimate, estimator_name
from perception.logs.outputs import OutputFolder
from perception.models.calib_io import CalibrationError, check_rigid, read_mapping, write_mapping
from perception.models.cameras import OmniCamera, PinholeCamera
from perception.models.rover import RoverKinematicModel
from perception.models.validation import ConfigError, real_number
from perception.rig import ImuModel, Rig, SensorMessage, SensorSpec, SunSensorModel, TriadFigures, read_only

log = logging.getLogger(__name__)

#: Messages within this of a tick [s] belong to it (stamps are whole nanoseconds).
TICK_TOLERANCE = 1e-6
#: A sensor's measured rate may differ from its declared ``rate_hz`` by this share.
RATE_TOLERANCE = 0.10
#: Samples up to this long before the first camera frame come with it [s] (an IMU's standstill,
#: which calibrates its gyro); earlier ones are left out.
MAX_LEAD = 10.0
#: The control rates a replay takes [Hz].
CONTROL_HZ_RANGE = (1.0, 1000.0)
#: How a user chooses among a log's topics in a replay: in the rig file.
RIG_TOPIC = "give the sensor's topic in the rig file (its `topic:` key)"

#: The columns of :func:`write_estimates`'s CSV: time, the dead-reckoned pose, every estimate.
#: ``t`` is from the first camera frame [s], ``t_log`` the same instant on the log's clock [s].
CSV_COLUMNS: tuple[str, ...] = ("t", "t_log", "x", "y", "yaw", *(f for f in ESTIMATE_FIELDS if f != "pose"))


@dataclass(frozen=True)
class LogRig:
    """A rig file read: the rig and where each sensor's messages are in a log.

    Attributes:
        rig: The sensors and the rover's kinematic model.
        topics: Sensor name -> the log's topic (None: the log's only topic of its kind).
        ephemeris_topics: Sun sensor name -> the topic of the ephemeris's sun direction.
        starts_at_rest: The rover stands still with its steering centred at the log's start.
        saturation_in_covariance: IMUs whose samples mark saturation by -1 at the start of
            their angular-velocity or linear-acceleration covariance (``saturation: covariance``;
            ``rover record`` writes them so). Other IMUs' samples carry the flag 0: ROS's -1
            there means "no estimate", and a driver may write it on every sample.
        odometry_overrides: :class:`~perception.odometry.flow.FlowOdometryConfig` fields the
            built-in estimator takes on this log (``builtin_estimator.odometry``).
    """

    rig: Rig
    topics: dict[str, str | None]
    ephemeris_topics: dict[str, str] = field(default_factory=dict)
    starts_at_rest: bool = False
    odometry_overrides: dict[str, Any] = field(default_factory=dict)
    saturation_in_covariance: frozenset[str] = frozenset()

    def builtin(self) -> Any:
        """The built-in estimator as this rig file sets it up (:class:`perception.RoverEstimator`)."""
        from perception.rover_estimator import RoverEstimator

        return RoverEstimator(
            read_only(self.rig),
            odometry_overrides=dict(self.odometry_overrides) or None,
            zero_steering_at_start=self.starts_at_rest,
        )


_SENSOR_KEYS = {
    "name",
    "kind",
    "rate_hz",
    "calibration",
    "topic",
    "mount",
    "gyro",
    "accel",
    "gamma",
    "bayer",
    "vignetting",
    "ground_view_deg",
    "fov_deg",
    "accuracy_deg",
    "noise_deg",
    "ephemeris_topic",
    "saturation",
}


def _mount(s: dict, key: str) -> np.ndarray:
    """A rig file's ``mount`` (body from sensor; default: the body frame), checked."""
    try:
        return check_rigid(np.asarray(s.get("mount", np.eye(4)), dtype=np.float64), "mount")
    except CalibrationError as exc:
        raise ConfigError(f"{key}.{exc}") from None
    except (TypeError, ValueError):
        raise ConfigError(
            f"{key}.mount: {s['mount']!r}; give a 4 x 4 rigid matrix (body from sensor)"
        ) from None


def _figures(data: Any, key: str) -> TriadFigures:
    if data is None:
        return TriadFigures()
    if not isinstance(data, dict):
        raise ConfigError(f"{key}: {data!r}; give a mapping of {sorted(TriadFigures.__dataclass_fields__)}")
    unknown = sorted(set(data) - set(TriadFigures.__dataclass_fields__))
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}: unknown; use {sorted(TriadFigures.__dataclass_fields__)}")
    values = {k: real_number(f"{key}.{k}", v, allow_inf=k == "range") for k, v in data.items()}
    if any(v < 0 for v in values.values()):
        raise ConfigError(f"{key}: {data!r}; the figures are >= 0")
    return TriadFigures(**values)


def load_rig(path: str | Path) -> LogRig:
    """Read a rig file (see the module's docstring).

    Raises:
        ConfigError: A missing or malformed key, a calibration that does not load, two sensors of
            one name; the message names the file and the key.
    """
    path = Path(path)
    d = read_mapping(
        path, {"sensors"}, {"rover", "steer_max_rate", "starts_at_rest", "builtin_estimator"}, what="rig file"
    )
    here = path.parent
    sensors = d["sensors"]
    if not isinstance(sensors, list) or not sensors:
        raise ConfigError(f"{path}: sensors: give a list of sensors (name, kind, rate_hz, ...)")
    specs, topics, ephemeris, saturating = [], {}, {}, set()
    for i, s in enumerate(sensors):
        key = f"{path}: sensors[{i}]"
        if not isinstance(s, dict):
            raise ConfigError(f"{key}: {s!r}; give a mapping (name, kind, rate_hz, ...)")
        unknown = sorted(set(s) - _SENSOR_KEYS, key=str)
        if unknown:
            raise ConfigError(f"{key}.{unknown[0]}: unknown key; use {sorted(_SENSOR_KEYS)}")
        for need in ("name", "kind", "rate_hz"):
            if need not in s:
                raise ConfigError(f"{key}.{need}: missing")
        name, kind = s["name"], s["kind"]
        if not isinstance(name, str) or not name.strip():
            raise ConfigError(f"{key}.name: {name!r}; give each sensor a non-empty name")
        own = {
            "pinhole": {"calibration", "gamma", "bayer", "vignetting"},
            "fisheye": {"calibration", "gamma", "bayer", "vignetting", "ground_view_deg"},
            "imu": {"mount", "gyro", "accel", "saturation"},
            "sun": {"mount", "fov_deg", "accuracy_deg", "noise_deg", "ephemeris_topic"},
        }
        if kind in ("wheel_encoders", "motor_current", "command"):
            raise ConfigError(
                f"{key}.kind: {kind!r}; proprioceptive sensors are not read from logs yet "
                "(rover replay reads cameras, IMUs and sun sensors): leave it out of the rig file"
            )
        if kind not in own:
            raise ConfigError(f"{key}.kind: {kind!r}; use pinhole, fisheye, imu or sun")
        foreign = sorted(set(s) - own[kind] - {"name", "kind", "rate_hz", "topic"}, key=str)
        if foreign:
            raise ConfigError(
                f"{key}.{foreign[0]}: not a key of a {kind} sensor; its keys: {sorted(own[kind])}"
            )
        if kind in ("pinhole", "fisheye"):
            if "calibration" not in s:
                raise ConfigError(f"{key}.calibration: missing (a {kind} camera's calibration file)")
            cal = here / str(s["calibration"])
            model: Any = PinholeCamera.load(cal) if kind == "pinhole" else OmniCamera.load(cal)
            mount = model.T_body_cam
        elif kind == "imu":
            model = ImuModel(
                gyro=_figures(s.get("gyro"), f"{key}.gyro"), accel=_figures(s.get("accel"), f"{key}.accel")
            )
            mount = _mount(s, key)
            if s.get("saturation", "none") not in ("none", "covariance"):
                raise ConfigError(
                    f"{key}.saturation: {s['saturation']!r}; give covariance (-1 at a covariance's start "
                    "marks a saturated sample) or none"
                )
            if s.get("saturation") == "covariance":
                saturating.add(name)
        else:
            figures = {
                k: real_number(f"{key}.{k}", s[k]) for k in ("fov_deg", "accuracy_deg", "noise_deg") if k in s
            }
            model = SunSensorModel(**figures)
            mount = _mount(s, key)
            if "ephemeris_topic" not in s:
                raise ConfigError(
                    f"{key}.ephemeris_topic: missing (the topic of the sun's direction in the world frame, "
                    "geometry_msgs/Vector3Stamped)"
                )
            ephemeris[name] = str(s["ephemeris_topic"])
        try:
            # a log's images are recorded: no readout window can be asked for
            photometry = {
                k: s[k] for k in ("gamma", "bayer", "vignetting", "ground_view_deg") if s.get(k) is not None
            }
            specs.append(SensorSpec(name, kind, s["rate_hz"], mount, model, **photometry))
        except ConfigError as exc:
            raise ConfigError(f"{key}: {exc}") from None
        topic = s.get("topic")
        if kind == "sun" and topic is None:
            raise ConfigError(
                f"{key}.topic: missing (the sun sensor's direction, geometry_msgs/Vector3Stamped)"
            )
        topics[name] = None if topic is None else str(topic)
    vehicle = RoverKinematicModel.load(here / str(d["rover"])) if d.get("rover") is not None else None
    steer = real_number(f"{path}: steer_max_rate", d.get("steer_max_rate", math.inf), allow_inf=True)
    rest = d.get("starts_at_rest", False)
    if not isinstance(rest, bool):
        raise ConfigError(f"{path}: starts_at_rest: {rest!r}; give true or false")
    odometry = _builtin_settings(d.get("builtin_estimator"), path)
    try:
        rig = Rig(specs, vehicle=vehicle, steer_max_rate=steer)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if odometry and not rig.of_kind("pinhole"):
        raise ConfigError(
            f"{path}: builtin_estimator.odometry: this rig has no downward camera, and the built-in "
            "estimator takes its odometry from the fisheye; leave the block out"
        )
    return LogRig(rig, topics, ephemeris, rest, odometry, frozenset(saturating))


def _builtin_settings(data: Any, path: Path) -> dict[str, Any]:
    """A rig file's ``builtin_estimator`` block: its odometry's FlowOdometryConfig fields, checked."""
    from perception.odometry.flow import FlowOdometryConfig

    if data is None:
        return {}
    if not isinstance(data, dict) or set(data) - {"odometry"}:
        raise ConfigError(
            f"{path}: builtin_estimator: {data!r}; give a mapping with odometry: {{FIELD: VALUE}}"
        )
    odo = data.get("odometry") or {}
    fields = FlowOdometryConfig.__dataclass_fields__
    if not isinstance(odo, dict):
        raise ConfigError(
            f"{path}: builtin_estimator.odometry: {odo!r}; give a mapping of FlowOdometryConfig fields"
        )
    unknown = sorted(set(odo) - set(fields), key=str)
    if unknown:
        raise ConfigError(
            f"{path}: builtin_estimator.odometry.{unknown[0]}: not a FlowOdometryConfig field; use "
            f"{sorted(fields)}"
        )
    try:
        FlowOdometryConfig(**odo)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: builtin_estimator.odometry: {exc}") from None
    return dict(odo)


def rig_files(rig: Rig) -> list[str]:
    """The files :func:`save_rig` writes: ``rig.yaml``, ``rover.yaml`` and each camera's calibration.

    Raises:
        ValueError: A camera's name cannot be a file name (a path separator, ``rig``, ``rover``).
    """
    files = ["rig.yaml"] + (["rover.yaml"] if rig.vehicle is not None else [])
    for spec in rig.values():
        if spec.kind not in ("pinhole", "fisheye"):
            continue
        if (
            spec.name in ("rig", "rover")
            or not spec.name
            or any(c in spec.name for c in "/\\\0")
            or spec.name.startswith(".")
        ):
            raise ValueError(
                f"sensor {spec.name!r}: its calibration file would be {spec.name}.yaml; rename it"
            )
        files.append(f"{spec.name}.yaml")
    return files


def save_rig(
    rig: Rig,
    folder: str | Path | OutputFolder,
    topics: dict[str, str] | None = None,
    overwrite: bool = False,
    ephemeris_topics: dict[str, str] | None = None,
    starts_at_rest: bool = False,
    odometry_overrides: dict[str, Any] | None = None,
    saturation_in_covariance: bool = False,
) -> Path:
    """Write ``rig`` as a rig file ``rig.yaml`` with its calibrations in ``folder``; its path.

    Each camera's calibration is ``<name>.yaml``, the rover's model ``rover.yaml``
    (:func:`rig_files`). A sun sensor is written with its two topics (``topics`` and
    ``ephemeris_topics``), and left out (with a warning) without them.

    Args:
        rig: The rig (cameras' models must be :class:`PinholeCamera` or :class:`OmniCamera`).
        folder: Where to write (created if missing), or an :class:`OutputFolder` whose products
            include :func:`rig_files` (staged; the caller commits).
        topics: Sensor name -> log topic (needed where the log has several topics of a kind).
        overwrite: Replace files of those names already in ``folder``.
        ephemeris_topics: Sun sensor name -> the topic of the ephemeris's sun direction.
        starts_at_rest: Write ``starts_at_rest: true`` (the log starts with the rover at rest,
            its steering centred).
        odometry_overrides: The built-in estimator's odometry settings for this log
            (``builtin_estimator.odometry``), or None.
        saturation_in_covariance: The log's IMU samples mark saturation by -1 at a covariance's
            start (``saturation: covariance``), as :class:`~perception.logs.bags.McapWriter` writes them.

    Raises:
        FileExistsError: A file to write is already there (without ``overwrite``); nothing is written.
        ValueError: A sensor's name cannot be a file name.
    """
    files = rig_files(rig)
    if not isinstance(folder, OutputFolder):
        there = [f for f in files if (Path(folder) / f).exists()]
        if there and not overwrite:
            raise FileExistsError(
                f"{folder}: holds {', '.join(there)}; pass overwrite=True or choose another folder"
            )
        with OutputFolder(folder, files, overwrite=True, announce=False) as out:
            path = save_rig(
                rig, out, topics, True, ephemeris_topics, starts_at_rest, odometry_overrides,
                saturation_in_covariance,
            )  # fmt: skip
            out.commit()
        return path
    topics, ephemeris_topics = topics or {}, ephemeris_topics or {}
    sensors = []
    for spec in rig.values():
        entry: dict[str, Any] = {"name": spec.name, "kind": spec.kind, "rate_hz": float(spec.rate_hz)}
        if spec.kind == "imu":
            entry["mount"] = np.asarray(spec.mount, dtype=np.float64).tolist()
            for triad in ("gyro", "accel"):
                entry[triad] = {k: float(v) for k, v in vars(getattr(spec.model, triad)).items()}
            if saturation_in_covariance:
                entry["saturation"] = "covariance"
        elif spec.kind == "sun":
            if spec.name not in topics or spec.name not in ephemeris_topics:
                log.warning(
                    "sensor %r (sun) left out of the rig file: its entry names the topics of its direction "
                    "and of the ephemeris (give both: topics, ephemeris_topics)",
                    spec.name,
                )
                continue
            entry["mount"] = np.asarray(spec.mount, dtype=np.float64).tolist()
            entry |= {k: float(v) for k, v in vars(spec.model).items()}
            entry["ephemeris_topic"] = ephemeris_topics[spec.name]
        else:
            with folder.writing(f"{spec.name}.yaml") as tmp:
                spec.model.save(tmp)
            entry["calibration"] = f"{spec.name}.yaml"
            if spec.gamma != 1.0:  # the camera's photometry, as its images were recorded
                entry["gamma"] = float(spec.gamma)
            if spec.bayer is not None:
                entry["bayer"] = spec.bayer
            if spec.vignetting != 1.0:
                entry["vignetting"] = float(spec.vignetting)
            if spec.ground_view_deg is not None:
                entry["ground_view_deg"] = float(spec.ground_view_deg)
        if spec.name in topics:
            entry["topic"] = topics[spec.name]
        sensors.append(entry)
    data: dict[str, Any] = {"sensors": sensors}
    if rig.vehicle is not None:
        with folder.writing("rover.yaml") as tmp:
            rig.vehicle.save(tmp)
        data["rover"] = "rover.yaml"
    if math.isfinite(rig.steer_max_rate):
        data["steer_max_rate"] = float(rig.steer_max_rate)
    if starts_at_rest:
        data["starts_at_rest"] = True
    if odometry_overrides:
        data["builtin_estimator"] = {"odometry": dict(odometry_overrides)}
    with folder.writing("rig.yaml") as tmp:
        write_mapping(tmp, data)
    return folder.path / "rig.yaml"


def _rgb(img: np.ndarray, depth: int | None) -> np.ndarray:
    """A decoded log image (BGR, BGRA or grey; 8 or 16 bits) as (H, W, 3) uint8 RGB."""
    from perception.logs.offline import to_8bit

    if img.dtype != np.uint8:
        img = to_8bit(img, max(depth or 16, 10))
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


@dataclass
class _Stream:
    """One sensor's messages in a log: their times (read first, nothing decoded) and the messages.

    ``messages()`` yields (t [s], sensor name, data) in time order; ``times`` are the same t.
    """

    name: str
    kind: str
    topic: str
    times: np.ndarray
    messages: Callable[[], Iterator[tuple[float, str, Any]]]


def _camera_stream(log_path: Path, spec: SensorSpec, topic: str | None) -> _Stream:
    """A camera's topic: its frames' times now, its RGB images as they are read."""
    from perception.logs.bags import log_images
    from perception.logs.offline import _log_source

    src = log_images(log_path, topic, choose=RIG_TOPIC)
    placed = _log_source(src, log_path)
    want = tuple(spec.model.image_size)

    def messages() -> Iterator[tuple[float, str, Any]]:
        skipped: dict[str, int] = {}
        for p in placed.placed:
            frame = p.item
            why = p.why or frame.why or ("" if frame.image is not None else "does not decode")
            if why or not math.isfinite(p.t):
                skipped[why or "no time"] = skipped.get(why or "no time", 0) + 1
                continue
            h, w = frame.image.shape[:2]
            if (w, h) != want:
                raise ValueError(
                    f"{log_path}: {src.topic}: a {w}x{h} px image at t={p.t:.6f} s, but sensor "
                    f"{spec.name!r}'s calibration is {want[0]}x{want[1]} px; give the calibration of this "
                    "camera"
                )
            yield p.t, spec.name, _rgb(frame.image, placed.depth)
        for why, n in skipped.items():
            log.warning("%s: %s: %d frames left out (%s)", log_path, src.topic, n, why)

    return _Stream(spec.name, spec.kind, src.topic, np.asarray(placed.times, dtype=np.float64), messages)


def _imu_stream(log_path: Path, spec: SensorSpec, topic: str | None, flags: bool) -> _Stream:
    """An IMU topic: (7,) gyro xyz [rad/s], accel xyz [m/s^2] and a saturation flag (0 without ``flags``)."""
    from perception.logs.bags import log_imu

    rows, name = log_imu(log_path, topic, choose=RIG_TOPIC, flags=flags)
    if not flags:
        rows = np.column_stack([rows, np.zeros(len(rows))])

    def messages() -> Iterator[tuple[float, str, Any]]:
        for r in rows:
            yield float(r[0]), spec.name, np.array(r[1:8], dtype=np.float64)

    return _Stream(spec.name, spec.kind, name, rows[:, 0].copy(), messages)


def _sun_stream(log_path: Path, spec: SensorSpec, topic: str, ephemeris_topic: str) -> _Stream:
    """A sun sensor's two topics paired by stamp: (7,) direction (sensor), ephemeris (world), no-sun flag."""
    from perception.logs.bags import log_vectors

    seen, eph = log_vectors(log_path, topic), log_vectors(log_path, ephemeris_topic)
    rows = []
    if len(eph):
        # the ephemeris sample nearest each reading: the one before or after it in time
        after = np.clip(np.searchsorted(eph[:, 0], seen[:, 0]), 0, len(eph) - 1)
        before = np.maximum(after - 1, 0)
        near = np.where(
            np.abs(eph[before, 0] - seen[:, 0]) < np.abs(eph[after, 0] - seen[:, 0]), before, after
        )
        for r, j in zip(seen, near, strict=True):
            if abs(eph[j, 0] - r[0]) <= 1e-3:
                no_sun = not np.all(np.isfinite(r[1:4]))
                rows.append([r[0], *(np.full(3, np.nan) if no_sun else r[1:4]), *eph[j, 1:4], float(no_sun)])
    if len(rows) < len(seen):
        log.warning(
            "%s: %s: %d of %d sun readings without an ephemeris sample on %s at their time: left out",
            log_path, topic, len(seen) - len(rows), len(seen), ephemeris_topic,
        )  # fmt: skip
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)

    def messages() -> Iterator[tuple[float, str, Any]]:
        for r in data:
            yield float(r[0]), spec.name, r[1:8].copy()

    return _Stream(spec.name, spec.kind, topic, data[:, 0].copy(), messages)


def _measured_rate(times: np.ndarray) -> float | None:
    """A stream's rate [Hz] from its median sample spacing (None with fewer than three samples)."""
    if len(times) < 3:
        return None
    d = np.diff(times)
    d = d[d > 0]
    return 1.0 / float(np.median(d)) if len(d) else None


def _check_streams(log_path: Path, log_rig: LogRig, streams: list[_Stream]) -> tuple[float, float]:
    """The log against the rig: rates as declared, time spans that overlap; (t_first_camera, t_end) [s].

    Raises:
        ValueError: A rate more than :data:`RATE_TOLERANCE` off its ``rate_hz`` (naming both), or
            time spans that do not overlap (naming each topic's, and a ``--time-offset`` that
            would put a sensor on the cameras' clock where one is clear).
    """
    for st in streams:
        rate = _measured_rate(st.times)
        declared = log_rig.rig[st.name].rate_hz
        if rate is not None and abs(rate / declared - 1.0) > RATE_TOLERANCE:
            raise ValueError(
                f"{log_path}: sensor {st.name!r} ({st.topic}): the rig file says rate_hz {declared:g}, "
                f"but its messages come at {rate:.4g} Hz (median spacing {1e3 / rate:.4g} ms); put its "
                "rate in the rig file"
            )
    cameras = [st for st in streams if st.kind in ("pinhole", "fisheye")]
    pace = cameras or streams
    spans = {st.name: (float(st.times[0]), float(st.times[-1])) for st in streams}
    lo, hi = max(a for a, _ in spans.values()), min(b for _, b in spans.values())
    if lo > hi:
        a0, b0 = min(spans[st.name][0] for st in pace), max(spans[st.name][1] for st in pace)
        listing = "; ".join(f"{st.name} ({st.topic}) {spans[st.name][0]:.3f} to {spans[st.name][1]:.3f} s"
                            for st in streams)  # fmt: skip
        hints = []
        for st in streams:
            a, b = spans[st.name]
            if st in pace or (b >= a0 and a <= b0):
                continue
            length, ref = b - a, max(b0 - a0, 1.0 / log_rig.rig[st.name].rate_hz)
            if 0.5 * ref <= length <= 3.0 * ref + 1.0:  # about as long: the same stretch on another clock
                hints.append(f"--time-offset {st.name}={0.5 * (a0 + b0 - a - b):.3f}")
        fix = (
            f"if a sensor's clock is offset by a constant, {' '.join(hints)} centres its samples on the "
            "cameras' (check the offset)"
            if hints
            else "put the sensors' stamps on one clock (or give --time-offset SENSOR=SECONDS)"
        )
        raise ValueError(f"{log_path}: the sensors' time spans do not overlap ({listing}); {fix}")
    t0 = min(spans[st.name][0] for st in pace)
    end = max(spans[st.name][1] for st in pace)
    for st in pace:
        gap = float(np.diff(st.times).max()) if len(st.times) > 1 else 0.0
        if gap > 10.0:
            log.warning(
                "%s: sensor %r (%s) has a gap of %.1f s between frames: the estimator is updated at every "
                "control tick through it",
                log_path, st.name, st.topic, gap,
            )  # fmt: skip
    for st in streams:
        if st in pace:
            continue
        a, b = spans[st.name]
        cover = (min(b, end) - max(a, t0)) / max(end - t0, 1e-9)
        if cover < 0.9:
            log.warning(
                "%s: sensor %r (%s) covers %.0f %% of the cameras' %.3f to %.3f s",
                log_path, st.name, st.topic, 100 * cover, t0, end,
            )  # fmt: skip
    return t0, end


@dataclass(frozen=True)
class ReplayStep:
    """One control tick of a replay.

    Attributes:
        t: Control time from the first camera frame [s].
        t_log: The same instant on the log's clock (its header stamps) [s].
        estimate: What the estimator returned (checked, :func:`perception.estimator.check_estimate`).
        messages: How many messages it was given at this tick.
    """

    t: float
    t_log: float
    estimate: dict[str, Any]
    messages: int


def replay(
    log_path: str | Path,
    log_rig: LogRig,
    estimator: Any,
    control_hz: float = 30.0,
    start_fix: Sequence[float] | Callable[[float], Sequence[float]] = (0.0, 0.0, 0.0),
    time_offsets: Mapping[str, float] | None = None,
) -> Iterator[ReplayStep]:
    """Feed a log's messages to ``estimator`` tick by tick, as the simulation does.

    Every check is made at once, before any message is read or given: the control rate, the
    start fix, the estimator's interface, and the log against the rig (each sensor's topic, its
    measured rate against ``rate_hz``, the sensors' time spans overlapping).

    Args:
        log_path: A ROS 1 bag, ROS 2 bag folder or MCAP file.
        log_rig: The rig and the topics (:func:`load_rig`).
        estimator: Any object with ``reset(start_fix)`` and ``update(messages, t)``
            (:mod:`perception.estimator`); built from a :func:`perception.rig.read_only` copy of
            ``log_rig.rig`` by its factory.
        control_hz: Ticks per second [Hz], in :data:`CONTROL_HZ_RANGE`.
        start_fix: The start fix (x [m], y [m], yaw [rad]), or a function of the first camera
            frame's time on the log's clock [s] that gives it (the truth's pose then).
        time_offsets: Sensor name -> seconds added to its stamps (a sensor on another clock).

    Returns:
        An iterator of a :class:`ReplayStep` per tick, from t = 0 (the first camera frame) to the
        cameras' last frame (messages after the last tick, less than a control period, are left
        out); the images are read as it is iterated.

    Raises:
        ValueError: A bad ``control_hz``, ``start_fix`` or offset; a log without a sensor's
            topic, a sensor's rate beyond 10 % of its ``rate_hz``, time spans that do not overlap.
            While iterating: images of another size than the calibration.
        EstimatorError: ``estimator`` lacks ``reset`` or ``update`` (at once); while iterating,
            it raised (or exited) or returned something malformed (named, with the step).
    """
    rate = real_number("control_hz", control_hz)
    lo, hi = CONTROL_HZ_RANGE
    if not lo <= rate <= hi:
        raise ValueError(f"control_hz={control_hz!r}: give a control rate from {lo:g} to {hi:g} Hz")
    if not callable(start_fix):
        _start_fix(start_fix)
    for name in ("reset", "update"):
        if not callable(getattr(estimator, name, None)):
            raise EstimatorError(
                f"estimator {estimator_name(estimator)} has no {name}() method; an estimator has "
                "reset(start_fix) and update(messages, t) (see perception.estimator)"
            )
    offsets = dict(time_offsets or {})
    for name, dt in offsets.items():
        if name not in log_rig.rig:
            raise ValueError(f"--time-offset {name}: no sensor of that name in the rig ({list(log_rig.rig)})")
        if not (isinstance(dt, int | float) and math.isfinite(dt)):
            raise ValueError(f"--time-offset {name}={dt!r}: give a finite number of seconds")
    log_path = Path(log_path)
    streams = []
    for name, spec in log_rig.rig.items():
        topic = log_rig.topics.get(name)
        if spec.kind == "imu":
            st = _imu_stream(log_path, spec, topic, name in log_rig.saturation_in_covariance)
        elif spec.kind == "sun":
            st = _sun_stream(log_path, spec, str(topic), log_rig.ephemeris_topics[name])
        else:
            st = _camera_stream(log_path, spec, topic)
        if not len(st.times):
            log.warning("%s: no usable message of sensor %r (%s)", log_path, name, st.topic)
            continue
        if name in offsets:
            st = _shifted(st, offsets[name])
        streams.append(st)
    if not streams:
        raise ValueError(f"{log_path}: no usable message from the rig's sensors")
    t0, end = _check_streams(log_path, log_rig, streams)
    fix = _start_fix(start_fix(t0) if callable(start_fix) else start_fix)
    return _replay(log_path, streams, estimator, rate, fix, t0, end)


def _start_fix(value) -> np.ndarray:
    fix = np.asarray(value, dtype=np.float64)
    if fix.shape != (3,) or not np.all(np.isfinite(fix)):
        raise ValueError(f"start_fix={list(value)!r}: give a finite (x, y, yaw) [m, rad]")
    return fix


def _shifted(st: _Stream, dt: float) -> _Stream:
    """``st`` with ``dt`` [s] added to its times."""
    inner = st.messages

    def messages() -> Iterator[tuple[float, str, Any]]:
        for t, name, data in inner():
            yield t + dt, name, data

    return _Stream(st.name, st.kind, st.topic, st.times + dt, messages)


def _replay(
    log_path: Path,
    streams: list[_Stream],
    estimator: Any,
    rate: float,
    fix: np.ndarray,
    t0: float,
    end: float,
) -> Iterator[ReplayStep]:
    merged = heapq.merge(*(st.messages() for st in streams), key=lambda m: m[0])
    who = estimator_name(estimator)
    try:
        estimator.reset(fix.copy())
    except (Exception, SystemExit) as exc:  # the user's code: any error (an exit too), named
        raise EstimatorError(f"estimator {who}, reset: {type(exc).__name__}: {exc}") from exc
    last = int(math.floor((end - t0 + TICK_TOLERANCE) * rate))  # the last tick at or before the cameras' end
    step = 0
    pending: list[SensorMessage] = []
    early = late = 0

    def tick() -> ReplayStep:
        t = step / rate
        try:
            values = estimator.update(list(pending), t)
        except (Exception, SystemExit) as exc:  # the user's code: any error (an exit too), named
            raise EstimatorError(f"estimator {who}, step {step}: {type(exc).__name__}: {exc}") from exc
        return ReplayStep(t, t0 + t, check_estimate(values, who, step), len(pending))

    for t_abs, name, data in merged:
        t = t_abs - t0
        if t < -MAX_LEAD:
            early += 1
            continue
        while t > step / rate + TICK_TOLERANCE and step <= last:
            yield tick()
            pending = []
            step += 1
        if step > last:
            late += 1
            continue
        if isinstance(data, np.ndarray):
            data.flags.writeable = False  # the estimator reads a sample; it cannot change it
        pending.append(SensorMessage(name, t, data))
    while step <= last:  # the ticks up to the cameras' last frame
        yield tick()
        pending = []
        step += 1
    if early:
        log.warning(
            "%s: %d messages more than %g s before the first camera frame left out", log_path, early, MAX_LEAD
        )
    if late:
        log.info("%s: %d messages after the last control tick (%.6f s) left out", log_path, late, last / rate)


def write_estimates(steps: Iterator[ReplayStep], path: str | Path) -> int:
    """Write replay steps as CSV (:data:`CSV_COLUMNS`; an estimate not returned is empty); the row count."""
    import csv

    n = 0
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(CSV_COLUMNS)
        for s in steps:
            pose = s.estimate["pose"]
            row = [f"{s.t:.6f}", f"{s.t_log:.9f}", *(repr(float(v)) for v in pose)]
            row += ["" if s.estimate.get(c) is None else repr(float(s.estimate[c])) for c in CSV_COLUMNS[5:]]
            out.writerow(row)
            n += 1
    return n

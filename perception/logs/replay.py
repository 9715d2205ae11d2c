"""Replay a robot log through any estimator: the same object that drives in the simulation.

A *rig file* (YAML) says what the log's sensors are, as :class:`perception.rig.Rig` does in
the simulation, and where their messages are::

    rover: rover.yaml            # optional: RoverKinematicModel.save (the built-in estimator needs it)
    steer_max_rate: 1.2          # optional [rad/s]
    sensors:
      - name: fisheye            # the ``sensor`` of its messages
        kind: fisheye            # pinhole | fisheye | imu
        rate_hz: 30
        calibration: fisheye.yaml   # OmniCamera.save (fisheye) or PinholeCamera.save (pinhole)
        topic: /fisheye/image_raw   # optional: the log's only topic of the kind's message type
      - name: imu
        kind: imu
        rate_hz: 200
        mount: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]]  # body from IMU
        gyro: {noise_density: 3.0e-4}       # optional data-sheet figures (TriadFigures)
        accel: {noise_density: 2.0e-3}

Paths are relative to the rig file. :func:`save_rig` writes one for a rig (the simulation's
``env.unwrapped.rig``, for example).

:func:`replay` reads the log's messages (each image and IMU sample placed on the log's time
line by :func:`perception.logs.log_time.place`, damaged messages left out with a warning), gives
them to the estimator in time order as :class:`~perception.rig.SensorMessage` (images as
(H, W, 3) uint8 RGB, IMU samples as gyro xyz [rad/s], accel xyz [m/s^2] and a saturation flag 0)
and calls its ``update`` at every control tick, as the simulation does: ``reset(start_fix)``,
then ``update(messages up to t, t)`` at t = 0, 1/control_hz, ... [s] from the first message.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from perception.estimator import ESTIMATE_FIELDS, check_estimate, estimator_name
from perception.models.calib_io import CalibrationError, check_rigid, read_mapping, write_mapping
from perception.models.cameras import OmniCamera, PinholeCamera
from perception.models.rover import RoverKinematicModel
from perception.models.validation import ConfigError, real_number
from perception.rig import ImuModel, Rig, SensorMessage, SensorSpec, TriadFigures

log = logging.getLogger(__name__)

#: Messages within this of a tick [s] belong to it (stamps are whole nanoseconds).
TICK_TOLERANCE = 1e-6

#: The columns of :func:`write_estimates`'s CSV: time, the dead-reckoned pose, every estimate.
#: ``t`` is from the first camera frame [s], ``t_log`` the same instant on the log's clock [s].
CSV_COLUMNS: tuple[str, ...] = ("t", "t_log", "x", "y", "yaw", *(f for f in ESTIMATE_FIELDS if f != "pose"))


@dataclass(frozen=True)
class LogRig:
    """A rig file read: the rig and where each sensor's messages are in a log.

    Attributes:
        rig: The sensors and the rover's kinematic model.
        topics: Sensor name -> the log's topic (None: the log's only topic of its kind).
    """

    rig: Rig
    topics: dict[str, str | None]


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
}


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
    d = read_mapping(path, {"sensors"}, {"rover", "steer_max_rate"}, what="rig file")
    here = path.parent
    sensors = d["sensors"]
    if not isinstance(sensors, list) or not sensors:
        raise ConfigError(f"{path}: sensors: give a list of sensors (name, kind, rate_hz, ...)")
    specs, topics = [], {}
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
        if kind in ("pinhole", "fisheye"):
            if "calibration" not in s:
                raise ConfigError(f"{key}.calibration: missing (a {kind} camera's calibration file)")
            cal = here / str(s["calibration"])
            model: Any = PinholeCamera.load(cal) if kind == "pinhole" else OmniCamera.load(cal)
            mount = model.T_body_cam
            if "mount" in s:
                raise ConfigError(f"{key}.mount: a camera's mount is its calibration's T_body_cam")
        elif kind == "imu":
            model = ImuModel(
                gyro=_figures(s.get("gyro"), f"{key}.gyro"), accel=_figures(s.get("accel"), f"{key}.accel")
            )
            try:
                mount = check_rigid(np.asarray(s.get("mount", np.eye(4)), dtype=np.float64), "mount")
            except CalibrationError as exc:
                raise ConfigError(f"{key}.{exc}") from None
            except (TypeError, ValueError):
                raise ConfigError(
                    f"{key}.mount: {s['mount']!r}; give a 4 x 4 rigid matrix (body from IMU)"
                ) from None
        else:
            raise ConfigError(f"{key}.kind: {kind!r}; use pinhole, fisheye or imu")
        try:
            # a log's images are recorded: no readout window can be asked for
            photometry = {k: s[k] for k in ("gamma", "bayer", "vignetting") if s.get(k) is not None}
            specs.append(SensorSpec(name, kind, s["rate_hz"], mount, model, **photometry))
        except ConfigError as exc:
            raise ConfigError(f"{key}: {exc}") from None
        topic = s.get("topic")
        topics[name] = None if topic is None else str(topic)
    vehicle = RoverKinematicModel.load(here / str(d["rover"])) if d.get("rover") is not None else None
    steer = real_number(f"{path}: steer_max_rate", d.get("steer_max_rate", math.inf), allow_inf=True)
    try:
        rig = Rig(specs, vehicle=vehicle, steer_max_rate=steer)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return LogRig(rig, topics)


def save_rig(
    rig: Rig, folder: str | Path, topics: dict[str, str] | None = None, overwrite: bool = False
) -> Path:
    """Write ``rig`` as a rig file ``rig.yaml`` with its calibrations in ``folder``; its path.

    Each camera's calibration is ``<name>.yaml``, the rover's model ``rover.yaml``. A sun sensor
    is left out (with a warning): logs carry cameras and IMUs only.

    Args:
        rig: The rig (cameras' models must be :class:`PinholeCamera` or :class:`OmniCamera`).
        folder: Where to write (created if missing).
        topics: Sensor name -> log topic, where the log has several topics of a kind.
        overwrite: Replace files of those names already in ``folder``.

    Raises:
        FileExistsError: A file to write is already there (without ``overwrite``); nothing is written.
        ValueError: A sensor's name cannot be a file name (a path separator, ``rig``, ``rover``).
    """
    folder = Path(folder)
    files = ["rig.yaml"] + (["rover.yaml"] if rig.vehicle is not None else [])
    specs = [s for s in rig.values() if s.kind in ("pinhole", "fisheye", "imu")]
    for spec in rig.values():
        if spec not in specs:
            log.warning(
                "sensor %r (%s) left out of the rig file: logs carry cameras and IMUs", spec.name, spec.kind
            )
    for spec in specs:
        if spec.kind == "imu":
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
    there = [f for f in files if (folder / f).exists()]
    if there and not overwrite:
        raise FileExistsError(
            f"{folder}: holds {', '.join(there)}; pass overwrite=True or choose another folder"
        )
    folder.mkdir(parents=True, exist_ok=True)
    sensors = []
    for spec in specs:
        entry: dict[str, Any] = {"name": spec.name, "kind": spec.kind, "rate_hz": float(spec.rate_hz)}
        if spec.kind == "imu":
            entry["mount"] = np.asarray(spec.mount, dtype=np.float64).tolist()
            for triad in ("gyro", "accel"):
                entry[triad] = {k: float(v) for k, v in vars(getattr(spec.model, triad)).items()}
        else:
            spec.model.save(folder / f"{spec.name}.yaml")
            entry["calibration"] = f"{spec.name}.yaml"
            if spec.gamma != 1.0:  # the camera's photometry, as its images were recorded
                entry["gamma"] = float(spec.gamma)
            if spec.bayer is not None:
                entry["bayer"] = spec.bayer
            if spec.vignetting != 1.0:
                entry["vignetting"] = float(spec.vignetting)
        if topics and spec.name in topics:
            entry["topic"] = topics[spec.name]
        sensors.append(entry)
    data: dict[str, Any] = {"sensors": sensors}
    if rig.vehicle is not None:
        rig.vehicle.save(folder / "rover.yaml")
        data["rover"] = "rover.yaml"
    if math.isfinite(rig.steer_max_rate):
        data["steer_max_rate"] = float(rig.steer_max_rate)
    return write_mapping(folder / "rig.yaml", data)


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


def _camera_stream(log_path: Path, spec: SensorSpec, topic: str | None) -> Iterator[tuple[float, str, Any]]:
    """(t, sensor, RGB image) of a camera's topic, in time order; unusable frames left out."""
    from perception.logs.bags import log_images
    from perception.logs.offline import _log_source

    src = log_images(log_path, topic)
    placed = _log_source(src, log_path)
    want = tuple(spec.model.image_size)
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
                f"{spec.name!r}'s calibration is {want[0]}x{want[1]} px; give the calibration of this camera"
            )
        yield p.t, spec.name, _rgb(frame.image, placed.depth)
    for why, n in skipped.items():
        log.warning("%s: %s: %d frames left out (%s)", log_path, src.topic, n, why)


def _imu_stream(log_path: Path, spec: SensorSpec, topic: str | None) -> Iterator[tuple[float, str, Any]]:
    """(t, sensor, (7,) gyro, accel, saturation 0) of an IMU topic, in time order."""
    from perception.logs.bags import log_imu

    rows, _ = log_imu(log_path, topic)
    for r in rows:
        yield float(r[0]), spec.name, np.r_[r[1:7], 0.0]


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
    start_fix: Sequence[float] = (0.0, 0.0, 0.0),
) -> Iterator[ReplayStep]:
    """Feed a log's messages to ``estimator`` tick by tick, as the simulation does.

    Args:
        log_path: A ROS 1 bag, ROS 2 bag folder or MCAP file.
        log_rig: The rig and the topics (:func:`load_rig`).
        estimator: Any object with ``reset(start_fix)`` and ``update(messages, t)``
            (:mod:`perception.estimator`); built from ``log_rig.rig`` by its factory.
        control_hz: Ticks per second [Hz].
        start_fix: The start fix (x [m], y [m], yaw [rad]).

    Returns:
        An iterator of a :class:`ReplayStep` per tick, from t = 0 (the first camera frame) to the
        last message; the log is read as it is iterated.

    Raises:
        ValueError: A bad ``control_hz`` or ``start_fix`` (at once). While iterating: a log
            without a sensor's topic, or images of another size than the calibration.
        TypeError: ``estimator`` lacks ``reset`` or ``update`` (at once).
        EstimatorError: While iterating: the estimator raised or returned something malformed
            (named, with the step).
    """
    rate = real_number("control_hz", control_hz)
    if not 0 < rate <= 1000:
        raise ValueError(f"control_hz={control_hz!r}: give a control rate in (0, 1000] Hz")
    fix = np.asarray(start_fix, dtype=np.float64)
    if fix.shape != (3,) or not np.all(np.isfinite(fix)):
        raise ValueError(f"start_fix={list(start_fix)!r}: give a finite (x, y, yaw) [m, rad]")
    for name in ("reset", "update"):
        if not callable(getattr(estimator, name, None)):
            raise TypeError(
                f"estimator {estimator_name(estimator)} has no {name}() method (see perception.estimator)"
            )
    return _replay(Path(log_path), log_rig, estimator, rate, fix)


def _replay(
    log_path: Path, log_rig: LogRig, estimator: Any, rate: float, fix: np.ndarray
) -> Iterator[ReplayStep]:
    from perception.estimator import EstimatorError

    streams, firsts = [], []
    for name, spec in log_rig.rig.items():
        make: Callable = _imu_stream if spec.kind == "imu" else _camera_stream
        stream = make(log_path, spec, log_rig.topics.get(name))
        first = next(stream, None)
        if first is None:
            log.warning("%s: no usable message of sensor %r", log_path, name)
            continue
        firsts.append((first[0], spec.kind != "imu"))
        streams.append(itertools.chain([first], stream))
    if not streams:
        raise ValueError(f"{log_path}: no usable message from the rig's sensors")
    # time 0 is the first camera frame (the cameras pace the loop); earlier IMU samples come with it
    cameras = [t for t, is_camera in firsts if is_camera]
    t0 = min(cameras) if cameras else min(t for t, _ in firsts)
    merged = heapq.merge(*streams, key=lambda m: m[0])
    who = estimator_name(estimator)
    try:
        estimator.reset(fix.copy())
    except Exception as exc:
        raise EstimatorError(f"estimator {who}, reset: {type(exc).__name__}: {exc}") from exc
    step = 0
    pending: list[SensorMessage] = []

    def tick() -> ReplayStep:
        t = step / rate
        try:
            values = estimator.update(list(pending), t)
        except Exception as exc:
            raise EstimatorError(f"estimator {who}, step {step}: {type(exc).__name__}: {exc}") from exc
        return ReplayStep(t, t0 + t, check_estimate(values, who, step), len(pending))

    for t_abs, name, data in merged:
        t = t_abs - t0
        while t > step / rate + TICK_TOLERANCE:
            yield tick()
            pending = []
            step += 1
        pending.append(SensorMessage(name, t, data))
    if pending:
        yield tick()


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

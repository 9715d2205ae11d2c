"""``rover record``: drive a mission and write a robot log of every rig sensor, its rig file and the truth.

The mission is driven as ``rover eval`` drives it (a named controller on the estimates of the
built-in estimator, honest loop), while every message the simulation samples for the rig is
written to an MCAP file (:class:`perception.logs.bags.McapWriter`):

- cameras: ``sensor_msgs/CompressedImage``, PNG (lossless), on ``/<name>/image_raw/compressed``;
  a field camera's frame as its image sensor made it, the RGGB Bayer mosaic (``bayer_rggb8``),
  which demosaics into the very image the estimator saw; ``raw=True``: ``sensor_msgs/Image`` on
  ``/<name>/image_raw``;
- an IMU: ``sensor_msgs/Imu`` on ``/<name>/data`` (a saturated sample flagged, see
  :meth:`~perception.logs.bags.McapWriter.imu`);
- a sun sensor: ``geometry_msgs/Vector3Stamped`` on ``/<name>/direction`` (its frame; NaN: no
  sun) and ``/<name>/ephemeris`` (the world frame).

The log's clock starts when the rover is placed: log time = simulation time + the settling
time (2 s), so every stamp is valid (positive) and the mission's first camera frame is at 2 s.
Beside the log: the rig file (``rig.yaml`` with its topics, the calibrations and ``rover.yaml``;
:func:`perception.logs.replay.save_rig`), the truth at every control step on the log's clock
(``truth.csv``, :mod:`perception.logs.truth`, and ``truth.tum``) and what the built-in estimator
gave in the loop (``estimates_in_loop.csv``, the columns of ``rover replay``'s
``estimates.csv``). So ``rover replay DIR/log.mcap --rig DIR/rig.yaml --truth DIR/truth.csv``
runs on it at once and scores its estimates, to compare with the loop's.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from perception.logs.bags import McapWriter
from perception.logs.outputs import OutputFolder
from perception.logs.replay import ReplayStep, rig_files, save_rig, write_estimates
from perception.logs.truth import TRUTH_COLUMNS, read_estimates, score, write_truth
from perception.models.drive_geometry import AXLES, WHEELS
from perception.odometry.trajectory import write_tum
from perception.rig import SensorMessage
from rover_env.config.rig import PERCEPTION_PRESETS, PresetName
from rover_env.sensors.rig import builtin_estimator
from rover_env.sim.transforms import quat_to_yaw
from rover_env.tools.registry import parse_controller

log = logging.getLogger(__name__)

#: What ``rover record`` writes besides the rig file (:func:`perception.logs.replay.rig_files`).
RECORD_FILES = ("log.mcap", "truth.csv", "truth.tum", "estimates_in_loop.csv")
#: Longest recording [s].
MAX_SECONDS = 3600.0


@dataclass(frozen=True)
class RecordResult:
    """What :func:`record` wrote.

    Attributes:
        folder: The output folder.
        seconds: Simulated time recorded after the start [s].
        termination: How the mission ended (``"recorded"``: it was still under way at the end).
        messages: Messages written per sensor.
        log_bytes: Size of ``log.mcap`` [bytes].
        loop_errors: The built-in estimator's errors in the loop against the truth (MAE per field,
            after the first second).
    """

    folder: Path
    seconds: float
    termination: str
    messages: dict[str, int]
    log_bytes: int
    loop_errors: dict[str, float] = field(default_factory=dict)


def topics_of(rig, raw: bool = False) -> tuple[dict[str, str], dict[str, str]]:
    """The log's topic of each sensor of ``rig``, and each sun sensor's ephemeris topic."""
    topics, ephemeris = {}, {}
    for name, spec in rig.items():
        if spec.kind in ("pinhole", "fisheye"):
            topics[name] = f"/{name}/image_raw" + ("" if raw else "/compressed")
        elif spec.kind == "imu":
            topics[name] = f"/{name}/data"
        elif spec.kind == "sun":
            topics[name], ephemeris[name] = f"/{name}/direction", f"/{name}/ephemeris"
    return topics, ephemeris


def record(
    mission: str,
    controller: str,
    seconds: float,
    out: str | Path,
    *,
    preset: PresetName = "train",
    seed: int = 0,
    raw: bool = False,
    camera_effects: str = "field",
    randomize: str | None = None,
    rig: str | None = None,
    overwrite: bool = False,
    progress: Callable[[float], None] | None = None,
) -> RecordResult:
    """Drive ``mission`` with ``controller`` for ``seconds``; its log, rig file and truth into ``out``.

    Args:
        mission: An environment id or scenario (as ``rover eval --missions`` takes).
        controller: A controller on the estimates (``slip_aware``, ``slip_unaware@imu``, ...).
        seconds: Simulated time to record after the start [s] (less if the mission ends first).
        out: The output folder (:class:`OutputFolder`; its files are committed together at the end).
        preset: Camera preset.
        seed: Episode seed.
        raw: Raw ``sensor_msgs/Image`` messages instead of PNG-compressed ones.
        camera_effects: ``"field"`` or ``"ideal"`` cameras.
        randomize: Domain randomisation (``"off"``, ``"on"`` or None: the scenario's).
        rig: A named rig in place of the mission's (``"standard"``, ``"fisheye_only"``; not
            ``"full"``, whose proprioceptive sensors have no log format yet).
        overwrite: Replace the results of an earlier recording in ``out``.
        progress: Called with the simulated time recorded [s].

    Raises:
        ValueError: A controller on the ground truth (no sensor runs then), a bad duration,
            preset or mission (before anything is written).
    """
    from rover_env.tools.evaluation import EvalJob, env_kwargs, make_mission_env

    if not (isinstance(seconds, int | float) and math.isfinite(seconds) and 0.0 < seconds <= MAX_SECONDS):
        raise ValueError(f"--seconds {seconds!r}: give a duration above 0 and at most {MAX_SECONDS:g} s")
    if rig == "full":
        raise ValueError(
            "--rig full: rover record writes cameras, IMUs and sun sensors; the full rig's wheel "
            "encoders, motor currents and command have no log format yet: record with --rig standard"
        )
    spec, source = parse_controller(controller)
    if source != "estimated":
        raise ValueError(
            f"--controller {controller!r} drives on the simulator's state, and no sensor runs then; record "
            "a controller that drives on the estimates (e.g. slip_aware, or slip_aware@imu for an IMU)"
        )
    if preset not in PERCEPTION_PRESETS:
        raise ValueError(f"--preset {preset!r}: use one of {sorted(PERCEPTION_PRESETS)}")
    # the environment rover eval would make for this run (its IMU, cameras, world and rig)
    job = EvalJob(
        controller, mission, seed, preset, camera_effects=camera_effects, randomize=randomize, rig=rig
    )
    kwargs = env_kwargs(job, spec.action_mode, source)
    # the folder first: a link or an earlier recording is refused before the simulation is built
    with OutputFolder(out, (*RECORD_FILES, "rig.yaml", "rover.yaml"), overwrite) as folder:
        # the fisheye renders whole frames (no windows chosen by the estimator): the log holds them
        kwargs["estimator"] = builtin_estimator(PERCEPTION_PRESETS[preset], fisheye_window=None)
        env = make_mission_env(mission, **kwargs)
        try:
            folder.add_products(rig_files(env.unwrapped.rig))  # the cameras' calibrations
            result = _record(
                env.unwrapped,
                spec.make(env),
                seconds,
                folder,
                seed,
                raw,
                progress,
                PERCEPTION_PRESETS[preset],
            )
        finally:
            env.close()
        folder.commit()
    return result


def _record(env, controller, seconds, folder: OutputFolder, seed, raw, progress, preset) -> RecordResult:
    """Drive and write into ``folder`` (its products staged; the caller commits)."""
    pipeline = env.pipeline
    rig = env.rig
    unlogged = [
        f"{n} ({s.kind})" for n, s in rig.items() if s.kind not in ("pinhole", "fisheye", "imu", "sun")
    ]
    if unlogged:
        raise ValueError(
            f"rover record writes cameras, IMUs and sun sensors; {', '.join(unlogged)} have no log "
            "format yet: record with a rig without them (--rig standard)"
        )
    offset = float(env.sim.settle_time)  # log time = simulation time + offset: every stamp > 0
    topics, ephemeris = topics_of(rig, raw)
    for cam in pipeline.cameras:
        if cam.image_sensor is not None:
            cam.image_sensor.keep_mosaics(8)
    counts = dict.fromkeys(rig, 0)
    truth_rows: list[dict[str, float]] = []
    loop_rows: list[ReplayStep] = []
    with folder.writing("log.mcap") as log_path, McapWriter(log_path) as writer:

        def write(messages: list[SensorMessage]) -> None:
            for m in messages:
                t = m.t + offset
                kind = rig[m.sensor].kind
                if kind in ("pinhole", "fisheye"):
                    cam = pipeline.sensors[m.sensor]
                    mosaic = None if cam.image_sensor is None else cam.image_sensor.mosaic_of(m.data)
                    writer.image(t, m.data, topics[m.sensor], m.sensor, mosaic=mosaic, compress=not raw)
                elif kind == "imu":
                    d = m.data
                    writer.imu(t, d[:3], d[3:6], topics[m.sensor], m.sensor, saturated=bool(d[6] > 0))
                elif kind == "sun":
                    writer.vector(t, m.data[:3], topics[m.sensor], m.sensor)
                    writer.vector(t, m.data[3:6], ephemeris[m.sensor], "world")
                counts[m.sensor] += 1

        pipeline.add_listener(write)
        obs, info = env.reset(seed=seed)
        controller.reset()
        termination = "recorded"
        while True:
            truth_rows.append(_truth_row(info, offset))
            t = float(info["t"])
            loop_rows.append(ReplayStep(t, t + offset, env.estimate_values, 0))
            if progress is not None:
                progress(t)
            if t >= seconds - 1e-9:
                break
            obs, _, term, trunc, info = env.step(controller.act(obs))
            if term or trunc:
                truth_rows.append(_truth_row(info, offset))
                t = float(info["t"])
                loop_rows.append(ReplayStep(t, t + offset, env.estimate_values, 0))
                termination = info["termination"] or "ended"
                break
    # the built-in estimator's downward odometry as the preset set it up in the loop
    odometry = ({"repeated_frames": "still"} | preset.odometry) if rig.of_kind("pinhole") else None
    save_rig(
        rig, folder, topics, ephemeris_topics=ephemeris, starts_at_rest=True, odometry_overrides=odometry,
        saturation_in_covariance=True,
    )  # fmt: skip
    with folder.writing("truth.csv") as tmp:
        write_truth(tmp, truth_rows)
    with folder.writing("truth.tum") as tmp:
        write_tum(
            tmp, [r["t_log"] for r in truth_rows], [r["_xyz"] for r in truth_rows],
            [r["_quat"] for r in truth_rows],
        )  # fmt: skip
    with folder.writing("estimates_in_loop.csv") as tmp:
        write_estimates(iter(loop_rows), tmp)
        loop = read_estimates(tmp)
    truth = {k: np.array([r[k] for r in truth_rows], dtype=np.float64) for k in TRUTH_COLUMNS}
    errors = {e.name: e.mae for e in score(loop, truth, skip=1.0)}
    size = log_path.stat().st_size if log_path.exists() else 0
    return RecordResult(
        folder.path, float(truth_rows[-1]["t_log"] - offset), termination, counts, size, errors
    )


def _truth_row(info: dict, offset: float) -> dict:
    """One row of ``truth.csv`` from ``info["ground_truth"]`` (and the pose for ``truth.tum``)."""
    gt = info["ground_truth"]
    pose = np.asarray(gt["pose"], dtype=np.float64)
    row: dict = {
        "t_log": float(info["t"]) + offset,
        "x": pose[0],
        "y": pose[1],
        "yaw": quat_to_yaw(pose[3:7]),
        "z": pose[2],
        "roll": float(gt["tilt"][0]),
        "pitch": float(gt["tilt"][1]),
        "v_x": float(gt["twist"][0]),
        "v_y": float(gt["twist"][1]),
        "omega": float(gt["twist"][2]),
        "_xyz": pose[:3],
        "_quat": pose[3:7],
    }
    for key, prefix, labels in (
        ("wheel_rate", "wheel_rate_", WHEELS),
        ("slip_ratio", "slip_", WHEELS),
        ("slip_angle", "slip_angle_", WHEELS),
        ("axle_roll", "axle_roll_", AXLES),
        ("axle_height", "axle_height_", AXLES),
        ("steering", "steering_", AXLES),
    ):
        for label, v in zip(labels, gt[key], strict=True):
            row[prefix + label] = float(v)
    return row

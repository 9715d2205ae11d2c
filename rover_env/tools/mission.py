"""Run a controller through a scenario and write a video, plots, metrics and a trajectory."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from controllers.base import Controller
from perception.fusion.slip import SLIP_EVENT
from perception.logs.outputs import OutputFolder
from perception.models.drive_geometry import WHEELS
from perception.odometry import trajectory as tum
from rover_env.envs.rover_env import RoverEnv
from rover_env.tools.estimator_metrics import SLIP_COLUMNS, EstimateLog, columns, estimator_summary

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MissionMetrics:
    """Summary of one mission. Lengths [m], times [s], energy [J].

    ``goal_error`` is the true distance of the body centre from the last waypoint when the
    episode ended (the judge's measure; with ``termination="off_target"`` the miss distance).
    """

    scenario: str
    seed: int
    success: bool
    termination: str
    time: float
    path_length: float
    course_length: float
    progress: float
    cross_track_rms: float
    energy: float
    mean_speed: float
    max_abs_slip: float
    time_in_slip: float
    stuck_events: int
    total_reward: float
    goal_error: float


@dataclass
class MissionLog:
    """Per-step records of a mission (ground truth)."""

    t: list[float]
    pose: list[np.ndarray]
    twist: list[np.ndarray]
    slip: list[np.ndarray]
    wheel_rate: list[np.ndarray]
    axle_roll: list[np.ndarray]
    steering: list[np.ndarray]
    friction: list[np.ndarray]
    cross_track: list[float]
    estimates: EstimateLog | None = None

    @classmethod
    def empty(cls) -> MissionLog:
        """A log with no records."""
        return cls([], [], [], [], [], [], [], [], [])

    def arrays(self) -> dict[str, np.ndarray]:
        """Every ground-truth record stacked into an array, by field name."""
        return {k: np.asarray(getattr(self, k)) for k in self._truth_fields()}

    @classmethod
    def _truth_fields(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls) if f.name != "estimates")


@dataclass
class MissionResult:
    """What :func:`run_mission` returns.

    Attributes:
        metrics: The mission's summary.
        log: Per-step ground truth (and estimates, with ``obs_source="estimated"``).
        estimator: The estimator's errors against the truth
            (:func:`~rover_env.tools.estimator_metrics.estimator_summary`), or None without estimates.
        estimate_arrays: The estimates' rows (:meth:`EstimateLog.arrays`), or None.
    """

    metrics: MissionMetrics
    log: MissionLog
    estimator: dict[str, float] | None = None
    estimate_arrays: dict | None = None


def run_mission(
    env: RoverEnv,
    controller: Controller,
    seed: int = 0,
    video_path: Path | None = None,
    video_every: int = 2,
    progress: Callable[[float], None] | None = None,
    rerun=None,
) -> MissionResult:
    """Drive one episode with ``controller`` and collect metrics, a log and the estimator's errors.

    Args:
        env: The environment (``render_mode="rgb_array"`` if a video is wanted).
        controller: Acts on the environment's observations.
        seed: Episode seed.
        video_path: Where to write an MP4 of the rendered frames, or None.
        video_every: Render every n-th control step into the video.
        progress: Called every 30 steps with the simulated time driven [s].
        rerun: A :class:`rover_env.tools.rerun_log.RerunLog` to log every step to (its run started).
    """
    obs, info = env.reset(seed=seed)
    controller.reset()
    rec = MissionLog.empty()
    if env.pipeline is not None:
        rec.estimates = EstimateLog(env.geometry.wheel_radius)
    writer = None
    if video_path is not None:
        from rover_env.tools.video import VideoWriter, draw_overlay, overlay_lines

        writer = VideoWriter(video_path, env.control_hz / video_every, env.render_size)
    energy = 0.0
    total_reward = 0.0
    stuck, stuck_time = 0, 0.0
    step = 0
    termination = "time_limit"
    success = False
    try:
        while True:
            action = controller.act(obs)
            obs, reward, term, trunc, info = env.step(action)
            total_reward += reward
            gt = info["ground_truth"]
            rec.t.append(info["t"])
            rec.pose.append(gt["pose"])
            rec.twist.append(gt["twist"])
            rec.slip.append(gt["slip_ratio"])
            rec.wheel_rate.append(gt["wheel_rate"])
            rec.axle_roll.append(gt["axle_roll"])
            rec.steering.append(gt["steering"])
            rec.friction.append(info["wheel_contact"]["friction"])
            rec.cross_track.append(float(info["cross_track"]))
            energy += info["wheel_power"] * env.control_dt
            if rec.estimates is not None:
                rec.estimates.add(info, env.estimate_values or {})
            if rerun is not None:
                rerun.log_step(info, env.pipeline.last_images if env.pipeline is not None else None)
            # stuck: commanding motion but the body barely moves for 2 s
            commanded = (
                abs(float(action[0])) > 0.05
                if env.action_mode.value == "drive"
                else float(np.abs(action[:4]).max()) > 0.05
            )
            if commanded and abs(gt["twist"][0]) < 0.02:
                stuck_time += env.control_dt
                if abs(stuck_time - 2.0) < 0.5 * env.control_dt:
                    stuck += 1
            else:
                stuck_time = 0.0
            if writer is not None and step % video_every == 0:
                frame = env.render()
                if frame is None:
                    raise RuntimeError("the environment drew no frame; make it with render_mode='rgb_array'")
                writer.write(draw_overlay(frame, overlay_lines(info["t"], info)))
            step += 1
            if progress is not None and step % 30 == 0:
                progress(float(info["t"]))
            if term or trunc:
                termination = info["termination"] or "unknown"
                success = bool(info["is_success"])
                break
    finally:
        if writer is not None:
            writer.close()
    arr = rec.arrays()
    xy = arr["pose"][:, :2]
    path_len = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()) if len(xy) > 1 else 0.0
    slip = np.abs(arr["slip"])
    metrics = MissionMetrics(
        scenario=env.scenario.name,
        seed=seed,
        success=success,
        termination=termination,
        time=float(arr["t"][-1]),
        path_length=path_len,
        course_length=env.course.length,
        progress=float(info["progress"]),
        cross_track_rms=float(np.sqrt(np.mean(arr["cross_track"] ** 2))),
        energy=float(energy),
        mean_speed=path_len / max(float(arr["t"][-1]), 1e-9),
        max_abs_slip=float(slip.max()),
        time_in_slip=float((slip.max(axis=1) > SLIP_EVENT).sum() * env.control_dt),
        stuck_events=stuck,
        total_reward=float(total_reward),
        goal_error=float(np.hypot(*(xy[-1] - np.asarray(env.scenario.course.waypoints[-1], dtype=float)))),
    )
    if rec.estimates is None or env.pipeline is None:
        return MissionResult(metrics, rec)
    fisheye = env.pipeline.fisheye  # the slip events' time scale: its frames, else control steps
    est = rec.estimates.arrays(fisheye.period if fisheye is not None else env.control_dt)
    return MissionResult(metrics, rec, estimator_summary(est), est)


def json_safe(obj):
    """``obj`` with NaN and infinities as None and numpy scalars as Python numbers (strict JSON)."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def write_tum(path: str | Path, rec: MissionLog) -> None:
    """Trajectory in TUM format: ``t x y z qx qy qz qw`` per line (world frame)."""
    arr = rec.arrays()
    tum.write_tum(path, arr["t"], arr["pose"][:, :3], arr["pose"][:, 3:7])


#: The plots of one mission (:func:`write_plots`).
PLOT_FILES = ("trajectory.png", "velocity_slip.png", "joints.png")
#: What :func:`write_outputs` may write for one mission (and a run's video and Rerun recording).
RUN_FILES = ("metrics.json", "trajectory.tum", "estimate.tum", *PLOT_FILES, "video.mp4", "mission.rrd")


def write_plots(out: OutputFolder, env: RoverEnv, result: MissionResult, prefix: str = "") -> list[Path]:
    """Trajectory, velocity and slip, and joint-angle plots (PNG), estimates against the truth.

    Staged in ``out`` under ``prefix`` (a subfolder's name and ``/``, or ""): ``trajectory.png``
    (course, friction map, true and dead-reckoned paths), ``velocity_slip.png`` (body twist and
    wheel slip ratios; the friction under each wheel) and ``joints.png`` (axle roll and
    steering). Returns their final paths.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arr = result.log.arrays()
    est = result.estimate_arrays
    t = arr["t"]
    paths = []
    fig, ax = plt.subplots(figsize=(7, 6))
    sc = env.scenario
    half = np.array(sc.terrain.size) / 2
    xs = np.linspace(-half[0], half[0], 400)
    ys = np.linspace(-half[1], half[1], 400)
    gx, gy = np.meshgrid(xs, ys)
    mu = env.sim.terrain.friction.mu_grid(gx, gy)
    im = ax.imshow(
        mu,
        origin="lower",
        extent=(-half[0], half[0], -half[1], half[1]),
        cmap="YlOrBr_r",
        vmin=0.0,
        vmax=1.2,
        alpha=0.6,
    )
    fig.colorbar(im, ax=ax, label="friction coefficient μ [-]")
    for patch in sc.friction.patches:  # each patch named by its μ
        loose = ", loose" if patch.slip_loss > 0 else ""
        ax.annotate(f"μ {patch.mu:g}{loose}", patch.center, ha="center", va="center", fontsize=8,
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.5", alpha=0.8))  # fmt: skip
    course = env.course.points
    ax.plot(course[:, 0], course[:, 1], "k--o", label="course")
    ax.plot(arr["pose"][:, 0], arr["pose"][:, 1], "b-", label="rover (ground truth)")
    shown = [course, arr["pose"][:, :2]]
    if est is not None:
        ax.plot(est["est_pose"][:, 0], est["est_pose"][:, 1], "r-", lw=1, label="dead reckoning (estimate)")
        shown.append(est["est_pose"][:, :2])
    pad = 2.0
    lo = np.min([p.min(0) for p in shown], axis=0) - pad
    hi = np.max([p.max(0) for p in shown], axis=0) + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{sc.name}: trajectory")
    ax.legend(loc="upper left", bbox_to_anchor=(0.0, -0.12), ncol=2, fontsize=8)  # below the map
    with out.writing(prefix + "trajectory.png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    paths.append(out.path / (prefix + "trajectory.png"))
    plt.close(fig)

    names = WHEELS
    colours = ("C0", "C1", "C2", "C3")
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for i, label in enumerate(("v_x [m/s]", "v_y [m/s]", "omega [rad/s]")):
        axes[0].plot(t, arr["twist"][:, i], colours[i], label=label)
        if est is not None:
            axes[0].plot(est["t"], est["est"][:, columns("v_x", "v_y", "omega")[i]], colours[i], ls=":", lw=1)
    axes[0].set_ylabel("twist [m/s, rad/s]")
    axes[0].set_title("body twist" + (": truth (solid), estimate (dotted)" if est is not None else ""))
    for i, n in enumerate(names):
        axes[1].plot(t, arr["slip"][:, i], colours[i], label=n)
        if est is not None:
            axes[1].plot(est["t"], est["est"][:, SLIP_COLUMNS[i]], colours[i], ls=":", lw=1)
        axes[2].plot(t, arr["friction"][:, i], colours[i], label=n)
    axes[1].set_ylabel("slip ratio [-]")
    axes[2].set_ylabel("friction μ under wheel [-]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:  # legends beside the axes, off the data
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    with out.writing(prefix + "velocity_slip.png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    paths.append(out.path / (prefix + "velocity_slip.png"))
    plt.close(fig)

    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for ax, key, label in (
        (axes[0], "axle_roll", "axle roll [deg]"),
        (axes[1], "steering", "steering [deg]"),
    ):
        for i, a in enumerate(("F", "R")):
            ax.plot(t, np.degrees(arr[key][:, i]), colours[i], label=f"{a}")
            if est is not None:
                col = columns(f"{key}_{a}")[0]
                ax.plot(est["t"], np.degrees(est["est"][:, col]), colours[i], ls=":", lw=1)
        ax.set_ylabel(label)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    axes[0].set_title("joints" + (": truth (solid), estimate (dotted)" if est is not None else ""))
    axes[1].set_xlabel("time [s]")
    with out.writing(prefix + "joints.png") as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    paths.append(out.path / (prefix + "joints.png"))
    plt.close(fig)
    return paths


#: Units of :class:`MissionMetrics`' fields ("-": a ratio or a label; "count": whole numbers).
METRIC_UNITS = {
    "scenario": "-", "seed": "-", "success": "-", "termination": "-", "time": "s", "path_length": "m",
    "course_length": "m", "progress": "m", "cross_track_rms": "m", "energy": "J", "mean_speed": "m/s",
    "max_abs_slip": "-", "time_in_slip": "s", "stuck_events": "count", "total_reward": "-", "goal_error": "m",
}  # fmt: skip


def metric_units(result: MissionResult) -> dict[str, dict[str, str]]:
    """Units of the keys of ``metrics.json``: the mission's metrics and the estimator's errors."""
    out = {"metrics": dict(METRIC_UNITS)}
    if result.estimator is not None:
        from rover_env.tools.estimator_metrics import estimator_unit

        out["estimator"] = {k: estimator_unit(k) for k in result.estimator}
    return out


def write_outputs(
    out: OutputFolder, env: RoverEnv, result: MissionResult, plots: bool = True, prefix: str = ""
) -> list[Path]:
    """Stage a mission's ``metrics.json`` (with the estimator's errors), TUM trajectories and plots.

    Written into ``out`` under ``prefix`` (a subfolder's name and ``/``, or ""), committed with
    the folder. ``trajectory.tum`` is the true pose; ``estimate.tum`` the dead-reckoned one
    (with estimates), both readable by ``evo``. Returns the final paths.
    """
    data = {"metrics": asdict(result.metrics), "estimator": result.estimator, "units": metric_units(result)}
    paths = [out.write_text(prefix + "metrics.json", json.dumps(json_safe(data), indent=2) + "\n")]
    with out.writing(prefix + "trajectory.tum") as tmp:
        write_tum(tmp, result.log)
    paths.append(out.path / (prefix + "trajectory.tum"))
    if result.estimate_arrays is not None:
        e = result.estimate_arrays
        # the body origin's height, as in trajectory.tum: the start's plus the estimated change
        with out.writing(prefix + "estimate.tum") as tmp:
            tum.write_planar_tum(tmp, e["t"], e["est_pose"], z=e["est_z"])
        paths.append(out.path / (prefix + "estimate.tum"))
    if plots:
        paths += write_plots(out, env, result, prefix)
    return paths


#: The demo's two drivers: (controller name in :data:`rover_env.tools.evaluation.CONTROLLERS`, label).
DEMO_RUNS = (
    ("slip_unaware", "path follower, slip-unaware"),
    ("slip_aware", "path follower + traction control"),
)


def demo_products() -> tuple[str, ...]:
    """What :func:`run_demo` writes: the video, plots and metrics, and each driver's folder."""
    files = [f for f in RUN_FILES if f not in ("video.mp4", "mission.rrd")]
    runs = tuple(f"{name}/{f}" for name, _ in DEMO_RUNS for f in files)
    clips = tuple(f"{name}/video.mp4" for name, _ in DEMO_RUNS)  # staged, stacked, never committed
    return ("metrics.json", "demo.mp4", "slip.png", *runs, *clips)


def run_demo(
    out: OutputFolder,
    scenario: str = "slope_loose",
    seed: int = 0,
    video: bool = True,
    progress: Callable[[float], None] | None = None,
    rerun: Path | None = None,
) -> dict[str, MissionResult]:
    """The headless demo: one mission driven on estimates without and with slip-aware traction control.

    Both drivers (:data:`DEMO_RUNS`: the path follower alone, and the path follower with
    per-wheel traction control) drive ``scenario`` on perception's estimates
    (``obs_source="estimated"``) from the same seed. On the default, the loose-sand slope, the
    first digs in and slides off while the second climbs to the goal. Writes into ``out``:

    - ``demo.mp4``: both runs one above the other (chase view with the friction patches, the
      downward and fisheye images, an overlay of the state), H.264;
    - ``slip.png``: both runs' slip and progress over time;
    - ``metrics.json``: both runs' metrics and the estimator's errors;
    - one folder per driver with its plots, ``metrics.json`` and TUM trajectories
      (:func:`write_outputs`).

    Args:
        out: The output folder (:func:`demo_products`), committed by the caller.
        scenario: A scenario preset name or YAML path.
        seed: The episode seed of both runs.
        video: Write ``demo.mp4`` (rendering costs most of the demo's time).
        progress: Called with the simulated time driven so far, both runs together [s].
        rerun: Also log both runs to this Rerun file (``.rrd``; :mod:`rover_env.tools.rerun_log`).

    Returns:
        {driver: its result}.
    """
    from rover_env.tools.registry import CONTROLLERS

    results: dict[str, MissionResult] = {}
    videos = []
    done_t = 0.0
    log_rr = None
    if rerun is not None:
        from rover_env.tools.rerun_log import RerunLog

        log_rr = RerunLog(rerun)
    for name, _ in DEMO_RUNS:
        spec = CONTROLLERS[name]
        env = RoverEnv(
            scenario=scenario, action_mode=spec.action_mode, render_mode="rgb_array" if video else None
        )
        try:
            ctrl = spec.make(env)
            clip = out.stage(f"{name}/video.mp4") if video else None
            base = done_t
            tick = None if progress is None else (lambda t, base=base: progress(base + t))
            if log_rr is not None:
                log_rr.start_run(name, env.course.points)
            result = run_mission(env, ctrl, seed=seed, video_path=clip, progress=tick, rerun=log_rr)
            if log_rr is not None:
                log_rr.end_run()
            write_outputs(out, env, result, prefix=f"{name}/")
            done_t += result.metrics.time
        finally:
            env.close()
        results[name] = result
        if clip is not None:
            videos.append(clip)
        log.info("demo %s: success=%s time=%.1f s", name, result.metrics.success, result.metrics.time)
    data = {
        "scenario": results[DEMO_RUNS[0][0]].metrics.scenario,
        "seed": seed,
        "runs": {n: {"metrics": asdict(r.metrics), "estimator": r.estimator} for n, r in results.items()},
    }
    out.write_text("metrics.json", json.dumps(json_safe(data), indent=2) + "\n")
    with out.writing("slip.png") as tmp:
        write_slip_comparison(tmp, results)
    if log_rr is not None:
        log_rr.close()
    if videos:
        from rover_env.tools.video import stack_videos

        with out.writing("demo.mp4") as tmp:
            stack_videos(videos, [label for _, label in DEMO_RUNS], tmp)
        for name, _ in DEMO_RUNS:
            out.unstage(f"{name}/video.mp4")
    return results


def write_slip_comparison(path: Path, results: dict[str, MissionResult]) -> Path:
    """Both demo runs' largest true slip ratio and progress along the course over time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = dict(DEMO_RUNS)
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    for k, (name, res) in enumerate(results.items()):
        arr = res.log.arrays()
        colour = f"C{k + 3}"
        axes[0].plot(arr["t"], np.abs(arr["slip"]).max(axis=1), colour, label=f"{labels.get(name, name)}")
        if res.estimate_arrays is not None:
            e = res.estimate_arrays
            axes[0].plot(e["t"], np.abs(e["est"][:, SLIP_COLUMNS]).max(axis=1), colour, ls=":", lw=1)
        start = np.asarray(arr["pose"][0, :2])
        axes[1].plot(arr["t"], np.linalg.norm(arr["pose"][:, :2] - start, axis=1), colour,
                     label=f"{labels.get(name, name)}: {res.metrics.termination}")  # fmt: skip
    axes[0].axhline(SLIP_EVENT, color="0.5", lw=0.8, ls="--", label=f"slip event ({SLIP_EVENT:g})")
    axes[0].set_ylabel("largest |slip ratio| [-]")
    axes[0].set_title("wheel slip: truth (solid), estimate (dotted)")
    axes[1].set_ylabel("distance from the start [m]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path

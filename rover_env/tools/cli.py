"""The ``rover`` command line: demo, eval, train, record, replay, odometry, kinematics, wheel-test, bench."""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path


class _Progress:
    """The command line's one progress display (tqdm on stderr).

    ``share(f)`` reports a finished share (0..1) of frames; ``sim(t)`` the simulated time driven
    [s], shown with the wall time and their ratio (the real-time factor).
    """

    def __init__(self, label: str, unit: str = "%", total: float | None = 100.0) -> None:
        from tqdm import tqdm

        fmt = "{desc}: {n:.1f}" + ("/{total:.0f}" if total else "") + " {unit} [wall {elapsed}, {rate_fmt}]"
        self._bar = tqdm(total=total, desc=label, unit=unit, file=sys.stderr, bar_format=fmt, leave=True)
        self._n = 0.0

    def share(self, frac: float) -> None:
        """Report the finished share of the work (0..1)."""
        self._to(100.0 * frac)

    def sim(self, t: float) -> None:
        """Report the simulated time driven [s] (or any count: runs done)."""
        self._to(t)

    def _to(self, n: float) -> None:
        if n > self._n:
            self._bar.update(n - self._n)
            self._n = n

    def close(self) -> None:
        self._bar.close()


class _LazyProgress:
    """A :class:`_Progress` that appears at its first report (not for a run refused before it starts)."""

    def __init__(self, label: str) -> None:
        self.label = label
        self._bar: _Progress | None = None

    def share(self, frac: float) -> None:
        """Report the finished share of the work (0..1)."""
        if self._bar is None:
            self._bar = _Progress(self.label)
        self._bar.share(frac)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _cmd_demo(args: argparse.Namespace) -> int:
    from perception.logs.outputs import OutputFolder, check_out
    from rover_env.config.scenario import load_scenario
    from rover_env.tools.mission import DEMO_RUNS, demo_products, run_demo

    check_out(args.out)
    load_scenario(args.scenario)  # the inputs before the output
    if args.rerun:
        from rover_env.tools.rerun_log import _rerun

        _rerun()  # the SDK is there, before anything runs
    rerun = Path(args.rerun) if args.rerun else None
    with contextlib.ExitStack() as stack:
        out = stack.enter_context(OutputFolder(args.out, demo_products(), args.overwrite))
        rr = None
        if rerun is not None:
            rr = stack.enter_context(OutputFolder(rerun.parent, (rerun.name,), args.overwrite))
        bar = _Progress(f"demo {args.scenario}: simulated", unit="s sim", total=None)
        start = time.perf_counter()
        try:
            results = run_demo(
                out, scenario=args.scenario, seed=args.seed, video=not args.no_video, progress=bar.sim,
                rerun=rr.stage(rerun.name) if rr is not None and rerun is not None else None,
            )  # fmt: skip
        finally:
            bar.close()
        out.commit()
        if rr is not None:
            rr.commit()
    for name, label in DEMO_RUNS:
        m = results[name].metrics
        est = results[name].estimator or {}
        slip = est.get("slip_mae_slipping", math.nan)
        print(
            f"{label}: {m.termination} after {m.time:.1f} s, goal error {m.goal_error:.2f} m, energy "
            f"{m.energy:.0f} J, slip MAE while slipping {_cell(slip)}"
        )
    print(
        f"wrote {'demo.mp4, ' if not args.no_video else ''}slip.png, metrics.json (every metric)"
        f"{', ' + str(args.rerun) if args.rerun else ''} and per-run plots and TUM trajectories "
        f"to {Path(args.out).resolve()} in {time.perf_counter() - start:.0f} s"
    )
    return 0


def _cell(v: float, fmt: str = ".3f") -> str:
    """A number for the terminal: "–" where it is unknown (NaN)."""
    return "–" if v is None or not math.isfinite(v) else format(v, fmt)


#: Most seeds one ``--seeds`` range may name (a sweep runs one episode per seed and controller).
MAX_SEEDS = 10_000


def _seeds(text: str) -> list[int]:
    """``"0-19"`` or ``"3"`` -> seeds (0 <= N <= M, at most ``MAX_SEEDS`` of them)."""
    lo, sep, hi = text.partition("-")
    try:
        a, b = (int(lo), int(hi)) if sep else (int(lo), int(lo))
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds: {text!r} is not N or N-M (whole numbers >= 0)") from None
    if b < a:
        raise argparse.ArgumentTypeError(f"seeds: {text!r} is an empty range; give N-M with N <= M")
    if b - a + 1 > MAX_SEEDS:
        raise argparse.ArgumentTypeError(
            f"seeds: {text!r} names {b - a + 1} seeds; at most {MAX_SEEDS} a range"
        )
    return list(range(a, b + 1))


def _int_in(lo: int, hi: int | None = None):
    """An argparse type: a whole number in [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if v < lo or (hi is not None and v > hi):
            span = f">= {lo}" if hi is None else f"from {lo} to {hi}"
            raise argparse.ArgumentTypeError(f"{text}: use a whole number {span}")
        return v

    return parse


def _float_in(lo: float, hi: float):
    """An argparse type: a finite number in (lo, hi]."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (math.isfinite(v) and lo < v <= hi):
            raise argparse.ArgumentTypeError(f"{text}: use a number above {lo:g} and at most {hi:g}")
        return v

    return parse


def _finite(text: str) -> float:
    """An argparse type: a finite number."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{text}: give a finite number")
    return v


def _max_workers() -> int:
    """Most local worker processes ``rover eval`` starts: four per CPU (each holds a simulation)."""
    import os

    return 4 * (os.cpu_count() or 1)


def _weight(text: str) -> tuple[str, float]:
    """``"slip=5"`` -> ("slip", 5.0); the term must be one of RewardConfig's, the weight in [0, 1e6]."""
    from rover_env.task.judge import RewardConfig

    key, sep, value = text.partition("=")
    terms = tuple(RewardConfig.__dataclass_fields__)
    try:
        if not sep:
            raise ValueError
        w = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"reward weight: {text!r} is not TERM=NUMBER") from None
    if key not in terms:
        raise argparse.ArgumentTypeError(
            f"reward weight: {key!r} is not a reward term; use one of {', '.join(terms)}"
        )
    if not (math.isfinite(w) and 0.0 <= w <= 1e6):
        raise argparse.ArgumentTypeError(f"reward weight: {text!r}; a weight is a number from 0 to 1e6")
    return key, w


def _cmd_eval(args: argparse.Namespace) -> int:
    from perception.logs.outputs import OutputFolder, check_out
    from rover_env.tools.evaluation import REPORT_FILES, check_jobs, jobs_for, preflight

    check_out(args.out)
    seeds = sorted({s for part in args.seeds for s in part})
    if args.rerun:
        from rover_env.tools.rerun_log import _rerun

        _rerun()  # the SDK is there, before anything runs
    jobs = jobs_for(
        args.controllers,
        args.missions,
        seeds,
        args.preset,
        args.out,
        args.videos,
        args.rerun,
        args.estimator,
        args.camera_effects,
        args.randomize,
        args.rig,
    )
    check_jobs(jobs)  # every input before the output folder is touched
    preflight(jobs)  # each estimator built once on each rig
    with OutputFolder(args.out, (*REPORT_FILES, "runs/"), args.overwrite, keep=args.resume) as folder:
        return _sweep(args, jobs, folder, _sweep_mark(folder.subfolder("runs/"), args.resume))


def _sweep_mark(runs: Path, resume: bool) -> str:
    """This sweep's mark in ``runs/sweep.json``: the earlier one's when resuming, else a new one.

    Each finished run's ``row.json`` carries it, so that ``--resume`` takes only the runs of the
    sweep it continues (not those of an earlier sweep in a folder given with ``--overwrite``).
    """
    import uuid

    from perception.logs.outputs import OutputFolder

    mark = runs / "sweep.json"
    if resume:
        try:
            return str(json.loads(mark.read_text())["sweep"])
        except (OSError, ValueError, KeyError, TypeError):
            logging.getLogger("rover").warning("--resume: %s names no sweep; every run is made again", mark)
    sweep = uuid.uuid4().hex
    with OutputFolder(runs, ("sweep.json",), overwrite=True, announce=False) as out:
        out.write_text("sweep.json", json.dumps({"sweep": sweep}) + "\n")
        out.commit()
    return sweep


def _sweep(args: argparse.Namespace, jobs: list, folder, sweep: str) -> int:
    """``rover eval``'s sweep into ``folder``: its report committed at the end, or a partial one."""
    from rover_env.tools.evaluation import finished_row, run_sweep, write_report

    fails = []
    finished: list[dict] = []  # the rows of the runs this sweep finished
    sys.stderr.write(f"{len(jobs)} runs on the {args.executor} executor\n")
    bar = _Progress("eval: runs", unit="runs", total=len(jobs))

    def show(done: int, total: int, row: dict) -> None:
        finished.append(row)
        if not row["success"]:
            fails.append(f"{row['controller']} {row['mission']} seed {row['seed']}: {row['termination']}")
        bar.sim(done)

    command = "rover " + " ".join(sys.argv[1:])
    try:
        rows = run_sweep(
            jobs, executor=args.executor, workers=args.workers, progress=show, resume=args.resume, sweep=sweep
        )
        bar.close()
    except BaseException:  # Ctrl-C or a failed run: report what finished, then stop
        bar.close()
        # what this sweep finished, and with --resume what the earlier one had (an earlier
        # sweep's rows in a folder given with --overwrite are not this report's)
        done = (
            [r for r in (finished_row(j, sweep) for j in jobs) if r is not None] if args.resume else finished
        )
        if done:
            title = f"Mission evaluation (partial: {len(done)} of {len(jobs)} runs)"
            write_report(done, folder, title=title, command=command)
            folder.commit()
            sys.stderr.write(
                f"\nstopped after {len(done)} of {len(jobs)} runs; their report is in {args.out}; "
                "the same command with --resume runs the rest\n"
            )
        else:
            sys.stderr.write(f"\nstopped before any of the {len(jobs)} runs finished\n")
        raise
    report = write_report(rows, folder, command=command)
    folder.commit()
    print(report.read_text())
    print(f"wrote report.md, results.csv, results.json, summary.csv and runs/ to {Path(args.out).resolve()}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    from perception.logs.outputs import check_out
    from rover_env.tools.training import TrainConfig, train

    check_out(args.out)
    residual = None if args.no_residual else tuple(args.residual)
    cfg = TrainConfig(
        algo=args.algo,
        missions=tuple(args.missions),
        total_steps=args.steps,
        n_envs=args.envs,
        obs_source=args.obs_source,
        preset=args.preset,
        residual=residual,
        base=args.base,
        seed=args.seed,
        eval_every=args.eval_every,
        checkpoint_every=args.eval_every,
        reward=dict(args.reward),
        camera_effects=args.camera_effects,
        randomize=args.randomize,
        episode_seeds=args.episode_seeds,
        imu=args.imu,
    )
    cfg.check()  # every mission's environment, here, before any worker starts
    if cfg.algo == "ppo" and cfg.total_steps < cfg.rollout():
        sys.stderr.write(
            f"--steps {cfg.total_steps} is below one rollout of {cfg.algo.upper()} ({cfg.rollout()} steps: "
            f"{cfg.rollout() // cfg.n_envs} on each of {cfg.n_envs} environments): it trains "
            f"{cfg.steps_trained()} steps\n"
        )
    elif cfg.algo == "sac" and cfg.total_steps <= cfg.rollout():
        sys.stderr.write(
            f"--steps {cfg.total_steps}: SAC starts learning after {cfg.rollout()} steps of random actions; "
            "this run gathers them and does not update the policy\n"
        )
    from perception.logs.outputs import OutputFolder
    from rover_env.tools.training import TRAIN_PRODUCTS

    with OutputFolder(args.out, TRAIN_PRODUCTS, args.overwrite) as folder:
        start = time.perf_counter()
        sys.stderr.write(
            f"training {args.algo} for {cfg.steps_trained()} steps on {args.envs} environments; "
            f"logs: {args.out}/tb\n"
        )
        out = train(cfg, folder, progress=True)
    imu = f"@imu:{args.imu}" if args.imu else ""
    flags = f" --camera-effects {args.camera_effects}"
    if args.randomize:
        flags += f" --randomize {args.randomize}"
    print(f"wrote {out / 'policy.zip'} in {(time.perf_counter() - start) / 60:.1f} min; "
          f"evaluate it as trained with: rover eval --controllers policy:{out}{imu}{flags} ...")  # fmt: skip
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from rover_env.tools.bench import (
        bench_cameras,
        bench_env,
        bench_physics,
        format_camera_table,
        format_env_table,
        format_table,
    )

    rows, env_rows = [], []
    for name in args.scenarios:
        rows.append(bench_physics(name, steps=args.steps))
        env_rows.append(bench_env(name, "estimated", "train", steps=min(args.steps, 90)))
        sys.stderr.write(f"benchmarked {name}\n")
    print("Physics only (a ground-truth environment: no camera, no perception), one process, ")
    print("control 30 Hz, physics 240 Hz:")
    print(format_table(rows))
    print("\nThe same slalom with the estimator in the loop (train preset), one process:")
    print(format_env_table(env_rows))
    cam_rows = []
    if not args.no_cameras:
        cam_rows = bench_cameras(args.scenarios[0], frames=args.frames, renderers=tuple(args.renderers))
        print(f"\nCameras ({args.scenarios[0]}), one process, median of {args.frames} frames:")
        print(format_camera_table(cam_rows))
    if args.json:
        data = {
            "physics": [asdict(r) for r in rows],
            "estimated": [asdict(r) for r in env_rows],
            "cameras": [asdict(r) for r in cam_rows],
        }
        Path(args.json).write_text(json.dumps(data, indent=2) + "\n")
    return 0


def _cmd_kinematics(args: argparse.Namespace) -> int:
    from perception.logs import bags
    from perception.logs.offline import run_folder_kinematics
    from perception.logs.outputs import check_out

    check_out(args.out)
    _need_source(args.source)
    if not bags.is_log(args.source):
        _need_fps(args)
    bar = _Progress("kinematics: frames")
    try:
        res = run_folder_kinematics(
            args.source, args.camera, args.rover, args.fps, args.out, steering=args.steering,
            progress=bar.share, topic=args.topic, overwrite=args.overwrite,
        )  # fmt: skip
    finally:
        bar.close()
    print(
        f"{res.frames} images, all 10 degrees of freedom on {res.all_valid}; wrote {res.csv_path} "
        f"and {res.mcap_path}"
    )
    return 0


def _cmd_odometry(args: argparse.Namespace) -> int:
    from perception.logs import bags
    from perception.logs.offline import run_folder_odometry
    from perception.logs.outputs import check_out
    from perception.models.cameras import PinholeCamera

    check_out(args.out)
    _need_source(args.source)
    calib = args.calib if args.calib is not None else args.camera
    if args.calib is not None:
        from perception.logs.offline import is_omni

        if is_omni(args.calib):
            raise ValueError(
                f"{args.calib}: an omnidirectional calibration (model: scaramuzza); give it as --camera "
                "for the fisheye's odometry (--calib is the downward camera's)"
            )
    if args.camera is not None:  # the fisheye's odometry: its calibration, checked before the output
        from perception.models.cameras import GROUND_PLANE_MISSING, OmniCamera

        omni = OmniCamera.load(args.camera)
        if omni.ground_plane is None:
            raise ValueError(f"{args.camera}: {GROUND_PLANE_MISSING}")
        from perception.odometry.fisheye import FisheyeOdometryConfig

        problem = omni.model_error() or omni.ground_view_error(max_height=FisheyeOdometryConfig().max_range)
        if problem:
            raise ValueError(f"{args.camera}: {problem}")
    if not bags.is_log(args.source):
        _need_fps(args)
        if args.calib is not None and PinholeCamera.load(args.calib).ground_plane is None:
            from perception.models.cameras import GROUND_PLANE_MISSING

            raise ValueError(f"{args.calib}: {GROUND_PLANE_MISSING}")
    if args.imu and args.imu_topic:
        raise ValueError("--imu and --imu-topic: give one IMU source")
    bar = _Progress("odometry: frames")
    roll, pitch, yaw = (math.radians(v) for v in args.imu_rpy)
    rpy = (roll, pitch, yaw)
    try:
        res = run_folder_odometry(
            args.source,
            calib,
            args.fps,
            args.out,
            progress=bar.share,
            imu=args.imu,
            imu_rpy=rpy,
            imu_still=args.imu_still,
            topic=args.topic,
            imu_topic=args.imu_topic,
            overwrite=args.overwrite,
        )
    finally:
        bar.close()
    print(
        f"{res.frames} images, {res.valid} of {res.pairs} pairs valid, path {res.distance:.2f} m; "
        f"wrote {res.csv_path}, {res.tum_path} and {res.mcap_path}"
    )
    if res.tum_imu_path is not None:
        print(f"gyro yaw (bias {res.imu_bias:.5f} rad/s taken out): wrote {res.tum_imu_path}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from perception.estimator import estimator_name
    from perception.logs import bags
    from perception.logs.outputs import OutputFolder, check_out
    from perception.logs.replay import load_rig, replay, write_estimates
    from perception.logs.truth import errors_table, read_estimates, read_truth, score
    from perception.rig import read_only
    from rover_env.tools.evaluation import load_estimator

    check_out(args.out)
    _need_source(args.source)
    if not bags.is_log(args.source):
        raise ValueError(
            f"{args.source}: not a ROS 1 bag, ROS 2 bag folder or MCAP file (replay reads robot logs)"
        )
    log_rig = load_rig(args.rig)  # the inputs before the output
    truth = read_truth(args.truth) if args.truth else None
    offsets = dict(args.time_offset or [])
    try:
        if args.estimator:
            who = args.estimator
            estimator = load_estimator(args.estimator)(read_only(log_rig.rig))
        else:
            who = "RoverEstimator (the built-in)"
            estimator = log_rig.builtin()
    except ValueError:
        raise
    except (Exception, SystemExit) as exc:  # the user's code: any error, named
        what = f"{type(exc).__name__}: {exc}"
        raise ValueError(f"estimator {who} on {args.rig}'s rig {log_rig.rig!r}: {what}") from exc
    start: object = (0.0, 0.0, 0.0)
    if args.start is not None:
        x, y, yaw_deg = args.start
        start = (x, y, math.radians(yaw_deg))
    elif truth is not None:  # the truth's pose at the log's first camera frame
        start = functools.partial(_truth_pose, truth)
    steps = replay(args.source, log_rig, estimator, args.control_hz, start, offsets)  # type: ignore[arg-type]
    products = ("estimates.csv", "errors.csv") if truth is not None else ("estimates.csv",)
    inputs = (args.source, args.rig, args.truth)
    with OutputFolder(args.out, products, args.overwrite, inputs=inputs) as folder:
        with folder.writing("estimates.csv") as tmp:
            n = write_estimates(steps, tmp)
        errors = None
        if truth is not None:
            errors = score(read_estimates(tmp), truth, skip=args.truth_skip)
            folder.write_text("errors.csv", errors_table(errors))
        folder.commit()
    csv_path = Path(args.out) / "estimates.csv"
    print(f"{n} control steps of {estimator_name(estimator)} on {args.source}; wrote {csv_path}")
    if errors is not None:
        print(f"errors against {args.truth} (after the first {args.truth_skip:g} s):")
        print(f"{'field':16s} {'unit':6s} {'ticks':>6s} {'MAE':>10s} {'p95':>10s}")
        for e in errors:
            print(f"{e.name:16s} {e.unit:6s} {e.n:6d} {_cell(e.mae, '10.4g')} {_cell(e.p95, '10.4g')}")
        print(f"wrote {Path(args.out) / 'errors.csv'}")
    return 0


def _truth_pose(truth: dict, t_log: float) -> tuple[float, float, float]:
    """The truth's planar pose (x, y, yaw) at ``t_log`` on the log's clock [s]."""
    import numpy as np

    t = truth["t_log"]
    yaw = float(np.interp(t_log, t, np.unwrap(truth["yaw"])))
    return float(np.interp(t_log, t, truth["x"])), float(np.interp(t_log, t, truth["y"])), yaw


def _offset(text: str) -> tuple[str, float]:
    """``"imu=-3600"`` -> ("imu", -3600.0): a sensor's clock offset [s]."""
    name, sep, value = text.partition("=")
    try:
        if not sep or not name:
            raise ValueError
        dt = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"time offset: {text!r} is not SENSOR=SECONDS") from None
    if not math.isfinite(dt):
        raise argparse.ArgumentTypeError(f"time offset: {text!r}; give a finite number of seconds")
    return name, dt


def _cmd_record(args: argparse.Namespace) -> int:
    from perception.logs.outputs import check_out
    from rover_env.tools.record import record

    check_out(args.out)
    bar = _LazyProgress(f"record {args.mission}: simulated")
    start = time.perf_counter()
    try:
        res = record(
            args.mission, args.controller, args.seconds, args.out, preset=args.preset, seed=args.seed,
            raw=args.raw, camera_effects=args.camera_effects, randomize=args.randomize, rig=args.rig,
            overwrite=args.overwrite, progress=lambda t: bar.share(t / args.seconds),
        )  # fmt: skip
    finally:
        bar.close()
    out = res.folder
    counts = ", ".join(f"{n} {name}" for name, n in res.messages.items())
    print(
        f"recorded {res.seconds:.2f} s of {args.mission} driven by {args.controller} ({res.termination}): "
        f"{counts} messages, log.mcap {res.log_bytes / 1e6:.1f} MB, in {time.perf_counter() - start:.0f} s"
    )
    vx = res.loop_errors.get("v_x", math.nan)
    print(f"the built-in estimator in the loop: v_x MAE {_cell(vx, '.4f')} m/s (after the first second)")
    print(f"wrote log.mcap, rig.yaml (its topics and calibrations), truth.csv, truth.tum and "
          f"estimates_in_loop.csv to {out.resolve()}")  # fmt: skip
    print(
        f"replay it: rover replay {out / 'log.mcap'} --rig {out / 'rig.yaml'} --truth {out / 'truth.csv'} "
        "--out REPLAY_DIR"
    )
    return 0


def _need_source(source: str) -> None:
    if not Path(source).exists():
        raise FileNotFoundError(f"{source}: no such file or folder")


def _need_fps(args: argparse.Namespace) -> None:
    if args.fps is None:
        raise ValueError(
            f"{args.source}: a folder of images needs --fps (a log's messages carry their times)"
        )


def _cmd_wheel_test(args: argparse.Namespace) -> int:
    from perception.logs.outputs import check_out
    from rover_env.tools.wheel_test import run

    check_out(args.out)
    bar = _LazyProgress("wheel-test")  # shown once the run starts (after the checks)
    try:
        rows = run(args, progress=bar.share)
    finally:
        bar.close()
    out = Path(args.out)
    print(f"{'slip':>6} {'DP/W':>7} {'sinkage mm':>10} {'torque Nm':>9}")
    for r in rows:
        print(
            f"{r.slip:+6.2f} {r.drawbar_pull_N / r.load_N:+7.3f} {1e3 * r.sinkage_m:10.2f} {r.torque_Nm:9.4f}"
        )
    print(f"wrote {out / 'wheel_test.csv'} and {out / 'wheel_test.png'}")
    return 0


def _cmd_scenarios(args: argparse.Namespace) -> int:
    from rover_env.config.scenario import list_scenarios, load_scenario, preset_path

    for name in list_scenarios():
        print(f"{name:16s} {load_scenario(name).description}")
    print(
        f"\nthe presets' files: {Path(str(preset_path('flat_patches'))).parent}; a YAML file of your "
        "own with 'base: NAME' takes a preset and replaces the keys it gives (docs/rover_and_scenarios.md)"
    )
    return 0


class _DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, except where there is none to show (None, off flags, required)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if (
            action.required
            or action.default is None
            or action.default is False
            or "default" in (action.help or "")
        ):
            return action.help or ""
        return super()._get_help_string(action) or ""


SOURCE_HELP = (
    "a folder of images (name order is time order), a ROS 1 .bag, a ROS 2 bag folder or an .mcap file "
    "(read with rosbags; no ROS installation needed)"
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``rover`` command."""
    p = argparse.ArgumentParser(
        prog="rover",
        description="Camera-based state estimation and slip-aware driving of planetary rovers: "
        "demo, eval, train, record, replay, odometry, kinematics, wheel-test, bench, scenarios.",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    fmt = _DefaultsFormatter
    d = sub.add_parser("demo", formatter_class=fmt, help="headless demo mission: video, plots and metrics")
    d.add_argument("--out", required=True, help="output folder (created if missing)")
    d.add_argument(
        "--scenario",
        default="slope_loose",
        help="scenario preset (slope_loose: the loose-sand slope) or YAML path",
    )
    d.add_argument("--seed", type=_int_in(0, 2**32 - 1), default=0, help="episode seed (0 to 2^32 - 1)")
    d.add_argument("--no-video", action="store_true", help="skip rendering the video")
    d.add_argument(
        "--rerun", metavar="FILE.rrd",
        help="also log both runs to this Rerun file: cameras, trajectories, twist, slip, joints "
        "(pip install 'rover-vision[rerun]')",
    )  # fmt: skip
    d.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    d.set_defaults(func=_cmd_demo)
    from rover_env.tools.evaluation import CONTROLLERS

    e = sub.add_parser(
        "eval",
        formatter_class=fmt,
        help="sweep controllers x missions x seeds; one merged report",
        description="Controllers: "
        + "; ".join(f"{k} ({v.description})" for k, v in CONTROLLERS.items())
        + ". Append @ground_truth to drive on the simulator's state instead of the estimates, "
        "@imu (or @imu:tactical) to drive on estimates fused with an IMU (BMI088 by default). "
        "policy:DIR loads a folder that rover train wrote: treat it as code (an older folder's "
        "pickled files run when loaded) and load only folders you made or trust.",
    )
    e.add_argument(
        "--controllers", nargs="+", default=["slip_unaware", "slip_aware", "slip_aware@ground_truth"],
        help="controllers to compare (above), each optionally with @ground_truth, @imu or @imu:tactical",
    )  # fmt: skip
    e.add_argument("--missions", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0"],
                   help="environment ids, scenario presets or YAML paths")  # fmt: skip
    e.add_argument(
        "--seeds", nargs="+", type=_seeds, default=[[0, 1, 2]], help="seeds: N or N-M (default: 0-2)"
    )
    e.add_argument("--preset", default="train", choices=("train", "eval"), help="camera preset")
    e.add_argument("--camera-effects", default="field", choices=("ideal", "field"),
                   help="estimated runs' cameras: as rendered, or through their image sensors")  # fmt: skip
    e.add_argument("--randomize", default=None, choices=("off", "on"),
                   help="domain randomisation, each run's world drawn from its seed "
                        "(default: each scenario's randomize key)")  # fmt: skip
    e.add_argument("--rig", default=None, choices=("standard", "fisheye_only", "full"),
                   help="estimated runs' sensors: the standard rig, the one-camera rig (the fisheye "
                        "alone; @imu adds an IMU) or the full rig (the BMI088, wheel encoders, motor "
                        "currents) (default: each mission's)")  # fmt: skip
    e.add_argument(
        "--estimator", metavar="[NAME=]MODULE:FACTORY", action="append",
        help="an estimator on the estimated-observation runs: a factory called with the rig "
        "(module:FACTORY or path/file.py:FACTORY; see docs/own_estimator.md), named NAME in the "
        "report, or built-in; repeat it to compare estimators side by side (default: the built-in)",
    )  # fmt: skip
    e.add_argument("--executor", default="local", choices=("local", "ray"),
                   help="local processes, or a Ray cluster (RAY_ADDRESS, else a local one)")  # fmt: skip
    e.add_argument("--workers", type=_int_in(1, _max_workers()), default=None,
                   help=f"local processes, 1 to {_max_workers()} (default: CPU count)")  # fmt: skip
    e.add_argument("--videos", action="store_true", help="write each run's video")
    e.add_argument(
        "--rerun", action="store_true",
        help="also log each run to Rerun: runs/<name>/mission.rrd (pip install 'rover-vision[rerun]')",
    )  # fmt: skip
    e.add_argument("--out", required=True, help="output folder (created if missing)")
    e.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    e.add_argument(
        "--resume", action="store_true", help="keep the runs an earlier, interrupted sweep finished in --out"
    )
    e.set_defaults(func=_cmd_eval)
    t = sub.add_parser(
        "train",
        formatter_class=fmt,
        help="train a PPO (or SAC) policy on the estimated-observation environments",
    )
    t.add_argument(
        "--out", required=True, help="output folder: policy, normalisation, checkpoints, TensorBoard"
    )
    t.add_argument("--algo", default="ppo", choices=("ppo", "sac"), help="stable-baselines3 algorithm")
    t.add_argument("--missions", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0",
                                                      "RoverSlopeLoose-v0"],
                   help="environment ids to train on, one per episode in turn")  # fmt: skip
    t.add_argument("--steps", type=_int_in(1), default=200_000, help="environment steps in all")
    t.add_argument(
        "--envs", type=_int_in(1, _max_workers()), default=2, help="environments, one process each"
    )
    t.add_argument("--obs-source", default="estimated", choices=("estimated", "ground_truth"),
                   help="train on perception's estimates or on the simulator's state")  # fmt: skip
    t.add_argument("--preset", default="train", choices=("train", "eval"),
                   help="camera preset (train: 160x120, 30 Hz; eval: 640x480, 60 Hz)")  # fmt: skip
    t.add_argument("--camera-effects", default="field", choices=("ideal", "field"),
                   help="the cameras: as rendered, or through their image sensors")  # fmt: skip
    t.add_argument("--randomize", default=None, choices=("off", "on"),
                   help="domain randomisation, each episode's world drawn from its seed "
                        "(default: each scenario's randomize key)")  # fmt: skip
    t.add_argument("--imu", default=None, metavar="PRESET",
                   help="an IMU on the rover (e.g. bmi088; default: none); evaluate the policy with "
                        "the same one: rover eval --controllers policy:OUT@imu:PRESET")  # fmt: skip
    t.add_argument("--residual", type=float, nargs=3, default=[0.5, 0.3, 0.3],
                   help="residual range on the drive command (speed, lam_F, lam_R)")  # fmt: skip
    t.add_argument("--base", default="traction", choices=("traction", "follower"),
                   help="the residual's base: traction control on each wheel (wheels action mode) "
                        "or the path follower alone (drive mode)")  # fmt: skip
    t.add_argument("--no-residual", action="store_true", help="learn the whole action")
    t.add_argument("--eval-every", type=_int_in(1), default=20_000,
                   help="steps between evaluations and checkpoints (>= 1)")  # fmt: skip
    t.add_argument("--reward", nargs="+", type=_weight, default=[], metavar="TERM=WEIGHT",
                   help="reward weights unlike the environment's (RewardConfig), e.g. slip=5")  # fmt: skip
    t.add_argument("--seed", type=_int_in(0, 2**32 - 1), default=0, help="training seed (0 to 2^32 - 1)")
    t.add_argument("--episode-seeds", type=_int_in(0, 2**62), default=10_000,
                   help="the first episode's seed: episode k of process i has episode_seeds + k envs + i "
                        "(episodes.csv lists them)")  # fmt: skip
    t.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    t.set_defaults(func=_cmd_train)
    b = sub.add_parser("bench", formatter_class=fmt, help="simulation speed benchmarks")
    b.add_argument(
        "--scenarios", nargs="+", default=["flat_patches", "rough"], help="scenario presets or YAML paths"
    )
    b.add_argument("--steps", type=_int_in(1, 1_000_000), default=600, help="environment steps per scenario")
    b.add_argument("--frames", type=_int_in(1, 10_000), default=8, help="frames per camera row")
    b.add_argument("--no-cameras", action="store_true", help="physics only")
    b.add_argument(
        "--renderers",
        nargs="+",
        default=["tiny", "gl"],
        choices=["tiny", "gl"],
        help="renderers of the camera rows",
    )
    b.add_argument("--json", help="also write the results to this JSON file")
    b.set_defaults(func=_cmd_bench)
    o = sub.add_parser(
        "odometry",
        formatter_class=fmt,
        help="visual odometry on downward-camera (--calib) or fisheye (--camera) images: a folder, a ROS 1 "
        "or 2 bag, or an MCAP file",
    )
    o.add_argument("source", help=SOURCE_HELP)
    which = o.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--calib",
        help="downward camera's calibration YAML (K, distortion, image_size, T_body_cam, ground_plane; a "
        "log's CameraInfo fills K, distortion and image_size where the YAML leaves them out)",
    )
    which.add_argument(
        "--camera",
        help="fisheye's omnidirectional calibration YAML (model: scaramuzza, ..., ground_plane; optional "
        "mask: an image of the rover's parts, zero on them): the fisheye's own odometry",
    )
    o.add_argument(
        "--fps", type=_float_in(0.0, 10_000.0), default=None,
        help="frame rate of the images [Hz] (a folder only; a log's times come from its messages)",
    )  # fmt: skip
    o.add_argument("--topic", help="the log's image topic (default: its only Image or CompressedImage topic)")
    o.add_argument("--out", required=True, help="output folder (odometry.csv, trajectory.tum, odometry.mcap)")
    o.add_argument(
        "--imu",
        help="IMU CSV beside the images (t, gyro_x, gyro_y, gyro_z, accel_x, accel_y, accel_z; s, rad/s, "
        "m/s^2; t = 0 at the first image): adds the gyro's yaw rate and trajectory_imu.tum",
    )
    o.add_argument(
        "--imu-rpy", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("ROLL", "PITCH", "YAW"),
        help="the IMU's mount in the body frame [deg]",
    )  # fmt: skip
    o.add_argument(
        "--imu-still", type=float, default=0.0,
        help="seconds of standstill at the IMU log's start, for the gyro's bias "
        "(default: fitted to the odometry's yaw rate)",
    )  # fmt: skip
    o.add_argument(
        "--imu-topic", help="read the IMU from this sensor_msgs/Imu topic of the log (instead of --imu)"
    )
    o.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    o.set_defaults(func=_cmd_odometry)
    k = sub.add_parser(
        "kinematics",
        formatter_class=fmt,
        help="fisheye kinematic state estimation: a folder of images, a ROS 1 or 2 bag, or an MCAP file",
    )
    k.add_argument("source", help=SOURCE_HELP)
    k.add_argument("--camera", required=True, help="omnidirectional calibration YAML (OmniCamera.save)")
    k.add_argument("--rover", required=True, help="rover geometry YAML (RoverKinematicModel.save)")
    k.add_argument("--steering", help="optional steering calibration YAML (eq. 5 ratio map)")
    k.add_argument(
        "--fps", type=_float_in(0.0, 10_000.0), default=None,
        help="frame rate of the images [Hz] (a folder only; a log's times come from its messages)",
    )  # fmt: skip
    k.add_argument("--topic", help="the log's image topic (default: its only Image or CompressedImage topic)")
    k.add_argument("--out", required=True, help="output folder (kinematics.csv, kinematics.mcap)")
    k.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    k.set_defaults(func=_cmd_kinematics)
    r = sub.add_parser(
        "replay",
        formatter_class=fmt,
        help="replay a robot log through any estimator (the one that drives in the simulation)",
    )
    r.add_argument("source", help="a ROS 1 bag, a ROS 2 bag folder or an MCAP file")
    r.add_argument(
        "--rig",
        required=True,
        help="rig file: the log's sensors, calibrations and topics (see docs/own_estimator.md)",
    )
    r.add_argument(
        "--estimator", help="module:FACTORY or path/file.py:FACTORY (default: the built-in RoverEstimator)"
    )
    r.add_argument(
        "--control-hz", type=_float_in(0.999, 1000.0), default=30.0,
        help="update() calls per second, 1 to 1000 [Hz]",
    )  # fmt: skip
    r.add_argument(
        "--start", type=_finite, nargs=3, default=None, metavar=("X", "Y", "YAW_DEG"),
        help="start fix: x, y [m], yaw [deg] (default: 0 0 0, or the truth's pose with --truth)",
    )  # fmt: skip
    r.add_argument(
        "--time-offset", type=_offset, action="append", metavar="SENSOR=SECONDS",
        help="add SECONDS to the stamps of the rig's sensor SENSOR (a sensor on another clock); repeatable",
    )  # fmt: skip
    r.add_argument(
        "--truth", metavar="TRUTH.csv",
        help="the truth beside a recorded log (rover record's truth.csv): also write errors.csv, each "
        "field's error against it",
    )  # fmt: skip
    r.add_argument(
        "--truth-skip", type=_float_in(-1e-9, 3600.0), default=1.0,
        help="seconds at the start not scored against the truth (the filters' start-up)",
    )  # fmt: skip
    r.add_argument("--out", required=True, help="output folder (estimates.csv; errors.csv with --truth)")
    r.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    r.set_defaults(func=_cmd_replay)
    wt = sub.add_parser(
        "wheel-test", formatter_class=fmt,
        help="single-wheel test bed on soil: drawbar pull, sinkage and torque against slip",
    )  # fmt: skip
    wt.add_argument(
        "--soil", required=True,
        help="a soil preset (toyoura, lunar_regolith, mars_simulant, dry_sand, ...) or a YAML file",
    )  # fmt: skip
    wt.add_argument("--radius", type=_float_in(0.0, 10.0), required=True, help="wheel radius to the rim [m]")
    wt.add_argument("--width", type=_float_in(0.0, 10.0), required=True, help="wheel width [m]")
    wt.add_argument("--load", type=float, required=True, help="vertical load on the wheel [N]")
    wt.add_argument("--grousers", type=int, default=0, help="number of grousers")
    wt.add_argument("--grouser-height", type=float, default=0.0, help="grouser height [m]")
    wt.add_argument(
        "--grouser-thickness", type=float, default=None, help="grouser tip thickness [m] (default 0.003)"
    )
    wt.add_argument(
        "--slips", type=float, nargs="+", required=True, metavar="S",
        help="slip ratios in [-1, 1] (negative: braking)",
    )  # fmt: skip
    wt.add_argument("--speed", type=_float_in(0.0, 10.0), default=0.01, help="carriage speed [m/s]")
    wt.add_argument(
        "--distance", type=_float_in(0.0, 100.0), default=1.0, help="carriage travel per slip [m]"
    )
    wt.add_argument("--out", required=True, help="output folder (wheel_test.csv, wheel_test.png)")
    wt.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    wt.set_defaults(func=_cmd_wheel_test)
    rc = sub.add_parser(
        "record", formatter_class=fmt,
        help="drive a mission and record every rig sensor to an MCAP log, with its rig file and the truth",
    )  # fmt: skip
    rc.add_argument("mission", help="environment id, scenario preset or YAML path")
    rc.add_argument(
        "--controller", required=True,
        help="the driver, on the estimates: slip_aware, slip_unaware, pure_pursuit, ppo or policy:DIR, "
        "optionally @imu[:PRESET] (an IMU on the rover, recorded too)",
    )  # fmt: skip
    rc.add_argument(
        "--seconds", type=_float_in(0.0, 3600.0), required=True, help="simulated time to record [s]"
    )
    rc.add_argument("--seed", type=_int_in(0, 2**32 - 1), default=0, help="episode seed")
    rc.add_argument("--preset", default="train", choices=("train", "eval"), help="camera preset")
    rc.add_argument("--camera-effects", default="field", choices=("ideal", "field"),
                    help="the cameras: as rendered, or through their image sensors")  # fmt: skip
    rc.add_argument("--randomize", default=None, choices=("off", "on"),
                    help="domain randomisation (default: the scenario's randomize key)")  # fmt: skip
    rc.add_argument("--rig", default=None, choices=("standard", "fisheye_only"),
                    help="a named rig in place of the mission's sensors")  # fmt: skip
    rc.add_argument(
        "--raw", action="store_true",
        help="raw sensor_msgs/Image frames (default: lossless PNG, a field camera's Bayer mosaic)",
    )  # fmt: skip
    rc.add_argument(
        "--out", required=True,
        help="output folder: log.mcap, rig.yaml (+ calibrations, rover.yaml), truth.csv, truth.tum, "
        "estimates_in_loop.csv",
    )  # fmt: skip
    rc.add_argument("--overwrite", action="store_true", help="replace the results of an earlier run in --out")
    rc.set_defaults(func=_cmd_record)
    s = sub.add_parser("scenarios", formatter_class=fmt, help="list the shipped scenario presets")
    s.set_defaults(func=_cmd_scenarios)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``rover`` command.

    Exit statuses: 0 done; 1 the input was read and nothing valid came of it; 2 bad input (an
    option, a file, an estimator's fault: one line saying what and how to fix it); 3 a failure no
    check foresaw; 130 interrupted (Ctrl-C, at any moment, without a traceback); 143 terminated.
    """
    try:
        return _main(argv)
    except KeyboardInterrupt:  # while the packages load, before the command's own handling
        sys.stderr.write("rover: interrupted\n")
        return 130


def _main(argv: list[str] | None) -> int:
    from perception.estimator import EstimatorError
    from perception.logs.offline import NothingValidError

    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s"
    )
    import signal

    def terminated(signum, frame):  # a kill (timeout, docker stop, Slurm): unwind, clean up
        raise _Terminated

    previous = signal.signal(signal.SIGTERM, terminated)
    try:
        from tqdm.contrib.logging import logging_redirect_tqdm

        with logging_redirect_tqdm():  # warnings on their own lines, not inside the progress bar
            return int(args.func(args))
    except NothingValidError as exc:  # the input was read; nothing valid came of it
        sys.stderr.write(f"rover {args.command}: error: {exc}\n")
        return 1
    except (ValueError, OSError, EstimatorError) as exc:  # includes CalibrationError and ConfigError
        sys.stderr.write(f"rover {args.command}: error: {_one_line(exc)}\n")
        return 2
    except _Terminated:
        sys.stderr.write(f"rover {args.command}: terminated\n")
        return 143
    except KeyboardInterrupt:
        sys.stderr.write(f"rover {args.command}: interrupted\n")
        return 130
    except Exception as exc:  # a failure no check foresaw: one line, the traceback on -v
        if args.verbose:
            raise
        sys.stderr.write(
            f"rover {args.command}: error: {type(exc).__name__}: {_one_line(exc)} (unexpected: run with -v "
            "for the traceback and report it)\n"
        )
        return 3
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the program is so that every ``with`` block cleans up."""


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line."""
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":
    raise SystemExit(main())

"""Sweeps of controllers x missions x seeds, in local processes or on a Ray cluster, into one report.

A run is named by an :class:`EvalJob`: a controller name (:data:`CONTROLLERS`, optionally with
``@ground_truth`` to drive on the simulator's state instead of perception's estimates), a
mission (a registered environment id or a scenario), a seed, a camera preset and, on estimated
observations, the estimator (the built-in one, or a user's: several side by side). Each run is a
fresh environment in its own process (:func:`run_job`); it returns one flat row of metrics
(:class:`~rover_env.tools.mission.MissionMetrics`) and, on estimated observations, the estimator's
errors (:func:`~rover_env.tools.estimator_metrics.estimator_summary`). :func:`run_sweep` runs the jobs
with the ``local`` executor (a process pool; one worker runs them in this process) or the
``ray`` executor (``ray.init()`` joins the cluster named by ``RAY_ADDRESS`` or starts a local
one); the rows are the same either way. :func:`write_report` writes ``results.csv``,
``results.json``, ``summary.csv`` and ``report.md``, one row of the tables per mission,
controller and estimator. Every file goes through :class:`perception.logs.outputs.OutputFolder`.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from perception.logs.outputs import OutputFolder
from rover_env.config.rig import PresetName
from rover_env.tools.registry import (  # noqa: F401 (the sweep's names)
    CONTROLLERS,
    OBS_SOURCES,
    ControllerSpec,
    controller_imu,
    parse_controller,
)

log = logging.getLogger(__name__)


def _path_label(path: str) -> str:
    """``<stem>-<6 hex digits of the absolute path>``: two files of one name get two labels."""
    import hashlib

    p = Path(path)
    return f"{p.stem}-{hashlib.sha1(str(p.resolve()).encode()).hexdigest()[:6]}"


@dataclass(frozen=True)
class EvalJob:
    """One run of a sweep.

    Attributes:
        controller: :data:`CONTROLLERS` name, optionally ``@ground_truth``, ``@estimated`` or
            ``@imu[:<preset>]`` (estimates with an IMU).
        mission: A registered environment id (``rover_env.ENV_IDS``), or a scenario preset name
            or YAML path (run in ``Rover-v0``).
        seed: Episode seed.
        preset: Camera preset of the estimator (``train`` or ``eval``).
        out: Folder for this run's metrics, TUM trajectories and plots (None: none written).
        video: Also write ``video.mp4`` there (composite camera view).
        rerun: Also write ``mission.rrd`` there (Rerun; :mod:`rover_env.tools.rerun_log`).
        estimator: The estimator on the estimated-observation runs: ``[NAME=]module:FACTORY``
            (or ``[NAME=]path/file.py:FACTORY``; :func:`load_estimator`), labelled NAME in the
            report (:func:`estimator_label`); None: the built-in.
        camera_effects: The cameras of estimated-observation runs: ``"ideal"`` or ``"field"``
            (the environment's ``camera_effects``).
        randomize: Domain randomisation of the world: ``"off"``, ``"on"`` or None (the
            mission's scenario says; the environment's ``randomize``). The episode's seed draws
            the world.
        rig: The sensors of estimated-observation runs: a named rig (the environment's ``rig``:
            ``"standard"``, ``"fisheye_only"``, the one-camera rig, or ``"full"``, with the
            BMI088, wheel encoders and motor currents) or None (the mission's).
    """

    controller: str
    mission: str
    seed: int
    preset: PresetName = "train"
    out: str | None = None
    video: bool = False
    rerun: bool = False
    estimator: str | None = None
    camera_effects: str = "field"
    randomize: str | None = None
    rig: str | None = None

    @property
    def name(self) -> str:
        """A file-name-safe label: controller (its estimator and rig), mission and seed."""
        base, at, source = (
            self.controller.rpartition("@") if "@" in self.controller else (self.controller, "", "")
        )
        if base.startswith("policy:"):
            base = "policy-" + _path_label(base[len("policy:") :])
        ctrl = f"{base}-{source.replace(':', '-')}" if at else base
        if self.estimator is not None:
            ctrl += "-" + _safe(estimator_label(self.estimator))
        if self.rig is not None:
            ctrl += f"-{self.rig}"
        mission = _path_label(self.mission) if self.mission.endswith((".yaml", ".yml")) else self.mission
        return f"{ctrl}_{mission}_{self.seed}"


def _safe(text: str) -> str:
    """``text`` as a file-name part: letters, digits, ``.``, ``_`` and ``-`` (others become ``-``)."""
    import re

    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-.") or "estimator"


#: How the built-in estimator is named in ``--estimator`` and in the reports.
BUILTIN = "built-in"


def split_estimator(spec: str) -> tuple[str, str]:
    """``"NAME=module:FACTORY"`` -> (NAME, ``"module:FACTORY"``); without ``NAME=``: (spec, spec).

    A name is what comes before the first ``=`` when that holds no path separator or ``:``
    (a path may hold an ``=``).
    """
    name, sep, rest = spec.partition("=")
    if sep and name and not any(c in name for c in "/\\:"):
        return name.strip(), rest.strip()
    return spec, spec


def estimator_label(spec: str | None) -> str:
    """The label of an estimator in reports: its NAME, else its spec; the built-in's is ``built-in``."""
    return BUILTIN if spec is None else split_estimator(spec)[0]


def make_mission_env(mission: str, **kwargs):
    """``gymnasium.make`` of a registered id, or of ``Rover-v0`` with ``mission`` as its scenario."""
    import gymnasium as gym

    import rover_env

    if mission in rover_env.ENV_IDS:
        return gym.make(mission, **kwargs)
    return gym.make("Rover-v0", scenario=mission, **kwargs)


def run_job(job: EvalJob) -> dict:
    """Run one job in a fresh environment; one flat row (JSON-serialisable) of its results.

    The row has the job's fields, ``obs_source``, the mission metrics, the estimator's errors
    (``est_*``, NaN on ground-truth runs) and the wall-clock time [s].
    """
    import time

    from rover_env.tools.mission import RUN_FILES, run_mission, write_outputs

    spec, source = parse_controller(job.controller)
    render = "rgb_array" if (job.video and job.out) else None
    env = make_mission_env(job.mission, **env_kwargs(job, spec.action_mode, source), render_mode=render)
    randomized = env.unwrapped.randomize is not None
    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        stack.callback(env.close)
        ctrl = spec.make(env)
        # this run's files: staged, committed together when it ends (a failed run leaves none)
        out = None
        if job.out:  # inside the sweep's runs/ folder, never through a link
            where = OutputFolder(job.out, RUN_FILES, True, announce=False, within=Path(job.out).parent)
            out = stack.enter_context(where)
        video = out.stage("video.mp4") if (out is not None and job.video) else None
        log_rr = None
        if job.rerun and out is not None:
            from rover_env.tools.rerun_log import RerunLog

            log_rr = RerunLog(out.stage("mission.rrd"))
            log_rr.start_run(job.name, env.unwrapped.course.points)
        result = run_mission(env.unwrapped, ctrl, seed=job.seed, video_path=video, rerun=log_rr)
        if log_rr is not None:
            log_rr.end_run()
            log_rr.close()
        if out is not None:
            write_outputs(out, env.unwrapped, result)
            out.commit()
    row = {"controller": job.controller, "mission": job.mission, "seed": job.seed, "preset": job.preset}
    row["obs_source"] = source
    row["estimator"] = estimator_label(job.estimator) if source == "estimated" else "none"
    row["estimator_spec"] = (
        split_estimator(job.estimator)[1] if source == "estimated" and job.estimator else ""
    )
    row["camera_effects"] = job.camera_effects if source == "estimated" else "none"
    row["randomize"] = "on" if randomized else "off"
    row["rig"] = (job.rig or "mission") if source == "estimated" else "none"
    row.update(asdict(result.metrics))
    row["wall_time"] = time.perf_counter() - start
    for k, v in (result.estimator or {}).items():
        row[f"est_{k}"] = v
    return row


def env_kwargs(job: EvalJob, action_mode: str, source: str) -> dict:
    """The ``gymnasium.make`` keywords of a job's environment (its estimator loaded)."""
    kwargs: dict = {
        "obs_source": source, "action_mode": action_mode, "preset": job.preset, "randomize": job.randomize,
    }  # fmt: skip
    imu = controller_imu(job.controller)
    if imu:
        kwargs["imu"] = imu
    if source == "estimated":
        kwargs["camera_effects"] = job.camera_effects
        if job.estimator is not None:
            kwargs["estimator"] = load_estimator(job.estimator)
        if job.rig is not None:
            kwargs["rig"] = job.rig
    return kwargs


def _init_worker() -> None:
    import cv2

    cv2.setNumThreads(1)  # one core per run


def _init_pool_worker() -> None:
    """A local worker process: one core, and Ctrl-C left to the parent (which stops the workers)."""
    import signal

    _init_worker()
    # Ctrl-C reaches the whole process group: the parent reports what finished and terminates
    # the workers, which would otherwise each print a traceback; terminated, a worker unwinds
    # (its run's staged files are removed) and exits
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit_terminated)


def _exit_terminated(signum, frame) -> None:
    raise SystemExit(143)


#: Each run's row, written into its folder as soon as it finishes (what ``resume`` reads).
ROW_FILE = "row.json"


def check_jobs(jobs: Sequence[EvalJob]) -> None:
    """Check every job's controller, mission and preset before anything runs (ValueError naming it)."""
    import rover_env
    from rover_env.config.scenario import load_scenario
    from rover_env.sensors.rig import PERCEPTION_PRESETS

    missions = {}
    labels: dict[str, str] = {}
    for spec in dict.fromkeys(job.estimator for job in jobs if job.estimator):
        label = estimator_label(spec)
        if label == BUILTIN:
            raise ValueError(
                f"--estimator {spec!r}: {BUILTIN!r} names the built-in estimator; name yours otherwise"
            )
        if label in labels and labels[label] != spec:
            raise ValueError(
                f"--estimator: {labels[label]!r} and {spec!r} are both named {label!r}; name them: "
                "NAME=module:FACTORY"
            )
        labels[label] = spec
        load_estimator(spec)
    for job in jobs:
        parse_controller(job.controller)
        if job.camera_effects not in ("ideal", "field"):
            raise ValueError(f"camera_effects {job.camera_effects!r}: use 'ideal' or 'field'")
        if job.randomize not in (None, "off", "on"):
            raise ValueError(f"randomize {job.randomize!r}: use 'off', 'on' or None (the scenario's)")
        if job.rig is not None:
            from rover_env.config.rig import RIG_NAMES

            if job.rig not in RIG_NAMES:
                raise ValueError(f"rig {job.rig!r}: use one of {list(RIG_NAMES)} or None (the mission's)")
        if job.preset not in PERCEPTION_PRESETS:
            raise ValueError(f"preset {job.preset!r}: use one of {sorted(PERCEPTION_PRESETS)}")
        if job.mission not in missions and job.mission not in rover_env.ENV_IDS:
            try:
                missions[job.mission] = load_scenario(job.mission)
            except (ValueError, OSError) as exc:  # ConfigError is a ValueError
                raise ValueError(
                    f"mission {job.mission!r}: not an environment id ({', '.join(rover_env.ENV_IDS)}), "
                    f"scenario preset or readable scenario file ({exc})"
                ) from None
        scenario = missions.get(job.mission)
        if job.rig is not None and scenario is not None and scenario.rig is not None:
            raise ValueError(
                f"rig {job.rig!r}: mission {job.mission!r} declares its own rig; leave --rig out for it"
            )


def finished_row(job: EvalJob, sweep: str | None = None) -> dict | None:
    """The row a finished run of ``job`` wrote into its folder (None: not run, or another job's).

    Another job's: another controller, mission, seed or preset, or an estimated run with other
    cameras, another estimator (its name or its factory) or (where ``job`` sets it) another
    randomisation; with ``sweep``, a row another sweep wrote (:func:`run_sweep`).
    """
    if job.out is None:
        return None
    path = Path(job.out) / ROW_FILE
    try:
        row = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    same = isinstance(row, dict) and all(
        row.get(k) == getattr(job, k) for k in ("controller", "mission", "seed", "preset")
    )
    if same:
        # the run's cameras, estimator and world ("none": a ground-truth run, which has neither)
        same = row.get("camera_effects") in ("none", job.camera_effects) and row.get("estimator") in (
            "none",
            estimator_label(job.estimator),
        )
        if job.randomize is not None:
            same = same and row.get("randomize") == job.randomize
        same = same and row.get("rig", "mission") in ("none", job.rig or "mission")
        spec = split_estimator(job.estimator)[1] if job.estimator else ""
        same = same and row.get("estimator_spec", "") in ("", spec)
        same = same and (sweep is None or row.get("sweep") == sweep)
    if not same:
        return None
    row.pop("sweep", None)
    return row


def run_sweep(
    jobs: Sequence[EvalJob],
    executor: str = "local",
    workers: int | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    resume: bool = False,
    sweep: str | None = None,
) -> list[dict]:
    """Run ``jobs``; their rows in the order of ``jobs``.

    Every job is checked before any runs (:func:`check_jobs`). A job with an ``out`` folder
    writes its row there (``row.json``, marked with ``sweep``) as soon as it finishes, so an
    interrupted sweep loses only the runs under way; with ``resume`` those finished rows are
    read back and their jobs skipped: only the rows of the sweep ``sweep`` when it is given
    (an earlier sweep's rows in the same folders are not this one's).

    Args:
        jobs: The runs.
        executor: ``"local"`` (a pool of ``workers`` processes; 1 runs them here) or ``"ray"``.
        workers: Local processes (default: the CPU count); with Ray, ignored (one CPU per run).
        progress: Called after each finished run with (finished, total, its row).
        resume: Skip the jobs whose folders hold their finished rows.
        sweep: This sweep's mark (``rover eval`` keeps it in ``runs/sweep.json``), or None.
    """
    if executor not in ("local", "ray"):
        raise ValueError(f"executor {executor!r}: use 'local' or 'ray'")
    check_jobs(jobs)  # fail before starting anything
    rows: list[dict | None] = [finished_row(job, sweep) if resume else None for job in jobs]
    if resume and any(r is not None for r in rows):
        log.info("resuming: %d of %d runs already finished", sum(r is not None for r in rows), len(jobs))
    todo = [i for i, r in enumerate(rows) if r is None]

    def done(i: int, row: dict) -> None:
        rows[i] = row
        out = jobs[i].out
        if out is not None:
            with OutputFolder(out, (ROW_FILE,), True, announce=False, within=Path(out).parent) as folder:
                folder.write_text(ROW_FILE, json.dumps(row | {"sweep": sweep}, default=float) + "\n")
                folder.commit()
        if progress is not None:
            progress(sum(r is not None for r in rows), len(jobs), row)

    run = [jobs[i] for i in todo]

    if executor == "ray":
        _run_ray(run, lambda k, row: done(todo[k], row))
    else:
        n = workers or os.cpu_count() or 1
        if n <= 1 or len(run) <= 1:
            _init_worker()
            for i in todo:
                done(i, run_job(jobs[i]))
        else:
            ctx = get_context("spawn")  # a clean interpreter: no inherited PyBullet or thread state
            pool = ProcessPoolExecutor(max_workers=n, mp_context=ctx, initializer=_init_pool_worker)
            futures = {pool.submit(run_job, jobs[i]): i for i in todo}
            try:
                for fut in as_completed(futures):
                    done(futures[fut], fut.result())
            except BaseException:  # Ctrl-C or a failed run: the runs under way are stopped now
                for proc in list(getattr(pool, "_processes", {}).values()):  # (no public way to stop one)
                    proc.terminate()
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
    return [r for r in rows if r is not None]


def _run_ray(jobs: Sequence[EvalJob], done: Callable[[int, dict], None]) -> None:
    try:
        import ray
    except ImportError:
        raise ImportError(
            "the ray executor needs Ray: pip install 'rover-vision[ray]' (or pip install ray)"
        ) from None
    started = not ray.is_initialized()
    if started:
        ray.init(address=os.environ.get("RAY_ADDRESS"), logging_level=logging.WARNING, log_to_driver=False)
    try:

        def remote_job(job: EvalJob) -> dict:
            _init_worker()
            return run_job(job)

        remote = ray.remote(num_cpus=1)(remote_job)
        pending = {remote.remote(job): i for i, job in enumerate(jobs)}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                done(pending.pop(ref), ray.get(ref))
    finally:
        if started:
            ray.shutdown()


def jobs_for(
    controllers: Iterable[str],
    missions: Iterable[str],
    seeds: Iterable[int],
    preset: PresetName = "train",
    out: str | Path | None = None,
    video: bool = False,
    rerun: bool = False,
    estimator: str | Sequence[str | None] | None = None,
    camera_effects: str = "field",
    randomize: str | None = None,
    rig: str | None = None,
) -> list[EvalJob]:
    """Every controller x mission x seed (x estimator); with ``out``, runs write into ``out/runs/<name>``.

    ``estimator``: one estimator spec, or several (None or ``"built-in"``: the built-in): every
    controller on estimated observations runs with each; a controller on the ground truth
    (``@ground_truth``) runs once.
    """
    specs = [estimator] if estimator is None or isinstance(estimator, str) else list(estimator)
    specs = [None if s in (None, BUILTIN) else s for s in specs] or [None]
    jobs = []
    for c in controllers:
        on_truth = "@" in c and c.rpartition("@")[2] == "ground_truth"  # (checked by check_jobs)
        for e in [None] if on_truth else list(dict.fromkeys(specs)):
            for m in missions:
                for s in seeds:
                    job = EvalJob(c, m, int(s), preset, estimator=e, rig=rig)
                    where = None if out is None else str(Path(out) / "runs" / job.name)
                    jobs.append(
                        EvalJob(c, m, int(s), preset, where, video, rerun, e, camera_effects, randomize, rig)
                    )
    return jobs


def preflight(jobs: Sequence[EvalJob]) -> None:
    """Build each estimator once on each rig of ``jobs`` before any run: a refusal is one error now.

    One environment per distinct (estimator, mission, IMU, preset, cameras, rig, randomisation)
    of the estimated-observation jobs is made and closed; its estimator factory is called with
    the rig, and the object it returns checked for the interface.

    Raises:
        ValueError: A factory refused the rig, or what it made is not an estimator (the message
            names the estimator and the mission).
    """
    from perception.estimator import EstimatorError

    seen = set()
    for job in jobs:
        spec, source = parse_controller(job.controller)
        if source != "estimated":
            continue
        kwargs = env_kwargs(job, spec.action_mode, source)
        key = (
            job.estimator,
            job.mission,
            kwargs.get("imu"),
            job.preset,
            job.camera_effects,
            job.rig,
            job.randomize,
        )
        if key in seen:
            continue
        seen.add(key)
        try:
            make_mission_env(job.mission, **kwargs).close()
        except (EstimatorError, TypeError) as exc:
            raise ValueError(f"estimator {estimator_label(job.estimator)} on {job.mission}: {exc}") from None


def load_estimator(spec: str):
    """The estimator factory of ``spec``: ``[NAME=]module:FACTORY`` or ``[NAME=]path/file.py:FACTORY``.

    A module is imported with the current folder on the path (as ``python -m`` has it), so
    ``examples.own_estimator:LucasKanadeEstimator`` works from the project's root; from
    anywhere else, give the file's path (``path/to/own_estimator.py:LucasKanadeEstimator``).

    Raises:
        ValueError: Not ``module:FACTORY``, the module does not import (or exits), or it has no
            callable FACTORY.
    """
    import importlib
    import importlib.util
    import sys

    spec = split_estimator(spec)[1]
    where, sep, name = spec.rpartition(":")
    if not sep or not where or not name:
        raise ValueError(
            f"--estimator {spec!r}: give [NAME=]module:FACTORY or [NAME=]path/file.py:FACTORY (or {BUILTIN})"
        )
    try:
        if where.endswith(".py"):
            path = Path(where)
            if not path.is_file():
                raise ValueError(f"--estimator {spec!r}: no file {where}")
            mod_spec = importlib.util.spec_from_file_location(path.stem, path)
            if mod_spec is None or mod_spec.loader is None:
                raise ValueError(f"--estimator {spec!r}: {where} cannot be imported as a module")
            module = importlib.util.module_from_spec(mod_spec)
            sys.modules.setdefault(path.stem, module)
            mod_spec.loader.exec_module(module)
        else:
            if "" not in sys.path and str(Path.cwd()) not in sys.path:
                sys.path.insert(0, str(Path.cwd()))
            module = importlib.import_module(where)
    except ValueError:
        raise
    except ModuleNotFoundError as exc:
        if exc.name is not None and where.split(".")[0] == exc.name.split(".")[0]:
            guess = where.replace(".", "/") + ".py"
            raise ValueError(
                f"--estimator {spec!r}: no module {where!r} from the current folder {Path.cwd()}; give the "
                f"file's path instead: path/to/{guess}:{name}"
            ) from None
        raise ValueError(
            f"--estimator {spec!r}: {where} does not import (ModuleNotFoundError: {exc})"
        ) from None
    except (Exception, SystemExit) as exc:  # the user's module: any error it raises at import
        raise ValueError(
            f"--estimator {spec!r}: {where} does not import ({type(exc).__name__}: {exc})"
        ) from None
    factory = getattr(module, name, None)
    if not callable(factory):
        raise ValueError(f"--estimator {spec!r}: {where} has no callable {name!r}")
    return factory


#: Summary columns: (row key, heading, how the runs are combined).
SUMMARY = (
    ("success", "success rate", "mean"),
    ("time", "time [s]", "success_mean"),
    ("cross_track_rms", "cross-track RMS [m]", "mean"),
    ("energy", "energy [J]", "mean"),
    ("time_in_slip", "time in slip [s]", "mean"),
    ("stuck_events", "stuck events", "mean"),
    ("progress", "progress [m]", "mean"),
    ("goal_error", "true goal error [m]", "mean"),
)
ESTIMATOR_SUMMARY = (
    ("est_mae_v_x", "v_x MAE [m/s]"),
    ("est_mae_omega", "omega MAE [rad/s]"),
    ("est_mae_slip", "slip MAE"),
    ("est_slip_mae_slipping", "slip MAE, abs(s) > 0.1"),
    ("est_slip_f1", "slip-event F1 (pooled)"),
    ("est_mae_steering", "steering MAE [rad]"),
    ("est_position_error_final", "dead-reckoning error at the end [m]"),
    ("est_segment_5m_percent", "5 m segment error [%]"),
)


def _num(v) -> float:
    """A row's value as a float; missing (None, as JSON stores NaN) is NaN."""
    return math.nan if v is None else float(v)


def summarize(rows: Sequence[dict]) -> list[dict]:
    """One row per (mission, controller, estimator): run count and the :data:`SUMMARY` and estimator columns.

    ``time`` is averaged over the successful runs only (NaN if none succeeded), the slip-event F1
    is pooled over the runs' events, and the rest are means over the runs that have the figure
    (NaN where none has: an estimator that does not return a field has no error for it).
    """
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["mission"], r["controller"], str(r.get("estimator", BUILTIN))), []).append(r)
    out = []
    for (mission, ctrl, est), rs in groups.items():
        s = {"mission": mission, "controller": ctrl, "estimator": est, "runs": len(rs)}
        for key, _, how in SUMMARY:
            vals = [_num(r.get(key)) for r in rs if how != "success_mean" or r["success"]]
            vals = [v for v in vals if math.isfinite(v)]
            s[key] = float(np.mean(vals)) if vals else math.nan
        for key, _ in ESTIMATOR_SUMMARY:
            vals = [v for v in (_num(r.get(key)) for r in rs) if math.isfinite(v)]
            s[key] = float(np.mean(vals)) if vals else math.nan
        # slip-event F1 over the events of all runs (a run's own F1 is 0 for one false event)
        counts = [[_num(r.get(f"est_slip_events_{k}")) for r in rs] for k in ("matched", "false", "missed")]
        tp, fp, fn = (float(np.sum(c)) if c and np.all(np.isfinite(c)) else math.nan for c in counts)
        s["est_slip_f1"] = 2 * tp / (2 * tp + fp + fn) if 2 * tp + fp + fn > 0 else math.nan
        out.append(s)
    return out


def _fmt(v) -> str:
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.3g}"
    return str(v)


#: The files :func:`write_report` writes.
REPORT_FILES = ("report.md", "results.csv", "results.json", "summary.csv")


def write_report(
    rows: Sequence[dict],
    out: str | Path | OutputFolder,
    title: str = "Mission evaluation",
    command: str | None = None,
) -> Path:
    """Write ``results.csv``, ``results.json``, ``summary.csv`` and ``report.md``.

    ``out``: an :class:`OutputFolder` whose products include :data:`REPORT_FILES` (staged, the
    caller commits), or a folder path (written and committed here, replacing an earlier
    report). ``command``, if given, is quoted under the title (the command that produced the
    rows). A figure nobody estimated is NaN in the CSV files, null in the JSON and "–" in the
    report. Returns the path of ``report.md``.
    """
    if not isinstance(out, OutputFolder):
        with OutputFolder(out, REPORT_FILES, overwrite=True, announce=False) as folder:
            path = write_report(rows, folder, title, command)
            folder.commit()
        return path
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with out.open("results.csv", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    from rover_env.tools.mission import json_safe

    out.write_text("results.json", json.dumps(json_safe(list(rows)), indent=1) + "\n")
    summary = summarize(rows)
    with out.open("summary.csv", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(summary[0]) if summary else ["mission"])
        w.writeheader()
        w.writerows(summary)
    seeds = sorted({r["seed"] for r in rows})
    lines = [
        f"# {title}",
        "",
        f"`{command}`\n" if command else "",
        f"{len(rows)} runs; seeds {seeds[0]}–{seeds[-1]} ({len(seeds)})." if seeds else "",
    ]
    estimators = sorted({str(r.get("estimator")) for r in rows if r.get("estimator") not in (None, "none")})
    if estimators:
        lines.append(f"Estimator on the estimated-observation runs: {', '.join(estimators)}.")
    specs = {}
    for r in rows:
        if r.get("estimator_spec"):
            specs[str(r.get("estimator"))] = str(r["estimator_spec"])
    for label, spec in sorted(specs.items()):
        if spec != label:
            lines.append(f"- `{label}`: `{spec}`")
    rigs = sorted({str(r.get("rig")) for r in rows if r.get("rig") not in (None, "none", "mission")})
    if rigs:
        lines.append(f"Sensors of the estimated-observation runs: the {', '.join(rigs)} rig.")
    for mission in dict.fromkeys(s["mission"] for s in summary):
        lines += ["", f"## {mission}", ""]
        lines.append("| controller | estimator | runs | " + " | ".join(h for _, h, _ in SUMMARY) + " |")
        lines.append("|---|---|---:|" + "---:|" * len(SUMMARY))
        for s in summary:
            if s["mission"] == mission:
                cells = [s["controller"], s["estimator"], str(s["runs"])] + [
                    _fmt(s[k]) for k, _, _ in SUMMARY
                ]
                lines.append("| " + " | ".join(cells) + " |")
        est = [s for s in summary if s["mission"] == mission and s["estimator"] != "none"]
        if est:
            lines += [
                "",
                "Estimator errors on the estimated-observation runs (means over runs; –: not estimated):",
            ]
            lines += ["", "| controller | estimator | " + " | ".join(h for _, h in ESTIMATOR_SUMMARY) + " |"]
            lines.append("|---|---|" + "---:|" * len(ESTIMATOR_SUMMARY))
            for s in est:
                cells = [s["controller"], s["estimator"]] + [_fmt(s[k]) for k, _ in ESTIMATOR_SUMMARY]
                lines.append("| " + " | ".join(cells) + " |")
    return out.write_text("report.md", "\n".join(lines) + "\n")


__all__ = [
    "CONTROLLERS",
    "make_mission_env",
    "ControllerSpec",
    "EvalJob",
    "jobs_for",
    "controller_imu",
    "check_jobs",
    "estimator_label",
    "preflight",
    "split_estimator",
    "finished_row",
    "parse_controller",
    "run_job",
    "run_sweep",
    "summarize",
    "write_report",
]

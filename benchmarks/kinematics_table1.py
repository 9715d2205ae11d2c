"""Reproduce the kinematics paper's Table I and Figs. 9-14 in simulation.

Three drives of 82, 170 and 257 s (the paper's dataset durations) over rough regolith, with the
fisheye at the paper's 640x480 and 30 frames per second and a low sun that sweeps the rover's
shadow over its wheels as it turns. The rover circles the terrain's centre, weaving: steering
alternates between double Ackermann, front-only and crab phases, speed varies between 0.3 and
1.0 m/s with a stop every minute. Every frame goes through :class:`KinematicStateEstimator`;
the simulator's joint states are the ground truth (the paper's IMUs, potentiometers and motor
encoder).

Per dataset: MAE of axle roll and steering (front, rear), of the axle-body distance, the
largest wheel-rotation drift over the run (any wheel, any time), the wheel-rate RMS error, the
share of frames on which all 10 degrees of freedom are measured and the estimator's time per
frame. Writes ``OUT/table1.md``, ``OUT/table1.csv``, ``OUT/dataset{1,2,3}.csv`` (per frame) and
``OUT/figs9-14.png`` (dataset 2, as in the paper).

Run: python benchmarks/kinematics_table1.py [--out DIR] [--datasets 1 2 3] [--scale 1.0] [--jobs 2]
(about 30 min on 2 cores; ``--scale 0.1`` for a quick look).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from perception.kinematics.fisheye import DOF_NAMES, KinematicStateEstimator
from rover_env.config.cameras import FisheyeCameraConfig
from rover_env.config.scenario import FrictionMapConfig, ScenarioConfig, SunConfig, TerrainConfig
from rover_env.sensors.cameras import FisheyeCamera
from rover_env.sim.simulation import RoverSim, quat_to_yaw
from rover_env.task.course import CourseConfig

# name: (duration [s], terrain seed, sun azimuth [deg], sun elevation [deg])
DATASETS = {1: (82.0, 3, 150.0, 35.0), 2: (170.0, 5, 230.0, 30.0), 3: (257.0, 9, 60.0, 40.0)}
CIRCLE = 9.0  # radius of the loop the rover drives around the terrain centre [m]

COLUMNS = (
    ["t"]
    + [f"{q}_{s}" for q in ("psi", "d", "lam") for s in ("F", "R")]
    + [f"theta_{w}" for w in ("FL", "FR", "RL", "RR")]
    + [f"rate_{w}" for w in ("FL", "FR", "RL", "RR")]
)


def commands(t: float, x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """Speed [m/s] and axle steering (lambda_F, lambda_R) [rad] at time t and pose (world frame).

    Steer toward a point ahead on the circle around the origin, weave on top, and cycle the
    steering mode every 15 s; stop for 3 s every 60 s.
    """
    r = math.hypot(x, y)
    ang = math.atan2(y, x) + 1.2  # a point ahead on the circle, counter-clockwise
    tx, ty = CIRCLE * math.cos(ang), CIRCLE * math.sin(ang)
    err = math.atan2(ty - y, tx - x) - yaw
    err = math.atan2(math.sin(err), math.cos(err))
    err += 0.05 * (r - CIRCLE)  # back toward the circle
    lam = float(np.clip(0.9 * err + 0.22 * math.sin(2 * math.pi * t / 6.5), -0.45, 0.45))
    mode = int(t // 15.0) % 3
    rear = (-lam, 0.0, 0.5 * lam)[mode]  # double Ackermann, front only, crab
    speed = 0.65 + 0.35 * math.sin(2 * math.pi * t / 23.0)
    if t % 60.0 > 57.0:
        speed = 0.0
    return speed, lam, rear


def drive(index: int, scale: float = 1.0) -> dict:
    """Run one dataset; returns per-frame arrays (ground truth, estimate, validity) and timing."""
    duration, seed, azimuth, elevation = DATASETS[index]
    duration *= scale
    scenario = ScenarioConfig(
        name=f"table1_dataset{index}",
        course=CourseConfig(waypoints=((CIRCLE, 0.0),)),
        terrain=TerrainConfig(
            kind="rough", size=(30.0, 30.0), roughness=0.05, wavelength=1.5, seed=seed, texture="regolith"
        ),
        friction=FrictionMapConfig(default_mu=0.8),
        sun=SunConfig(azimuth_deg=azimuth, elevation_deg=elevation),
    )
    sim = RoverSim(scenario)
    try:
        sim.reset(CIRCLE, 0.0, math.pi / 2)
        g = sim.geometry
        cam = FisheyeCamera(sim, FisheyeCameraConfig.preset("full"))
        est = KinematicStateEstimator(cam.model, g.kinematic_model(cam.T_body_cam))
        truth, estimate, valid, spent = [], [], [], 0.0
        n = int(round(duration / cam.period))
        for i in range(n):
            if i % 600 == 0:  # progress, every 20 s of drive
                sys.stderr.write(f"dataset {index}: {i * cam.period:.0f} of {duration:.0f} s\n")
            frame = cam.capture()
            gt = sim.ground_truth()
            t0 = time.perf_counter()
            s = est.update(frame.image, frame.t)
            spent += time.perf_counter() - t0
            truth.append(
                np.r_[frame.t, gt.axle_roll, gt.axle_height, gt.steering, gt.wheel_angle, gt.wheel_rate]
            )
            estimate.append(np.r_[frame.t, s.psi, s.depth, s.lam, s.theta, s.theta_dot])
            valid.append([s.valid[k] for k in DOF_NAMES])
            speed, lam_f, lam_r = commands(frame.t, *gt.pose[:2], quat_to_yaw(gt.pose[3:]))
            sim.rover.command(g.drive.wheel_speeds(speed, lam_f, lam_r) / g.wheel_radius, lam_f, lam_r)
            sim.step(cam.period)
    finally:
        sim.close()
    return dict(
        index=index,
        truth=np.array(truth),
        estimate=np.array(estimate),
        valid=np.array(valid, dtype=bool),
        ms=spent / max(n, 1) * 1e3,
    )


def metrics(run: dict) -> dict:
    """Table I's numbers for one dataset (angles in degrees, lengths in mm)."""
    T, E, V = run["truth"], run["estimate"], run["valid"]
    err = E - T
    drift = (E[:, 7:11] - E[0, 7:11]) - (T[:, 7:11] - T[0, 7:11])
    # the estimate is the rotation since the last frame over the frame interval: compare it with
    # the true rotation over the same interval (the instantaneous rate jitters on rough ground)
    true_rate = np.diff(T[:, 7:11], axis=0) / np.diff(T[:, 0])[:, None]
    moving = np.abs(true_rate) > 0.5  # rate error as a share, where the wheels turn
    rate_err = np.where(moving, (E[1:, 11:15] - true_rate) / np.where(moving, np.abs(true_rate), 1.0), np.nan)
    return dict(
        dataset=run["index"],
        duration=float(T[-1, 0] - T[0, 0]),
        frames=len(T),
        roll_mae=np.degrees(np.abs(err[:, 1:3]).mean(axis=0)),
        depth_mae=1e3 * np.abs(err[:, 3:5]).mean(axis=0),
        steer_mae=np.degrees(np.abs(err[:, 5:7]).mean(axis=0)),
        drift=float(np.abs(drift).max()),
        rate_rms=100 * float(np.sqrt(np.nanmean(rate_err**2))),
        all_dof=float(V[1:].all(axis=1).mean()),  # the first frame has no rotation yet
        dof_valid=V[1:].mean(axis=0),
        ms=run["ms"],
    )


def table(rows: list[dict]) -> str:
    head = (
        "| dataset | duration [s] | roll MAE F / R [deg] | steering MAE F / R [deg] | depth MAE F / R [mm] "
        "| max wheel-rotation drift [rad] | wheel-rate RMS err [%] | frames with all 10 DOF | ms/frame |\n"
        "|---|---:|---|---|---|---:|---:|---:|---:|\n"
    )
    body = "".join(
        f"| {m['dataset']} | {m['duration']:.0f} | {m['roll_mae'][0]:.3f} / {m['roll_mae'][1]:.3f} "
        f"| {m['steer_mae'][0]:.3f} / {m['steer_mae'][1]:.3f} "
        f"| {m['depth_mae'][0]:.2f} / {m['depth_mae'][1]:.2f} "
        f"| {m['drift']:.3f} | {m['rate_rms']:.2f} | {100 * m['all_dof']:.2f} % | {m['ms']:.1f} |\n"
        for m in rows
    )
    paper = (
        "\nThe paper (real rover): roll MAE 1.32-2.41 deg, steering MAE 1.86-2.55 deg, drift 0.86-3.70 rad.\n"
    )
    return head + body + paper


def plot(run: dict, path: Path) -> Path:
    """Figs. 9-14 of the paper for one dataset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    T, E = run["truth"], run["estimate"]
    t = T[:, 0]
    fig, ax = plt.subplots(3, 2, figsize=(13, 10), sharex=True)
    for i, (axle, c) in enumerate((("front", "C0"), ("rear", "C1"))):
        ax[0, 0].plot(t, np.degrees(T[:, 1 + i]), c, lw=1.5, alpha=0.5, label=f"{axle} truth")
        ax[0, 0].plot(t, np.degrees(E[:, 1 + i]), c + "--", lw=0.8, label=f"{axle} fisheye")
        ax[0, 1].plot(t, np.degrees(T[:, 5 + i]), c, lw=1.5, alpha=0.5, label=f"{axle} truth")
        ax[0, 1].plot(t, np.degrees(E[:, 5 + i]), c + "--", lw=0.8, label=f"{axle} fisheye")
        ax[1, 0].plot(t, np.degrees(E[:, 1 + i] - T[:, 1 + i]), c, lw=0.7, label=axle)
        ax[1, 1].plot(t, np.degrees(E[:, 5 + i] - T[:, 5 + i]), c, lw=0.7, label=axle)
    rear_t = T[:, 9:11].mean(axis=1) - T[0, 9:11].mean()
    rear_e = E[:, 9:11].mean(axis=1) - E[0, 9:11].mean()
    ax[2, 0].plot(t, rear_t, "k", lw=1.5, alpha=0.5, label="truth (mean of RL, RR)")
    ax[2, 0].plot(t, rear_e, "C2--", lw=0.8, label="fisheye")
    for k, w in enumerate(("FL", "FR", "RL", "RR")):
        d = (E[:, 7 + k] - E[0, 7 + k]) - (T[:, 7 + k] - T[0, 7 + k])
        ax[2, 1].plot(t, d, lw=0.8, label=w)
    titles = (
        ("Fig. 9: axle roll [deg]", "Fig. 10: steering [deg]"),
        ("Fig. 12: axle roll error [deg]", "Fig. 11: steering error [deg]"),
        ("Fig. 13: rear wheel rotation [rad]", "Fig. 14: wheel rotation drift [rad]"),
    )
    for r in range(3):
        for c in range(2):
            ax[r, c].set_title(titles[r][c])
            ax[r, c].legend(fontsize=7, loc="best")
            ax[r, c].grid(alpha=0.3)
    ax[2, 0].set_xlabel("time [s]")
    ax[2, 1].set_xlabel("time [s]")
    fig.suptitle(f"Fisheye kinematic state estimation, simulated dataset {run['index']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_frames(run: dict, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(
            [f"true_{c}" for c in COLUMNS] + [f"est_{c}" for c in COLUMNS] + [f"valid_{d}" for d in DOF_NAMES]
        )
        for a, b, v in zip(run["truth"], run["estimate"], run["valid"], strict=True):
            w.writerow([f"{x:.6g}" for x in a] + [f"{x:.6g}" for x in b] + [int(x) for x in v])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/kinematics_table1"))
    ap.add_argument("--datasets", type=int, nargs="+", default=[1, 2, 3], choices=sorted(DATASETS))
    ap.add_argument("--scale", type=float, default=1.0, help="share of each dataset's duration to drive")
    ap.add_argument("--jobs", type=int, default=2, help="datasets driven at once (processes)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        runs = list(pool.map(drive, args.datasets, [args.scale] * len(args.datasets)))
    rows = [metrics(r) for r in runs]
    text = table(rows)
    (args.out / "table1.md").write_text(text)
    with open(args.out / "table1.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["dataset", "duration_s", "frames", "roll_mae_F_deg", "roll_mae_R_deg", "steer_mae_F_deg",
                    "steer_mae_R_deg", "depth_mae_F_mm", "depth_mae_R_mm", "max_drift_rad", "rate_rms_pct",
                    "all_dof_share", "ms_per_frame"] + [f"valid_{d}" for d in DOF_NAMES])  # fmt: skip
        for m in rows:
            w.writerow(
                [
                    m["dataset"],
                    f"{m['duration']:.1f}",
                    m["frames"],
                    *np.round(m["roll_mae"], 4),
                    *np.round(m["steer_mae"], 4),
                    *np.round(m["depth_mae"], 3),
                    round(m["drift"], 4),
                    round(m["rate_rms"], 3),
                    round(m["all_dof"], 5),
                    round(m["ms"], 2),
                    *np.round(m["dof_valid"], 5),
                ]  # fmt: skip
            )
    for r in runs:
        write_frames(r, args.out / f"dataset{r['index']}.csv")
    fig_run = next((r for r in runs if r["index"] == 2), runs[0])
    plot(fig_run, args.out / "figs9-14.png")
    sys.stdout.write(text)
    print(f"wrote {args.out}/table1.md, table1.csv, dataset*.csv, figs9-14.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

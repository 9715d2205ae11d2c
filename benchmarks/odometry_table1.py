"""The odometry paper's Table I: path-segment endpoint error with odometry yaw and with IMU yaw.

On each terrain the rover drives laps of a circle (``--radius``, ``--speed``) until ``--distance``
metres, with the eval preset's cameras (640x480 downward at 60 Hz, fisheye at 30 Hz) and an IMU
(``--imu``, BMI088 by default) attached to the simulation; the estimator runs on their messages
alone (``rover_env.sensors.rig.PerceptionPipeline``), the truth is read for scoring only.

Two dead-reckoned paths are scored against the truth by the paper's method
(``perception.odometry.trajectory.path_segment_errors``, 20, 50, 100 and 150 m segments, 1 m stride):

* **odometry yaw**: the visual odometry's own twists (v_x, v_y, omega) integrated, as the paper's
  optical-flow column;
* **IMU yaw**: the same odometry velocities, turned by the estimator's fused heading (the gyro,
  its bias calibrated at the standstill before t = 0 and tracked by the slip filter).

Both columns use the vision-only velocities, as the paper does (``odometry_gyro=False``: the
gyro's roll and pitch rates are not given to the odometry's fit).

With ``--camera-effects field`` the cameras deliver their images through their image sensors
(noise, auto-exposure, motion blur, vignetting, the downward lens's distortion), and with
``--randomize-light SEED`` each terrain gets a sun, haze and sky light drawn from the domain
randomisation's ranges (``rover_env.config.randomize``) with that seed.

Writes a markdown table (``--out``/table1.md) and a figure of the paths (``--out``/table1_paths.png).

With ``--rig fisheye_only`` the rover carries the one-camera rig and the odometry is the fisheye's.

Run: LP_NUM_THREADS=1 python benchmarks/odometry_table1.py [--distance 300] [--out benchmarks/results/imu]
[--camera-effects field] [--randomize-light 7] [--rig fisheye_only]
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from perception.odometry.flow import integrate_twist
from perception.odometry.trajectory import path_segment_errors
from rover_env.config.imu import ImuConfig
from rover_env.config.randomize import RandomizeConfig, WorldDraw
from rover_env.config.rig import named_rig
from rover_env.config.scenario import load_scenario
from rover_env.sensors.rig import PerceptionPipeline
from rover_env.sim.simulation import RoverSim, quat_to_yaw

TERRAINS = {"flat": "flat_patches", "rough": "rough", "shadow-heavy": "shadow_heavy"}
LENGTHS = (20.0, 50.0, 100.0, 150.0)


def drive(
    scenario: str,
    imu: str,
    distance: float,
    radius: float,
    speed: float,
    preset: str,
    field: bool = False,
    light: WorldDraw | None = None,
    rig: str = "standard",
) -> dict:
    """Laps of a circle: the truth, the odometry's twists and the fused heading at each frame.

    ``field``: field cameras; ``light``: a world draw whose sun, haze and sky light are used;
    ``rig``: ``"standard"`` (the downward camera's odometry) or ``"fisheye_only"`` (the fisheye's).
    """
    scn = load_scenario(scenario)
    if light is not None:
        sun = replace(scn.sun, elevation_deg=light.sun_elevation_deg, azimuth_deg=light.sun_azimuth_deg)
        scn = replace(scn, sun=sun)
    sim = RoverSim(scn)
    if light is not None:
        sim.haze, sim.ambient = light.sun_transmission, light.ambient
    try:
        # the paper's method: vision-only velocities in both columns (no gyro rates in the fit)
        sensors = named_rig(rig, ImuConfig.preset(imu))
        pipe = PerceptionPipeline(sim, preset, rig=sensors, odometry_gyro=False, camera_effects=field)
        pipe.imu.reset(0)
        for k, cam in enumerate(pipe.cameras):
            cam.reset_effects(k)
        g = sim.geometry
        gt = sim.reset(0.0, -radius, 0.0)  # the circle's centre at the origin
        yaw0 = quat_to_yaw(gt.pose[3:])
        pipe.reset(np.array([0.0, -radius, yaw0]), sim.take_messages(), sim.t)
        lam = math.atan(0.5 * g.wheelbase / radius)
        sim.rover.command(g.drive.wheel_speeds(speed, lam, -lam) / g.wheel_radius, lam, -lam)
        truth, odo_t, odo_tw, fused = [], [], [], []
        along, last = 0.0, gt.pose[:2].copy()
        dt = 1.0 / 30.0
        while along < distance:
            sim.step(dt)
            est = pipe.process(sim.take_messages(), sim.t)
            gt = sim.ground_truth()
            along += float(np.linalg.norm(gt.pose[:2] - last))
            last = gt.pose[:2].copy()
            truth.append([gt.pose[0], gt.pose[1], quat_to_yaw(gt.pose[3:])])
            o = est.odometry
            ok = o is not None and o.valid and abs(o.t - sim.t) < 1e-6
            odo_t.append(sim.t)
            odo_tw.append(o.twist if ok else np.full(3, np.nan))
            fused.append(est.values["odometry_pose"][2])
        return {
            "t": np.array(odo_t),
            "truth": np.unwrap(np.array(truth), axis=0),
            "twist": np.array(odo_tw),
            "heading": np.unwrap(np.array(fused)),
            "start": np.array([0.0, -radius, yaw0]),
        }
    finally:
        sim.close()


def paths(run: dict) -> tuple[np.ndarray, np.ndarray]:
    """(odometry-yaw path, IMU-yaw path), each (n, 3), from the run's start fix."""
    t = np.concatenate([[0.0], run["t"]])
    tw = np.vstack([np.zeros(3), run["twist"]])
    odo = integrate_twist(t, tw, run["start"])[1:]
    # the odometry's velocities (the last valid one held), turned by the fused heading
    v = tw[:, :2].copy()
    for k in range(1, len(v)):
        if not np.all(np.isfinite(v[k])):
            v[k] = v[k - 1]
    head = np.concatenate([[run["start"][2]], run["heading"]])
    xy = [run["start"][:2]]
    for k in range(1, len(t)):
        h = 0.5 * (head[k - 1] + head[k])
        c, s = math.cos(h), math.sin(h)
        d = t[k] - t[k - 1]
        xy.append(xy[-1] + d * np.array([c * v[k, 0] - s * v[k, 1], s * v[k, 0] + c * v[k, 1]]))
    imu = np.column_stack([np.array(xy)[1:], head[1:]])
    return odo, imu


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distance", type=float, default=300.0, help="metres driven per terrain")
    ap.add_argument("--radius", type=float, default=8.0)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--imu", default="bmi088")
    ap.add_argument("--preset", default="eval", choices=("eval", "train"))
    ap.add_argument("--terrains", nargs="+", default=list(TERRAINS), choices=list(TERRAINS))
    ap.add_argument("--out", default="benchmarks/results/imu")
    ap.add_argument("--camera-effects", default="ideal", choices=("ideal", "field"))
    ap.add_argument("--randomize-light", type=int, default=None, metavar="SEED")
    ap.add_argument(
        "--rig", default="standard", choices=("standard", "fisheye_only"),
        help="the downward camera's odometry, or the one-camera rig's (the fisheye's)",
    )  # fmt: skip
    args = ap.parse_args(argv)
    if not (args.distance > 0 and args.radius >= 3 and 0 < args.speed <= 2):
        ap.error("--distance > 0, --radius >= 3 m and --speed in (0, 2] m/s")
    cv2.setNumThreads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    lines = [
        f"Path-segment endpoint error, {args.preset} preset, IMU {args.imu}, laps of a {args.radius:g} m "
        f"circle at {args.speed:g} m/s, {args.distance:g} m per terrain (mean +- std, % of length), "
        f"{args.camera_effects} cameras, {args.rig} rig"
        + ("" if args.randomize_light is None else f", light randomised (seed {args.randomize_light})"),
        "",
        "| terrain | yaw | " + " | ".join(f"{L:g} m" for L in LENGTHS) + " |",
        "|---|---|" + "---:|" * len(LENGTHS),
    ]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(args.terrains), figsize=(5 * len(args.terrains), 5), squeeze=False)
    for ax, name in zip(axes[0], args.terrains, strict=True):
        # each terrain its own light from the seed, whichever terrains are run
        rng = None
        if args.randomize_light is not None:
            rng = np.random.default_rng([args.randomize_light, list(TERRAINS).index(name)])
        light = None if rng is None else WorldDraw.draw(RandomizeConfig(), rng, 0)
        if light is not None:
            lines.insert(
                1,
                f"- {name}: sun at {light.sun_elevation_deg:.0f} deg elevation, "
                f"{light.sun_azimuth_deg:.0f} deg azimuth, haze {light.sun_transmission:.2f}, "
                f"sky light {light.ambient:.2f}",
            )
        run = drive(
            TERRAINS[name],
            args.imu,
            args.distance,
            args.radius,
            args.speed,
            args.preset,
            args.camera_effects == "field",
            light,
            args.rig,
        )
        odo, imu = paths(run)
        for label, est in (("odometry", odo), ("IMU", imu)):
            cells = []
            for e in path_segment_errors(run["truth"], est, LENGTHS):
                cells.append(
                    "-"
                    if e.count == 0
                    else f"{e.mean:.2f} +- {e.std:.2f} m ({100 * e.mean / e.length:.1f} %)"
                )
            lines.append(f"| {name} | {label} | " + " | ".join(cells) + " |")
            print(lines[-1], flush=True)
        ax.plot(run["truth"][:, 0], run["truth"][:, 1], "k", lw=1, label="truth")
        ax.plot(odo[:, 0], odo[:, 1], lw=1, label="odometry yaw")
        ax.plot(imu[:, 0], imu[:, 1], lw=1, label="IMU yaw")
        ax.set_title(f"{name} ({TERRAINS[name]})")
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend()
    (out / "table1.md").write_text("\n".join(lines) + "\n")
    fig.tight_layout()
    fig.savefig(out / "table1_paths.png", dpi=100)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

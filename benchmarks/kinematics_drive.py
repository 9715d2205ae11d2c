"""The fisheye kinematics estimator on rendered frames of a steady turn, against the simulator.

For each speed: the rover turns (lambda_F = -lambda_R), the fisheye is captured at its rate and
every frame goes through :class:`KinematicStateEstimator`, on one thread. Prints roll and
steering MAE, wheel-rate RMS error per wheel (share of the true rate over each frame interval,
which is what the estimate measures), rotation drift at the end, the share of valid degrees of
freedom and the estimator's milliseconds per frame, median and mean (CPU time of its thread,
which a busy shared machine disturbs less than the wall clock; rendering is not counted).
The drive is rendered first and the timed estimator runs over the recorded frames, as on a
camera log; the last column is a second estimator's median time inside the render loop, where
the renderer evicts the estimator's data from the caches between frames.

Run: python benchmarks/kinematics_drive.py [--speeds 0.5 1 2] [--seconds 3] [--preset full]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one thread, before numpy loads

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from perception.kinematics.fisheye import KinematicStateEstimator  # noqa: E402
from rover_env.config.cameras import FisheyeCameraConfig  # noqa: E402
from rover_env.config.scenario import FrictionMapConfig, ScenarioConfig, SunConfig, TerrainConfig  # noqa: E402
from rover_env.sensors.cameras import FisheyeCamera  # noqa: E402
from rover_env.sim.simulation import RoverSim  # noqa: E402
from rover_env.task.course import CourseConfig  # noqa: E402


def drive(speed: float, seconds: float, preset: str, steer: float, sun_elevation: float) -> dict:
    scenario = ScenarioConfig(
        name="kinematics_turn",
        course=CourseConfig(waypoints=((10.0, 10.0),)),
        terrain=TerrainConfig(size=(60.0, 60.0), texture="regolith"),
        friction=FrictionMapConfig(default_mu=1.0),
        sun=SunConfig(azimuth_deg=180.0, elevation_deg=sun_elevation),
    )
    sim = RoverSim(scenario)
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        cam = FisheyeCamera(sim, FisheyeCameraConfig.preset(preset))
        est = KinematicStateEstimator(cam.model, g.kinematic_model(cam.T_body_cam))
        sim.rover.command(g.drive.wheel_speeds(speed, steer, -steer) / g.wheel_radius, steer, -steer)
        sim.step(1.0)
        # the drive is rendered and recorded first, with a second estimator in the render loop
        # (whose caches the renderer flushes between frames)
        frames, truth, live = [], [], []
        live_est = KinematicStateEstimator(cam.model, g.kinematic_model(cam.T_body_cam))
        for _ in range(int(round(seconds / cam.period)) + 1):
            frame = cam.capture()
            frames.append((frame.image, frame.t))
            truth.append(sim.ground_truth())
            t0 = time.thread_time()
            live_est.update(frame.image, frame.t)
            live.append(time.thread_time() - t0)
            sim.step(cam.period)
        # then the estimator runs over the recording, as on a camera log
        rows, spent, theta0, last = [], [], None, None
        for (image, t), gt in zip(frames, truth, strict=True):
            t0 = time.thread_time()
            s = est.update(image, t)
            spent.append(time.thread_time() - t0)
            if theta0 is None:
                theta0 = (s.theta.copy(), gt.wheel_angle.copy())
            # the true rate over the frame interval (the estimate is the rotation since the last frame)
            rate = (gt.wheel_angle - last[0]) / (t - last[1]) if last else gt.wheel_rate
            last = (gt.wheel_angle.copy(), t)
            rows.append(
                np.r_[
                    s.psi - gt.axle_roll,
                    s.lam - gt.steering,
                    s.theta_dot - rate,
                    (s.theta - theta0[0]) - (gt.wheel_angle - theta0[1]),
                    rate,
                    [s.quality],
                ]
            )
    finally:
        sim.close()
    R = np.array(rows)[1:]  # the first frame has no rotation yet
    rate = np.abs(R[:, 12:16]).mean(axis=0)
    return dict(
        psi_mae=np.degrees(np.abs(R[:, 0:2]).mean(axis=0)),
        lam_mae=np.degrees(np.abs(R[:, 2:4]).mean(axis=0)),
        rate_rms=100 * np.sqrt((R[:, 4:8] ** 2).mean(axis=0)) / rate,
        drift=np.abs(R[-1, 8:12]),
        valid=float(R[:, 16].mean()),
        ms=(1e3 * float(np.median(spent)), 1e3 * float(np.mean(spent))),
        ms_live=1e3 * float(np.median(live)),
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="[m/s]")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--preset", default="full", choices=("full", "half", "train"))
    ap.add_argument("--steer", type=float, default=8.6, help="axle steering [deg]")
    ap.add_argument("--sun-elevation", type=float, default=45.0, help="[deg], behind the rover")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    print(
        "| speed | psi MAE F/R [deg] | lambda MAE F/R [deg] | wheel-rate RMS err FL/FR/RL/RR [%] | "
        "theta drift FL/FR/RL/RR [rad] | DOF valid | ms/frame median / mean | ms/frame in the render loop |"
    )
    print("|---|---|---|---|---|---:|---:|---:|")
    for v in args.speeds:
        r = drive(v, args.seconds, args.preset, math.radians(args.steer), args.sun_elevation)

        def fmt(a, p):
            return " / ".join(f"{x:.{p}f}" for x in a)

        print(
            f"| {v:g} m/s | {fmt(r['psi_mae'], 3)} | {fmt(r['lam_mae'], 3)} | {fmt(r['rate_rms'], 1)} | "
            f"{fmt(r['drift'], 3)} | {100 * r['valid']:.0f} % | {fmt(r['ms'], 1)} | {r['ms_live']:.1f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

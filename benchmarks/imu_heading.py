"""Dead reckoning after a steady circle with and without an IMU: heading and position error.

For each IMU choice and seed, ``--env`` (estimated observations, ``--preset``) drives a constant
command (speed 0.25 of v_max, steering +-0.5: about 0.5 m/s on a 2 m radius) for ``--seconds``;
the dead-reckoned pose (``info["estimate"]["odometry_pose"]``) is compared with the truth at the
end. Heading errors are net of the start fix's own yaw error; position errors are given as a
share of the distance driven.

Run: python benchmarks/imu_heading.py [--env RoverRoughSlippery-v0] [--seconds 30] [--seeds 0 1]
"""

from __future__ import annotations

import argparse
import math

import cv2
import gymnasium as gym
import numpy as np

import rover_env  # noqa: F401  (registers the missions)
from rover_env.sim.simulation import quat_to_yaw

ACTION = np.array([0.25, 0.5, -0.5], dtype=np.float32)


def drive(env_id: str, preset: str, imu: str | None, seed: int, seconds: float) -> dict:
    """Heading error [deg], position error [m] and distance [m] after the circle."""
    env = gym.make(env_id, obs_source="estimated", preset=preset, imu=imu)
    try:
        _, info = env.reset(seed=seed)
        yaw0 = info["estimate"]["odometry_pose"][2] - quat_to_yaw(info["ground_truth"]["pose"][3:])
        prev = info["ground_truth"]["pose"][:2].copy()
        dist = 0.0
        for _ in range(int(round(seconds * env.unwrapped.control_hz))):
            _, _, term, trunc, info = env.step(ACTION)
            p = info["ground_truth"]["pose"]
            dist += float(np.linalg.norm(p[:2] - prev))
            prev = p[:2].copy()
            if term or trunc:
                break
        est, gt = info["estimate"]["odometry_pose"], info["ground_truth"]["pose"]
        yaw_err = math.remainder(est[2] - quat_to_yaw(gt[3:]) - yaw0, 2 * math.pi)
        return {"yaw": math.degrees(yaw_err), "pos": float(np.linalg.norm(est[:2] - gt[:2])), "dist": dist}
    finally:
        env.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="RoverRoughSlippery-v0")
    ap.add_argument("--preset", default="train", choices=("train", "eval"))
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--imus", nargs="+", default=["none", "bmi088", "tactical"])
    args = ap.parse_args(argv)
    if not (0 < args.seconds <= 600):
        ap.error("--seconds: give a duration in (0, 600]")
    cv2.setNumThreads(1)
    print(f"{args.env}, preset {args.preset}, {args.seconds:g} s circle, seeds {args.seeds}")
    print("| IMU | seed | heading error [deg] | position error [m] | share of distance |")
    print("|---|---:|---:|---:|---:|")
    for imu in args.imus:
        for seed in args.seeds:
            r = drive(args.env, args.preset, None if imu == "none" else imu, seed, args.seconds)
            share = 100 * r["pos"] / r["dist"]
            print(f"| {imu} | {seed} | {r['yaw']:+.2f} | {r['pos']:.2f} | {share:.1f} % |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

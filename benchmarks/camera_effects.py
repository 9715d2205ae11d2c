"""Field cameras against ideal ones, side by side in one run: time per step and the estimators' errors.

The same scripted drive (constant speed and steering) runs with ``camera_effects="ideal"``,
with ``"field"`` and its motion blur off (noise, auto-exposure, vignetting, gamma only), and
with ``"field"`` in full; the physics is the same in all three. Prints, per variant, the wall
time per step (one thread: ``LP_NUM_THREADS=1``, OpenCV's threads 1) and the MAE of the
observation's twist, wheel rates and axle roll against the truth, after the first second.

Run: ``LP_NUM_THREADS=1 python benchmarks/camera_effects.py [--env RoverShadows-v0] [--seed 1]
[--steps 300] [--speed 0.8] [--preset train]``
"""

from __future__ import annotations

import argparse
import time

import cv2
import gymnasium as gym
import numpy as np

import rover_env
from rover_env.tools.estimator_metrics import EstimateLog, field_errors

FIELDS = ("v_x", "omega", "wheel_rate_FL", "wheel_rate_FR", "wheel_rate_RL", "wheel_rate_RR", "axle_roll_F")


def run(env_id: str, variant: str, seed: int, steps: int, speed: float, preset: str) -> tuple[float, dict]:
    env = gym.make(
        env_id, camera_effects="ideal" if variant == "ideal" else "field", preset=preset, renderer="gl"
    )
    try:
        if variant == "field, no blur":
            for cam in env.unwrapped.pipeline.cameras:
                cam._motion = None
        obs, info = env.reset(seed=seed)
        log = EstimateLog(env.unwrapped.geometry.wheel_radius)
        action = np.array([speed / env.unwrapped.v_max, 0.1, 0.0], np.float32)
        wall = time.perf_counter()
        for _ in range(steps):
            obs, _, term, trunc, info = env.step(action)
            log.add(obs, info)
            if term or trunc:
                break
        wall = (time.perf_counter() - wall) / len(log.t)
        errors = field_errors([log.arrays(env.unwrapped.pipeline.fisheye.period)])
    finally:
        env.close()
    return wall, {k: errors[k][0] for k in FIELDS}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="RoverShadows-v0", choices=rover_env.ENV_IDS)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--speed", type=float, default=0.8, help="[m/s]")
    ap.add_argument("--preset", default="train", choices=("train", "eval"))
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    print(f"{args.env}, preset {args.preset}, GL, seed {args.seed}, {args.steps} steps at {args.speed} m/s\n")
    print("| variant | ms a step | " + " | ".join(f"{f} MAE" for f in FIELDS) + " |")
    print("|---|---:|" + "---:|" * len(FIELDS))
    for variant in ("ideal", "field, no blur", "field"):
        wall, err = run(args.env, variant, args.seed, args.steps, args.speed, args.preset)
        print(
            f"| {variant} | {1e3 * wall:.1f} | " + " | ".join(f"{err[f]:.4f}" for f in FIELDS) + " |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

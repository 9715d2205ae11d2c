"""Field cameras against ideal ones, side by side in one run: time per step and the estimators' errors.

The same scripted drive (constant speed and steering) runs with ``camera_effects="ideal"``,
with ``"field"`` and its motion blur off (noise, auto-exposure, vignetting, gamma only), and
with ``"field"`` in full; the physics is the same in all three. The three environments step in
turn, in one process, so that the machine's drift touches all alike. Prints, per variant, the
median wall time per step (one thread: ``LP_NUM_THREADS=1``, OpenCV's threads 1) and the MAE
of the observation's twist, wheel rates and axle roll against the truth, after the first
second, and the field cameras' cost against the ideal ones.

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


VARIANTS = ("ideal", "field, no blur", "field")


def run(env_id: str, seed: int, steps: int, speed: float, preset: str) -> dict[str, tuple[float, dict]]:
    """Each variant's median wall time per step [s] and its errors, the variants stepped in turn.

    One environment per variant, all in this process; each step of the drive is taken by every
    variant before the next, so that the machine's drift touches all alike.
    """
    envs = {
        v: gym.make(env_id, camera_effects="ideal" if v == "ideal" else "field", preset=preset, renderer="gl")
        for v in VARIANTS
    }
    try:
        for cam in envs["field, no blur"].unwrapped.pipeline.cameras:
            cam._motion = None
        logs, walls = {}, {v: [] for v in VARIANTS}
        for v, env in envs.items():
            env.reset(seed=seed)
            logs[v] = EstimateLog(env.unwrapped.geometry.wheel_radius)
        action = np.array([speed / envs["ideal"].unwrapped.v_max, 0.1, 0.0], np.float32)
        done = set()
        for _ in range(steps):
            for v, env in envs.items():
                if v in done:
                    continue
                t0 = time.perf_counter()
                obs, _, term, trunc, info = env.step(action)
                walls[v].append(time.perf_counter() - t0)
                logs[v].add(info, env.unwrapped.estimate_values or {})
                if term or trunc:
                    done.add(v)
        out = {}
        for v, env in envs.items():
            errors = field_errors([logs[v].arrays(env.unwrapped.pipeline.fisheye.period)])
            out[v] = (float(np.median(walls[v])), {k: errors[k][0] for k in FIELDS})
        return out
    finally:
        for env in envs.values():
            env.close()


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
    results = run(args.env, args.seed, args.steps, args.speed, args.preset)
    for variant, (wall, err) in results.items():
        print(f"| {variant} | {1e3 * wall:.1f} | " + " | ".join(f"{err[f]:.4f}" for f in FIELDS) + " |")
    ideal = results["ideal"][0]
    print(f"\nfield against ideal: {100 * (results['field'][0] / ideal - 1):+.1f} % a step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Perception time per train-preset step, replayed on recorded camera frames, one thread.

A drive with ``obs_source="estimated"`` is recorded once (every sensor message of every step, a
steady turn with a speed ramp, so the wheels turn and the ground moves); the environment's own
:class:`perception.RoverEstimator` (the built-in estimator in the loop) is then reset and fed the
recorded messages step by step, ``--repeat`` times, with ``cv2.setNumThreads(1)``. Each step's
time is split into the odometry (downward frames), the fisheye kinematics and the rest (slip
filter, dead reckoning, the fisheye window request). The figures are medians over steps of the
fastest repeat (a shared machine's load only ever adds time). Replaying the same frames also
checks the estimator is deterministic: every repeat's estimates must equal the live run's.

Run: python benchmarks/perception_speed.py [--envs Rover-v0 RoverRoughSlippery-v0] [--steps 300]
"""

from __future__ import annotations

import argparse
import time

import cv2
import gymnasium as gym
import numpy as np

import rover_env  # noqa: F401  (registers the missions)


def record(env_id: str, preset: str, steps: int, renderer: str) -> tuple:
    """The environment, its estimator's reset and update calls, and the live estimates of ``steps`` steps."""
    env = gym.make(env_id, obs_source="estimated", preset=preset, renderer=renderer)
    est = env.unwrapped.pipeline.estimator  # the built-in perception.RoverEstimator
    log = []
    update, reset = est.update, est.reset

    def keep_reset(start_fix):
        log.append(("reset", np.array(start_fix, dtype=np.float64), 0.0, None))
        return reset(start_fix)

    def keep_update(messages, t):
        out = update(messages, t)
        log.append(("step", list(messages), t, _values(out)))
        return out

    est.update, est.reset = keep_update, keep_reset  # instance attributes shadow the methods
    try:
        env.reset(seed=0)
        for k in range(steps):
            ramp = min(1.0, 0.2 + k / 60)  # 0.4 -> 2 m/s: 3.5 -> 17 rad/s wheel rates
            env.step(np.array([ramp, 0.15, -0.15], dtype=np.float32))
    finally:
        del est.update, est.reset
    return env, log


def _values(est: dict) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(est[k], dtype=np.float64)) for k in sorted(est)])


def replay(est, log) -> tuple[np.ndarray, bool]:
    """Per step (odometry, kinematics, total) [ms], and whether every estimate matched the live run."""
    clocks = {"odometry": 0.0, "kinematics": 0.0}
    odo, kin = est.odometry.update, est.kinematics.update

    def timed(name, fn):
        def run(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                clocks[name] += time.perf_counter() - t0

        return run

    est.odometry.update, est.kinematics.update = timed("odometry", odo), timed("kinematics", kin)
    rows, same = [], True
    try:
        for kind, payload, t, live in log:
            if kind == "reset":
                est.reset(payload)
                continue
            clocks["odometry"] = clocks["kinematics"] = 0.0
            t0 = time.perf_counter()
            out = est.update(payload, t)
            total = time.perf_counter() - t0
            same &= bool(np.array_equal(_values(out), live, equal_nan=True))
            rows.append((clocks["odometry"], clocks["kinematics"], total))
    finally:
        del est.odometry.update, est.kinematics.update
    return np.asarray(rows) * 1e3, same


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0"])
    ap.add_argument("--preset", default="train", choices=("train", "eval"))
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--renderer", default="auto", choices=("auto", "gl", "tiny"))
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    print(f"{args.preset} preset, {args.steps} steps replayed {args.repeat} times, one thread")
    cols = ("mission", "odometry ms/step", "kinematics ms/step", "rest ms/step", "perception ms/step")
    print("| " + " | ".join(cols + ("p90", "same estimates")) + " |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for env_id in args.envs:
        env, log = record(env_id, args.preset, args.steps, args.renderer)
        try:
            runs = [replay(env.unwrapped.pipeline.estimator, log) for _ in range(args.repeat)]
        finally:
            env.close()
        best = min(runs, key=lambda r: float(np.median(r[0][:, 2])))[0]
        odo, kin, tot = (float(np.median(best[:, i])) for i in range(3))
        # the rest is measured per step, not as a difference of medians
        rest = float(np.median(best[:, 2] - best[:, 0] - best[:, 1]))
        p90 = float(np.percentile(best[:, 2], 90))
        same = all(r[1] for r in runs)
        same_s = "yes" if same else "NO"
        print(f"| {env_id} | {odo:.2f} | {kin:.2f} | {rest:.2f} | {tot:.2f} | {p90:.2f} | {same_s} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

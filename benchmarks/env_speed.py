"""Environment steps per second per core, with the estimator in the loop, and where the time goes.

For each registered mission and preset, one process drives it with ``obs_source="estimated"`` (a steady turn)
and splits each step's wall-clock time into physics, rendering (both cameras at their rates) and
perception (odometry, fisheye kinematics, slip filter), from the pipeline's own clocks; the rest
is the environment's bookkeeping. A ground-truth run of the same drive gives the physics-only
rate. Real-time factor = simulated seconds per wall-clock second (control at 30 Hz).

Each figure is the median of ``--repeat`` runs (a shared machine's load changes between runs).

Each preset is run with each renderer (``--renderers tiny gl``) in the same process, one after
the other, so the two are compared under the same load. Run it with ``LP_NUM_THREADS=1`` so that
Mesa's llvmpipe rasterises on one core (one environment per core).

Run: LP_NUM_THREADS=1 python benchmarks/env_speed.py [--steps 150] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import gymnasium as gym
import numpy as np

import rover_env

ACTION = np.array([0.5, 0.1, -0.1], dtype=np.float32)


def run(
    env_id: str, obs_source: str, preset: str, steps: int, renderer: str = "gl", after_warmup=None, **kwargs
) -> dict:
    """Milliseconds per step (``ms``), real-time factor, the pipeline's split (``parts``) of one drive.

    ``after_warmup``: called with no arguments once the warm-up steps are done (a caller's own
    clocks start there). ``kwargs`` go to ``gym.make`` (``rig="fisheye_only"``, ``imu="bmi088"``, ...).
    """
    env = gym.make(env_id, obs_source=obs_source, preset=preset, renderer=renderer, **kwargs)
    try:
        env.reset(seed=0)
        for _ in range(10):  # warm-up
            env.step(ACTION)
        if after_warmup is not None:
            after_warmup()
        pipe = env.unwrapped.pipeline
        before = dict(pipe.timing) if pipe is not None else {}
        frames = dict(pipe.frames) if pipe is not None else {}
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(ACTION)
        wall = time.perf_counter() - t0
        parts = {k: (pipe.timing[k] - before[k]) / steps * 1e3 for k in before} if pipe is not None else {}
        if pipe is not None:
            fisheye = pipe.frames["fisheye"] - frames["fisheye"]
            windowed = (pipe.frames["fisheye_windowed"] - frames["fisheye_windowed"]) / max(fisheye, 1)
        else:
            windowed = float("nan")
        return dict(
            ms=wall / steps * 1e3, rtf=steps * env.unwrapped.control_dt / wall, parts=parts, windowed=windowed
        )
    finally:
        env.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--presets", nargs="+", default=["train", "eval"])
    ap.add_argument("--envs", nargs="+", default=list(rover_env.ENV_IDS))
    ap.add_argument("--renderers", nargs="+", default=["tiny", "gl"], choices=["tiny", "gl"])
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure; the median run is shown")
    args = ap.parse_args(argv)
    if os.environ.get("LP_NUM_THREADS") != "1":
        print("note: run with LP_NUM_THREADS=1 for one core per environment (Mesa llvmpipe)")

    def median_run(env_id, obs_source, preset, steps, renderer="gl"):
        runs = sorted(
            (run(env_id, obs_source, preset, steps, renderer) for _ in range(args.repeat)),
            key=lambda r: r["ms"],
        )
        return runs[len(runs) // 2]

    cv2.setNumThreads(1)
    print(
        "| mission | preset | renderer | steps/s | real-time factor | ms/step | physics | rendering "
        "| perception | other | rendering share | fisheye frames in windows |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for env_id in args.envs:
        gt = median_run(env_id, "ground_truth", "train", args.steps * 10)
        print(
            f"| {env_id} | physics only (ground truth) | - | {1e3 / gt['ms']:.0f} | {gt['rtf']:.1f}x | "
            f"{gt['ms']:.2f} | {gt['ms']:.2f} | - | - | - | - | - |",
            flush=True,
        )
        for preset in args.presets:
            for renderer in args.renderers:
                # TinyRenderer at the eval preset runs at ~0.04x real time: fewer steps
                n = args.steps if renderer == "gl" or preset == "train" else max(10, args.steps // 10)
                r = median_run(env_id, "estimated", preset, n, renderer)
                p = r["parts"]
                other = r["ms"] - sum(p.values())
                print(
                    f"| {env_id} | {preset} | {renderer} | {1e3 / r['ms']:.1f} | {r['rtf']:.2f}x | "
                    f"{r['ms']:.1f} | "
                    f"{p['physics']:.1f} | {p['rendering']:.1f} | {p['perception']:.1f} | {other:.1f} | "
                    f"{100 * p['rendering'] / r['ms']:.0f} % | {100 * r['windowed']:.0f} % |",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

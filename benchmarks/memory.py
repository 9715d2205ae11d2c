"""Resident memory over many resets and steps: resets must reposition bodies, not reload models.

Runs one environment through ``--resets`` episodes of ``--steps / --resets`` steps each (random
actions) and prints the resident set size (RSS, from /proc/self/statm) after the first episode
and at the end, and their difference. The default is the acceptance's 10,000 resets and 100,000
steps with ground-truth observations (physics and resets only); ``--obs-source estimated`` adds
the cameras and estimators (use fewer steps: they render every frame).

Run: python benchmarks/memory.py [--resets 10000] [--steps 100000] [--obs-source ground_truth]
"""

from __future__ import annotations

import argparse
import os
import time

import gymnasium as gym
import numpy as np

import rover_env  # noqa: F401


def rss_mb() -> float:
    """Resident set size of this process [MB]."""
    with open("/proc/self/statm") as f:
        pages = int(f.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="Rover-v0")
    ap.add_argument("--resets", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--obs-source", default="ground_truth", choices=("ground_truth", "estimated"))
    ap.add_argument("--preset", default="train")
    ap.add_argument("--renderer", default="gl", choices=("gl", "tiny"))
    args = ap.parse_args(argv)
    env = gym.make(args.env, obs_source=args.obs_source, preset=args.preset, renderer=args.renderer)
    rng = np.random.default_rng(0)
    per = max(1, args.steps // args.resets)
    t0 = time.perf_counter()
    base = None
    steps = 0
    for ep in range(args.resets):
        env.reset(seed=ep)
        for _ in range(per):
            _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            steps += 1
            if term or trunc:
                break
        if ep == 0:
            base = rss_mb()
        if (ep + 1) % max(1, args.resets // 10) == 0:
            print(
                f"{ep + 1} resets, {steps} steps, RSS {rss_mb():.1f} MB, {time.perf_counter() - t0:.0f} s",
                flush=True,
            )
    end = rss_mb()
    env.close()
    print(
        f"\n{args.env} ({args.obs_source}): {args.resets} resets, {steps} steps: RSS {base:.1f} MB after the "
        f"first episode, {end:.1f} MB at the end, growth {end - base:+.1f} MB (target <= 50 MB)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

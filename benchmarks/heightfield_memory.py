"""Peak memory of a simulation against the size of its rough terrain's heightfield.

Each size runs in a fresh process: ``Rover-v0``'s scenario with a rough terrain of N x N
heightfield points (its 40 m square at a cell of 40 / (N - 1) m), ground-truth observations, one reset
and 30 steps; the process's peak resident set (``ru_maxrss``) is compared with the same run on
flat ground. Prints, per size, the peak and the memory per heightfield point.

Run: python benchmarks/heightfield_memory.py [--points 251 501 1001]
(1001 x 1001 is the largest grid a scenario may ask for: ``rover_env.config.scenario``.)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

_CHILD = r"""
import dataclasses, json, resource, sys
import gymnasium as gym
import numpy as np
import rover_env
n = int(sys.argv[1])
sc = rover_env.load_scenario(rover_env.MISSIONS["Rover-v0"])
if n > 0:  # the mission's 40 m square, at a cell that gives n points a side
    side = sc.terrain.size[0]
    cell = side / (n - 1)
    rough = dataclasses.replace(sc.terrain, kind="rough", size=(side, side), cell=cell, roughness=0.02)
    sc = dataclasses.replace(sc, terrain=rough)
env = gym.make("Rover-v0", scenario=sc, obs_source="ground_truth")
env.reset(seed=0)
for _ in range(30):
    env.step(np.array([0.5, 0.0, 0.0], np.float32))
env.close()
print(json.dumps({"peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def peak_mb(points: int) -> float:
    """Peak RSS [MB] of a process that runs the environment with ``points`` x ``points`` (0: flat)."""
    cmd = [sys.executable, "-c", _CHILD, str(points)]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"{points} x {points} points: the run failed:\n{out.stderr[-2000:]}")
    return float(json.loads(out.stdout.strip().splitlines()[-1])["peak_mb"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, nargs="+", default=[251, 501, 1001], help="points along each side")
    args = ap.parse_args(argv)
    flat = peak_mb(0)
    print(f"flat ground: peak {flat:.0f} MB\n")
    print("| heightfield | points | peak [MB] | above flat [MB] | per point [kB] |")
    print("|---|---:|---:|---:|---:|")
    for n in args.points:
        peak = peak_mb(n)
        per_point = (peak - flat) * 1024 / (n * n)
        print(f"| {n} x {n} | {n * n:,} | {peak:.0f} | {peak - flat:.0f} | {per_point:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

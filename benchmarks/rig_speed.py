"""The one-camera rig's environment step against the two-camera rig's, side by side.

Each round runs one environment in a fresh process per rig, in turn (standard, fisheye_only,
fisheye_only, standard, ...), so both see the same machine load; each process drives ``--steps``
control steps of a steady turn after a warm-up (``benchmarks/env_speed.py``'s ``run``), on one
core (``LP_NUM_THREADS=1``, ``cv2.setNumThreads(1)``). Prints the median milliseconds per step of
each rig, split into physics, rendering and perception, and the one-camera rig's over the
two-camera rig's, per mission.

Run: LP_NUM_THREADS=1 python benchmarks/rig_speed.py [--preset train] [--rounds 5] [--steps 150]
    [--imu bmi088]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]
RIGS = ("standard", "fisheye_only")

PROBE = r"""
import json, sys
sys.path.insert(0, sys.argv[1] + "/benchmarks")
import cv2
cv2.setNumThreads(1)
from env_speed import run
kw = {"rig": sys.argv[4]}
if sys.argv[6] != "none":
    kw["imu"] = sys.argv[6]
print(json.dumps(run(sys.argv[2], "estimated", sys.argv[3], int(sys.argv[5]), "gl", **kw)))
"""


def probe(env_id: str, preset: str, rig: str, steps: int, imu: str | None) -> dict:
    """One fresh process's run of ``env_id`` with ``rig``: its ``run`` result."""
    env = dict(os.environ, LP_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-c", PROBE, str(HERE), env_id, preset, rig, str(steps), imu or "none"]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=HERE, check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{env_id} ({rig}): {out.stderr.strip()[-600:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--envs", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0"])
    ap.add_argument("--preset", default="train", choices=["train", "eval"])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--imu", default=None, help="an IMU preset on both rigs (default: none)")
    args = ap.parse_args(argv)
    print(
        f"preset {args.preset}, {args.rounds} rounds of {args.steps} steps, OpenGL, one core per process"
        + (f", IMU {args.imu}" if args.imu else "")
        + "\n"
    )
    print(
        "| mission | rig | ms/step | physics | rendering | perception | real-time factor "
        "| one camera / two cameras |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for env_id in args.envs:
        runs: dict[str, list[dict]] = {r: [] for r in RIGS}
        for k in range(args.rounds):
            order = RIGS if k % 2 == 0 else RIGS[::-1]
            for rig in order:
                runs[rig].append(probe(env_id, args.preset, rig, args.steps, args.imu))
        med = {r: statistics.median(x["ms"] for x in runs[r]) for r in RIGS}
        for rig in RIGS:
            parts = {
                p: statistics.median(x["parts"][p] for x in runs[rig])
                for p in ("physics", "rendering", "perception")
            }
            rtf = statistics.median(x["rtf"] for x in runs[rig])
            ratio = f"{med['fisheye_only'] / med['standard']:.3f}" if rig == "fisheye_only" else ""
            print(
                f"| {env_id} | {rig} | {med[rig]:.1f} | {parts['physics']:.1f} | {parts['rendering']:.1f} "
                f"| {parts['perception']:.1f} | {rtf:.2f}x | {ratio} |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

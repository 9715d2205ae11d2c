"""The one-camera rig's environment step against the two-camera rig's, side by side.

Each round runs one environment in a fresh process per rig, in turn (standard, fisheye_only,
fisheye_only, standard, ...), so both see the same machine load; each process drives ``--steps``
control steps of a steady turn after a warm-up (``benchmarks/env_speed.py``'s ``run``), on one
core (``LP_NUM_THREADS=1``, ``cv2.setNumThreads(1)``). Prints the median milliseconds per step of
each rig, split into physics, rendering and perception, and the one-camera rig's over the
two-camera rig's, per mission.

With ``--stages`` it also prints where each rig's time goes: the milliseconds per step of the
fisheye's and the downward camera's rendering (the GL rasteriser's own work, waited for before
the read-back, and the exposure's motion blur within them) and of each estimator (the fisheye's
and the downward camera's odometry, the fisheye kinematics), each function timed in place.

Run: LP_NUM_THREADS=1 python benchmarks/rig_speed.py [--preset train] [--rounds 5] [--steps 150]
    [--imu bmi088] [--stages]
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
import json, sys, time
sys.path.insert(0, sys.argv[1] + "/benchmarks")
import cv2
cv2.setNumThreads(1)
from env_speed import run
kw = {"rig": sys.argv[4]}
if sys.argv[6] != "none":
    kw["imu"] = sys.argv[6]
clock = {}
if sys.argv[7] == "stages":
    import moderngl
    import perception.fisheye_kinematics as fk
    import perception.fisheye_odometry as fo
    import perception.odometry as od
    import rover_env.rendering.gl as gl
    import rover_env.sensors.cameras as cams

    def timed(owner, name, key, before=None):
        f = getattr(owner, name)
        clock[key] = 0.0

        def g(*a, **k):
            t = time.perf_counter()
            if before is not None:
                before(*a)
            out = f(*a, **k)
            clock[key] += time.perf_counter() - t
            return out

        setattr(owner, name, g)

    timed(gl.GLRenderer, "_render_fisheye", "fisheye rendering")
    timed(gl.GLRenderer, "_render_K", "downward rendering")
    # the rasteriser's own work: llvmpipe draws when the read-back waits for it
    timed(moderngl.Framebuffer, "read", "  GL rasteriser (both cameras)", before=lambda fbo: fbo.ctx.finish())
    timed(cams, "blur", "  motion blur (both cameras)")
    timed(fo.FisheyeOdometry, "update", "fisheye odometry")
    timed(od.FlowOdometry, "update", "downward odometry")
    timed(fk.KinematicStateEstimator, "update", "fisheye kinematics")
def restart():
    clock.update(dict.fromkeys(clock, 0.0))
r = run(sys.argv[2], "estimated", sys.argv[3], int(sys.argv[5]), "gl", after_warmup=restart, **kw)
r["stages"] = {k: v / int(sys.argv[5]) * 1e3 for k, v in clock.items()}
print(json.dumps(r))
"""


def probe(env_id: str, preset: str, rig: str, steps: int, imu: str | None, stages: bool = False) -> dict:
    """One fresh process's run of ``env_id`` with ``rig``: its ``run`` result (and ``stages`` [ms/step])."""
    env = dict(os.environ, LP_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-c", PROBE, str(HERE), env_id, preset, rig, str(steps), imu or "none"]
    cmd.append("stages" if stages else "plain")
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
    ap.add_argument("--stages", action="store_true", help="also time the rendering and each estimator")
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
    stages: dict[str, dict[str, list[dict]]] = {}
    for env_id in args.envs:
        runs: dict[str, list[dict]] = {r: [] for r in RIGS}
        for k in range(args.rounds):
            order = RIGS if k % 2 == 0 else RIGS[::-1]
            for rig in order:
                runs[rig].append(probe(env_id, args.preset, rig, args.steps, args.imu, args.stages))
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
        if args.stages:
            stages[env_id] = {r: x for r, x in runs.items()}
    if args.stages:
        print("\nWhere the time goes [ms/step, medians; indented: part of the rendering above]\n")
        names = list(next(iter(stages.values()))["standard"][0]["stages"])
        print("| stage | " + " | ".join(f"{e} {r}" for e in stages for r in RIGS) + " |")
        print("|---|" + "---:|" * (len(stages) * len(RIGS)))
        for name in names:
            cells = [
                f"{statistics.median(x['stages'][name] for x in stages[e][r]):.2f}"
                for e in stages
                for r in RIGS
            ]
            print(f"| {name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

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
and the downward camera's odometry, within the fisheye's the OpenCV calls it makes, the fisheye
kinematics), each function timed in place.

With ``--floor`` two more one-camera runs join each round, to find how fast the fisheye odometry
would have to be: the one-camera step with the odometry's work left out (its ``update`` returns
at once), as the rig is and with a leaner split of the ground's views (a 30-degree disc about the
body's -z and four sectors beyond it, each view aimed at its middle: fewer rendered pixels for
the same fisheye pixels) and with the ground's views rendered at 0.8 of the resolution
(``ground_oversample``; the coarsest at which the fisheye odometry's yaw error rose by no more
than a tenth), and with both. The two-camera step less each is what the odometry may cost.

Run: LP_NUM_THREADS=1 python benchmarks/rig_speed.py [--preset train] [--rounds 5] [--steps 150]
    [--imu bmi088] [--stages] [--floor]
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
#: --floor's one-camera variants: (row label, variant passed to the probe)
FLOOR = (
    ("fisheye_only, no odometry", "no_odometry"),
    ("fisheye_only, lean views, no odometry", "lean_no_odometry"),
    ("fisheye_only, ground at 0.8, no odometry", "coarse_no_odometry"),
    ("fisheye_only, lean views at 0.8, no odometry", "lean_coarse_no_odometry"),
)

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
    import perception.kinematics.fisheye as fk
    import perception.odometry.fisheye as fo
    import perception.odometry.flow as od
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
    # the OpenCV calls of the fisheye odometry (Lucas-Kanade, the corner detector), while it runs
    inside = [False]
    clock["  OpenCV calls (fisheye odometry)"] = 0.0
    for name in ("calcOpticalFlowPyrLK", "goodFeaturesToTrack"):
        def cv_timed(*a, _f=getattr(cv2, name), **k):
            if not inside[0]:
                return _f(*a, **k)
            t = time.perf_counter()
            out = _f(*a, **k)
            clock["  OpenCV calls (fisheye odometry)"] += time.perf_counter() - t
            return out
        setattr(cv2, name, cv_timed)
    fo_update = fo.FisheyeOdometry.update
    def fo_flagged(*a, **k):
        inside[0] = True
        try:
            return fo_update(*a, **k)
        finally:
            inside[0] = False
    fo.FisheyeOdometry.update = fo_flagged
if sys.argv[8] in ("coarse_no_odometry", "lean_coarse_no_odometry"):
    import rover_env.config.rig as rig_config
    rig_config.FISHEYE_ONLY_CAMERA["ground_oversample"] = 0.8  # (the same dict the rig module reads)
if sys.argv[8].endswith("no_odometry"):
    import perception.odometry.fisheye as fo
    fo.FisheyeOdometry.update = lambda self, image, t, **kw: None  # its work left out
if sys.argv[8].startswith("lean_"):
    import numpy as np
    import rover_env.sensors.cameras as cams
    kin_roi = cams._kinematics_roi

    def lean(cfg, g, mount):
        roi = kin_roi(cfg, g, mount)
        if len(roi) < 2:
            return roi
        return (roi[0], *cams.ground_in_parts(cfg, np.array(mount).reshape(4, 4), roi[1]))

    cams._kinematics_roi = lean
def restart():
    clock.update(dict.fromkeys(clock, 0.0))
r = run(sys.argv[2], "estimated", sys.argv[3], int(sys.argv[5]), "gl", after_warmup=restart, **kw)
r["stages"] = {k: v / int(sys.argv[5]) * 1e3 for k, v in clock.items()}
print(json.dumps(r))
"""


def probe(
    env_id: str,
    preset: str,
    rig: str,
    steps: int,
    imu: str | None,
    stages: bool = False,
    variant: str = "as_is",
) -> dict:
    """One fresh process's run of ``env_id`` with ``rig``: its ``run`` result (and ``stages`` [ms/step]).

    ``variant``: ``as_is``, or one of :data:`FLOOR`'s.
    """
    env = dict(os.environ, LP_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-c", PROBE, str(HERE), env_id, preset, rig, str(steps), imu or "none"]
    cmd += ["stages" if stages else "plain", variant]
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
    ap.add_argument(
        "--floor",
        action="store_true",
        help="also run the one-camera rig without its odometry (see the docstring)",
    )
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
    rows = [(r, r, "as_is") for r in RIGS] + (
        [(label, "fisheye_only", v) for label, v in FLOOR] if args.floor else []
    )
    floors: dict[str, dict[str, float]] = {}
    for env_id in args.envs:
        runs: dict[str, list[dict]] = {label: [] for label, _, _ in rows}
        for k in range(args.rounds):
            order = rows if k % 2 == 0 else rows[::-1]
            for label, rig, variant in order:
                stages_k = args.stages and variant == "as_is"
                runs[label].append(probe(env_id, args.preset, rig, args.steps, args.imu, stages_k, variant))
        med = {label: statistics.median(x["ms"] for x in runs[label]) for label, _, _ in rows}
        floors[env_id] = med
        for label, _, _ in rows:
            parts = {
                p: statistics.median(x["parts"][p] for x in runs[label])
                for p in ("physics", "rendering", "perception")
            }
            rtf = statistics.median(x["rtf"] for x in runs[label])
            ratio = f"{med[label] / med['standard']:.3f}" if label != "standard" else ""
            print(
                f"| {env_id} | {label} | {med[label]:.1f} | {parts['physics']:.1f} "
                f"| {parts['rendering']:.1f} | {parts['perception']:.1f} | {rtf:.2f}x | {ratio} |",
                flush=True,
            )
        if args.stages:
            stages[env_id] = {r: runs[r] for r in RIGS}
    if args.floor:
        print(
            "\nWhat the fisheye odometry may cost for the one-camera step to be no slower [ms/step]: "
            "the two-camera step less the one-camera step without the odometry\n"
        )
        print("| mission | " + " | ".join(label for label, _ in FLOOR) + " |")
        print("|---|" + "---:|" * len(FLOOR))
        for env_id, med in floors.items():
            print(
                f"| {env_id} | "
                + " | ".join(f"{med['standard'] - med[label]:.1f}" for label, _ in FLOOR)
                + " |"
            )
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

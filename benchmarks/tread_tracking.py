"""How often the fisheye loses a wheel's tread, and how well it measures the rate, per setting.

Records the fisheye frames of the slip-accuracy drives (open-loop commands: the frames do not
depend on the estimator) once per mission and seed, then runs the fisheye kinematics estimator
over them with each variant of its settings, side by side:

    LP_NUM_THREADS=1 python benchmarks/tread_tracking.py --seeds 411 412 413 414 415 416 \\
        --envs RoverShadows-v0 --variant static_rate=0

Per mission and variant it prints the share of wheel-frames without a rotation (lost), the
wheel rates' MAE against the truth over the measured ones [rad/s], and the share measured more
than 1 rad/s off. The truth is the simulator's wheel rate at the middle of each frame interval
(a frame pair's rotation is the mean rate over it). The first two frames are left out.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import slip_accuracy as sa  # noqa: E402

import rover_env  # noqa: E402
from perception.kinematics.fisheye import KinematicStateEstimator  # noqa: E402
from rover_env.sensors.rig import builtin_estimator  # noqa: E402
from rover_env.tools.estimator_metrics import FIELDS  # noqa: E402

WHEELS = ("FL", "FR", "RL", "RR")


def record(env_id: str, seed: int, preset: str, camera_effects: str) -> dict:
    """The fisheye frames given to the estimator on one drive, its set-up and the true wheel rates."""
    factory = builtin_estimator(preset)
    rec: dict = {"frames": [], "t": [], "zero": None}

    def make(rig):
        est = factory(rig)
        kin = est.kinematics
        rec["setup"] = (kin.camera, kin.model, kin.config, kin.calibration, kin.gamma, kin.bayer)
        update, zero = kin.update, kin.zero_steering

        def on_update(image, t):
            rec["frames"].append(np.array(image, copy=True))
            rec["t"].append(t)
            return update(image, t)

        def on_zero(image):
            rec["zero"] = len(rec["frames"])  # before the frame of this index is given
            return zero(image)

        kin.update, kin.zero_steering = on_update, on_zero
        return est

    span = sa.patch_span(env_id)
    run = sa.drive(
        seed,
        preset,
        env_id,
        span,
        20.0,
        0.05,
        "gl",
        None,
        {"camera_effects": camera_effects, "estimator": make},
    )
    cols = [FIELDS.index(f"wheel_rate_{w}") for w in WHEELS]
    rec["truth_t"], rec["truth_rate"] = run["t"], run["tru"][:, cols]
    return rec


def measure(rec: dict, changes: dict) -> tuple[np.ndarray, np.ndarray]:
    """(lost, error) per wheel-frame of ``rec`` with the kinematics settings ``changes`` (NaN: lost)."""
    camera, model, config, calibration, gamma, bayer = rec["setup"]
    config = dataclasses.replace(config, **changes)
    est = KinematicStateEstimator(camera, model, config, calibration, gamma, bayer)
    lost, err = [], []
    prev = None
    for k, (img, t) in enumerate(zip(rec["frames"], rec["t"], strict=True)):
        if rec["zero"] == k:
            est.zero_steering(img)
        s = est.update(img, t)
        if prev is not None and k >= 2:
            mid = 0.5 * (prev + t)
            truth = np.array([np.interp(mid, rec["truth_t"], rec["truth_rate"][:, j]) for j in range(4)])
            ok = np.array([s.valid[f"theta_{w}"] for w in WHEELS])
            lost.append(~ok)
            err.append(np.where(ok, np.abs(s.theta_dot - truth), np.nan))
        prev = t
    return np.array(lost), np.array(err)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="train", choices=("train", "eval"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[411, 412, 413])
    ap.add_argument("--envs", nargs="+", default=list(rover_env.ENV_IDS), choices=rover_env.ENV_IDS)
    ap.add_argument("--camera-effects", default="field", choices=("ideal", "field"))
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="KEY=VALUE[,KEY=VALUE]",
        help="KinematicsConfig fields of a variant beside the defaults (repeatable)",
    )
    args = ap.parse_args(argv)
    variants = [("defaults", {})]
    for v in args.variant:
        changes = {}
        for item in v.split(","):
            key, _, value = item.partition("=")
            changes[key.strip()] = ast.literal_eval(value.strip())
        variants.append((v, changes))
    cams = args.camera_effects
    print(f"preset {args.preset}, GL, {cams} cameras, seeds {args.seeds}\n")
    print("| mission | variant | wheel-frames | lost | rate MAE [rad/s] | off by > 1 rad/s |")
    print("|---|---|---:|---:|---:|---:|")
    for env_id in args.envs:
        recs = [record(env_id, s, args.preset, cams) for s in args.seeds]
        for name, changes in variants:
            parts = [measure(r, changes) for r in recs]
            lost = np.concatenate([p[0] for p in parts]).ravel()
            err = np.concatenate([p[1] for p in parts]).ravel()
            err = err[np.isfinite(err)]
            print(
                f"| {env_id} | {name} | {lost.size} | {100 * lost.mean():.1f} % | {err.mean():.3f} | "
                f"{100 * (err > 1.0).sum() / lost.size:.2f} % |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

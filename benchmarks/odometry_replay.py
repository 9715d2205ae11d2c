"""Record the downward odometry's inputs of one closed-loop mission, then replay them through other
odometry settings, against the truth.

    python benchmarks/odometry_replay.py record --mission Rover-v0 --seed 9 --out rec/flat9.npz
    python benchmarks/odometry_replay.py record --mission RoverSlopeLoose-v0 --seed 6 \\
        --set static_rate=0.1 --out rec/slope6.npz
    python benchmarks/odometry_replay.py replay rec/slope6.npz --variants base static_rate=0.1 \\
        "static_rate=0.1 static_shrink=0"

``record`` runs one ``rover eval`` job (``slip_aware@imu``, field cameras, randomisation on, the
built-in train-preset estimator with ``--set`` odometry fields over its own) and keeps every
frame the estimator's ``FlowOdometry.update`` is given, with its time, ground plane and
gyro rates, and the truth's body twist at every control step (an ``.npz`` of a few tens of
megabytes). ``replay`` rebuilds the mission's estimator for the same seed (its nominal
calibration and odometry configuration), runs a fresh ``FlowOdometry`` per variant over the
recorded frames and prints the valid pairs and the speed and yaw-rate errors of the valid
estimates against the truth's mean over each frame interval, and the median time of an update
(one thread; compare variants of one run only). The frames are those of the
recorded drive: a replay shows what another setting reads on the same images, not how the
mission would have driven with it.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import sys
import time
from pathlib import Path

import cv2
import numpy as np


def _fields(pairs) -> dict:
    out = {}
    for p in pairs:
        key, sep, value = p.partition("=")
        if not sep:
            raise SystemExit(f"--set/--variants: {p!r}; use field=value")
        out[key] = value
    return out


def _value(old, text: str):
    """``text`` as a value of ``old``'s type (a bool from True/False, a tuple or None literally)."""
    if isinstance(old, bool):
        if text not in ("True", "False"):
            raise SystemExit(f"--set/--variants: {text!r}; use True or False")
        return text == "True"
    if isinstance(old, (int, float)):
        return type(old)(text)
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def _typed(config, fields: dict):
    try:
        return dataclasses.replace(config, **{k: _value(getattr(config, k), v) for k, v in fields.items()})
    except AttributeError as e:
        raise SystemExit(f"unknown odometry field: {e}") from None


def record(args) -> int:
    from perception.odometry import flow as od
    from rover_env.envs.rover_env import RoverEnv
    from rover_env.sensors.rig import builtin_estimator
    from rover_env.tools import evaluation

    frames, ts, planes, rates = [], [], [], []
    update = od.FlowOdometry.update

    def spy(self, image, t, ground_plane=None, rate_xy=None):
        frames.append(np.asarray(image).copy())
        ts.append(t)
        planes.append(np.full(3, np.nan) if ground_plane is None else np.asarray(ground_plane, float))
        rates.append(np.full(2, np.nan) if rate_xy is None else np.asarray(rate_xy, float))
        return update(self, image, t, ground_plane, rate_xy)

    gt_t, gt_twist = [], []
    step = RoverEnv.step

    def truth(self, action):
        out = step(self, action)
        gt_t.append(out[4]["t"])
        gt_twist.append(np.asarray(out[4]["ground_truth"]["twist"], float))
        return out

    od.FlowOdometry.update = spy  # type: ignore[method-assign]
    RoverEnv.step = truth  # type: ignore[method-assign]
    overrides = {k: float(v) for k, v in _fields(args.set).items()}
    factory = builtin_estimator("train", odometry_overrides=overrides)
    module = type(sys)("odometry_replay_estimator")
    module.FACTORY = factory  # type: ignore[attr-defined]
    sys.modules[module.__name__] = module
    job = evaluation.EvalJob(
        "slip_aware@imu",
        args.mission,
        args.seed,
        estimator=f"{module.__name__}:FACTORY",
        camera_effects="field",
        randomize="on",
    )
    row = evaluation.run_job(job)
    print(
        f"{args.mission} seed {args.seed} {overrides or 'as built in'}: success {row['success']}, goal error "
        f"{row['goal_error']:.3f} m, v_x MAE {row['est_mae_v_x']:.4f} m/s, 5 m segments "
        f"{row['est_segment_5m_percent']:.2f} %; {len(frames)} frames"
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        args.out,
        mission=args.mission,
        seed=args.seed,
        frames=np.array(frames),
        t=np.array(ts),
        planes=np.array(planes),
        rates=np.array(rates),
        gt_t=np.array(gt_t),
        gt_twist=np.array(gt_twist),
    )
    return 0


def replay(args) -> int:
    import gymnasium as gym

    import rover_env  # noqa: F401
    from perception.odometry.flow import FlowOdometry

    cv2.setNumThreads(1)
    d = np.load(args.recording)
    mission, seed = str(d["mission"]), int(d["seed"])
    env = gym.make(mission, camera_effects="field", preset="train", randomize="on")
    env.reset(seed=seed)
    base = env.unwrapped.pipeline.estimator.odometry
    camera, config = base.camera, base.config
    env.close()
    gt_t, twist = d["gt_t"], d["gt_twist"]

    def truth(t0: float, t1: float) -> tuple[float, float]:
        m = (gt_t > t0 - 1e-9) & (gt_t <= t1 + 1e-9)
        if not m.any():
            mid = 0.5 * (t0 + t1)
            return float(np.interp(mid, gt_t, twist[:, 0])), float(np.interp(mid, gt_t, twist[:, 2]))
        return float(twist[m, 0].mean()), float(twist[m, 2].mean())

    print(f"{mission} seed {seed}, {len(d['t'])} frames")
    print(
        "| variant | valid pairs | v_x bias [m/s] | v_x MAE [m/s] | yaw-rate MAE [rad/s] "
        "| ms a frame (median) |"
    )
    print("|---|---:|---:|---:|---:|---:|")
    for variant in args.variants:
        fields = {} if variant == "base" else _fields(variant.split())
        odo = FlowOdometry(camera, _typed(config, fields))
        errors, pairs, prev, times = [], 0, None, []
        for img, t, plane, rate in zip(d["frames"], d["t"], d["planes"], d["rates"], strict=True):
            plane_or_none = None if np.isnan(plane).any() else plane
            t0 = time.perf_counter()
            est = odo.update(img, float(t), plane_or_none, None if np.isnan(rate).any() else rate)
            times.append(time.perf_counter() - t0)
            if est is not None:
                pairs += 1
                if est.valid:
                    v, w = truth(prev, float(t))
                    errors.append((est.v_x - v, est.omega - w))
            prev = float(t)
        e = np.array(errors).reshape(-1, 2)
        print(
            f"| {variant} | {len(e)}/{pairs} | {e[:, 0].mean():+.4f} | {np.abs(e[:, 0]).mean():.4f} | "
            f"{np.abs(e[:, 1]).mean():.4f} | {1e3 * np.median(times):.2f} |"
        )
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record", help="run one closed-loop mission and keep the odometry's inputs")
    rec.add_argument("--mission", required=True)
    rec.add_argument("--seed", type=int, required=True)
    rec.add_argument("--set", nargs="*", default=[], help="FlowOdometryConfig fields, field=value")
    rec.add_argument("--out", required=True, help="the recording (.npz)")
    rep = sub.add_parser("replay", help="replay a recording through odometry settings")
    rep.add_argument("recording")
    rep.add_argument("--variants", nargs="+", default=["base"], help='"base", or "field=value field=value"')
    args = ap.parse_args(argv)
    return record(args) if args.cmd == "record" else replay(args)


if __name__ == "__main__":
    raise SystemExit(main())

"""The downward odometry's speed bias on a straight drive, per world: the calibration error it meets.

    LP_NUM_THREADS=1 python benchmarks/odometry_scale.py --seeds 6 7 14 15 [--env Rover-v0]

Drives straight at a constant command (``--action``, a share of the top speed) for ``--steps``
control steps and prints, for each camera model and randomisation, the mean of the odometry's
valid v_x estimates against the truth's speed over each frame interval, as a share of the speed,
after the first 2 s. With randomisation on, each seed draws the world and the camera mounts'
errors (the estimator keeps the nominal calibration), so this is the scale error dead reckoning
meets in the randomised closed loop.
"""

from __future__ import annotations

import argparse

import cv2
import gymnasium as gym
import numpy as np

import rover_env
from perception.odometry import flow as od


def bias(
    env_id: str, effects: str, randomize: str, seed: int, steps: int, action: float
) -> tuple[float, int]:
    """Mean (estimate - truth) / truth of the odometry's valid v_x [%], and the estimates counted."""
    estimates: list[tuple[float, float]] = []
    update = od.FlowOdometry.update

    def spy(self, image, t, ground_plane=None, rate_xy=None):
        out = update(self, image, t, ground_plane, rate_xy)
        if out is not None and out.valid:
            estimates.append((t, out.v_x))
        return out

    od.FlowOdometry.update = spy  # type: ignore[method-assign]
    make = {"camera_effects": effects, "preset": "train", "randomize": randomize, "obs_source": "estimated"}
    env = gym.make(env_id, **make)
    try:
        env.reset(seed=seed)
        truth = []
        for _ in range(steps):
            _, _, term, trunc, info = env.step(np.array([action, 0.0, 0.0], np.float32))
            truth.append((info["t"], info["ground_truth"]["twist"][0]))
            if term or trunc:
                break
    finally:
        env.close()
        od.FlowOdometry.update = update  # type: ignore[method-assign]
    gt, est = np.array(truth), np.array(estimates).reshape(-1, 2)
    est = est[est[:, 0] > 2.0]
    # the truth's mean over each frame interval (the control steps within it)
    frame = float(np.median(np.diff(est[:, 0])))
    inside = [(gt[:, 0] > t - frame + 1e-9) & (gt[:, 0] <= t + 1e-9) for t in est[:, 0]]
    true_v = np.array([gt[m, 1].mean() for m in inside])
    return float(100.0 * np.mean(est[:, 1] - true_v) / np.mean(true_v)), len(est)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--env", default="Rover-v0", choices=rover_env.ENV_IDS)
    ap.add_argument("--seeds", type=int, nargs="+", default=[6, 7, 14, 15])
    ap.add_argument("--steps", type=int, default=360)
    ap.add_argument("--action", type=float, default=0.8, help="drive command, a share of the top speed")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    print(f"{args.env}, train preset, straight at {args.action} of the top speed, {args.steps} steps")
    print("| cameras | randomisation | seed | v_x bias [% of speed] | valid estimates |")
    print("|---|---|---:|---:|---:|")
    cases = [("ideal", "off", args.seeds[0]), ("field", "off", args.seeds[0])]
    cases += [("field", "on", s) for s in args.seeds] + [("ideal", "on", s) for s in args.seeds]
    for effects, randomize, seed in cases:
        b, n = bias(args.env, effects, randomize, seed, args.steps, args.action)
        print(f"| {effects} | {randomize} | {seed} | {b:+.2f} | {n} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

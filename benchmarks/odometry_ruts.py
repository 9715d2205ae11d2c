"""The downward odometry on rutted soil: laps of a circle on sand, the later ones over the ruts.

    python benchmarks/odometry_ruts.py [--soil toyoura] [--speed 0.4] [--steer 0.35] [--laps 2]

The rover drives a circle (drive-mode action: constant speed and opposite steering of the two
axles) on a scenario of flat ground covered by one soil patch, with the estimated observation
(train preset, field cameras, the built-in estimator). From its second lap on, the downward
camera looks ahead onto the tracks its wheels left on the first. The drive is run twice: with
the ruts drawn in the images, and with them left out (the renderer's ruts taken away); the
physics is the same (the actions do not depend on the estimates), so the two differ only in
what the camera saw. For each lap it prints the odometry's valid frame pairs and the errors of
the valid ones against the truth's mean over each frame interval: v_x bias and MAE [m/s] and
yaw-rate MAE [rad/s].
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np


def drive(args, draw_ruts: bool) -> tuple[np.ndarray, np.ndarray]:
    """One run: the odometry's estimates (t, valid, v_x, omega) and the truth (t, v_x, omega, yaw)."""
    from perception.odometry import flow as od
    from rover_env.config.scenario import FrictionMapConfig, FrictionPatch, load_scenario
    from rover_env.envs.rover_env import RoverEnv
    from rover_env.rendering import renderer_for
    from rover_env.sim.transforms import quat_to_yaw

    sc = load_scenario("flat_patches")
    patch = FrictionPatch(mu=0.5, center=(0.0, 0.0), size=(30.0, 30.0), soil=args.soil)
    sc = dataclasses.replace(
        sc,
        name="odometry_ruts",
        terrain=dataclasses.replace(sc.terrain, texture="sand"),
        friction=FrictionMapConfig(default_mu=0.8, patches=(patch,)),
        start=dataclasses.replace(sc.start, jitter_position=0.0, jitter_yaw_deg=0.0),
        duration=1e4,
    )
    estimates: list[tuple[float, bool, float, float]] = []
    update = od.FlowOdometry.update

    def spy(self, image, t, ground_plane=None, rate_xy=None):
        est = update(self, image, t, ground_plane, rate_xy)
        if est is not None:
            estimates.append((float(t), bool(est.valid), float(est.v_x), float(est.omega)))
        return est

    od.FlowOdometry.update = spy  # type: ignore[method-assign]
    env = RoverEnv(
        scenario=sc, obs_source="estimated", preset="train", camera_effects="field", randomize="off"
    )
    truth = []
    try:
        env.reset(seed=args.seed)
        if not draw_ruts:
            renderer_for(env.sim).ruts = None
        action = np.array([args.speed / env.v_max, args.steer, -args.steer], np.float32)
        yaw, last = 0.0, None
        while yaw < 2 * math.pi * args.laps:
            _, _, term, trunc, info = env.step(action)
            gt = info["ground_truth"]
            heading = quat_to_yaw(gt["pose"][3:7])
            if last is not None:
                yaw += math.remainder(heading - last, 2 * math.pi)
            last = heading
            truth.append((info["t"], gt["twist"][0], gt["twist"][2], yaw))
            if term or trunc:
                raise RuntimeError(f"the episode ended at {info['t']:.1f} s ({info.get('termination')})")
    finally:
        env.close()
        od.FlowOdometry.update = update  # type: ignore[method-assign]
    return np.array(estimates), np.array(truth)


def table(rows) -> str:
    lines = [
        "| ruts in the images | lap | valid pairs | v_x bias [m/s] | v_x MAE [m/s] | yaw-rate MAE [rad/s] |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r[0]} | {r[1]} | {r[2]}/{r[3]} | {r[4]:+.4f} | {r[5]:.4f} | {r[6]:.4f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--soil", default="toyoura", help="soil preset of the patch")
    ap.add_argument("--speed", type=float, default=0.4, help="body speed [m/s]")
    ap.add_argument("--steer", type=float, default=0.35, help="each axle's steering, a share of its limit")
    ap.add_argument("--laps", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    import cv2

    cv2.setNumThreads(1)
    rows = []
    for draw in (True, False):
        est, truth = drive(args, draw)
        t_gt, v_gt, w_gt, yaw = truth.T
        prev = None
        errs: dict[int, list] = {}
        counts: dict[int, list[int]] = {}
        for t, valid, v, w in est:
            if prev is not None:
                m = (t_gt > prev - 1e-9) & (t_gt <= t + 1e-9)
                lap = int(np.interp(t, t_gt, yaw) // (2 * math.pi)) + 1
                c = counts.setdefault(lap, [0, 0])
                c[1] += 1
                if valid and m.any():
                    c[0] += 1
                    errs.setdefault(lap, []).append((v - v_gt[m].mean(), w - w_gt[m].mean()))
            prev = t
        for lap in sorted(counts):
            if lap > args.laps:
                continue
            e = np.array(errs.get(lap, [(math.nan, math.nan)]))
            rows.append(
                ("drawn" if draw else "left out", lap, counts[lap][0], counts[lap][1], e[:, 0].mean(),
                 np.abs(e[:, 0]).mean(), np.abs(e[:, 1]).mean())
            )  # fmt: skip
        print(table(rows[-len(counts) :]), flush=True)
    print()
    print(f"soil {args.soil}, {args.speed} m/s, steering {args.steer} of the limit, seed {args.seed}:")
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

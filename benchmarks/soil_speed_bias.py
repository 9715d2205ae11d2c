"""The estimated forward speed's bias on soil, in 3 s windows of one closed-loop mission.

Drives a mission on the estimates (train preset, field cameras, no IMU) with a follower and
prints, per 3 s window, the true speed, the estimate's mean signed error, the wheels' sinkage
and the body's roll and pitch. ``--no-grip`` runs the built-in estimator without the slip
filter's zero-slip pseudo-measurements (``SlipConfig(grip_std=0)``): on soil every driven
wheel slips, so a "gripping wheel" prior pulls the speed toward the treads'.

    python benchmarks/soil_speed_bias.py --scenario slope_soil --controller slip_aware --seed 0 [--no-grip]
"""

from __future__ import annotations

import argparse
import functools

import numpy as np

from controllers import PathFollower, SlipAwareController
from perception import RoverEstimator
from perception.fusion.slip import SlipConfig
from rover_env.envs import RoverEnv


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="slope_soil", help="scenario preset or YAML path")
    ap.add_argument("--controller", choices=["slip_unaware", "slip_aware"], default="slip_aware")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-grip", action="store_true", help="no zero-slip pseudo-measurements")
    args = ap.parse_args(argv)
    if args.controller == "slip_unaware":
        cls, mode = PathFollower, "drive"
    else:
        cls, mode = SlipAwareController, "wheels"
    est = functools.partial(RoverEstimator, slip=SlipConfig(grip_std=0.0)) if args.no_grip else None
    env = RoverEnv(scenario=args.scenario, obs_source="estimated", action_mode=mode, estimator=est)
    rows = []
    try:
        controller = cls.for_env(env)
        controller.reset()
        obs, info = env.reset(seed=args.seed)
        while True:
            obs, _, term, trunc, info = env.step(controller.act(obs))
            gt = info["ground_truth"]
            soil = env.unwrapped.sim.rover.soil
            sink = np.asarray(soil.sinkage, float) if soil is not None else np.zeros(4)
            tilt = np.degrees(gt["tilt"])
            rows.append([info["t"], gt["twist"][0], info["estimate"]["twist"][0], *sink, *tilt])
            if term or trunc:
                break
    finally:
        env.close()
    a = np.array(rows)
    t, v_true, v_est = a[:, 0], a[:, 1], a[:, 2]
    print(f"termination: {info['termination']}, {t[-1]:.1f} s\n")
    print(
        "| window [s] | true v_x [m/s] | bias [m/s] | bias [%] | sinkage FL FR RL RR [mm]"
        " | roll, pitch [deg] |"
    )
    print("|---|---:|---:|---:|---|---|")
    for lo in range(0, int(t[-1]) + 1, 3):
        m = (t >= lo) & (t < lo + 3) & (v_true > 0.05)
        if m.sum() < 5:
            continue
        bias = float(np.mean(v_est[m] - v_true[m]))
        sink = " ".join(f"{1e3 * x:.1f}" for x in a[m, 3:7].mean(0))
        print(
            f"| {lo}-{lo + 3} | {v_true[m].mean():.3f} | {bias:+.4f} | {100 * bias / v_true[m].mean():+.1f} |"
            f" {sink} | {a[m, 7].mean():+.1f}, {a[m, 8].mean():+.1f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Slip accuracy of the estimator in the loop on drives that make the wheels slip.

The rover cruises straight over each mission's first low-friction patch (every registered
mission has one on its first leg); on the patch the speed command cycles through full throttle
(the wheels spin: s > 0), a reversed command (they skid and turn backwards: s < 0) and a slow
roll, so that every wheel goes through several slip events. The
environment runs with ``obs_source="estimated"``; the estimate is compared with the simulator's
slip every step (:func:`rover_env.tools.estimator_metrics.slip_metrics`: MAE while |s_true| > 0.1 and
otherwise, F1 and onset latency in fisheye frames of the filter's slip-event detection,
``info["slip"]["events"]``). An event is |s| >= 0.2 for two frames in a row, ending below 0.1, on
a wheel whose tread or ground speed is at least 0.15 m/s (``SlipConfig.event_min_speed``): the
filter's rule, applied to the true slip to label the truth. An estimated event on true slip that
rises above 0.15 but makes no true event (it peaks below 0.2, or stays above it for a single
frame) is neither a match nor a false alarm ("in band"); an estimated event may start up to two
frames after the true excursion it answers has ended (the detector confirms over two frames).

Run: python benchmarks/slip_accuracy.py [--preset eval] [--seeds 201 202 203] [--ramp 0.05]
[--envs Rover-v0 ...] [--camera-effects ideal field] [--imu bmi088] [--rig full] (seeds the
tests never use); one row per mission and camera model (the same seeds and drives for each)
and one for all missions.
With ``--ramp 0`` the speed command steps: the wheels jump by up to 10 rad/s within a frame,
beyond the tread tracker's search, and are lost for several frames.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np

import rover_env
from rover_env.config.imu import IMU_PRESETS
from rover_env.tools.estimator_metrics import EstimateLog, slip_metrics


def patch_span(env_id: str, margin: float = 0.05) -> tuple[float, float]:
    """The x range [m] in which the mission's first low-friction patch crosses the course (y = 0)."""
    patch = rover_env.load_scenario(rover_env.MISSIONS[env_id]).friction.patches[0]
    cx, cy = patch.center
    if patch.shape == "circle" and abs(cy) < patch.radius:
        half = float(np.sqrt(patch.radius**2 - cy**2))
    elif patch.shape == "rect" and patch.yaw_deg == 0.0 and abs(cy) < patch.size[1] / 2:
        half = patch.size[0] / 2
    else:
        raise ValueError(
            f"{env_id}: its first patch {patch} does not cross y = 0 as a circle or an upright rect"
        )
    return cx - half + margin, cx + half - margin


def add_camera_effects(ap: argparse.ArgumentParser) -> None:
    """The ``--camera-effects`` option: one or both camera models, run on the same seeds."""
    ap.add_argument(
        "--camera-effects",
        nargs="+",
        default=["field"],
        choices=("ideal", "field"),
        help="the cameras' images: 'field' (the image sensor model), 'ideal' (as rendered), or both",
    )


def drive(
    seed: int,
    preset: str,
    env_id: str,
    patch_x: tuple[float, float],
    seconds: float,
    ramp: float = 0.0,
    renderer: str = "gl",
    imu: str | None = None,
    make=None,
    setup=None,
) -> dict:
    """One drive over the patch; ``make``: more ``gym.make`` keywords, ``setup(env)``: called before reset."""
    env = gym.make(env_id, obs_source="estimated", preset=preset, renderer=renderer, imu=imu, **(make or {}))
    try:
        if setup is not None:
            setup(env)
        wall = time.perf_counter()
        obs, info = env.reset(seed=seed)
        log = EstimateLog(env.unwrapped.geometry.wheel_radius)
        rng = np.random.default_rng(seed)
        burst = int(rng.integers(15, 25))  # steps per phase
        v = 0.0
        for k in range(int(round(seconds * env.unwrapped.control_hz))):
            x = info["ground_truth"]["pose"][0]
            on_patch = patch_x[0] < x < patch_x[1]
            phase = (k // burst) % 3
            target = 0.4 if not on_patch else (1.0, -0.2, 0.3)[phase]
            # the command ramps like a drive with an acceleration limit (ramp_rate per step)
            v = float(np.clip(target, v - ramp, v + ramp)) if ramp > 0 else target
            obs, _, term, trunc, info = env.step(np.array([v, 0.0, 0.0], np.float32))
            log.add(info, env.unwrapped.estimate_values or {})
            if term or trunc or x > patch_x[1] + 0.5:
                break
        wall = time.perf_counter() - wall
        frame = env.unwrapped.pipeline.fisheye.period
    finally:
        env.close()
    return log.arrays(frame) | {"wall": wall, "steps": k + 1}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="eval", choices=("train", "eval"))
    ap.add_argument("--seeds", type=int, nargs="+", default=[201, 202, 203])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument(
        "--ramp",
        type=float,
        default=0.05,
        help="largest change of the speed action per step (0.05, the default, is 3 m/s^2 at 30 Hz, "
        "a motor controller's acceleration limit; 0: steps, a stress case)",
    )
    ap.add_argument("--envs", nargs="+", default=list(rover_env.ENV_IDS), choices=rover_env.ENV_IDS)
    ap.add_argument("--renderer", default="gl", choices=("gl", "tiny"))
    add_camera_effects(ap)
    ap.add_argument(
        "--imu",
        default=None,
        choices=sorted(IMU_PRESETS),
        help="an IMU on the rover (a preset name; default: none)",
    )
    ap.add_argument(
        "--rig",
        default=None,
        choices=("standard", "fisheye_only", "full"),
        help="a named rig (full: with the BMI088, encoders and motor currents; default: the scenario's)",
    )
    args = ap.parse_args(argv)
    head = f"preset {args.preset}, renderer {args.renderer}, imu {args.imu}, rig {args.rig}"
    print(f"{head}, seeds {args.seeds}, ramp {args.ramp}", flush=True)
    print(
        "| mission | cameras | steps | slip MAE, abs(s) > 0.1 | slip MAE, otherwise | events "
        "| false / in band "
        "| precision | recall | F1 | latency median / max [frames] | within 2 frames |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    every: dict[str, list] = {c: [] for c in args.camera_effects}
    for env_id in args.envs + (["all"] if len(args.envs) > 1 else []):
        for cams in args.camera_effects:
            if env_id == "all":
                runs = every[cams]
            else:
                span = patch_span(env_id)
                make = {"camera_effects": cams} | ({"rig": args.rig} if args.rig else {})
                runs = [
                    drive(
                        s, args.preset, env_id, span, args.seconds, args.ramp, args.renderer, args.imu, make
                    )
                    for s in args.seeds
                ]
                every[cams] += runs
            m = slip_metrics(runs)
            steps = sum(len(r["t"]) for r in runs)
            print(
                f"| {env_id} | {cams} | {steps} | {m['mae_slip']:.3f} ({m['n_slip']} wheel-steps) "
                f"| {m['mae_calm']:.3f} "
                f"| {m['events']} | {m['false']} / {m['in_band']} | {m['precision']:.2f} | {m['recall']:.2f} "
                f"| {m['f1']:.2f} "
                f"| {m['latency_median']:.1f} / {m['latency_max']:.1f} | {100 * m['within_2']:.0f} % |",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Observation errors of the estimator in the loop, per field and mission, and slip accuracy.

For each registered mission (``rover_env.MISSIONS``) and seed, the pure-pursuit controller drives
the course on the *estimated* observation (closed loop); every step, the observation's state
fields are compared with the simulator's ground truth of the same fields. Prints, per mission:

- per field: MAE and 95th percentile of |estimate - truth| (physical units), over the steps after
  the first second (the filters' start-up);
- slip: per-wheel slip-ratio MAE while |s_true| > 0.1 and otherwise (steps where the truth's
  tread or ground speed is at least 5 cm/s), and slip-event detection (hysteresis on |s|:
  on after two frames in a row at 0.2 or more, off below 0.1, labelled alike on both sides):
  precision, recall, F1 over events (an estimated event matches a true one it overlaps or starts
  within two frames of its end) and the
  median and largest onset latency in camera frames, from the truth's first frame at 0.2.

With ``--camera-effects ideal field`` the same seeds run with both camera models and the table
holds both side by side.

Run: python benchmarks/observation_errors.py [--preset eval] [--seeds 101 102] [--seconds 40]
[--camera-effects field] (the seeds are ones the tests never use).
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
from slip_accuracy import add_camera_effects

import rover_env
from controllers.pure_pursuit import PurePursuit
from rover_env.envs import OBS_FIELDS
from rover_env.tools.estimator_metrics import EstimateLog, field_errors, slip_metrics


def run(
    env_id: str, seed: int, preset: str, seconds: float, renderer: str = "gl", make=None, setup=None
) -> dict:
    """One closed-loop drive; ``make``: more ``gym.make`` keywords, ``setup(env)``: called before reset."""
    env = gym.make(env_id, obs_source="estimated", preset=preset, renderer=renderer, **(make or {}))
    try:
        if setup is not None:
            setup(env)
        ctrl = PurePursuit(OBS_FIELDS)
        obs, info = env.reset(seed=seed)
        ctrl.reset()
        log = EstimateLog(env.unwrapped.geometry.wheel_radius)
        steps = int(round(seconds * env.unwrapped.control_hz))
        wall = time.perf_counter()
        for _ in range(steps):
            obs, _, term, trunc, info = env.step(ctrl.act(obs))
            log.add(info, env.unwrapped.estimate_values or {})
            if term or trunc:
                break
        wall = time.perf_counter() - wall
        fisheye_period = env.unwrapped.pipeline.fisheye.period
        timing = env.unwrapped.pipeline.timing
    finally:
        env.close()
    return log.arrays(fisheye_period) | {"wall": wall, "success": bool(info["is_success"]), "timing": timing}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="eval", choices=("train", "eval"))
    ap.add_argument("--missions", nargs="+", default=list(rover_env.ENV_IDS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[101, 102])
    ap.add_argument("--renderer", default="gl", choices=("gl", "tiny"))
    ap.add_argument("--seconds", type=float, default=40.0, help="longest drive per episode [s]")
    add_camera_effects(ap)
    args = ap.parse_args(argv)
    cams = args.camera_effects
    for env_id in args.missions:
        by_cams = {
            c: [
                run(env_id, s, args.preset, args.seconds, args.renderer, make={"camera_effects": c})
                for s in args.seeds
            ]
            for c in cams
        }
        print(
            f"\n### {env_id} ({rover_env.MISSIONS[env_id]}), preset {args.preset}, renderer {args.renderer}"
        )
        print(f"\nseeds {args.seeds}")
        for c, runs in by_cams.items():
            steps = sum(len(r["t"]) for r in runs)
            wall = sum(r["wall"] for r in runs)
            print(
                f"- {c} cameras: {steps} steps, {steps / wall:.1f} steps/s, "
                f"reached the goal {sum(r['success'] for r in runs)} of {len(runs)}"
            )
        print("\n| field | " + " | ".join(f"{c} MAE | {c} p95" for c in cams) + " |")
        print("|---|" + "---:|---:|" * len(cams))
        errors = {c: field_errors(runs) for c, runs in by_cams.items()}
        for name in errors[cams[0]]:
            cells = " | ".join(f"{errors[c][name][0]:.4f} | {errors[c][name][1]:.4f}" for c in cams)
            print(f"| {name} | {cells} |")
        print()
        for c, runs in by_cams.items():
            slip_line(c, slip_metrics(runs))
    return 0


def slip_line(cams: str, m: dict) -> None:
    """Print one camera model's slip figures."""
    print(
        f"{cams} cameras: slip ratio MAE: {m['mae_slip']:.3f} while |s| > 0.1 ({m['n_slip']} wheel-steps), "
        f"{m['mae_calm']:.3f} otherwise; events: {m['events']}, false {m['false']}, in the band "
        f"{m['in_band']}, precision {m['precision']:.2f}, "
        f"recall {m['recall']:.2f}, F1 {m['f1']:.2f}, onset latency median {m['latency_median']:.1f} "
        f"/ max {m['latency_max']:.1f} camera frames ({100 * m['within_2']:.0f} % within 2)"
    )


if __name__ == "__main__":
    raise SystemExit(main())

"""What the built-in estimator sees of the soil: sinkage per wheel, slip on soil, and their cost.

Sinkage (``sinkage``): the rover with the ``full`` rig (BMI088, encoders, currents; field
cameras) crosses level ground of one soil with domain randomisation on (sun, haze, ambient
light, ground texture, camera mounts); in ``wheels`` action mode one axle's wheels turn up to
3.5 times as fast as the other's, the lead changing axle every few seconds, so that the wheels
slip from about -0.7 to 0.7; straight, and turning (the axles steered +-17 deg). Every control
step the estimate's ``sinkage_*`` (reported where its quality reaches 0.3, else absent) is
compared with the simulator's: MAE per wheel over the reported steps, the relative error where
the true sinkage is 10 mm or more, the share of steps reported, and the estimator's time spent
on sinkage per step.

Slip on soil (``slip``): ``benchmarks/slip_accuracy.py``'s drives (full throttle, reverse and a
slow roll over each mission's soil), with the BMI088 on the standard rig and with the ``full``
rig (wheel encoders), scored by ``slip_metrics`` per axle: the front wheels on fresh soil, the
rear ones in the front wheels' ruts.

Run: python benchmarks/soil_estimation.py sinkage [--seeds 701 ... 706] [--presets eval train]
     python benchmarks/soil_estimation.py slip [--seeds 601 ... 620]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np
import yaml

import rover_env
from rover_env.config.io import to_dict
from rover_env.config.scenario import load_scenario

SOILS = ("cmu_testbed_smooth", "toyoura", "lunar_regolith")
WHEELS = ("FL", "FR", "RL", "RR")


def soil_scenario(soil: str, folder: Path) -> Path:
    """A level 80 m square of ``soil`` (the shipped ``flat_patches`` otherwise) as a scenario file."""
    d = to_dict(load_scenario("flat_patches"))
    d["friction"] = {
        "default_mu": 0.7,
        "patches": [{"shape": "rect", "center": [0.0, 0.0], "size": [80.0, 80.0], "mu": 0.5, "soil": soil}],
    }
    d.pop("imu", None)
    d["name"], d["duration"] = f"level_{soil}", 1000.0
    d["terrain"]["size"] = [80.0, 80.0]
    path = folder / f"level_{soil}.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def sinkage_drive(scenario: Path, preset: str, seed: int, turning: bool, steps: int) -> dict:
    """One drive; per step the estimated (NaN: not reported) and true sinkage [m], and timing."""
    env = gym.make(
        "Rover-v0", scenario=str(scenario), preset=preset, rig="full", action_mode="wheels", randomize="on"
    )
    try:
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        ph = rng.uniform(0.0, 2.0 * math.pi, 3)
        est, true = [], []
        for k in range(steps):
            t = k / env.unwrapped.control_hz
            base = 0.25 + 0.1 * math.sin(t / 2.0 + ph[0])
            lead = 1.0 + 2.5 * (0.5 + 0.5 * math.sin(t / 3.0 + ph[1]))
            f, r = (base * lead, base) if math.sin(t / 5.0 + ph[2]) > 0 else (base, base * lead)
            lam = 0.6 * math.sin(t / 2.5) if turning else 0.0
            info = env.step(np.array([f, f, r, r, lam, -lam], dtype=np.float32))[4]
            if k >= 15:  # after the start
                v = env.unwrapped.estimate_values
                est.append([v.get(f"sinkage_{w}", np.nan) for w in WHEELS])
                true.append(info["ground_truth"]["sinkage"])
        timing = env.unwrapped.pipeline.estimator.timing["sinkage"]
    finally:
        env.close()
    return {"est": np.array(est), "true": np.array(true), "sinkage_s": timing, "steps": steps}


def sinkage_table(args) -> None:
    folder = Path(args.tmp)
    folder.mkdir(parents=True, exist_ok=True)
    print(f"seeds {args.seeds}, {args.steps} steps a drive, rig full, randomize on, field cameras")
    print(
        "| soil | preset | drive | reported | MAE FL / FR / RL / RR [mm] | MAE [mm] "
        "| rel. error, true >= 10 mm | bias [mm] | sinkage cost [ms/step] |"
    )
    print("|---|---|---|---:|---|---:|---:|---:|---:|")
    for preset in args.presets:
        for soil in SOILS:
            scen = soil_scenario(soil, folder)
            for turning in (False, True):
                runs = [sinkage_drive(scen, preset, s, turning, args.steps) for s in args.seeds]
                E = np.concatenate([r["est"] - r["true"] for r in runs]) * 1000.0
                T = np.concatenate([r["true"] for r in runs]) * 1000.0
                ok = np.isfinite(E)
                mae = [np.mean(np.abs(E[ok[:, i], i])) if ok[:, i].any() else math.nan for i in range(4)]
                deep = ok & (T >= 10.0)
                rel = 100.0 * np.mean(np.abs(E[deep]) / T[deep]) if deep.any() else math.nan
                cost = 1000.0 * sum(r["sinkage_s"] for r in runs) / sum(r["steps"] for r in runs)
                print(
                    f"| {soil} | {preset} | {'turning' if turning else 'straight'} | {100 * ok.mean():.0f} % "
                    f"| {' / '.join(f'{m:.1f}' for m in mae)} | {np.mean(np.abs(E[ok])):.2f} | {rel:.1f} % "
                    f"| {np.mean(E[ok]):+.2f} | {cost:.2f} |",
                    flush=True,
                )


def slip_table(args) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from slip_accuracy import drive, patch_span

    from rover_env.tools.estimator_metrics import slip_metrics

    print(f"seeds {args.seeds}, preset {args.preset}, field cameras; slip_accuracy.py's drives")
    print("| mission | rig | wheels | slip MAE, abs(s) > 0.1 | slip MAE, otherwise | F1 | within 2 frames |")
    print("|---|---|---|---:|---:|---:|---:|")
    for env_id in ("RoverSlopeLoose-v1", "RoverSoftSand-v0"):
        span = patch_span(env_id)
        for rig, make in (("standard + BMI088", {}), ("full (encoders)", {"rig": "full"})):
            imu = None if make else "bmi088"
            runs = [
                drive(s, args.preset, env_id, span, 20.0, 0.05, "gl", imu, dict(make)) for s in args.seeds
            ]
            for label, cols in (("front", [0, 1]), ("rear", [2, 3]), ("all", [0, 1, 2, 3])):
                m = slip_metrics(runs, wheels=cols)
                print(
                    f"| {env_id} | {rig} | {label} | {m['mae_slip']:.3f} | {m['mae_calm']:.3f} "
                    f"| {m['f1']:.2f} | {100 * m['within_2']:.0f} % |",
                    flush=True,
                )


def main(argv=None) -> int:
    cv2.setNumThreads(1)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="part", required=True)
    s = sub.add_parser("sinkage", help="sinkage per wheel on three soils")
    s.add_argument("--seeds", type=int, nargs="+", default=list(range(701, 707)))
    s.add_argument("--presets", nargs="+", default=["eval", "train"], choices=("eval", "train"))
    s.add_argument("--steps", type=int, default=300, help="control steps a drive (30 per second)")
    s.add_argument("--tmp", default="/tmp/soil_estimation", help="folder for the scenario files it writes")
    p = sub.add_parser("slip", help="slip on the two soil missions, with and without encoders")
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(601, 621)))
    p.add_argument("--preset", default="train", choices=("eval", "train"))
    args = ap.parse_args(argv)
    assert rover_env.ENV_IDS  # registers the environments
    t0 = time.perf_counter()
    if args.part == "sinkage":
        sinkage_table(args)
    else:
        slip_table(args)
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

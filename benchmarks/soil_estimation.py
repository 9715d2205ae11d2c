"""What the built-in estimator sees of the soil: sinkage per wheel, slip on soil, and their cost.

Sinkage (``sinkage``): the rover with the ``full`` rig (BMI088, encoders, currents; field
cameras) crosses level ground of one soil with domain randomisation on (sun, haze, ambient
light, ground texture, camera mounts); in ``wheels`` action mode one axle's wheels turn up to
3.5 times as fast as the other's, the lead changing axle every few seconds, so that the wheels
slip from about -0.7 to 0.7; straight, and turning (the axles steered +-17 deg). Every control
step the estimate's ``sinkage_*`` (the track over the last 0.8 s of frames, absent where too
few measured it) is compared with the simulator's: MAE per wheel over the reported steps, the
relative error where the true sinkage is 10 mm or more, the share of steps reported, and the
estimator's time spent on sinkage per step. With ``--capture DIR`` every frame measured for
sinkage is kept, and ``sinkage-replay DIR`` runs them through the estimator as it is then
(with ``--set`` for its ``SinkageConfig``), in seconds: the drives do not depend on the
sinkage.

Slip on soil (``slip``): ``benchmarks/slip_accuracy.py``'s drives (full throttle, reverse and a
slow roll over each mission's soil), with the BMI088 on the standard rig and with the ``full``
rig (wheel encoders), scored by ``slip_metrics`` per axle: the front wheels on fresh soil, the
rear ones in the front wheels' ruts.

Soil identification (``identify``): the rover with the ``full`` rig crosses level ground of one
soil, its rear axle braking ever harder so that the front wheels' slip sweeps from 0 to about
0.8 and back (``brake``: straight, the rear wheels in the front ones' ruts; ``crab``:
crabbing, every wheel on fresh soil); at 2.5, 5, 7.5,
10 and 15 m of travel the estimator's pull curve is compared with the truth's (the soil's
steady state at the fresh wheels' mean load): DP/W error over slips 0.05-0.7, the best slips,
the quality, how far it drives until the curve stays within 0.05, the per-wheel pull ratios
against the truth's, and the identification's cost per step.

Run: python benchmarks/soil_estimation.py sinkage [--seeds 701 ... 706] [--presets eval train] [--capture DIR]
     python benchmarks/soil_estimation.py sinkage-replay DIR [--set soil_break=1.0] [--per-frame]
     python benchmarks/soil_estimation.py slip [--seeds 601 ... 620]
     python benchmarks/soil_estimation.py identify [--seeds 801 802 803] [--drives sweep crab]
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
from perception.fusion.soil import SLIPS, SoilIdConfig
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


def sinkage_drive(
    scenario: Path, preset: str, seed: int, turning: bool, steps: int, capture: Path | None = None
) -> dict:
    """One drive; per step the estimated (NaN: not reported) and true sinkage [m], and timing.

    With ``capture``, every frame measured for sinkage (its image and joints, as the estimator
    gave them to :meth:`SinkageEstimator.measure`, its time and the truth at the step's end) is
    written to ``capture/{soil}_{preset}_{seed}_{straight|turning}.npz`` for ``sinkage-replay``.
    """
    env = gym.make(
        "Rover-v0", scenario=str(scenario), preset=preset, rig="full", action_mode="wheels", randomize="on"
    )
    frames: list[dict] = []
    try:
        env.reset(seed=seed)
        estimator = env.unwrapped.pipeline.estimator
        if capture is not None:
            measure = estimator.sinkage.measure

            def recorded(image, psi, depth, delta):
                t = estimator.kinematics.state.t
                frames.append({"img": np.array(image), "psi": psi, "depth": depth, "delta": delta, "t": t})
                return measure(image, psi, depth, delta)

            estimator.sinkage.measure = recorded
        rng = np.random.default_rng(seed)
        ph = rng.uniform(0.0, 2.0 * math.pi, 3)
        est, true = [], []
        for k in range(steps):
            t = k / env.unwrapped.control_hz
            base = 0.25 + 0.1 * math.sin(t / 2.0 + ph[0])
            lead = 1.0 + 2.5 * (0.5 + 0.5 * math.sin(t / 3.0 + ph[1]))
            f, r = (base * lead, base) if math.sin(t / 5.0 + ph[2]) > 0 else (base, base * lead)
            lam = 0.6 * math.sin(t / 2.5) if turning else 0.0
            n = len(frames)
            info = env.step(np.array([f, f, r, r, lam, -lam], dtype=np.float32))[4]
            for rec in frames[n:]:
                rec["true"] = np.array(info["ground_truth"]["sinkage"])
            if k >= 15:  # after the start
                v = env.unwrapped.estimate_values
                est.append([v.get(f"sinkage_{w}", np.nan) for w in WHEELS])
                true.append(info["ground_truth"]["sinkage"])
        timing = env.unwrapped.pipeline.estimator.timing["sinkage"]
    finally:
        env.close()
    if capture is not None and frames:
        soil = yaml.safe_load(scenario.read_text())["friction"]["patches"][0]["soil"]
        drive = "turning" if turning else "straight"
        np.savez_compressed(
            capture / f"{soil}_{preset}_{seed}_{drive}.npz",
            **{key: np.stack([np.asarray(f[key]) for f in frames]) for key in frames[0]},
        )
    return {"est": np.array(est), "true": np.array(true), "sinkage_s": timing, "steps": steps}


def sinkage_table(args) -> None:
    folder = Path(args.tmp)
    folder.mkdir(parents=True, exist_ok=True)
    capture = Path(args.capture) if args.capture else None
    if capture is not None:
        capture.mkdir(parents=True, exist_ok=True)
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
                runs = [sinkage_drive(scen, preset, s, turning, args.steps, capture) for s in args.seeds]
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


def sinkage_replay(args) -> None:
    """The sinkage of captured frames (``sinkage --capture``) through today's estimator and track."""
    from dataclasses import replace

    from perception.kinematics.sinkage import SinkageConfig, SinkageEstimator, SinkageTrack

    files = sorted(Path(args.folder).glob("*.npz"))
    if not files:
        raise SystemExit(f"{args.folder}: no captured drives (*.npz); write them with: sinkage --capture DIR")
    config = SinkageConfig()
    for item in args.set:
        key, _, value = item.partition("=")
        config = replace(config, **{key: type(getattr(config, key))(value)})
    estimators = {}
    print(f"{len(files)} drives from {args.folder}; {'each frame' if args.per_frame else 'the track'}")
    print(f"SinkageConfig: {', '.join(args.set) if args.set else 'the defaults'}")
    print(
        "| preset | frames | reported | MAE FL / FR / RL / RR [mm] | MAE [mm] "
        "| rel. error, true >= 10 mm | ms/frame |"
    )
    print("|---|---:|---:|---|---:|---:|---:|")
    for preset in ("eval", "train"):
        errs, trues, cost, n = [], [], 0.0, 0
        for f in (f for f in files if f"_{preset}_" in f.name):
            if preset not in estimators:
                env = gym.make("Rover-v0", preset=preset, rig="full")
                sink = env.unwrapped.pipeline.estimator.sinkage
                estimators[preset] = (sink.camera, sink.model)
                env.close()
            est = SinkageEstimator(*estimators[preset], config)
            track = SinkageTrack()
            with np.load(f) as z:
                d = {k: z[k] for k in z.files}
            for i in range(len(d["t"])):
                t0 = time.perf_counter()
                m = est.measure(d["img"][i], d["psi"][i], d["depth"][i], d["delta"][i])
                cost += time.perf_counter() - t0
                n += 1
                zr = m.reported()[0] if args.per_frame else track.update(float(d["t"][i]), m).reported()[0]
                errs.append(1000.0 * (zr - d["true"][i]))
                trues.append(1000.0 * d["true"][i])
        if not n:
            continue
        E, T = np.array(errs), np.array(trues)
        ok = np.isfinite(E)
        mae = " / ".join(
            f"{np.mean(np.abs(E[ok[:, i], i])):.1f}" if ok[:, i].any() else "–" for i in range(4)
        )
        deep = ok & (T >= 10.0)
        rel = f"{100.0 * np.mean(np.abs(E[deep]) / T[deep]):.1f} %" if deep.any() else "–"
        print(
            f"| {preset} | {n} | {100 * ok.mean():.0f} % | {mae} | {np.mean(np.abs(E[ok])):.2f} | {rel} "
            f"| {1000.0 * cost / n:.2f} |",
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


#: Travel at which the identified curve is scored [m].
CHECKPOINTS = (2.5, 5.0, 7.5, 10.0, 15.0)


def identify_drive(
    scenario: Path, preset: str, seed: int, drive: str, steps: int, period: float = 16.0
) -> dict:
    """One identification drive: the estimator's pull curve at each checkpoint of travel, and the truth's.

    ``brake``: straight; the front wheels' tread runs at 0.9 m/s and the rear wheels (in the
    front ones' ruts) brake ever harder, their tread slowed from 0.9 m/s to a standstill and
    back every ``period`` seconds (16), so that the front wheels' slip sweeps from about 0.05
    to 0.8 (a drawbar pull test with the rear axle as the load). ``crab``: the same while crabbing, both axles
    steered 7.5 deg to one side, then the other (every 6 s), so that the rear wheels run on
    fresh soil 10 cm beside the front ones' ruts.
    """
    from rover_env.config.soil import load_soil
    from rover_env.sim.terramechanics import PullCurves, WheelSpec

    env = gym.make(
        "Rover-v0", scenario=str(scenario), preset=preset, rig="full", action_mode="wheels", randomize="on"
    )
    try:
        env.reset(seed=seed)
        est = env.unwrapped.pipeline.estimator
        soil = est.soil
        g = env.unwrapped.sim.rover.geom
        soil_name = yaml.safe_load(scenario.read_text())["friction"]["patches"][0]["soil"]
        curves = PullCurves(load_soil(soil_name), WheelSpec(radius=g.wheel_radius, width=g.wheel_width))
        rng = np.random.default_rng(seed)
        phase = rng.uniform(0.0, 1.0)
        hz = env.unwrapped.control_hz
        loads, marks, wheel_err, history, own = [], {}, [], [], []
        for k in range(steps):
            t = k / hz
            u = (t / period + phase) % 1.0
            target = 0.8 * (2.0 * u if u < 0.5 else 2.0 - 2.0 * u)
            lam = 0.25 * (1.0 if (t // 6.0) % 2 == 0 else -1.0) if drive == "crab" else 0.0
            rear = 0.45 * (1.0 - target / 0.8)  # of v_max, 2 m/s; steering of 30 deg
            a = np.array([0.45, 0.45, rear, rear, lam, lam], dtype=np.float32)
            info = env.step(a)[4]
            gt = info["ground_truth"]
            loads.append(np.asarray(gt["load"])[soil.fresh])
            # what the data allow: the fresh wheels' own DP/W against their true slip, while
            # the rear axle brakes harder (the front slip rising) and while it lets go
            for i in np.flatnonzero(soil.fresh & (np.asarray(gt["slip_ratio"]) > 0)):
                own.append((gt["slip_ratio"][i], gt["drawbar_pull"][i] / gt["load"][i], u < 0.5))
            cur = soil.last
            if cur.identified:
                true_ratio = env.unwrapped.soil_truth()["pull_ratio"]
                ok = np.isfinite(cur.wheel_pull_ratio) & np.isfinite(true_ratio)
                wheel_err.extend(np.abs(cur.wheel_pull_ratio - true_ratio)[ok])
                history.append((soil.travel, cur))
            for d in CHECKPOINTS:
                if d not in marks and soil.travel >= d:
                    marks[d] = cur
            if soil.travel >= CHECKPOINTS[-1]:
                break
        load = float(np.mean(np.concatenate(loads)))
        timing = est.timing["soil"] / (k + 1)
        timing_sinkage = est.timing["sinkage"] / (k + 1)
    finally:
        env.close()
    dpw, eff = curves.curve(load)
    truth = np.interp(SLIPS, curves.SLIPS, dpw)
    best_pull = float(curves.SLIPS[np.nanargmax(dpw)])
    best_eff = float(curves.SLIPS[np.nanargmax(eff)])
    judged = (SLIPS >= 0.05 - 1e-9) & (SLIPS <= 0.7 + 1e-9)
    # the travel after which the curve stays within 0.05 of the truth over slips 0.05-0.7
    within = [np.max(np.abs(c.pull_ratio[judged] - truth[judged])) <= 0.05 for _, c in history]
    settle = math.nan
    for i in range(len(within)):
        if all(within[i:]):
            settle = history[i][0]
            break
    # the fresh wheels' own DP/W, binned by slip (0.05 wide, at least 20 steps; the median: a
    # wheel all but unloaded reads a DP/W of several), less the truth's
    own_s, own_d, rising = np.array(own).T if own else (np.zeros(0), np.zeros(0), np.zeros(0))
    gap: dict[str, dict[float, float]] = {"all": {}, "rising": {}, "falling": {}}
    for phase, sel in (("all", own_s == own_s), ("rising", rising > 0), ("falling", rising == 0)):
        for lo in np.arange(0.05, 0.9, 0.05):
            m = sel & (own_s >= lo) & (own_s < lo + 0.05)
            if m.sum() >= 20:
                ss = np.interp(lo + 0.025, curves.SLIPS, dpw)
                gap[phase][round(lo, 2)] = float(np.median(own_d[m]) - ss)
    return {
        "own_gap": gap,
        "marks": marks,
        "truth": truth,
        "best_pull": best_pull,
        "best_eff": best_eff,
        "judged": judged,
        "wheel_mae": float(np.mean(wheel_err)) if wheel_err else math.nan,
        "settle": settle if within and within[-1] else math.inf,
        "soil_s": timing,
        "sinkage_s": timing_sinkage,
    }


def identify_table(args) -> None:
    folder = Path(args.tmp)
    folder.mkdir(parents=True, exist_ok=True)
    print(
        f"seeds {args.seeds}, preset {args.preset}, rig full, randomize on, field cameras, "
        f"braking cycle {args.period:g} s"
    )
    print(
        "| soil | drive | travel [m] | identified | DP/W error 0.05-0.7, mean / max "
        "| max, std <= 0.025 | slip_best_pull (truth) | slip_best_efficiency (truth) | soil_quality |"
    )
    print("|---|---|---:|---:|---|---:|---|---|---:|")
    summary = []
    for soil in args.soils:
        scen = soil_scenario(soil, folder)
        for drive in args.drives:
            runs = [identify_drive(scen, args.preset, s, drive, args.steps, args.period) for s in args.seeds]
            for d in CHECKPOINTS:
                rows = [(r, r["marks"].get(d)) for r in runs]
                rows = [(r, c) for r, c in rows if c is not None and c.identified]
                n = sum(1 for r in runs if d in r["marks"])
                if not n:
                    continue
                if not rows:
                    print(f"| {soil} | {drive} | {d:g} | 0/{n} | – | – | – | – | – |")
                    continue
                err = [np.abs(c.pull_ratio[r["judged"]] - r["truth"][r["judged"]]) for r, c in rows]
                std = SoilIdConfig().quality_std  # what the soil quality counts as identified
                accepted = [c.pull_ratio_std[r["judged"]] <= std for r, c in rows]
                acc = [e[a] for e, a in zip(err, accepted, strict=True)]
                acc_max = max((float(a.max()) for a in acc if len(a)), default=math.nan)
                bp = ", ".join(f"{c.slip_best_pull:.2f}" for _, c in rows)
                be = ", ".join(f"{c.slip_best_efficiency:.2f}" for _, c in rows)
                print(
                    f"| {soil} | {drive} | {d:g} | {len(rows)}/{n} "
                    f"| {np.mean([e.mean() for e in err]):.3f} / {max(e.max() for e in err):.3f} "
                    f"| {'–' if math.isnan(acc_max) else f'{acc_max:.3f}'} "
                    f"| {bp} ({rows[0][0]['best_pull']:.2f}) | {be} ({rows[0][0]['best_eff']:.2f}) "
                    f"| {np.mean([c.quality for _, c in rows]):.2f} |",
                    flush=True,
                )
            summary.append((soil, drive, runs))
    print()
    print(
        "| soil | drive | travel until within 0.05 for good [m] | pull_ratio_* MAE against the truth's "
        "| soil cost [ms/step] | sinkage cost [ms/step] | both [ms/step] |"
    )
    print("|---|---|---|---:|---:|---:|---:|")
    for soil, drive, runs in summary:
        settle = ", ".join("never" if not math.isfinite(r["settle"]) else f"{r['settle']:.1f}" for r in runs)
        mae = np.nanmean([r["wheel_mae"] for r in runs])
        cost = 1000.0 * np.mean([r["soil_s"] for r in runs])
        cost_z = 1000.0 * np.mean([r["sinkage_s"] for r in runs])
        print(
            f"| {soil} | {drive} | {settle} | {mae:.3f} | {cost:.3f} | {cost_z:.3f} | {cost + cost_z:.3f} |",
            flush=True,
        )
    print()
    print("What the data allow: the fresh wheels' own DP/W (the truth's pull over load, the median in")
    print("bins of their true slip) less the steady state's, averaged over the runs; all steps, and")
    print("split by the rear axle braking harder (the front slip rising) or letting go (falling)")
    print("| soil | drive | steps | " + " | ".join(f"{lo:.2f}" for lo in np.arange(0.05, 0.9, 0.05)) + " |")
    print("|---|---|---|" + "---:|" * len(np.arange(0.05, 0.9, 0.05)))
    for soil, drive, runs in summary:
        for phase in ("all", "rising", "falling"):
            cells = []
            for lo in np.arange(0.05, 0.9, 0.05):
                v = [r["own_gap"][phase][round(lo, 2)] for r in runs if round(lo, 2) in r["own_gap"][phase]]
                cells.append(f"{np.mean(v):+.3f}" if v else "–")
            print(f"| {soil} | {drive} | {phase} | " + " | ".join(cells) + " |", flush=True)


def main(argv=None) -> int:
    cv2.setNumThreads(1)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="part", required=True)
    s = sub.add_parser("sinkage", help="sinkage per wheel on three soils")
    s.add_argument("--seeds", type=int, nargs="+", default=list(range(701, 707)))
    s.add_argument("--presets", nargs="+", default=["eval", "train"], choices=("eval", "train"))
    s.add_argument("--steps", type=int, default=300, help="control steps a drive (30 per second)")
    s.add_argument("--tmp", default="/tmp/soil_estimation", help="folder for the scenario files it writes")
    s.add_argument("--capture", help="also write every frame measured for sinkage to this folder")
    r = sub.add_parser("sinkage-replay", help="captured frames (sinkage --capture) through today's sinkage")
    r.add_argument("folder", help="the folder sinkage --capture wrote")
    r.add_argument("--set", nargs="*", default=[], help="SinkageConfig fields, key=value")
    r.add_argument("--per-frame", action="store_true", help="each frame's own reading, not the track's")
    p = sub.add_parser("slip", help="slip on the two soil missions, with and without encoders")
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(601, 621)))
    p.add_argument("--preset", default="train", choices=("eval", "train"))
    i = sub.add_parser("identify", help="the soil's pull curve identified on three soils")
    i.add_argument("--seeds", type=int, nargs="+", default=[801, 802, 803])
    i.add_argument("--preset", default="train", choices=("eval", "train"))
    i.add_argument("--drives", nargs="+", default=["brake", "crab"], choices=("brake", "crab"))
    i.add_argument("--soils", nargs="+", default=list(SOILS), choices=SOILS)
    i.add_argument("--steps", type=int, default=1500, help="at most this many control steps (30 a second)")
    i.add_argument("--period", type=float, default=16.0, help="the rear axle's braking cycle [s]")
    i.add_argument("--tmp", default="/tmp/soil_estimation", help="folder for the scenario files it writes")
    args = ap.parse_args(argv)
    assert rover_env.ENV_IDS  # registers the environments
    t0 = time.perf_counter()
    if args.part == "sinkage":
        sinkage_table(args)
    elif args.part == "sinkage-replay":
        sinkage_replay(args)
    elif args.part == "identify":
        identify_table(args)
    else:
        slip_table(args)
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Observation errors of the estimator in the loop, per field and mission, and slip accuracy.

For each registered mission (``rover_env.MISSIONS``) and seed, the pure-pursuit controller drives
the course on the *estimated* observation (closed loop); every step, the observation's state
fields are compared with the simulator's ground truth of the same fields. Prints, per mission:

- per field: MAE and 95th percentile of |estimate - truth| (physical units), over the steps after
  the first second (the filters' start-up);
- slip: per-wheel slip-ratio MAE while |s_true| > 0.1 and otherwise (steps where the truth's
  tread or ground speed is at least 5 cm/s), and slip-event detection (hysteresis on |s|:
  on after two frames in a row at 0.2 or more, off below 0.1, labelled alike on both sides):
  precision, recall, F1 over events (an estimated event matches a true one it overlaps) and the
  median and largest onset latency in camera frames, from the truth's first frame at 0.2.

Run: python benchmarks/observation_errors.py [--preset eval] [--seeds 101 102] [--seconds 40]
(the seeds are ones the tests never use).
"""

from __future__ import annotations

import argparse
import math
import time

import gymnasium as gym
import numpy as np

import rover_env
from controllers.pure_pursuit import PurePursuit
from perception.slip import SlipConfig, slip_events
from rover_env.envs import OBS_FIELDS

FIELDS = OBS_FIELDS[:17]
EVENT_FRAMES = 2  # frames in a row with |s| >= 0.2 that make a slip event (SlipConfig.event_hold)
EVENT_SPEED = SlipConfig().event_min_speed  # [m/s] no event on a slower wheel
TRUTH = (
    [("twist", i) for i in range(3)]
    + [("wheel_rate", i) for i in range(4)]
    + [("slip_ratio", i) for i in range(4)]
    + [("axle_roll", i) for i in range(2)]
    + [("axle_height", i) for i in range(2)]
    + [("steering", i) for i in range(2)]
)


class StepLog:
    """A drive's rows for :func:`slip_metrics`: per step the estimate, the filter's slip events,
    the truth, the wheels' speeds (tread or ground, [m/s]) and the time [s]."""

    def __init__(self, radius: float) -> None:
        self.radius = radius
        self.est, self.events, self.tru, self.speed, self.t = [], [], [], [], []

    def add(self, obs: np.ndarray, info: dict) -> None:
        gt = info["ground_truth"]
        self.est.append(obs[:17].astype(np.float64))
        self.events.append(info["slip"]["events"])
        self.tru.append([gt[k][i] for k, i in TRUTH])
        self.speed.append(np.maximum(np.abs(gt["wheel_rate"] * self.radius), np.abs(gt["twist"][0])))
        self.t.append(info["t"])

    def arrays(self, frame: float) -> dict:
        """The rows as arrays, with the fisheye's frame period [s] and the wheel radius [m]."""
        names = ("est", "events", "tru", "speed", "t")
        return {k: np.array(getattr(self, k)) for k in names} | {"frame": frame, "radius": self.radius}


def run(env_id: str, seed: int, preset: str, seconds: float) -> dict:
    env = gym.make(env_id, obs_source="estimated", preset=preset)
    try:
        ctrl = PurePursuit(OBS_FIELDS)
        obs, info = env.reset(seed=seed)
        ctrl.reset()
        log = StepLog(env.unwrapped.geometry.wheel_radius)
        steps = int(round(seconds * env.unwrapped.control_hz))
        wall = time.perf_counter()
        for _ in range(steps):
            obs, _, term, trunc, info = env.step(ctrl.act(obs))
            log.add(obs, info)
            if term or trunc:
                break
        wall = time.perf_counter() - wall
        fisheye_period = env.unwrapped.pipeline.fisheye.period
    finally:
        env.close()
    return log.arrays(fisheye_period) | {"wall": wall, "success": bool(info["is_success"])}


def events(on: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) index ranges of True runs."""
    d = np.diff(np.r_[0, on.astype(int), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1), strict=True))


def slip_metrics(runs: list[dict]) -> dict:
    err_slip, err_calm, tp, fp, fn, lat = [], [], 0, 0, 0, []
    for rr in runs:
        keep = rr["t"] >= 1.0
        s_est, s_true = rr["est"][keep, 7:11], rr["tru"][keep, 7:11]
        moving = rr["speed"][keep] >= 0.05
        big = np.abs(s_true) > 0.1
        err = np.abs(s_est - s_true)
        err_slip.extend(err[moving & big].tolist())
        err_calm.extend(err[moving & ~big].tolist())
        # the truth's events: |s| >= 0.2 for two frames in a row (a one-frame spike is none) on a
        # wheel moving at EVENT_SPEED or more (tread or ground), ending below 0.1: the rule of the
        # slip filter's own detection (SlipConfig), whose events are scored; latency runs from the
        # truth's first such frame
        ev_est = np.asarray(rr["events"], bool)[keep]
        ev_true = slip_events(s_true, min_frames=EVENT_FRAMES, speed=rr["speed"][keep], min_speed=EVENT_SPEED)
        for w in range(4):
            e_runs, t_runs = events(ev_est[:, w]), events(ev_true[:, w])
            matched = set()
            for a0, a1 in t_runs:
                hit = [k for k, (b0, b1) in enumerate(e_runs) if b0 < a1 and a0 < b1]
                if hit:
                    tp += 1
                    matched.update(hit)
                    lat.append(max(0, e_runs[hit[0]][0] - (a0 - (EVENT_FRAMES - 1))))
                else:
                    fn += 1
            fp += len(e_runs) - len(matched)
    prec = tp / max(tp + fp, 1)
    rec = tp / max(tp + fn, 1)
    f1 = 2 * prec * rec / max(prec + rec, 1e-12)
    # latencies are counted in control steps; a fisheye frame spans frame / (step time) of them
    step = float(np.median(np.diff(runs[0]["t"]))) if runs and len(runs[0]["t"]) > 1 else math.nan
    lat_frames = np.array(lat) * step / runs[0]["frame"] if lat else np.zeros(0)
    return dict(
        mae_slip=float(np.mean(err_slip)) if err_slip else math.nan,
        n_slip=len(err_slip),
        mae_calm=float(np.mean(err_calm)) if err_calm else math.nan,
        events=tp + fn,
        precision=prec,
        recall=rec,
        f1=f1,
        latency_median=float(np.median(lat_frames)) if len(lat_frames) else math.nan,
        latency_max=float(lat_frames.max()) if len(lat_frames) else math.nan,
        within_2=float(np.mean(lat_frames <= 2 + 1e-9)) if len(lat_frames) else math.nan,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="eval", choices=("train", "eval"))
    ap.add_argument("--missions", nargs="+", default=list(rover_env.ENV_IDS))
    ap.add_argument("--seeds", type=int, nargs="+", default=[101, 102])
    ap.add_argument("--seconds", type=float, default=40.0, help="longest drive per episode [s]")
    args = ap.parse_args(argv)
    for env_id in args.missions:
        runs = [run(env_id, s, args.preset, args.seconds) for s in args.seeds]
        steps = sum(len(r["t"]) for r in runs)
        wall = sum(r["wall"] for r in runs)
        print(
            f"\n### {env_id} ({rover_env.MISSIONS[env_id]}), preset {args.preset}, seeds {args.seeds}: "
            f"{steps} steps, {steps / wall:.1f} steps/s, reached the goal {sum(r['success'] for r in runs)}"
            f" of {len(runs)}\n"
        )
        print("| field | MAE | p95 |")
        print("|---|---:|---:|")
        keep = [r["t"] >= 1.0 for r in runs]
        err = np.vstack([np.abs(r["est"] - r["tru"])[k] for r, k in zip(runs, keep, strict=True)])
        for j, name in enumerate(FIELDS):
            print(f"| {name} | {err[:, j].mean():.4f} | {np.percentile(err[:, j], 95):.4f} |")
        m = slip_metrics(runs)
        print(
            f"\nslip ratio MAE: {m['mae_slip']:.3f} while |s| > 0.1 ({m['n_slip']} wheel-steps), "
            f"{m['mae_calm']:.3f} otherwise; events: {m['events']}, precision {m['precision']:.2f}, "
            f"recall {m['recall']:.2f}, F1 {m['f1']:.2f}, onset latency median {m['latency_median']:.1f} "
            f"/ max {m['latency_max']:.1f} camera frames ({100 * m['within_2']:.0f} % within 2)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

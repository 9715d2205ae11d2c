"""Record the slip filter's inputs on the slip-accuracy drives once, then replay them through other
filter settings in seconds (the drives do not depend on the estimates, so a replay of the same
inputs is the live run; it reproduces the live events exactly with the same settings).

    python benchmarks/slip_replay.py record --seeds 301 302 303 304 305 306 --imu bmi088 --out rec/
    python benchmarks/slip_replay.py score rec/ [--set event_on=0.21 grip_std=0.05]
    python benchmarks/slip_replay.py score rec/ --perfect-odometry   # the truth's v_x instead
    python benchmarks/slip_replay.py record --closed-loop slip_unaware --camera-effects ideal \
        --envs Rover-v0 --seeds 100 101 102 103 104 --out rec/
    python benchmarks/slip_replay.py window rec/FILE.pkl --run 0 --from 10.8 --to 11.9 --out w.npz

``record`` runs ``slip_accuracy.drive`` (``--preset``, train by default) on every mission and
writes one pickle per mission and seed set (local files of your own: ``score`` unpickles them).
With ``--closed-loop CONTROLLER`` it runs that controller's missions on the estimates instead
(as ``rover eval``): a replay of the same inputs then gives the events of other event settings
exactly (``event_*``: no controller reads the events), and of other filter settings on the same
drive (the slip-aware controller, which reads the slip, would have driven a little differently).
``score`` prints the slip metrics of ``rover_env.tools.estimator_metrics.slip_metrics`` per
mission and in all.
``window`` writes the filter's inputs of one recorded run between two times, with the truth's
slip at each estimate, as plain arrays (``.npz``): the test fixtures of recorded skids
(``tests/data/``) are made with it.
"""

from __future__ import annotations

import argparse
import ast
import pickle
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import perception.fusion.slip as ps  # noqa: E402
from rover_env.sim.geometry import RoverGeometry  # noqa: E402
from rover_env.tools.estimator_metrics import slip_metrics  # noqa: E402

METHODS = (
    "add_odometry", "add_wheels", "add_gyro", "add_accel", "calibrate_gyro", "estimate", "twist_at", "reset",
)  # fmt: skip


def record(args) -> None:
    import slip_accuracy as sa

    import rover_env

    calls: list = []
    originals = {}
    for name in METHODS:
        originals[name] = getattr(ps.SlipEstimator, name)

        def wrap(self, *a, _n=name, **k):
            calls.append((_n, a, k))
            return originals[_n](self, *a, **k)

        setattr(ps.SlipEstimator, name, wrap)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for env_id in args.envs or rover_env.ENV_IDS:
        runs = []
        for seed in args.seeds:
            calls.clear()
            if args.closed_loop:
                run = closed_loop(env_id, seed, args)
            else:
                span = sa.patch_span(env_id)
                make = {"camera_effects": args.camera_effects}
                run = sa.drive(seed, args.preset, env_id, span, 20.0, 0.05, args.renderer, args.imu, make)
            runs.append({"seed": seed, "run": run, "calls": list(calls)})
        tag = f"_{args.closed_loop}" if args.closed_loop else ""
        tag += "_randomized" if args.randomize == "on" else ""
        tag += f"_{args.rig}" if args.rig else ""
        preset = "" if args.preset == "train" else f"_{args.preset}"
        path = out / f"{env_id}{tag}_{args.imu}_{args.camera_effects}{preset}_{args.seeds[0]}.pkl"
        with open(path, "wb") as fh:
            pickle.dump(runs, fh)
        print(f"recorded {env_id}, seeds {args.seeds}: {path}", flush=True)


def closed_loop(env_id: str, seed: int, args) -> dict:
    """One mission of ``args.closed_loop`` on the estimates (``args.preset``); its per-step log."""
    from rover_env.tools.estimator_metrics import EstimateLog
    from rover_env.tools.evaluation import load_estimator, make_mission_env, parse_controller

    spec, source = parse_controller(args.closed_loop)
    extra: dict = {"imu": args.imu} if args.imu else {}
    if args.estimator:
        extra["estimator"] = load_estimator(args.estimator)
    if args.rig:
        extra["rig"] = args.rig
    env = make_mission_env(
        env_id, obs_source=source, action_mode=spec.action_mode, preset=args.preset, randomize=args.randomize,
        camera_effects=args.camera_effects, renderer=args.renderer, **extra,
    )  # fmt: skip
    try:
        ctrl = spec.make(env)
        obs, _ = env.reset(seed=seed)
        ctrl.reset()
        log = EstimateLog(env.unwrapped.geometry.wheel_radius)
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(ctrl.act(obs))
            log.add(info, env.unwrapped.estimate_values or {})
            done = term or trunc
        fisheye = env.unwrapped.pipeline.fisheye  # the events' time scale, as rover eval's
        return log.arrays(fisheye.period if fisheye is not None else env.unwrapped.control_dt)
    finally:
        env.close()


def _wheel_xy() -> np.ndarray:
    """The rover's wheel centres (FL, FR, RL, RR) in the body frame [m]."""
    g = RoverGeometry()
    return np.array([[s * g.wheelbase / 2, side * g.track / 2] for s in (1, -1) for side in (1, -1)])


def replay(rec: dict, config, perfect_odometry: bool = False) -> dict:
    """The run of ``rec`` with its slip estimates and events from a fresh filter of ``config``."""
    est = ps.SlipEstimator(_wheel_xy(), RoverGeometry().wheel_radius, config)
    t_run, tru = rec["run"]["t"], rec["run"]["tru"]
    out = {}
    for name, a, k in rec["calls"]:
        if name == "reset":
            est.reset()
            out = {}
            continue
        if name == "add_odometry" and perfect_odometry:
            z = np.array(a[1], dtype=float)
            z[0] = np.interp(a[0] - 0.5 * a[2], t_run, tru[:, 0])
            a = (a[0], z, *a[2:])
        r = getattr(est, name)(*a, **k)
        if name == "estimate":
            out[round(a[0], 9)] = (r.slip_ratio.copy(), r.events.copy())
    run = dict(rec["run"])
    run["est"] = run["est"].copy()
    run["est"][:, 7:11] = [out[round(t, 9)][0] for t in t_run]
    run["events"] = np.array([out[round(t, 9)][1] for t in t_run])
    return run


def score(args) -> None:
    changes = {}
    for item in args.set or []:
        key, _, value = item.partition("=")
        changes[key] = ast.literal_eval(value)
    config = ps.SlipConfig(**changes)
    every = []
    print(
        "| mission | F1 | false | missed | events | within 2 frames | latest [frames] | slip MAE, slipping |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for path in sorted(Path(args.folder).glob("*.pkl")):
        with open(path, "rb") as fh:  # your own recording
            recs = pickle.load(fh)  # noqa: S301
        runs = [replay(r, config, args.perfect_odometry) for r in recs]
        every += runs
        _row(path.stem, slip_metrics(runs))
    _row("all", slip_metrics(every))


def window(args) -> None:
    """The inputs of run ``args.run`` of a recording between ``args.t0`` and ``args.t1`` as arrays."""
    with open(args.recording, "rb") as fh:  # your own recording
        rec = pickle.load(fh)[args.run]  # noqa: S301
    names = ("add_odometry", "add_wheels", "add_gyro", "add_accel", "estimate")
    inside = [(n, a, k) for n, a, k in rec["calls"] if n in names and args.t0 <= a[0] <= args.t1]
    out: dict[str, list] = {"order": []}
    for n, a, k in inside:
        out["order"].append(names.index(n))
        if n == "add_odometry":  # t, twist, dt, quality, covariance (NaN: none)
            cov = k.get("cov")
            cov = np.full(9, np.nan) if cov is None else np.asarray(cov, float).ravel()
            out.setdefault("odometry", []).append([a[0], *a[1], a[2], a[3], *cov])
        elif n == "add_wheels":  # t, rates, dt, valid, steering, own deviations (NaN: none)
            std = a[5] if len(a) > 5 and a[5] is not None else np.full(4, np.nan)
            out.setdefault("wheels", []).append([a[0], *a[1], a[2], *np.asarray(a[3], float), *a[4], *std])
        elif n == "add_gyro":  # t, rate, dt, std
            out.setdefault("gyro", []).append(list(a[:4]))
        elif n == "add_accel":  # t, (a_x, a_y), dt
            out.setdefault("accel", []).append([a[0], *a[1], a[2]])
    t = rec["run"]["t"]
    keep = (t >= args.t0) & (t <= args.t1)
    np.savez_compressed(
        args.out,
        **{k: np.asarray(v, float) for k, v in out.items()},
        t=t[keep],
        slip_true=rec["run"]["tru"][keep, 7:11],
        speed=rec["run"]["speed"][keep],
        wheel_xy=_wheel_xy(),
        wheel_radius=RoverGeometry().wheel_radius,
    )
    print(f"wrote {args.out}: {len(inside)} calls, {keep.sum()} estimates")


def _row(name: str, m: dict) -> None:
    print(
        f"| {name} | {m['f1']:.3f} | {m['false']} | {m['missed']} | {m['events']} "
        f"| {100 * m['within_2']:.1f} % | {m['latency_max']:.0f} | {m['mae_slip']:.3f} |"
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="drive and record the filter's inputs")
    r.add_argument("--seeds", type=int, nargs="+", required=True)
    r.add_argument("--imu", default=None, help="IMU preset (default: none)")
    r.add_argument("--renderer", default="gl", choices=("gl", "tiny"))
    r.add_argument(
        "--preset", default="train", choices=("train", "eval"), help="camera preset (default: train)"
    )
    r.add_argument("--envs", nargs="+", default=None, help="environment ids (default: all)")
    r.add_argument(
        "--closed-loop", default=None, metavar="CONTROLLER", help="drive the missions with this controller"
    )
    r.add_argument(
        "--camera-effects", default="field", choices=("ideal", "field"), help="the cameras (default: field)"
    )
    r.add_argument(
        "--randomize", default="off", choices=("off", "on"), help="domain randomisation (closed loop)"
    )
    r.add_argument("--estimator", default=None, help="estimator factory, as rover eval's (closed loop)")
    r.add_argument("--rig", default=None, help="the sensor rig, as rover eval's --rig (closed loop)")
    r.add_argument("--out", required=True, help="folder for the recordings")
    s = sub.add_parser("score", help="replay recordings through a filter's settings")
    s.add_argument("folder")
    s.add_argument("--set", nargs="+", metavar="KEY=VALUE", help="SlipConfig fields to change")
    s.add_argument("--perfect-odometry", action="store_true", help="the truth's v_x for the odometry's")
    w = sub.add_parser("window", help="one recorded run's inputs between two times, as arrays (.npz)")
    w.add_argument("recording")
    w.add_argument("--run", type=int, default=0, help="index of the run in the recording")
    w.add_argument("--from", dest="t0", type=float, required=True, help="[s]")
    w.add_argument("--to", dest="t1", type=float, required=True, help="[s]")
    w.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    {"record": record, "score": score, "window": window}[args.cmd](args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

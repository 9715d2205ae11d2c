"""The fisheye's odometry against the downward camera's, on the same rendered drives.

Drives missions on the estimates (the built-in estimator, path follower, whole fisheye frames)
and runs :class:`perception.fisheye_odometry.FisheyeOdometry` on every fisheye frame beside
the downward camera's :class:`perception.odometry.FlowOdometry`, both with the ground plane of
the fisheye kinematics' latest wheels. Each estimate is compared with the true body twist at
the middle of its frame pair (interpolated between control steps). Prints, per mission and
camera, the MAE of v_x, v_y and omega over valid estimates, the share of valid pairs, and the
fisheye's MAE over the downward camera's.

    LP_NUM_THREADS=1 python benchmarks/fisheye_odometry.py --missions Rover-v0 RoverRoughSlippery-v0 \
        RoverShadows-v0 --seeds 0 1 --preset train
"""

from __future__ import annotations

import argparse

import numpy as np

from controllers import PathFollower
from perception import RoverEstimator
from perception.fisheye_odometry import FisheyeOdometry, FisheyeOdometryConfig
from rover_env.envs import RoverEnv


class _Tap(RoverEstimator):
    """The built-in estimator, recording its downward odometry and running the fisheye's beside it."""

    config = FisheyeOdometryConfig()
    parts_mask = False

    def __init__(self, rig, **kw) -> None:
        super().__init__(rig, fisheye_window=None, **kw)
        mask = None
        if self.parts_mask:
            from perception.rover_parts import kinematics_roi
            from rover_env.sim.geometry import RoverGeometry

            g = RoverGeometry()
            mask = ~kinematics_roi(self.fish.model, self.model, g.roll_limit, g.travel_limit, g.steer_limit)
        self.fish_odo = FisheyeOdometry(self.fish.model, self.config, mask=mask)
        self.records: dict[str, list] = {"downward": [], "fisheye": []}

    def reset(self, start_fix) -> None:
        super().reset(start_fix)
        self.fish_odo.reset()
        self.records = {"downward": [], "fisheye": []}

    def _on_fisheye(self, img, t) -> None:
        est = self.fish_odo.update(img, t, ground_plane=self.wheel_ground_plane())
        super()._on_fisheye(img, t)
        if est is not None:
            self.records["fisheye"].append((t, est.dt, est.valid, *est.twist))

    def _on_downward(self, img, t) -> None:
        super()._on_downward(img, t)
        est = self._last_odom
        if est is not None and est.t == t:
            self.records["downward"].append((t, est.dt, est.valid, *est.twist))


def run(mission: str, seed: int, preset: str) -> tuple[dict, np.ndarray]:
    """One drive: the two cameras' records and the truth (t, v_x, v_y, omega) per control step."""
    holder: dict = {}

    def factory(rig):
        holder["est"] = _Tap(rig)
        return holder["est"]

    import dataclasses

    import rover_env
    from rover_env.config.rig import SensorConfig
    from rover_env.config.scenario import load_scenario

    # the fisheye renders its whole image (the presets' region of interest holds only the parts
    # the kinematics reads)
    sc = load_scenario(rover_env.MISSIONS.get(mission, mission))
    rig = (
        SensorConfig(name="fisheye", kind="fisheye", camera={"roi": False}),
        SensorConfig(name="downward", kind="pinhole"),
    )
    sc = dataclasses.replace(sc, rig=rig)
    env = RoverEnv(scenario=sc, obs_source="estimated", preset=preset, estimator=factory)
    try:
        controller = PathFollower.for_env(env)
        controller.reset()
        obs, info = env.reset(seed=seed)
        truth = []
        while True:
            obs, _, term, trunc, info = env.step(controller.act(obs))
            gt = info["ground_truth"]
            truth.append((info["t"], gt["twist"][0], gt["twist"][1], gt["twist"][2]))
            if term or trunc:
                break
    finally:
        env.close()
    rec = holder["est"].records
    return rec, np.array(truth)


def errors(records, truth: np.ndarray) -> tuple[np.ndarray, float]:
    """(3,) MAE of (v_x, v_y, omega) over valid estimates against the truth mid-pair; valid share."""
    r = np.array(records, dtype=float).reshape(-1, 6)
    if len(r) == 0:
        return np.full(3, np.nan), 0.0
    mid = r[:, 0] - 0.5 * r[:, 1]
    keep = (mid >= truth[0, 0]) & (mid <= truth[-1, 0])
    r, mid = r[keep], mid[keep]
    ref = np.column_stack([np.interp(mid, truth[:, 0], truth[:, k]) for k in (1, 2, 3)])
    valid = r[:, 2] > 0
    if not valid.any():
        return np.full(3, np.nan), 0.0
    return np.abs(r[valid, 3:6] - ref[valid]).mean(axis=0), float(valid.mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--missions", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--preset", choices=["train", "eval"], default="train")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="FisheyeOdometryConfig fields")
    ap.add_argument("--parts-mask", action="store_true", help="mask the rover's parts from its model")
    args = ap.parse_args(argv)
    _Tap.parts_mask = args.parts_mask
    if args.set:
        import ast
        import dataclasses

        kv = {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.set)}
        _Tap.config = dataclasses.replace(FisheyeOdometryConfig(), **kv)
        print(f"fisheye odometry: {kv}")
    print(f"preset {args.preset}, seeds {args.seeds}, path follower on the estimates, no IMU\n")
    print(
        "| mission | camera | v_x MAE [m/s] | v_y MAE [m/s] | omega MAE [rad/s] | valid pairs |"
        " fisheye / downward (v_x, v_y, omega) |"
    )
    print("|---|---|---:|---:|---:|---:|---|")
    for mission in args.missions:
        recs: dict[str, list] = {"downward": [], "fisheye": []}
        truths = []
        for seed in args.seeds:
            rec, truth = run(mission, seed, args.preset)
            truths.append(truth)
            for k in recs:
                recs[k].append(rec[k])
        out = {}
        for cam in ("downward", "fisheye"):
            maes, shares, counts = [], [], []
            for rec, truth in zip(recs[cam], truths, strict=True):
                mae, share = errors(rec, truth)
                maes.append(mae)
                shares.append(share)
                counts.append(len(rec))
            w = np.array(counts, float)
            out[cam] = (np.average(np.array(maes), axis=0, weights=w), float(np.average(shares, weights=w)))
        ratio = out["fisheye"][0] / out["downward"][0]
        for cam in ("downward", "fisheye"):
            mae, share = out[cam]
            extra = ", ".join(f"{x:.2f}" for x in ratio) if cam == "fisheye" else ""
            print(
                f"| {mission} | {cam} | {mae[0]:.4f} | {mae[1]:.4f} | {mae[2]:.4f}"
                f" | {100 * share:.1f} % | {extra} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

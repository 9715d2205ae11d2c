"""The fisheye's odometry against the downward camera's, on the same rendered drives.

Drives missions on the estimates (the built-in estimator with both cameras, path follower, no
IMU) with the fisheye rendering what the one-camera rig's fisheye renders (the kinematics'
windows and the ground near its axis, ``roi_ground_deg``), and runs the one-camera rig's
:class:`perception.odometry.fisheye.FisheyeOdometry` (the same settings and mask of the rover's
parts) on every fisheye frame beside the downward camera's :class:`perception.odometry.flow.FlowOdometry`,
both on the ground plane of the fisheye kinematics' current wheels. Each estimate is compared
with the true body twist at the middle of its frame pair (interpolated between control steps).

Prints, per mission and camera, the MAE of v_x, v_y and omega over valid estimates, the share of
valid pairs, and the fisheye's MAE over the downward camera's; then, per mission, the fisheye's
speed error (mean |speed error| over mean speed, pairs above 0.1 m/s) and yaw-rate MAE on
straight (|omega| < 0.05 rad/s) and turning pairs; with ``--shadow-truth``, the share of valid
fisheye pairs among those whose odometry view holds the rover's shadow (at least 5 % of its
ground pixels, from a labelled render of each frame: slower).

    LP_NUM_THREADS=1 python benchmarks/fisheye_odometry.py --missions Rover-v0 RoverRoughSlippery-v0 \
        RoverShadows-v0 --seeds 0 1 --preset train [--shadow-truth] [--out results.md]
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import math
import sys

import numpy as np

from controllers import PathFollower
from perception import RoverEstimator
from perception.models.rover_parts import kinematics_roi
from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig
from perception.odometry.wheel_tracks import wheel_contacts
from rover_env.config.rig import FISHEYE_ONLY_CAMERA
from rover_env.envs import RoverEnv

CAMERAS = ("downward", "fisheye")

#: The fisheye's settings over the one-camera rig's (``--camera``).
_camera_overrides: dict = {}


class _Tap(RoverEstimator):
    """The built-in estimator, recording its downward odometry and running the fisheye's beside it."""

    overrides: dict = {}

    def __init__(self, rig, **kw) -> None:
        super().__init__(rig, **kw)
        lim = self.model.joint_limits
        mask = None if lim is None else ~kinematics_roi(self.fish.model, self.model, *lim)
        w = self.fish.model.image_size[0]
        cfg = FisheyeOdometryConfig.for_ground_view(self.fish.ground_view_deg, w, **self.overrides)
        self.fish_odo = FisheyeOdometry(self.fish.model, cfg, mask=mask)
        self.records: dict[str, list] = {c: [] for c in CAMERAS}

    def reset(self, start_fix) -> None:
        super().reset(start_fix)
        self.fish_odo.reset()
        self.records = {c: [] for c in CAMERAS}

    def _on_fisheye(self, img, t) -> None:
        super()._on_fisheye(img, t)  # the kinematics first: the plane under this frame
        plane = self.wheel_ground_plane()
        s = self.kinematics.state
        contacts = wheel_contacts(
            self.model.wheel_frames(s.psi, s.depth, s.delta), self.model.wheel_radius, plane
        )
        est = self.fish_odo.update(img, t, ground_plane=plane, contacts=contacts)
        if est is not None:
            self.records["fisheye"].append((t, est.dt, est.valid, *est.twist))

    def _on_downward(self, img, t) -> None:
        super()._on_downward(img, t)
        est = self._last_odom
        if est is not None and est.t == t:
            self.records["downward"].append((t, est.dt, est.valid, *est.twist))


def _shadow_share(env: RoverEnv, estimator: _Tap) -> float:
    """Share of the fisheye odometry's view of the ground that lies in shadow, from a labelled render."""
    cam = env.pipeline.fisheye
    view = cam.render_view()
    usable = estimator.fish_odo.learned_mask & (view.segmentation == env.sim.terrain.body_id)
    n = int(usable.sum())
    return float((view.shadow & usable).sum()) / n if n else 0.0


def run(mission: str, seed: int, preset: str, shadow_truth: bool = False):
    """One drive: the two cameras' records, the truth (t, v_x, v_y, omega) per step, (t, shadow share)."""
    holder: dict = {}

    def factory(rig):
        from rover_env.sensors.rig import builtin_estimator

        base = builtin_estimator(preset)
        holder["est"] = _Tap(rig, **_builtin_kwargs(base, rig))
        return holder["est"]

    import rover_env
    from rover_env.config.rig import SensorConfig
    from rover_env.config.scenario import load_scenario

    sc = load_scenario(rover_env.MISSIONS.get(mission, mission))
    rig = (
        SensorConfig(name="fisheye", kind="fisheye", camera=FISHEYE_ONLY_CAMERA | _camera_overrides),
        SensorConfig(name="downward", kind="pinhole"),
    )
    sc = dataclasses.replace(sc, rig=rig)
    env = RoverEnv(scenario=sc, obs_source="estimated", preset=preset, estimator=factory)
    try:
        controller = PathFollower.for_env(env)
        controller.reset()
        obs, info = env.reset(seed=seed)
        truth, shade = [], []
        while True:
            obs, _, term, trunc, info = env.step(controller.act(obs))
            gt = info["ground_truth"]
            truth.append((info["t"], gt["twist"][0], gt["twist"][1], gt["twist"][2]))
            if shadow_truth:
                shade.append((info["t"], _shadow_share(env, holder["est"])))
            if term or trunc:
                break
    finally:
        env.close()
    return holder["est"].records, np.array(truth), np.array(shade).reshape(-1, 2)


def _builtin_kwargs(factory, rig) -> dict:
    """The keywords the built-in factory gives RoverEstimator (its odometry settings, windows, start)."""
    est = factory(rig)
    return {
        "odometry": est.odometry.config,
        "fisheye_window": est.fisheye_window,
        "zero_steering_at_start": est.zero_steering_at_start,
    }


def pairs(records, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_mid, estimate (n, 3), valid (n,)) and the truth mid-pair (n, 3), within the drive."""
    r = np.array(records, dtype=float).reshape(-1, 6)
    mid = r[:, 0] - 0.5 * r[:, 1]
    keep = (mid >= truth[0, 0]) & (mid <= truth[-1, 0])
    r, mid = r[keep], mid[keep]
    ref = np.column_stack([np.interp(mid, truth[:, 0], truth[:, k]) for k in (1, 2, 3)])
    return mid, r[:, 3:6], r[:, 2] > 0, ref


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--missions", nargs="+", default=["Rover-v0", "RoverRoughSlippery-v0", "RoverShadows-v0"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--preset", choices=["train", "eval"], default="train")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="FisheyeOdometryConfig fields")
    ap.add_argument(
        "--camera", nargs="*", default=[], metavar="KEY=VALUE", help="fisheye camera fields over the rig's"
    )
    ap.add_argument("--shadow-truth", action="store_true", help="valid share while the shadow is in view")
    ap.add_argument("--out", help="also write the tables to this Markdown file")
    args = ap.parse_args(argv)
    if args.set:
        _Tap.overrides = {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.set)}
    _camera_overrides.update(
        {k: ast.literal_eval(v) for k, v in (item.split("=", 1) for item in args.camera)}
    )
    camera = FISHEYE_ONLY_CAMERA | _camera_overrides
    lines = [
        f"`python benchmarks/fisheye_odometry.py {' '.join(argv if argv is not None else sys.argv[1:])}`",
        "",
        f"preset {args.preset}, seeds {args.seeds}, path follower on the estimates, no IMU; the fisheye "
        f"odometry of the one-camera rig (ground view {camera['roi_ground_deg']:g} deg, rendered at "
        f"{camera['ground_oversample']:g} of the parts' resolution"
        + (f", {_Tap.overrides}" if _Tap.overrides else "")
        + ")",
        "",
        "| mission | camera | v_x MAE [m/s] | v_y MAE [m/s] | omega MAE [rad/s] | valid pairs |"
        " fisheye / downward (v_x, v_y, omega) |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    second = [
        "",
        "| mission | pairs | fisheye speed error, straight / turning | fisheye yaw-rate MAE, straight / "
        "turning [rad/s] | downward speed error, straight / turning | valid while the shadow is in view |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for mission in args.missions:
        per = {c: [] for c in CAMERAS}
        shades = []
        for seed in args.seeds:
            rec, truth, shade = run(mission, seed, args.preset, args.shadow_truth)
            for c in CAMERAS:
                per[c].append(pairs(rec[c], truth))
            shades.append(shade)
        out = {}
        for c in CAMERAS:
            est = np.vstack([p[1] for p in per[c]])
            valid = np.concatenate([p[2] for p in per[c]])
            ref = np.vstack([p[3] for p in per[c]])
            out[c] = (np.abs(est[valid] - ref[valid]).mean(axis=0), float(valid.mean()), est, valid, ref)
        ratio = out["fisheye"][0] / out["downward"][0]
        for c in CAMERAS:
            mae, share = out[c][:2]
            extra = ", ".join(f"{x:.2f}" for x in ratio) if c == "fisheye" else ""
            cells = f"{mae[0]:.4f} | {mae[1]:.4f} | {mae[2]:.4f} | {100 * share:.1f} %"
            lines.append(f"| {mission} | {c} | {cells} | {extra} |")

        def split(c, out=out):
            _, _, est, valid, ref = out[c]
            speed, speed_hat = np.hypot(ref[:, 0], ref[:, 1]), np.hypot(est[:, 0], est[:, 1])
            res = []
            for turning in (False, True):
                sel = valid & (speed > 0.1) & ((np.abs(ref[:, 2]) >= 0.05) == turning)
                if not sel.any():
                    res.append((math.nan, math.nan, 0))
                    continue
                err = np.abs(speed_hat[sel] - speed[sel]).mean() / speed[sel].mean()
                res.append((100.0 * err, float(np.abs(est[sel, 2] - ref[sel, 2]).mean()), int(sel.sum())))
            return res

        f_s, f_t = split("fisheye")
        d_s, d_t = split("downward")
        shadow_cell = "-"
        if args.shadow_truth:
            inview, valid_in = 0, 0
            for (mid, _, valid, _), shade in zip(per["fisheye"], shades, strict=True):
                share = np.interp(mid, shade[:, 0], shade[:, 1])
                sel = share >= 0.05
                inview += int(sel.sum())
                valid_in += int((valid & sel).sum())
            shadow_cell = f"{100 * valid_in / max(inview, 1):.1f} % of {inview}"
        second.append(
            f"| {mission} | {f_s[2]} / {f_t[2]} | {f_s[0]:.2f} % / {f_t[0]:.2f} % "
            f"| {f_s[1]:.4f} / {f_t[1]:.4f} | {d_s[0]:.2f} % / {d_t[0]:.2f} % | {shadow_cell} |"
        )
        print(lines[-2] + "\n" + lines[-1], flush=True)
    text = "\n".join(lines + second) + "\n"
    print(text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Ablations: what each of the estimator's and renderer's design choices buys, on the current code.

Each ablation runs the same drives twice (or more), with the choice as it ships and without it,
and prints one table row per variant. The estimator's variants go through the environment's
``estimator=`` keyword (:func:`rover_env.sensors.rig.builtin_estimator` with one parameter
changed), the cameras' through the scenario's rig, the renderer's through a
:class:`~rover_env.rendering.gl.GLRenderer` made with other arguments; the physics and the drive
are the same in every variant.

Ablations (``python benchmarks/ablations.py NAME ...``; all of them by default):

- ``grip``: the slip filter's zero-slip pseudo-measurement of gripping wheels
  (``SlipConfig.grip_std`` 0.03 against 0): slip error of gripping wheels, closed-loop drives of
  ``RoverRoughSlippery-v0`` at the train preset.
- ``features``: the train preset's odometry (100 features out to 5 % of the border) against the
  paper's defaults scaled to 160 px (50 features, 15 %): yaw-rate and speed errors, same drives.
- ``odometry_gyro``: with a BMI088, the gyro's roll and pitch rates given to the odometry's 3-D
  fit or not: speed error, same drives.
- ``peer``: the fisheye's check of a wheel's rotation against the other wheels
  (``KinematicsConfig.peer_tolerance`` 0.05 rad against none): slip events, slip drives
  (:mod:`slip_accuracy`) of ``RoverShadows-v0``.
- ``check_strong``: the features' check also of strong tread correlations
  (``TreadConfig.check_strong``): slip events and time per step, same slip drives.
- ``shadow_px``: the GL shadow map's edge (2048 against 8192 texels): wheel-rate error, slip
  events and time per step, same slip drives.
- ``lod_bias``: GL's texture sampling one mipmap level sharper than the footprint asks
  (``LOD_BIAS`` -1 against 0): slip events, slip drives of ``Rover-v0`` and ``RoverShadows-v0``.
- ``fisheye_readout``: the fisheye rendered whole, as its region of interest, or as the windows
  of that region the estimator asks for (the shipped presets): fisheye rendering time per frame
  and the share of its pixels drawn (not black), closed-loop drives of ``Rover-v0`` at both
  presets.

Run: ``LP_NUM_THREADS=1 python benchmarks/ablations.py [NAME ...] [--renderer gl]`` (seeds the tests
never use; each ablation names its own). Results: ``benchmarks/results/gl/ablations.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import observation_errors  # noqa: E402
import slip_accuracy  # noqa: E402

import rover_env  # noqa: E402
from perception.fusion.slip import SlipConfig  # noqa: E402
from perception.kinematics.fisheye import KinematicsConfig  # noqa: E402
from perception.kinematics.wheel_rotation import TreadConfig  # noqa: E402
from rover_env.config.rig import standard_rig  # noqa: E402
from rover_env.sensors.rig import builtin_estimator  # noqa: E402
from rover_env.tools.estimator_metrics import FIELDS, START_UP, slip_metrics  # noqa: E402

COURSE_SECONDS = 40.0
SLIP_SECONDS = 20.0


# ------------------------------------------------------------------ variants
def gl_with(**kwargs) -> Callable:
    """A ``setup(env)`` that gives the environment a GL renderer made with ``kwargs``."""

    def setup(env) -> None:
        from rover_env.rendering.gl import GLRenderer

        sim = env.unwrapped.sim
        rv = sim.rover
        links = {(rv.body_id, link): path for link, path in rv.link_textures.items()}
        made = sim.attachment(
            "renderer", lambda: GLRenderer(sim.client, sim.terrain, link_textures=links, **kwargs)
        )
        if not isinstance(made, GLRenderer):
            raise RuntimeError("the environment made its renderer before the ablation could")

    return setup


def fisheye_rig(env_id: str, **camera) -> dict:
    """``gym.make`` keywords: ``env_id``'s scenario with the standard rig's fisheye settings changed."""
    scenario = rover_env.load_scenario(rover_env.MISSIONS[env_id])
    rig = tuple(
        dataclasses.replace(s, camera=camera) if s.kind == "fisheye" else s
        for s in standard_rig(scenario.imu)
    )
    return {"scenario": dataclasses.replace(scenario, rig=rig)}


def timed_fisheye(store: dict) -> Callable:
    """A ``setup(env)`` that times the fisheye's rendering and counts the pixels it draws."""

    def setup(env) -> None:
        cam = env.unwrapped.pipeline.fisheye
        render = cam._render

        def _render(*args, **kwargs):
            t0 = time.perf_counter()
            view = render(*args, **kwargs)
            store.setdefault("ms", []).append(1e3 * (time.perf_counter() - t0))
            store.setdefault("drawn", []).append(float(np.any(view.rgb > 0, axis=2).mean()))
            return view

        cam._render = _render

    return setup


# ------------------------------------------------------------------ runs
def course(env_id, seeds, preset, renderer, make=None, setup=None) -> list[dict]:
    return [
        observation_errors.run(env_id, s, preset, COURSE_SECONDS, renderer, make=make, setup=setup)
        for s in seeds
    ]


def slip_drives(env_id, seeds, preset, renderer, make=None, setup=None) -> list[dict]:
    span = slip_accuracy.patch_span(env_id)
    return [
        slip_accuracy.drive(s, preset, env_id, span, SLIP_SECONDS, 0.05, renderer, make=make, setup=setup)
        for s in seeds
    ]


def ms_per_step(runs) -> float:
    steps = sum(r.get("steps", len(r["t"])) for r in runs)
    return 1e3 * sum(r["wall"] for r in runs) / steps


def field(runs, name: str) -> tuple[float, float]:
    """(MAE, p95) of |estimate - truth| of the field ``name``, or of all fields ``name_*`` together."""
    cols = [j for j, f in enumerate(FIELDS) if f == name or f.startswith(name + "_")]
    err = np.concatenate([np.abs(r["est"] - r["tru"])[r["t"] >= START_UP][:, cols].ravel() for r in runs])
    return float(err.mean()), float(np.percentile(err, 95))


def speed_error(runs, above: float = 0.5) -> float:
    """Standard deviation of the estimated speed's relative error [%] where the true |v_x| > ``above`` m/s."""
    j = FIELDS.index("v_x")
    rel = []
    for r in runs:
        keep = (r["t"] >= START_UP) & (np.abs(r["tru"][:, j]) > above)
        rel.append((r["est"][keep, j] - r["tru"][keep, j]) / r["tru"][keep, j])
    rel = np.concatenate(rel)
    return 100.0 * float(np.std(rel)) if len(rel) else math.nan


def events_row(runs) -> str:
    m = slip_metrics(runs)
    return (
        f"{m['events']} | {m['false']} | {m['in_band']} | {m['missed']} | {m['precision']:.2f} "
        f"| {m['recall']:.2f} | {m['f1']:.2f} | {m['mae_slip']:.3f} | {m['mae_calm']:.3f}"
    )


EVENTS_HEAD = (
    "| variant | true events | false | in band | missed | precision | recall | F1 | slip MAE, abs(s) > 0.1 "
    "| slip MAE, otherwise | wheel rate MAE / p95 [rad/s] | ms a step |\n"
    "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
)


def events_table(variants: dict[str, list[dict]]) -> None:
    print(EVENTS_HEAD)
    for name, runs in variants.items():
        mae, p95 = field(runs, "wheel_rate")
        print(
            f"| {name} | {events_row(runs)} | {mae:.3f} / {p95:.3f} | {ms_per_step(runs):.1f} |", flush=True
        )


# ------------------------------------------------------------------ ablations
ROUGH, ROUGH_SEEDS = "RoverRoughSlippery-v0", [301, 302]
SHADOWS, SHADOW_SEEDS = "RoverShadows-v0", [301, 302, 303, 304, 305, 306]


def title(what: str, env_id: str, seeds, drives: str, extra: str = "") -> None:
    print(f"\n## {what}\n\n{env_id}, train preset{extra}, seeds {seeds}, {drives}\n", flush=True)


def table_head(*columns: str) -> None:
    print("| variant | " + " | ".join(columns) + " |")
    print("|---|" + "---:|" * len(columns))


def ab_grip(renderer: str) -> None:
    title("grip: the zero-slip pseudo-measurement", ROUGH, ROUGH_SEEDS, "closed loop")
    table_head("slip MAE, gripping (abs(s) <= 0.1)", "slip MAE, abs(s) > 0.1", "v_x MAE [m/s]")
    for name, grip in (("grip_std 0.03 (shipped)", 0.03), ("grip_std 0 (none)", 0.0)):
        factory = builtin_estimator("train", slip=SlipConfig(grip_std=grip))
        m = slip_metrics(runs := course(ROUGH, ROUGH_SEEDS, "train", renderer, make={"estimator": factory}))
        vx = field(runs, "v_x")[0]
        print(f"| {name} | {m['mae_calm']:.4f} | {m['mae_slip']:.3f} | {vx:.4f} |", flush=True)


def ab_features(renderer: str) -> None:
    title("features: the train preset's odometry", ROUGH, ROUGH_SEEDS, "closed loop")
    table_head("yaw rate MAE / p95 [rad/s]", "v_x MAE / p95 [m/s]", "v_y MAE [m/s]", "speed error [%]")
    variants = {
        "100 features, 5 % border (shipped)": {},
        "50 features, 15 % border (the paper's)": {"max_features": 50, "roi_margin": 0.15},
    }
    for name, odometry in variants.items():
        factory = builtin_estimator("train", odometry_overrides=odometry)
        runs = course(ROUGH, ROUGH_SEEDS, "train", renderer, make={"estimator": factory})
        w, vx, vy = field(runs, "omega"), field(runs, "v_x"), field(runs, "v_y")
        row = f"{w[0]:.4f} / {w[1]:.4f} | {vx[0]:.4f} / {vx[1]:.4f} | {vy[0]:.4f} | {speed_error(runs):.1f}"
        print(f"| {name} | {row} |", flush=True)


def ab_odometry_gyro(renderer: str) -> None:
    title(
        "odometry_gyro: the gyro's roll and pitch rates in the odometry's fit",
        ROUGH,
        ROUGH_SEEDS,
        "closed loop",
        ", a BMI088",
    )
    table_head(
        "speed error [%] (std, relative, above 0.5 m/s)", "v_x MAE / p95 [m/s]", "yaw rate MAE [rad/s]"
    )
    for name, on in (("with the gyro's rates (shipped)", True), ("without", False)):
        make = {"estimator": builtin_estimator("train", odometry_gyro=on), "imu": "bmi088"}
        runs = course(ROUGH, ROUGH_SEEDS, "train", renderer, make=make)
        vx, w = field(runs, "v_x"), field(runs, "omega")
        print(f"| {name} | {speed_error(runs):.1f} | {vx[0]:.4f} / {vx[1]:.4f} | {w[0]:.4f} |", flush=True)


def ab_peer(renderer: str) -> None:
    title("peer: the fisheye's check against the other wheels", SHADOWS, SHADOW_SEEDS, "slip drives")
    variants = {}
    for name, tol in (("peer_tolerance 0.05 rad (shipped)", 0.05), ("no peer check", math.inf)):
        factory = builtin_estimator("train", kinematics=KinematicsConfig(peer_tolerance=tol))
        variants[name] = slip_drives(SHADOWS, SHADOW_SEEDS, "train", renderer, make={"estimator": factory})
    events_table(variants)


def ab_check_strong(renderer: str) -> None:
    title(
        "check_strong: the features check strong tread correlations too", SHADOWS, SHADOW_SEEDS, "slip drives"
    )
    variants = {}
    for name, on in (("strong correlations taken (shipped)", False), ("check_strong=True", True)):
        kinematics = KinematicsConfig(tread=TreadConfig(check_strong=on))
        factory = builtin_estimator("train", kinematics=kinematics)
        variants[name] = slip_drives(SHADOWS, SHADOW_SEEDS, "train", renderer, make={"estimator": factory})
    events_table(variants)


def ab_shadow_px(renderer: str) -> None:
    if renderer != "gl":
        print("\n## shadow_px: GL only; skipped")
        return
    title("shadow_px: the GL shadow map's edge", SHADOWS, SHADOW_SEEDS, "slip drives")
    variants = {}
    for px in (2048, 8192):
        name = f"{px} texels" + (" (shipped)" if px == 2048 else "")
        variants[name] = slip_drives(SHADOWS, SHADOW_SEEDS, "train", renderer, setup=gl_with(shadow_px=px))
    events_table(variants)


def ab_lod_bias(renderer: str) -> None:
    if renderer != "gl":
        print("\n## lod_bias: GL only; skipped")
        return
    seeds = [201, 202, 203]
    for env_id in ("Rover-v0", SHADOWS):
        title("lod_bias: the mipmap level bias", env_id, seeds, "slip drives")
        variants = {}
        for bias in (-1.0, 0.0):
            name = f"LOD_BIAS {bias:+.0f}" + (" (shipped)" if bias == -1 else "")
            variants[name] = slip_drives(env_id, seeds, "train", renderer, setup=gl_with(lod_bias=bias))
        events_table(variants)


def ab_fisheye_readout(renderer: str) -> None:
    env_id = "Rover-v0"
    for preset, seeds in (("train", [301, 302, 303]), ("eval", [301])):
        print(f"\n## fisheye_readout\n\n{env_id}, {preset} preset, seeds {seeds}, closed loop\n", flush=True)
        table_head(
            "fisheye rendering [ms a frame]", "pixels drawn", "wheel rate MAE [rad/s]", "axle roll MAE [rad]"
        )
        variants = {
            "whole frame": (fisheye_rig(env_id, roi=False), None),
            "region of interest": (fisheye_rig(env_id, roi=True), None),
            "windows of the region (shipped)": ({}, "preset"),
        }
        for name, (make, window) in variants.items():
            store: dict = {}
            make = make | {"estimator": builtin_estimator(preset, fisheye_window=window)}
            runs = course(env_id, seeds, preset, renderer, make=make, setup=timed_fisheye(store))
            ms, drawn = np.median(store["ms"]), 100 * np.mean(store["drawn"])
            wheel, roll = field(runs, "wheel_rate")[0], field(runs, "axle_roll")[0]
            print(f"| {name} | {ms:.1f} | {drawn:.0f} % | {wheel:.3f} | {roll:.4f} |", flush=True)


ABLATIONS = {
    "grip": ab_grip,
    "features": ab_features,
    "odometry_gyro": ab_odometry_gyro,
    "peer": ab_peer,
    "check_strong": ab_check_strong,
    "shadow_px": ab_shadow_px,
    "lod_bias": ab_lod_bias,
    "fisheye_readout": ab_fisheye_readout,
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help=f"ablations, of {list(ABLATIONS)} (default: all)")
    ap.add_argument("--renderer", default="gl", choices=("gl", "tiny"))
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in ABLATIONS]
    if unknown:
        ap.error(f"unknown ablation(s) {unknown}; choose from {list(ABLATIONS)}")
    print(f"# Ablations, renderer {args.renderer}")
    for name in args.names or list(ABLATIONS):
        t0 = time.perf_counter()
        ABLATIONS[name](args.renderer)
        print(f"\n({name}: {time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

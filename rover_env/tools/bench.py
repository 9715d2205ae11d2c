"""Benchmarks of the simulation: physics-only real-time factor, and milliseconds per camera frame."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from rover_env.config.rig import PresetName
from rover_env.envs.rover_env import ObsSourceName, RoverEnv


@dataclass(frozen=True)
class PhysicsBenchResult:
    """One row of the physics benchmark.

    Attributes:
        scenario: Scenario name.
        steps_per_s: Environment steps per second (control steps, wall clock).
        real_time_factor: Simulated seconds per wall-clock second.
        ms_per_step: Wall-clock milliseconds per environment step.
        us_per_physics_step: Wall-clock microseconds inside ``stepSimulation`` per physics step,
            measured during the same run.
        physics_share: Fraction of the wall time spent inside ``stepSimulation``.
        physics_bound_rtf: Real-time factor if everything outside ``stepSimulation`` were free:
            the ceiling that PyBullet itself sets at this physics rate.
    """

    scenario: str
    steps_per_s: float
    real_time_factor: float
    ms_per_step: float
    us_per_physics_step: float
    physics_share: float
    physics_bound_rtf: float


def _slalom(steps: int) -> list[np.ndarray]:
    """Drive-mode actions of a slalom at 1 m/s: wheels, steering and suspension all work."""
    return [np.array([0.5, 0.5 * np.sin(k / 15), -0.5 * np.sin(k / 15)], np.float32) for k in range(steps)]


@dataclass(frozen=True)
class EnvBenchResult:
    """One row of the whole-environment benchmark.

    Attributes:
        scenario: Scenario name.
        obs_source: ``ground_truth`` (physics only) or ``estimated`` (cameras and perception).
        preset: Camera preset of the estimator (unused with ground truth).
        steps_per_s: Environment steps per second (control steps, wall clock).
        real_time_factor: Simulated seconds per wall-clock second.
    """

    scenario: str
    obs_source: ObsSourceName
    preset: PresetName
    steps_per_s: float
    real_time_factor: float


def bench_env(
    scenario: str,
    obs_source: ObsSourceName,
    preset: PresetName = "train",
    steps: int = 90,
    control_hz: float = 30.0,
    seed: int = 0,
) -> EnvBenchResult:
    """Time ``steps`` environment steps of the slalom with ``obs_source`` on one core."""
    env = RoverEnv(scenario=scenario, control_hz=control_hz, obs_source=obs_source, preset=preset)
    try:
        env.reset(seed=seed)
        actions = _slalom(steps)
        for a in actions[:10]:  # warm up
            env.step(a)
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        wall = time.perf_counter() - t0
    finally:
        env.close()
    return EnvBenchResult(scenario, obs_source, preset, steps / wall, steps / control_hz / wall)


def bench_physics(
    scenario: str, steps: int = 600, control_hz: float = 30.0, seed: int = 0
) -> PhysicsBenchResult:
    """Time ``steps`` environment steps of physics only on one core: a ground-truth environment.

    No camera is attached, so nothing renders. The rover drives a slalom at 1 m/s so that
    wheels, steering and suspension all work. Time inside ``stepSimulation`` is accumulated
    during the same run, so the split between PyBullet and the Python around it is measured,
    not estimated.
    """
    env = RoverEnv(scenario=scenario, control_hz=control_hz, obs_source="ground_truth")
    try:
        env.reset(seed=seed)
        actions = _slalom(steps)
        for a in actions[:30]:  # warm up
            env.step(a)
        sim = env.sim
        raw_step = sim._step_physics
        spent = [0.0, 0]
        clock = time.perf_counter

        def timed_step() -> None:
            t = clock()
            raw_step()
            spent[0] += clock() - t
            spent[1] += 1

        sim._step_physics = timed_step
        t0 = clock()
        for a in actions:
            env.step(a)
        wall = clock() - t0
        sim._step_physics = raw_step
    finally:
        env.close()
    sim_time = steps / control_hz
    return PhysicsBenchResult(
        scenario=scenario,
        steps_per_s=steps / wall,
        real_time_factor=sim_time / wall,
        ms_per_step=wall / steps * 1e3,
        us_per_physics_step=spent[0] / max(spent[1], 1) * 1e6,
        physics_share=spent[0] / wall,
        physics_bound_rtf=sim_time / spent[0],
    )


def format_env_table(rows: list[EnvBenchResult]) -> str:
    """Markdown table of whole-environment rows."""
    lines = [
        "| scenario | observation | preset | env steps/s | real-time factor |",
        "|---|---|---|---:|---:|",
    ]
    for r in rows:
        preset = r.preset if r.obs_source == "estimated" else "-"
        lines.append(
            f"| {r.scenario} | {r.obs_source} | {preset} | {r.steps_per_s:.1f} | {r.real_time_factor:.2f}x |"
        )
    return "\n".join(lines)


def format_table(rows: list[PhysicsBenchResult]) -> str:
    """Markdown table of benchmark rows."""
    lines = [
        "| scenario | env steps/s | real-time factor | ms/step | us/stepSimulation | "
        "time in stepSimulation | real-time factor if Python were free |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.scenario} | {r.steps_per_s:.0f} | {r.real_time_factor:.1f}x | "
            f"{r.ms_per_step:.2f} | {r.us_per_physics_step:.0f} | {100 * r.physics_share:.0f} % | "
            f"{r.physics_bound_rtf:.1f}x |"
        )
    return "\n".join(lines)


@dataclass(frozen=True)
class CameraBenchResult:
    """One row of the camera benchmark (median over the frames).

    Attributes:
        camera: ``downward`` or ``fisheye``.
        preset: Resolution preset (``full`` 640x480, ``half`` 320x240, ``train`` 160x120).
        renderer: ``tiny`` (TinyRenderer) or ``gl`` (OpenGL, :mod:`rover_env.rendering.gl`).
        shadows: Sun shadows on.
        ms_per_frame: Wall-clock milliseconds per captured frame.
        ms_remap: Fisheye only: the atlas-to-image remap alone [ms] (NaN for the pinhole).
        face_pixels: Pixels rendered per frame (the fisheye renders cube faces).
    """

    camera: str
    preset: str
    renderer: str
    shadows: bool
    ms_per_frame: float
    ms_remap: float
    face_pixels: int


def bench_cameras(
    scenario: str = "flat_patches",
    presets: tuple[str, ...] = ("full", "half", "train"),
    frames: int = 8,
    renderers: tuple[str, ...] = ("tiny", "gl"),
) -> list[CameraBenchResult]:
    """Time frame capture of both cameras at each preset and renderer, with and without shadows.

    The rover drives between frames so that every frame sees a new scene (and a new shadow). GL
    rows are left out, with a warning, where no OpenGL context can be created.
    """
    import logging
    import math

    from rover_env.config.cameras import DownwardCameraConfig, FisheyeCameraConfig, check_renderer
    from rover_env.config.scenario import load_scenario
    from rover_env.rendering import resolve_renderer
    from rover_env.sensors.cameras import DownwardCamera, FisheyeCamera
    from rover_env.sim.simulation import RoverSim

    rows: list[CameraBenchResult] = []
    for renderer in renderers:
        try:
            sim = RoverSim(load_scenario(scenario), renderer=resolve_renderer(check_renderer(renderer)))
        except RuntimeError as exc:
            logging.getLogger(__name__).warning("no %s rows: %s", renderer, exc)
            continue
        try:
            sim.reset(0.0, 0.0, 0.3)
            sim.rover.command(np.full(4, 5.0), 0.2, -0.2)
            for preset in presets:
                for shadows in (True, False):
                    down = DownwardCamera(sim, DownwardCameraConfig.preset(preset, shadows=shadows))
                    fish = FisheyeCamera(sim, FisheyeCameraConfig.preset(preset, shadows=shadows))
                    for name, cam in (("downward", down), ("fisheye", fish)):
                        cam.capture()  # warm-up
                        times = []
                        for _ in range(frames):
                            sim.step(1 / 30)
                            t = time.perf_counter()
                            cam.capture()
                            times.append(time.perf_counter() - t)
                        remap_ms = math.nan
                        if name == "fisheye":
                            rm = fish.remapper
                            atlas = rm.atlas(
                                [np.zeros((*fc.size[::-1], 3), np.uint8) + 90 for fc in rm.faces]
                            )
                            rt = []
                            for _ in range(30):
                                t = time.perf_counter()
                                rm.remap(atlas)
                                rt.append(time.perf_counter() - t)
                            remap_ms = float(np.median(rt)) * 1e3
                            pixels = rm.face_pixels
                        else:
                            pixels = down.config.width * down.config.height
                        rows.append(
                            CameraBenchResult(
                                name,
                                preset,
                                renderer,
                                shadows,
                                float(np.median(times)) * 1e3,
                                remap_ms,
                                pixels,
                            )
                        )
        finally:
            sim.close()
    return rows


def format_camera_table(rows: list[CameraBenchResult]) -> str:
    """Markdown table of camera rows, with fisheye/downward ratios measured in the same run."""
    down = {(r.preset, r.renderer, r.shadows): r.ms_per_frame for r in rows if r.camera == "downward"}
    lines = [
        "| camera | preset | renderer | shadows | ms/frame | rendered px | remap ms | fisheye / downward |",
        "|---|---|---|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        ratio = ""
        if r.camera == "fisheye" and (r.preset, r.renderer, r.shadows) in down:
            ratio = f"{r.ms_per_frame / down[(r.preset, r.renderer, r.shadows)]:.2f}"
        remap = "" if r.camera == "downward" else f"{r.ms_remap:.2f}"
        lines.append(
            f"| {r.camera} | {r.preset} | {r.renderer} | {'on' if r.shadows else 'off'} | "
            f"{r.ms_per_frame:.1f} | {r.face_pixels} | {remap} | {ratio} |"
        )
    return "\n".join(lines)

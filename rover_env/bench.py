"""Benchmarks of the simulation: physics-only environment steps per second, real-time factor."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from rover_env.envs.rover_env import RoverEnv


@dataclass(frozen=True)
class PhysicsBenchResult:
    """One row of the physics benchmark.

    Attributes:
        scenario: Scenario name.
        steps_per_s: Environment steps per second (control steps, wall clock).
        real_time_factor: Simulated seconds per wall-clock second.
        ms_per_step: Wall-clock milliseconds per environment step.
        us_per_physics_step: Wall-clock microseconds per physics substep (stepSimulation only).
        us_per_substep_python: Python work per substep: springs and friction map [us].
    """

    scenario: str
    steps_per_s: float
    real_time_factor: float
    ms_per_step: float
    us_per_physics_step: float
    us_per_substep_python: float


def bench_physics(
    scenario: str, steps: int = 600, control_hz: float = 30.0, seed: int = 0
) -> PhysicsBenchResult:
    """Time ``steps`` environment steps of physics only (no rendering) on one core.

    The rover drives a slalom at 1 m/s so that wheels, steering and suspension all work.
    """
    env = RoverEnv(scenario=scenario, control_hz=control_hz)
    try:
        env.reset(seed=seed)
        actions = [
            np.array([0.5, 0.5 * np.sin(k / 15), -0.5 * np.sin(k / 15)], np.float32) for k in range(steps)
        ]
        for a in actions[:30]:  # warm up
            env.step(a)
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        wall = time.perf_counter() - t0
        sim = env.sim
        n = 2000
        t0 = time.perf_counter()
        for _ in range(n):
            sim.client.stepSimulation()
        t_step = (time.perf_counter() - t0) / n
        t0 = time.perf_counter()
        for _ in range(n):
            sim.rover.apply_passive()
            sim.rover.apply_friction(sim.terrain)
        t_py = (time.perf_counter() - t0) / n
    finally:
        env.close()
    return PhysicsBenchResult(
        scenario=scenario,
        steps_per_s=steps / wall,
        real_time_factor=steps / control_hz / wall,
        ms_per_step=wall / steps * 1e3,
        us_per_physics_step=t_step * 1e6,
        us_per_substep_python=t_py * 1e6,
    )


def format_table(rows: list[PhysicsBenchResult]) -> str:
    """Markdown table of benchmark rows."""
    lines = [
        "| scenario | env steps/s | real-time factor | ms/step | us/stepSimulation | us/substep python |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r.scenario} | {r.steps_per_s:.0f} | {r.real_time_factor:.1f}x | "
            f"{r.ms_per_step:.2f} | {r.us_per_physics_step:.0f} | {r.us_per_substep_python:.0f} |"
        )
    return "\n".join(lines)

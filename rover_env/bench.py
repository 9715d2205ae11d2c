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


def bench_physics(
    scenario: str, steps: int = 600, control_hz: float = 30.0, seed: int = 0
) -> PhysicsBenchResult:
    """Time ``steps`` environment steps of physics only (no rendering) on one core.

    The rover drives a slalom at 1 m/s so that wheels, steering and suspension all work.
    Time inside ``stepSimulation`` is accumulated during the same run, so the split between
    PyBullet and the Python around it is measured, not estimated.
    """
    env = RoverEnv(scenario=scenario, control_hz=control_hz)
    try:
        env.reset(seed=seed)
        actions = [
            np.array([0.5, 0.5 * np.sin(k / 15), -0.5 * np.sin(k / 15)], np.float32) for k in range(steps)
        ]
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

"""A single-wheel test bed in PyBullet, as terramechanics laboratories run one.

A carriage moves along x at a constant speed; a hanger on it is free to move vertically and
carries the load (its weight and the wheel's); the wheel turns on the hanger at the rate that
makes the slip asked for. The soil (:class:`rover_env.sim.soil_contact.SoilContact`) is the
only thing under the wheel. Each slip starts on fresh soil from the wheel settled at rest under
its load, drives the carriage ``distance`` metres (the rim as far at slip 1; several contact
lengths, as the soil's shear builds over one) and averages the last 40 %:

- drawbar pull: the force the carriage's drive holds the hanger back with (its load cell),
- load: the soil's vertical force on the wheel,
- sinkage: the depth of the grousers' tips (the rim for a smooth wheel) below the surface,
- torque: the torque the wheel's motor applies.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pybullet as pb
from pybullet_utils.bullet_client import BulletClient

from rover_env.config.io import ConfigError, check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.geometry import GRAVITY
from rover_env.sim.soil_contact import SoilContact
from rover_env.sim.terramechanics import WheelSpec, slip_velocities

log = logging.getLogger(__name__)

COLUMNS = ("slip", "drawbar_pull_N", "load_N", "sinkage_m", "torque_Nm")


@dataclass(frozen=True)
class WheelTestRow:
    """One slip's steady state on the test bed (SI units; see the module's docstring)."""

    slip: float
    drawbar_pull_N: float
    load_N: float
    sinkage_m: float
    torque_Nm: float


def run_wheel_test(
    soil: SoilConfig,
    wheel: WheelSpec,
    load: float,
    slips,
    *,
    speed: float = 0.01,
    distance: float = 1.0,
    settle: float = 1.0,
    dt: float = 1.0 / 240.0,
) -> list[WheelTestRow]:
    """Drive ``wheel`` on ``soil`` under ``load`` [N] at each slip in ``slips``.

    Args:
        soil: The soil.
        wheel: The wheel.
        load: Vertical load on the wheel [N], > 0.
        slips: Slip ratios in [-1, 1] (1: spinning in place; -1: locked).
        speed: Carriage speed [m/s] (the wheel's rim speed at slip 1).
        distance: How far the carriage travels per slip [m]; the last 40 % is averaged.
        settle: Time the wheel settles at rest under its load before each run [s].
        dt: Physics step [s].

    Raises:
        ConfigError: A load <= 0, a slip outside [-1, 1], or another impossible figure.
    """
    check_range("load", load, 0.0, 1e6, lo_open=True)
    slips = [float(s) for s in np.atleast_1d(np.asarray(slips, dtype=np.float64))]
    for s in slips:
        if not -1.0 <= s <= 1.0:
            raise ConfigError(
                f"slip: {s!r} is outside [-1, 1]; give slip ratios from -1 (locked) to 1 (spinning)"
            )
    check_range("speed", speed, 0.0, 10.0, lo_open=True)
    check_range("distance", distance, 0.0, 100.0, lo_open=True)
    check_range("settle", settle, 0.0, 3600.0)
    bed = _Bed(soil, wheel, load, dt)
    try:
        bed.settle(settle)
        rows = []
        for s in slips:
            rows.append(bed.run(s, speed, distance / speed))
            if abs(rows[-1].load_N / load - 1.0) > 0.01:
                log.warning(
                    "slip %+.2f: the soil carried %.1f N of the %.1f N load (the wheel was still sinking);"
                    " drive further (distance) or lighten the load",
                    s,
                    rows[-1].load_N,
                    load,
                )
            log.info(
                "slip %+.2f: DP/W %+.3f, sinkage %.1f mm",
                s,
                rows[-1].drawbar_pull_N / load,
                1e3 * rows[-1].sinkage_m,
            )
        return rows
    finally:
        bed.close()


class _Bed:
    """The carriage, hanger and wheel in their own PyBullet client."""

    def __init__(self, soil: SoilConfig, wheel: WheelSpec, load: float, dt: float) -> None:
        from rover_env.sim._quiet import quiet_c_output

        with quiet_c_output():
            self.c = BulletClient(connection_mode=pb.DIRECT)
        self.wheel, self.load, self.dt = wheel, float(load), float(dt)
        self.c.setGravity(0, 0, -GRAVITY)
        self.c.setPhysicsEngineParameter(fixedTimeStep=dt, numSubSteps=1)
        m_total = self.load / GRAVITY
        m_wheel = min(1.0, 0.3 * m_total)
        r = wheel.radius
        i_wheel = 0.5 * m_wheel * r * r
        self.body = self.c.createMultiBody(
            baseMass=0.0,
            basePosition=[0.0, 0.0, wheel.shear_radius],
            linkMasses=[5.0, m_total - m_wheel, m_wheel],
            linkCollisionShapeIndices=[-1, -1, -1],
            linkVisualShapeIndices=[-1, -1, -1],
            linkPositions=[[0, 0, 0]] * 3,
            linkOrientations=[[0, 0, 0, 1]] * 3,
            linkInertialFramePositions=[[0, 0, 0]] * 3,
            linkInertialFrameOrientations=[[0, 0, 0, 1]] * 3,
            linkParentIndices=[0, 1, 2],
            linkJointTypes=[pb.JOINT_PRISMATIC, pb.JOINT_PRISMATIC, pb.JOINT_REVOLUTE],
            linkJointAxis=[[1, 0, 0], [0, 0, 1], [0, 1, 0]],
        )
        self.c.changeDynamics(self.body, 2, localInertiaDiagonal=[i_wheel, i_wheel, i_wheel])
        for link in (-1, 0, 1, 2):
            self.c.changeDynamics(self.body, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0)
        # the hanger is free: no motor holds it
        self.c.setJointMotorControl2(self.body, 1, pb.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0)
        self.soil = SoilContact(soil, wheel, 1, dt)
        self.rs = wheel.shear_radius
        self._start = self.c.saveState()

    def _drive(self, v: float, w: float, big: float = 1e5) -> None:
        self.c.setJointMotorControl2(self.body, 0, pb.VELOCITY_CONTROL, targetVelocity=v, force=big)
        self.c.setJointMotorControl2(self.body, 2, pb.VELOCITY_CONTROL, targetVelocity=w, force=big)

    def _substep(self) -> tuple[np.ndarray, float]:
        c = self.c
        st = c.getLinkState(self.body, 2, computeLinkVelocity=1)
        z = st[0][2]
        vx, _, vz = st[6]
        spin = c.getJointState(self.body, 2)[1]
        sink = self.rs - z
        f = self.soil.step(np.array([sink]), np.array([vx]), np.array([spin]), np.zeros(1), np.array([-vz]))[
            0
        ]
        fx, fz, _, torque = (float(v) for v in f)
        c.applyExternalForce(self.body, 2, [fx, 0.0, fz], st[0], pb.WORLD_FRAME)
        # the soil's shear resists the spin about the axle (+y)
        c.applyExternalTorque(self.body, 2, [0.0, -torque, 0.0], pb.WORLD_FRAME)
        c.stepSimulation()
        return f.copy(), sink

    def settle(self, seconds: float) -> None:
        """Let the wheel sink under its load at rest, then keep that as each run's start."""
        self.c.restoreState(self._start)
        self.soil.reset()
        self._drive(0.0, 0.0)
        for _ in range(int(round(seconds / self.dt))):
            self._substep()
        self._settled = self.c.saveState()
        self._soil_state = self.soil.snapshot()

    def run(self, slip: float, speed: float, duration: float) -> WheelTestRow:
        self.c.restoreState(self._settled)
        self.soil.restore(self._soil_state)
        v, w = slip_velocities(np.array([slip]), speed, self.wheel.radius)
        self._drive(float(v[0]), float(w[0]))
        n = int(round(duration / self.dt))
        keep = max(1, int(0.4 * n))
        acc = np.zeros(5)
        for k in range(n):
            f, sink = self._substep()
            if k >= n - keep:
                carriage = self.c.getJointState(self.body, 0)[3]
                motor = self.c.getJointState(self.body, 2)[3]
                acc += (-carriage, f[1], sink, motor, 1.0)
        dp, fz, sink, torque, cnt = acc
        return WheelTestRow(
            slip=float(slip),
            drawbar_pull_N=dp / cnt,
            load_N=fz / cnt,
            sinkage_m=sink / cnt,
            torque_Nm=torque / cnt,
        )

    def close(self) -> None:
        try:
            self.c.disconnect()
        except pb.error:  # pragma: no cover
            pass


def wheel_test_table(rows: list[WheelTestRow]) -> str:
    """The rows as ``wheel_test.csv`` text (header :data:`COLUMNS`)."""
    lines = [",".join(COLUMNS)]
    for r in rows:
        lines.append(
            f"{r.slip:.4f},{r.drawbar_pull_N:.5f},{r.load_N:.5f},{r.sinkage_m:.6f},{r.torque_Nm:.6f}"
        )
    return "\n".join(lines) + "\n"

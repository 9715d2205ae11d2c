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

Before it runs, each slip's steady state (:func:`rover_env.sim.terramechanics.steady_state`)
must be one the test bed can reach: the soil must carry the load before the wheel sinks past its
axle, and the contact's stiffness at that sinkage must be one the physics step resolves (a soil
whose sinkage barely changes with the load rings faster than the step, and the explicit contact
blows up). After it runs, a result that cannot be physical (a negative or non-finite sinkage,
no load carried, a wheel buried past its axle) is an error, not a row. The work is bounded:
a run of more than :data:`MAX_STEPS` physics steps is refused before it starts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pybullet as pb
from pybullet_utils.bullet_client import BulletClient

from rover_env.config.io import ConfigError, check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.geometry import GRAVITY
from rover_env.sim.soil_contact import SoilContact
from rover_env.sim.terramechanics import REST_SPEED, WheelSpec, contact_forces, slip_velocities, steady_state

log = logging.getLogger(__name__)

COLUMNS = ("slip", "drawbar_pull_N", "load_N", "sinkage_m", "torque_Nm")
#: Most physics steps one test-bed run may take (all slips; 1e4 s of simulated travel at 240 Hz,
#: a few minutes of computing).
MAX_STEPS = 2_400_000
#: Largest contact frequency times the physics step the test bed accepts, omega * dt (an explicit
#: step of an undamped spring diverges at 2; this keeps a margin).
MAX_OMEGA_DT = 1.0


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
    progress: Callable[[float], None] | None = None,
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
        progress: Called with the finished share of the run (0..1).

    Raises:
        ConfigError: A load <= 0, a slip outside [-1, 1], or another impossible figure; a
            steady state the test bed cannot reach (the wheel buried past its axle, a contact
            too stiff for the physics step), or a run longer than :data:`MAX_STEPS` (before
            anything runs); a result that cannot be physical (after the run; the message names
            the figure).
    """
    slips, total = check_wheel_test(soil, wheel, load, slips, speed, distance, settle, dt)
    bed = _Bed(soil, wheel, load, dt)
    done = 0

    def tick(n: int) -> None:
        nonlocal done
        done += n
        if progress is not None:
            progress(min(1.0, done / total))

    try:
        bed.settle(settle)
        tick(int(round(settle / dt)))
        rows = []
        for s in slips:
            rows.append(bed.run(s, speed, distance / speed, tick))
            _check_row(rows[-1], load, wheel, soil)
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

    def run(
        self, slip: float, speed: float, duration: float, tick: Callable[[int], None] | None = None
    ) -> WheelTestRow:
        self.c.restoreState(self._settled)
        self.soil.restore(self._soil_state)
        v, w = slip_velocities(np.array([slip]), speed, self.wheel.radius)
        self._drive(float(v[0]), float(w[0]))
        n = int(round(duration / self.dt))
        keep = max(1, int(0.4 * n))
        acc = np.zeros(5)
        for k in range(n):
            if tick is not None and k % 2400 == 2399:
                tick(2400)
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


#: Fewest physics steps of travel per slip (the last 40 % are averaged).
MIN_STEPS = 24


def check_wheel_test(
    soil: SoilConfig,
    wheel: WheelSpec,
    load: float,
    slips,
    speed: float = 0.01,
    distance: float = 1.0,
    settle: float = 1.0,
    dt: float = 1.0 / 240.0,
) -> tuple[list[float], int]:
    """Every check of :func:`run_wheel_test` that needs no run; (the slips, the physics steps in all).

    Raises:
        ConfigError: A load <= 0, a slip outside [-1, 1], a speed, distance or settling time
            out of range, a travel of fewer than :data:`MIN_STEPS` steps a slip or a run of more
            than :data:`MAX_STEPS` in all, or a steady state the bed cannot reach or resolve
            (:func:`check_steady_state`).
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
    per_slip = int(round(distance / speed / dt))
    settling = int(round(settle / dt))
    if per_slip < MIN_STEPS:
        raise ConfigError(
            f"speed, distance: {distance:g} m at {speed:g} m/s is {per_slip} physics steps of travel a slip; "
            f"give at least {MIN_STEPS} ({MIN_STEPS * dt * speed:.3g} m at this speed)"
        )
    total = len(slips) * per_slip + settling
    if total > MAX_STEPS:
        slowest = len(slips) * distance / ((MAX_STEPS - settling) * dt)
        raise ConfigError(
            f"speed, distance: {speed:g} m/s over {distance:g} m is {distance / speed:.3g} s of travel for "
            f"each of {len(slips)} slips ({total:.3g} physics steps at {1 / dt:g} Hz); the test bed runs "
            f"at most {MAX_STEPS:.3g}: give a speed above {slowest:.3g} m/s or a shorter distance"
        )
    check_steady_state(soil, wheel, load, slips, speed, dt)
    return slips, total


def _soil_figures(soil: SoilConfig) -> str:
    return f"k_c = {soil.k_c:g}, k_phi = {soil.k_phi:g}, n = {soil.n:g}"


def check_steady_state(
    soil: SoilConfig, wheel: WheelSpec, load: float, slips, speed: float, dt: float = 1.0 / 240.0
) -> None:
    """Refuse a test the bed cannot run: each slip's steady state must be reachable and resolvable.

    The soil must carry ``load`` [N] before the wheel sinks past its axle (its radius), and the
    contact's stiffness there, k = dF_z/dz, must ring slower than the physics step resolves:
    sqrt(k / m) dt <= :data:`MAX_OMEGA_DT`, m the load's mass.

    Raises:
        ConfigError: Naming the slip, the figure and the soil's parameters.
    """
    s = np.atleast_1d(np.asarray(slips, dtype=np.float64))
    v_ref = max(speed, 2 * REST_SPEED)  # the steady sinkage barely depends on the speed
    ss = steady_state(soil, wheel, load, s, speed=v_ref)
    mass = load / GRAVITY
    for k, slip in enumerate(s):
        h = float(ss.sinkage[k])
        if not ss.converged[k] or h >= wheel.radius:
            raise ConfigError(
                f"soil {soil.name}: at slip {slip:+.2f} the soil carries the {load:g} N load only with the "
                f"wheel buried past its axle (sinkage above the radius, {wheel.radius:g} m): it is too soft "
                f"for this load ({_soil_figures(soil)}); lighten the load or check the soil's moduli"
            )
        v, w = slip_velocities(np.array([slip]), v_ref, wheel.radius)
        dz = max(1e-3 * h, 1e-9)
        f_up, f_dn = (
            float(contact_forces(soil, wheel, np.array([z]), v, w, np.zeros(1)).normal[0])
            for z in (h + dz, h - dz)
        )
        stiffness = (f_up - f_dn) / (2 * dz)  # [N/m]
        omega = math.sqrt(max(stiffness, 0.0) / mass)
        if omega * dt > MAX_OMEGA_DT:
            raise ConfigError(
                f"soil {soil.name}: at slip {slip:+.2f} the wheel's steady sinkage would be "
                f"{1e3 * h:.3g} mm, where the soil's stiffness ({stiffness:.3g} N/m under {load:g} N) "
                f"rings at {omega / (2 * math.pi):.0f} Hz, too fast for the {1 / dt:g} Hz physics step to "
                f"resolve; a soil that barely yields ({_soil_figures(soil)}) is rigid ground: check it"
            )


def _check_row(row: WheelTestRow, load: float, wheel: WheelSpec, soil: SoilConfig) -> None:
    """A result that cannot be physical is an error naming the figure."""
    values = (row.drawbar_pull_N, row.load_N, row.sinkage_m, row.torque_Nm)
    why = ""
    if not all(math.isfinite(v) for v in values):
        why = (
            f"non-finite figures (drawbar pull {row.drawbar_pull_N}, load {row.load_N}, "
            f"sinkage {row.sinkage_m})"
        )
    elif row.sinkage_m < 0.0:
        why = f"a negative sinkage, {row.sinkage_m:.4g} m (the wheel above the soil)"
    elif row.load_N < 0.5 * load:
        why = f"the soil carrying {row.load_N:.3g} N of the {load:g} N load"
    elif row.sinkage_m >= wheel.radius:
        why = f"a sinkage of {row.sinkage_m:.3g} m, past the wheel's axle (radius {wheel.radius:g} m)"
    if why:
        raise ConfigError(
            f"soil {soil.name}: at slip {row.slip:+.2f} the test bed ended with {why}: not a physical steady "
            f"state; check the soil's figures ({_soil_figures(soil)}) and the load"
        )


def wheel_test_table(rows: list[WheelTestRow]) -> str:
    """The rows as ``wheel_test.csv`` text (header :data:`COLUMNS`)."""
    lines = [",".join(COLUMNS)]
    for r in rows:
        lines.append(
            f"{r.slip:.4f},{r.drawbar_pull_N:.5f},{r.load_N:.5f},{r.sinkage_m:.6f},{r.torque_Nm:.6f}"
        )
    return "\n".join(lines) + "\n"

"""The soil's forces on wheels, substep by substep: the force law of :mod:`terramechanics` with its state.

:func:`rover_env.sim.terramechanics.contact_forces` is a function of a wheel's sinkage and
slip. Stepping it in a simulation at 240 Hz needs three things more, all here:

- **Slip that takes soil to build.** A rolling wheel's shear is set by the soil that has passed
  under it: after a change of slip, about one contact length of travel. Each wheel's slip is
  therefore a state, the soil's shear deflection ``J`` (the stretched-string model of tyre
  dynamics, with the contact length as the relaxation length):
  ``dJ/dt = (r omega - v) - |v| J / L``, and the slip ratio the force law sees follows from
  ``J / L``, which in steady rolling is exactly ``(r omega - v)/v``. Without it, a wheel that
  barely turns would see the full slip of 1 and the whole of the soil's strength, a force that
  jumps at zero speed and chatters in an explicit simulation.
- **Rolling that takes soil too.** The stress shape and shear of a rolling wheel (Wong–Reece)
  build up as the wheel rolls through its contact length from rest (``rolled``, signed by the
  direction, 0 at rest); until then the contact is the symmetric one of a wheel at rest, and
  the wheel shears the soil by the slip it has accumulated since it started (``hold``,
  bounded at five shear moduli): on a slope it creeps until the soil's shear balances it,
  then stands, as static friction would. The direction turns only when the wheel has rolled
  back as far, not at every jitter about zero speed.
- **Damping.** The soil resists being pressed faster, ``damping`` Pa s/m times the sinking
  speed over the contact's area (loading only, as Project Chrono's SCM soil does): a wheel
  dropped on soil settles instead of bouncing on Bekker's spring. Its shear deflection is
  damped the same way (``shear_damping``, on the deflection's rate, which is zero in steady
  rolling): a braked wheel on a slope does not rock on the soil's shear spring.
- **New soil.** The deflection relaxes, and the rolling state advances, only with travel onto
  ground the contact has not worked yet (past the stretch, at most a contact long, it has):
  a wheel rocking back and forth in place does not ratchet downhill.
"""

from __future__ import annotations

import math

import numpy as np

from rover_env.config.io import check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.terramechanics import N_PARAMS, WheelSpec, _compiled, _contact_kernel, _params

__all__ = ["SoilContact"]

#: How far the held shear may grow, in shear moduli (the soil's strength is reached by then).
HOLD_CAP = 5.0


@_compiled
def _advance(track, i, step, length):  # pragma: no cover (compiled)
    """Move wheel ``i``'s ``track`` (position, front, back) by ``step``; the new ground reached."""
    pos = track[i, 0] + step
    front, back = track[i, 1], track[i, 2]
    fresh = max(pos - front, 0.0) + max(back - pos, 0.0)
    front = max(front, pos)
    back = min(back, pos)
    back = max(back, front - length)  # the worked stretch is at most a contact long
    front = min(front, back + length)
    track[i, 0], track[i, 1], track[i, 2] = pos, front, back
    return fresh


@_compiled
def _soil_step(
    p, h, vx, w, vy, sink_rate, zp, jprev, dt, damping, shear_damping, n_theta,
    hold, deflection, rolled, travel, turn, work, out,
):  # pragma: no cover (compiled)  # fmt: skip
    """One substep of :class:`SoilContact` for every wheel: its soil state, then its forces."""
    slip, side, sin_beta, moving, direction, rate_x, rate_y = (
        work[0], work[1], work[2], work[3], work[4], work[5], work[6]
    )  # fmt: skip
    for i in range(h.shape[0]):
        r, rs, k_x, k_y = p[i, 0], p[i, 1], p[i, 10], p[i, 11]
        rim = r * w[i]
        # the deflection relaxes over the contact's length (the last step's, or the sinkage's)
        arc = rs * (out[i, 5] - out[i, 6])
        if arc <= 0.0:
            arc = 2.0 * rs * math.acos(min(max(1.0 - max(h[i], 0.0) / rs, -1.0), 1.0))
        length = max(arc, 0.05 * r)
        # new soil: travel past the stretch of ground (and of rim) the contact has already
        # worked, at most a contact length; moving back and forth inside it brings none
        fresh_x = _advance(travel, i, vx[i] * dt, length)
        fresh = max(fresh_x, _advance(turn, i, rim * dt, length))
        keep = math.exp(-fresh_x / length)
        cap = 100.0 * length
        jx = min(max(deflection[0, i] * keep + (rim - vx[i]) * dt, -cap), cap)
        jy = min(max(deflection[1, i] * keep - vy[i] * dt, -cap), cap)
        rate_x[i] = (jx - deflection[0, i]) / dt
        rate_y[i] = (jy - deflection[1, i]) / dt
        deflection[0, i], deflection[1, i] = jx, jy
        # how much of the contact the wheel has rolled through, signed by the direction: the
        # kinematic shear of a rolling wheel builds over a contact length of travel and turns
        # round only when the wheel has rolled back as far (never at a jitter about zero speed)
        heading = -1.0 if rim + vx[i] < 0.0 else 1.0
        forget = math.exp(-fresh / length)
        rolled[i] = heading + (rolled[i] - heading) * forget
        d = -1.0 if rolled[i] < 0.0 else 1.0
        direction[i] = d
        moving[i] = abs(rolled[i])
        q = min(max(d * jx / length, -1.0), 99.0)
        s = q / (1.0 + abs(q)) if q >= 0.0 else q
        slip[i] = s
        side[i] = (jy / length) * ((1.0 - s) if s >= 0.0 else 1.0)
        speed = math.hypot(vx[i], vy[i])
        sin_beta[i] = vy[i] / speed if speed > 0.0 else 0.0
        # the shear a wheel at rest holds: what it has slipped, forgotten as it rolls on
        held = HOLD_CAP * max(k_x, k_y)
        hold[0, i] = min(max(hold[0, i] * forget + (rim - vx[i]) * dt, -held), held)
        hold[1, i] = min(max(hold[1, i] * forget - vy[i] * dt, -held), held)
    _contact_kernel(p, h, slip, side, sin_beta, moving, direction, zp, jprev, hold[0], hold[1], n_theta, out)
    for i in range(h.shape[0]):
        area = p[i, 2] * p[i, 1] * (out[i, 5] - out[i, 6])
        out[i, 1] += damping * max(sink_rate[i], 0.0) * area
        drag = shear_damping * area  # the shear deflection's rate: zero in steady rolling
        out[i, 0] += drag * rate_x[i]
        out[i, 2] += drag * rate_y[i]
        out[i, 3] += p[i, 1] * drag * rate_x[i]


@_compiled
def _ground_step(
    p, index, wheels, ground, normal, dt, damping, shear_damping, n_theta,
    hold, deflection, rolled, travel, turn, work, out, inputs, force, torque, sinkage,
):  # pragma: no cover (compiled)  # fmt: skip
    """One substep of :class:`SoilGround`: world frames, the soil's step, world forces."""
    h, vx, w, vy, sink_rate, zeros = inputs[0], inputs[1], inputs[2], inputs[3], inputs[4], inputs[5]
    frames = np.empty((index.shape[0], 3, 3))
    for i in range(index.shape[0]):
        n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
        # the axle: the y axis of the wheel's frame (quaternion x, y, z, w)
        qx, qy, qz, qw = wheels[i, 3], wheels[i, 4], wheels[i, 5], wheels[i, 6]
        a0, a1, a2 = 2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx)
        frames[i, 2, 0], frames[i, 2, 1], frames[i, 2, 2] = a0, a1, a2
        # heading = axle x normal (in the ground's plane), left = normal x heading
        x0, x1, x2 = a1 * n2 - a2 * n1, a2 * n0 - a0 * n2, a0 * n1 - a1 * n0
        norm = max(math.sqrt(x0 * x0 + x1 * x1 + x2 * x2), 1e-12)
        x0, x1, x2 = x0 / norm, x1 / norm, x2 / norm
        y0, y1, y2 = n1 * x2 - n2 * x1, n2 * x0 - n0 * x2, n0 * x1 - n1 * x0
        frames[i, 0, 0], frames[i, 0, 1], frames[i, 0, 2] = x0, x1, x2
        frames[i, 1, 0], frames[i, 1, 1], frames[i, 1, 2] = y0, y1, y2
        c0, c1, c2 = 0.0, 0.0, wheels[i, 2] - ground[i]  # from the ground point below the centre
        v0, v1, v2 = wheels[i, 7], wheels[i, 8], wheels[i, 9]
        h[i] = p[i, 1] - (c0 * n0 + c1 * n1 + c2 * n2) if index[i] >= 0 else -1.0
        vx[i] = v0 * x0 + v1 * x1 + v2 * x2
        vy[i] = v0 * y0 + v1 * y1 + v2 * y2
        sink_rate[i] = -(v0 * n0 + v1 * n1 + v2 * n2)
        w[i] = wheels[i, 10] * a0 + wheels[i, 11] * a1 + wheels[i, 12] * a2
    _soil_step(
        p, h, vx, w, vy, sink_rate, zeros, zeros, dt, damping, shear_damping, n_theta,
        hold, deflection, rolled, travel, turn, work, out,
    )  # fmt: skip
    for i in range(index.shape[0]):
        on = index[i] >= 0
        sinkage[i] = max(h[i], 0.0) if on else 0.0
        for k in range(3):
            if on:
                force[i, k] = (
                    out[i, 0] * frames[i, 0, k] + out[i, 2] * frames[i, 1, k] + out[i, 1] * normal[i, k]
                )
                torque[i, k] = -out[i, 3] * frames[i, 2, k]
            else:
                force[i, k] = 0.0
                torque[i, k] = 0.0


class SoilContact:
    """Soil forces on ``n`` identical wheels, updated every physics substep.

    Args:
        soil: The soil.
        wheel: The wheels' geometry.
        n: Number of wheels.
        dt: The physics substep [s].
        damping: Resistance to sinking [Pa s/m] (Chrono's SCM default 3e4).
        shear_damping: Resistance to the rate of the soil's shear deflection [Pa s/m]
            (assumed; zero in steady rolling, it damps a wheel rocking on the soil's shear).
        n_theta: Integration nodes along the contact arc.
    """

    def __init__(
        self,
        soil: SoilConfig,
        wheel: WheelSpec,
        n: int,
        dt: float,
        *,
        damping: float = 3.0e4,
        shear_damping: float = 1.0e4,
        n_theta: int = 24,
    ) -> None:
        check_range("dt", dt, 0.0, 1.0, lo_open=True)
        check_range("damping", damping, 0.0, 1e8)
        check_range("shear_damping", shear_damping, 0.0, 1e8)
        self.soil, self.wheel, self.n, self.dt = soil, wheel, int(n), float(dt)
        self.damping = float(damping)
        self.shear_damping = float(shear_damping)
        self.n_theta = max(int(n_theta), 3)
        self._p = np.ascontiguousarray(np.broadcast_to(_params(soil, wheel), (self.n, N_PARAMS)))
        self._out = np.zeros((self.n, 9))
        self._zeros = np.zeros(self.n)
        #: The held shear displacement of each wheel along and across it [m] (rows x, y).
        self.hold = np.zeros((2, self.n))
        #: The soil's shear deflection under each rolling wheel along and across it [m].
        self.deflection = np.zeros((2, self.n))
        #: How far through its contact each wheel has rolled, signed (-1..1; 0: from rest).
        self.rolled = np.zeros(self.n)
        # per wheel: travel of the centre and of the rim, and the stretch each has worked
        # (columns: position, front, back) [m]
        self._travel = np.zeros((self.n, 3))
        self._turn = np.zeros((self.n, 3))
        self._work = np.zeros((7, self.n))  # the kernel's inputs and the deflection's rates

    def reset(self) -> None:
        """Forget the held shear and the deflection (a new episode)."""
        self.hold[:] = 0.0
        self.deflection[:] = 0.0
        self.rolled[:] = 0.0
        self._travel[:] = 0.0
        self._turn[:] = 0.0

    def step(self, sinkage, v_x, omega, v_y, sink_rate, prior=None, prior_shear=None) -> np.ndarray:
        """The soil's forces now; advances the held shear by one substep.

        Args:
            sinkage: (n,) depth of each rim's lowest point below the original surface [m].
            v_x: (n,) centre velocity along each wheel's heading [m/s].
            omega: (n,) spin rate, positive rolling forward [rad/s].
            v_y: (n,) centre velocity across each wheel, to its left [m/s].
            sink_rate: (n,) how fast each wheel sinks (its centre's downward speed along the
                ground's normal) [m/s].
            prior: (n,) the rut under each wheel: its earlier sinkage [m] (None: virgin soil).
            prior_shear: (n,) the shear earlier passes left in it [m] (None: none).

        Returns:
            (n, 4) view: drawbar pull F_x [N], normal F_z [N], lateral F_y [N] and the torque
            the soil resists the wheel's spin with [N m], in each wheel's travel frame. The
            array is reused by the next call.
        """
        z = self._zeros
        _soil_step(
            self._p,
            np.ascontiguousarray(sinkage, dtype=np.float64),
            np.ascontiguousarray(v_x, dtype=np.float64),
            np.ascontiguousarray(omega, dtype=np.float64),
            np.ascontiguousarray(v_y, dtype=np.float64),
            np.ascontiguousarray(sink_rate, dtype=np.float64),
            z if prior is None else np.ascontiguousarray(prior, dtype=np.float64),
            z if prior_shear is None else np.ascontiguousarray(prior_shear, dtype=np.float64),
            self.dt,
            self.damping,
            self.shear_damping,
            self.n_theta,
            self.hold,
            self.deflection,
            self.rolled,
            self._travel,
            self._turn,
            self._work,
            self._out,
        )
        return self._out[:, :4]

    @property
    def last(self) -> np.ndarray:
        """The last step's full output, (n, 9).

        Columns: F_x, F_z, F_y, T, slip, theta_f, theta_r, theta_m and the shear left at the
        exit (see :class:`rover_env.sim.terramechanics.ContactForces`).
        """
        return self._out


class SoilGround:
    """The deformable soils under a vehicle's wheels in the world frame.

    Each substep the vehicle gives its wheels' centres, axles and velocities and which soil
    each stands on (-1: rigid ground); this returns the world force at each centre and the
    torque about it. Frames: the ground's normal n (up), the wheel's heading ``x = axle x n``
    in the ground's plane, its left ``y = n x x``.

    Args:
        soils: The soils (a wheel's index picks one).
        wheel: The wheels' geometry.
        n: Number of wheels.
        dt: Physics substep [s].
    """

    def __init__(self, soils: list[SoilConfig], wheel: WheelSpec, n: int, dt: float) -> None:
        if not soils:
            raise ValueError("SoilGround needs at least one soil")
        self.wheel = wheel
        self.contact = SoilContact(soils[0], wheel, n, dt)
        self._rows = np.stack([_params(s, wheel) for s in soils])
        self.index = np.full(n, -1, dtype=np.int64)
        #: The last substep's sinkage of each wheel on soil [m] (0 on rigid ground).
        self.sinkage = np.zeros(n)
        self._inputs = np.zeros((6, n))
        self._force = np.zeros((n, 3))
        self._torque = np.zeros((n, 3))

    def reset(self) -> None:
        """Forget every wheel's soil state (a new episode)."""
        self.contact.reset()
        self.index[:] = -1
        self.sinkage[:] = 0.0

    def step(self, index, wheels, ground, normal) -> tuple[np.ndarray, np.ndarray]:
        """The soil's force and torque on each wheel (zero for wheels on rigid ground).

        Args:
            index: (n,) soil of each wheel (-1: rigid ground).
            wheels: (n, 13) per wheel: centre [m] (3), the wheel frame's orientation as a
                quaternion x, y, z, w (its y axis the axle, positive spin rolling forward) (4),
                centre velocity [m/s] (3), angular velocity [rad/s] (3); world frame.
            ground: (n,) height of the original ground below each centre [m].
            normal: (n, 3) the ground's unit normal there.

        Returns:
            ``(force, torque)``, (n, 3) each, world frame [N], [N m]; reused by the next call.
        """
        index = np.asarray(index, dtype=np.int64)
        changed = index != self.index
        if changed.any():  # a wheel onto or off soil: its soil state starts afresh
            c = self.contact
            for k in np.flatnonzero(changed):
                c.hold[:, k] = 0.0
                c.deflection[:, k] = 0.0
                c.rolled[k] = 0.0
                c._travel[k] = 0.0
                c._turn[k] = 0.0
                c._out[k] = 0.0
                if index[k] >= 0:
                    c._p[k] = self._rows[index[k]]
            self.index = index.copy()
        c = self.contact
        _ground_step(
            c._p,
            index,
            np.ascontiguousarray(wheels, dtype=np.float64),
            np.ascontiguousarray(ground, dtype=np.float64),
            np.ascontiguousarray(normal, dtype=np.float64),
            c.dt,
            c.damping,
            c.shear_damping,
            c.n_theta,
            c.hold,
            c.deflection,
            c.rolled,
            c._travel,
            c._turn,
            c._work,
            c._out,
            self._inputs,
            self._force,
            self._torque,
            self.sinkage,
        )
        return self._force, self._torque

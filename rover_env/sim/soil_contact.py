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

import numpy as np

from rover_env.config.io import check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.terramechanics import N_PARAMS, WheelSpec, _contact_kernel, _params

__all__ = ["SoilContact"]

#: How far the held shear may grow, in shear moduli (the soil's strength is reached by then).
HOLD_CAP = 5.0


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
        self._cap = HOLD_CAP * max(soil.shear_modulus, soil.shear_modulus_lateral)
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
        h = np.asarray(sinkage, dtype=np.float64)
        vx = np.asarray(v_x, dtype=np.float64)
        w = np.asarray(omega, dtype=np.float64)
        vy = np.asarray(v_y, dtype=np.float64)
        r, rs, dt = self.wheel.radius, self.wheel.shear_radius, self.dt
        rim = r * w
        # the deflection relaxes over the contact's length (the last step's, or the sinkage's)
        last = self._out
        arc = rs * (last[:, 5] - last[:, 6])
        length = np.maximum(
            np.where(arc > 0.0, arc, 2.0 * rs * np.arccos(np.clip(1.0 - np.maximum(h, 0.0) / rs, -1.0, 1.0))),
            0.05 * r,
        )
        # new soil: travel past the stretch of ground (and of rim) the contact has already
        # worked, at most a contact length; moving back and forth inside it brings none
        fresh_x = self._advance(self._travel, vx * dt, length)
        fresh_rim = self._advance(self._turn, rim * dt, length)
        keep = np.exp(-fresh_x / length)
        jx = np.clip(self.deflection[0] * keep + (rim - vx) * dt, -100.0 * length, 100.0 * length)
        jy = np.clip(self.deflection[1] * keep - vy * dt, -100.0 * length, 100.0 * length)
        rate_x, rate_y = (jx - self.deflection[0]) / dt, (jy - self.deflection[1]) / dt
        self.deflection[0], self.deflection[1] = jx, jy
        # how much of the contact the wheel has rolled through, signed by the direction: the
        # kinematic shear of a rolling wheel builds over a contact length of travel and turns
        # round only when the wheel has rolled back as far (never at a jitter about zero speed)
        fresh = np.maximum(fresh_x, fresh_rim)
        heading = np.where(rim + vx < 0.0, -1.0, 1.0)
        self.rolled[:] = heading + (self.rolled - heading) * np.exp(-fresh / length)
        direction = np.where(self.rolled < 0.0, -1.0, 1.0)
        moving = np.abs(self.rolled)
        q = np.clip(direction * jx / length, -1.0, 99.0)
        slip = np.where(q >= 0.0, q / (1.0 + np.abs(q)), q)
        side = (jy / length) * np.where(slip >= 0.0, 1.0 - slip, 1.0)
        speed = np.hypot(vx, vy)
        sin_beta = np.divide(vy, speed, out=np.zeros_like(speed), where=speed > 0.0)
        # the shear a wheel at rest holds: what it has slipped, forgotten as it rolls on
        forget = np.exp(-fresh / length)
        self.hold[0] = np.clip(self.hold[0] * forget + (rim - vx) * dt, -self._cap, self._cap)
        self.hold[1] = np.clip(self.hold[1] * forget - vy * dt, -self._cap, self._cap)
        z = self._zeros
        _contact_kernel(
            self._p,
            h,
            slip,
            side,
            sin_beta,
            moving,
            direction,
            z if prior is None else np.asarray(prior, dtype=np.float64),
            z if prior_shear is None else np.asarray(prior_shear, dtype=np.float64),
            self.hold[0],
            self.hold[1],
            self.n_theta,
            self._out,
        )
        out = self._out
        area = self.wheel.width * rs * (out[:, 5] - out[:, 6])
        if self.damping > 0.0:
            out[:, 1] += self.damping * np.maximum(np.asarray(sink_rate, dtype=np.float64), 0.0) * area
        if self.shear_damping > 0.0:  # the shear deflection's rate: zero in steady rolling
            drag = self.shear_damping * area
            out[:, 0] += drag * rate_x
            out[:, 2] += drag * rate_y
            out[:, 3] += rs * drag * rate_x
        return out[:, :4]

    @staticmethod
    def _advance(track: np.ndarray, step: np.ndarray, length: np.ndarray) -> np.ndarray:
        """Move ``track``'s positions by ``step``; return how far each went onto new ground."""
        pos = track[:, 0] + step
        front, back = track[:, 1], track[:, 2]
        fresh = np.maximum(pos - front, 0.0) + np.maximum(back - pos, 0.0)
        front = np.maximum(front, pos)
        back = np.minimum(back, pos)
        back = np.maximum(back, front - length)  # the worked stretch is at most a contact long
        front = np.minimum(front, back + length)
        track[:, 0], track[:, 1], track[:, 2] = pos, front, back
        return fresh

    @property
    def last(self) -> np.ndarray:
        """The last step's full output, (n, 9).

        Columns: F_x, F_z, F_y, T, slip, theta_f, theta_r, theta_m and the shear left at the
        exit (see :class:`rover_env.sim.terramechanics.ContactForces`).
        """
        return self._out

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
- **Unloading.** Bekker's pressure–sinkage curve is the soil's loading curve; soil pressed
  and then relieved springs back only by its rebound, along the stiff unloading line
  ``k_u = k0 + A_u z`` (Wong 2008, Sec. 2.4.4). A rolling wheel's contact meets fresh soil at
  its front at ``v sin(theta_f)``, so it may rise that fast and stay carried; each wheel keeps
  the deepest it has pressed the soil under it (``pressed``, let go at that rate), and where
  it has risen above that by ``d`` each node's stress is at most its unloading line's,
  ``p(z + d) - k_u(z + d) d``. Without it a wheel bounced out of its rut on Bekker's curve as
  on a spring (the rear wheels' hop, ``docs/terramechanics.md``). A wheel that has not rolled
  yet keeps the model's rest state, Bekker's curve both ways (its static sinkage after being
  set down); one that rolled and stopped keeps its rolled state until it rolls on.
- **New soil.** The deflection relaxes, and the rolling state advances, only with travel onto
  ground the contact has not worked yet (past the stretch, at most a contact long, it has):
  a wheel rocking back and forth in place does not ratchet downhill.
"""

from __future__ import annotations

import numpy as np

from rover_env.config.io import check_range
from rover_env.config.soil import SoilConfig
from rover_env.sim.terramechanics import N_PARAMS, PullCurves, WheelSpec, _ground_step, _params, _soil_step

__all__ = ["SoilContact"]


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
        #: The deepest each wheel has pressed the soil under it [m] (forgotten as it rolls on).
        self.pressed = np.zeros(self.n)
        self._work = np.zeros((8, self.n))  # the kernel's inputs, the deflection's rates, the rise

    def reset(self) -> None:
        """Forget the held shear and the deflection (a new episode)."""
        for a in self._state():
            a[...] = 0.0

    def forget(self, wheel: int) -> None:
        """Fresh soil state for one wheel (it went onto or off the soil)."""
        self.hold[:, wheel] = 0.0
        self.deflection[:, wheel] = 0.0
        for a in (self.rolled, self._out, self._travel, self._turn, self.pressed):
            a[wheel] = 0.0

    def snapshot(self) -> tuple[np.ndarray, ...]:
        """Copies of every wheel's soil state, for :meth:`restore`."""
        return tuple(a.copy() for a in self._state())

    def restore(self, snap: tuple[np.ndarray, ...]) -> None:
        """Put back the soil state of :meth:`snapshot`."""
        for now, kept in zip(self._state(), snap, strict=True):
            now[...] = kept

    def _state(self) -> tuple[np.ndarray, ...]:
        return (self.hold, self.deflection, self.rolled, self._out, self._travel, self._turn, self.pressed)

    def _checked(self, name: str, a) -> np.ndarray:
        a = np.ascontiguousarray(a, dtype=np.float64)
        if a.shape != (self.n,):
            raise ValueError(f"{name}: shape {a.shape}; expected ({self.n},), one per wheel")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: {a!r} holds NaN or infinity; give finite values")
        return a

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
        z, ok = self._zeros, self._checked
        _soil_step(
            self._p,
            ok("sinkage", sinkage),
            ok("v_x", v_x),
            ok("omega", omega),
            ok("v_y", v_y),
            ok("sink_rate", sink_rate),
            z if prior is None else ok("prior", prior),
            z if prior_shear is None else ok("prior_shear", prior_shear),
            self.dt,
            self.damping,
            self.shear_damping,
            self.n_theta,
            self.hold,
            self.deflection,
            self.rolled,
            self._travel,
            self._turn,
            self.pressed,
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
        #: (len(soils), N_PARAMS) each soil's parameters with the wheel's (``terramechanics._params``).
        self.rows = np.stack([_params(s, wheel) for s in soils])
        #: Each soil's steady-state pull curves (the truth's figures; solved at first use).
        self.curves = [PullCurves(s, wheel) for s in soils]
        self.index = np.full(n, -1, dtype=np.int64)
        #: The last substep's sinkage of each wheel on soil [m] (0 on rigid ground).
        self.sinkage = np.zeros(n)
        self._inputs = np.zeros((5, n))
        self._zeros = np.zeros(n)
        #: Per wheel, the last substep's frame (rows: heading, left, axle; world).
        self.frames = np.zeros((n, 3, 3))
        self._force = np.zeros((n, 3))
        self._torque = np.zeros((n, 3))

    def reset(self) -> None:
        """Forget every wheel's soil state (a new episode)."""
        self.contact.reset()
        self.index[:] = -1
        self.sinkage[:] = 0.0

    def step(
        self, index, wheels, ground, normal, prior=None, prior_shear=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The soil's force and torque on each wheel (zero for wheels on rigid ground).

        Args:
            index: (n,) soil of each wheel (-1: rigid ground).
            wheels: (n, 13) per wheel: centre [m] (3), the wheel frame's orientation as a
                quaternion x, y, z, w (its y axis the axle, positive spin rolling forward) (4),
                centre velocity [m/s] (3), angular velocity [rad/s] (3); world frame.
            ground: (n,) height of the original ground below each centre [m].
            normal: (n, 3) the ground's unit normal there.
            prior: (n,) the largest earlier sinkage where each wheel goes [m] (None: virgin).
            prior_shear: (n,) the shear left there, along each wheel's heading [m] (None: none).

        Returns:
            ``(force, torque)``, (n, 3) each, world frame [N], [N m]; reused by the next call.
        """
        index = np.asarray(index, dtype=np.int64)
        n = self.index.shape[0]
        wheels = np.ascontiguousarray(wheels, dtype=np.float64)
        if index.shape != (n,) or wheels.shape != (n, 13):
            raise ValueError(f"index {index.shape}, wheels {wheels.shape}: expected ({n},) and ({n}, 13)")
        if not np.all(np.isfinite(wheels)):
            raise ValueError("wheels: a wheel's state holds NaN or infinity; the simulation has diverged")
        changed = index != self.index
        if changed.any():  # a wheel onto or off soil: its soil state starts afresh
            c = self.contact
            for k in np.flatnonzero(changed):
                c.forget(int(k))
                if index[k] >= 0:
                    c._p[k] = self.rows[index[k]]
            self.index = index.copy()
        c = self.contact
        _ground_step(
            c._p,
            index,
            np.ascontiguousarray(wheels, dtype=np.float64),
            np.ascontiguousarray(ground, dtype=np.float64),
            np.ascontiguousarray(normal, dtype=np.float64),
            self._zeros if prior is None else np.ascontiguousarray(prior, dtype=np.float64),
            self._zeros if prior_shear is None else np.ascontiguousarray(prior_shear, dtype=np.float64),
            c.dt,
            c.damping,
            c.shear_damping,
            c.n_theta,
            c.hold,
            c.deflection,
            c.rolled,
            c._travel,
            c._turn,
            c.pressed,
            c._work,
            c._out,
            self._inputs,
            self.frames,
            self._force,
            self._torque,
            self.sinkage,
        )
        return self._force, self._torque

"""RoverSim: one PyBullet client with a terrain and a rover, stepped at a fixed physics rate.

Each simulation owns its own ``BulletClient`` (never the global pybullet module), so any number
of them coexist in one process. The simulation owns the clock: every physics model (springs,
friction map, loose-soil dig; motors inside PyBullet) updates at every physics substep, so the
trajectory does not depend on how :meth:`RoverSim.step` calls are chunked. Sensors attached with
:meth:`RoverSim.attach_sensor` are sampled at their own rates, at the exact substep of each
sample, and hand out timestamped :class:`SensorMessage` objects (no simulator state).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from functools import partial
from typing import Protocol

import numpy as np
import pybullet as pb
from pybullet_utils.bullet_client import BulletClient

from perception.rig import SensorMessage
from rover_env.config.scenario import ScenarioConfig
from rover_env.rendering.base import check_renderer
from rover_env.rendering.shadows import ShadowCaster
from rover_env.sim.geometry import RoverGeometry
from rover_env.sim.ground_truth import GroundTruth
from rover_env.sim.rover import Rover
from rover_env.sim.terrain import Terrain
from rover_env.sim.transforms import quat_to_yaw, yaw_to_quat  # noqa: F401 (the simulation's names)

log = logging.getLogger(__name__)


class Sensor(Protocol):
    """What :meth:`RoverSim.attach_sensor` needs of a sensor."""

    @property
    def period(self) -> float:
        """Time between samples [s]; a whole number of physics steps."""
        ...

    def sample(self) -> np.ndarray:
        """The sensor's output now (at the simulation's current time)."""
        ...


def resolve_renderer(name: str) -> str:
    """The renderer that ``name`` (``"auto"``, ``"gl"`` or ``"tiny"``) selects on this machine.

    ``"auto"`` is ``"gl"`` where a headless EGL OpenGL context can be created, else ``"tiny"``
    (with one warning per process naming what is missing).

    Raises:
        ValueError: Unknown name.
        rover_env.rendering.gl.GLUnavailableError: ``"gl"`` where it cannot start.
    """
    check_renderer(name)
    if name == "tiny":
        return name
    from rover_env.rendering.gl import GLUnavailableError, usable_here

    ok, why = usable_here()
    if ok:
        return "gl"
    if name == "gl":
        raise GLUnavailableError(f"renderer='gl': {why}; or use renderer='tiny'")
    _warn_fallback(why)
    return "tiny"


@functools.lru_cache(maxsize=1)
def _warn_fallback(why: str) -> None:
    log.warning("OpenGL rendering is not available, so TinyRenderer draws the cameras (slower): %s", why)


#: Most constraint-solver iterations per physics step (a step's cost grows with them).
MAX_SOLVER_ITERATIONS = 1000


class RoverSim:
    """A terrain, a rover and the physics loop.

    Args:
        scenario: Terrain, friction map and sun (the course is the task's business).
        geometry: Rover geometry.
        physics_hz: Physics rate [Hz].
        settle_time: Physics time spent at reset letting the suspension settle [s].
        solver_iterations: Constraint-solver iterations per physics step. Cost grows with it
            (contacts dominate a step); motor accuracy under load improves as its square: a
            braked rover on an 8 deg slope creeps 19 mm in 5 s at 10, 4 mm at 20 (see the tests).
        renderer: ``"auto"`` (the default: ``"gl"`` where a headless EGL OpenGL 3.3 context can
            be created, else ``"tiny"`` with one warning saying what is missing), ``"gl"``
            (:class:`rover_env.rendering.gl.GLRenderer`: 10-20x faster on a CPU, and runs on a GPU)
            or ``"tiny"`` (PyBullet's TinyRenderer). Both draw the same sun, sky light and shadows.
            The GL context is created at the first render (so a simulation made before a
            fork renders in the child) and released by :meth:`close`.

    Raises:
        ValueError: Unknown renderer name.
        rover_env.rendering.gl.GLUnavailableError: ``renderer="gl"`` where no context can be created.
    """

    def __init__(
        self,
        scenario: ScenarioConfig,
        geometry: RoverGeometry | None = None,
        physics_hz: float = 240.0,
        settle_time: float = 0.5,
        solver_iterations: int = 10,
        renderer: str = "auto",
    ) -> None:
        if not (60.0 <= physics_hz <= 2000.0):
            raise ValueError(f"physics_hz={physics_hz}: use 60 to 2000 Hz (240 recommended)")
        if (
            isinstance(solver_iterations, bool)
            or not isinstance(solver_iterations, int)
            or not (1 <= solver_iterations <= MAX_SOLVER_ITERATIONS)
        ):
            raise ValueError(
                f"solver_iterations={solver_iterations!r}: use a whole number from 1 to "
                f"{MAX_SOLVER_ITERATIONS} (10 is the default; 20 halves a braked rover's creep)"
            )
        self.scenario = scenario
        self.geometry = geometry or RoverGeometry()
        self.dt = 1.0 / physics_hz
        self.settle_time = settle_time
        #: The renderer in use: ``"gl"`` or ``"tiny"``.
        self.renderer = resolve_renderer(renderer)
        self._gl = None
        from rover_env.sim._quiet import quiet_c_output

        with quiet_c_output():  # PyBullet prints "argv[0]=" on connecting
            self.client = BulletClient(connection_mode=pb.DIRECT)
        self._closed = False
        c = self.client
        c.setPhysicsEngineParameter(
            fixedTimeStep=self.dt,
            numSubSteps=1,
            enableConeFriction=1,
            deterministicOverlappingPairs=1,
            numSolverIterations=solver_iterations,
            # 0.1 mm: a rolling sphere's stale manifold points drop out at once (at 2 mm each
            # wheel carried three, doubling the contact rows).
            contactBreakingThreshold=0.0001,
        )
        c.setGravity(0, 0, -9.81)
        self.terrain = Terrain(c, scenario.terrain, scenario.friction)
        self.rover = Rover(c, self.geometry)
        self._steps = 0
        self._step_physics = partial(pb.stepSimulation, physicsClientId=c._client)
        self._state_id = c.saveState()
        self._sensors: list[tuple[str, Sensor, int]] = []
        self._inbox: list[SensorMessage] = []
        #: Wall-clock seconds spent so far in physics (substeps and their models) and in sampling
        #: sensors (rendering).
        self.timing = {"physics": 0.0, "sensors": 0.0}

    # ------------------------------------------------------------------ sensors
    def attach_sensor(self, name: str, sensor: Sensor) -> None:
        """Sample ``sensor`` every ``sensor.period`` seconds of simulation time from now on.

        Samples are taken at t = 0 after each :meth:`reset` and then at every whole multiple of
        the period, at the exact physics substep; sensors attached earlier are sampled first at
        equal times. Collect them with :meth:`take_messages`. A sensor with a true ``preroll``
        attribute (an IMU) is also sampled while the rover settles at rest before t = 0, at
        negative times: the standstill a rover uses to calibrate its gyro.

        Raises:
            ValueError: ``name`` is taken, or the period is not a whole number of physics steps.
        """
        if any(n == name for n, _, _ in self._sensors):
            raise ValueError(f"a sensor named {name!r} is already attached; give each sensor its own name")
        every = sensor.period / self.dt
        if not math.isfinite(every) or round(every) < 1 or abs(every - round(every)) > 1e-6:
            raise ValueError(
                f"sensor {name!r}: period {sensor.period!r} s is not a whole number of physics steps "
                f"({self.dt:g} s); use a rate that divides {1 / self.dt:g} Hz"
            )
        self._sensors.append((name, sensor, int(round(every))))

    def take_messages(self) -> list[SensorMessage]:
        """The sensor messages sampled since the last call, in time order (then attach order)."""
        out, self._inbox = self._inbox, []
        return out

    def _sample_sensors(self, first: bool = False, only=None) -> None:
        if not self._sensors:
            return
        t0 = time.perf_counter()
        t = self.t
        for name, sensor, every in self._sensors if only is None else only:
            if first or self._steps % every == 0:
                self._inbox.append(SensorMessage(name, t, sensor.sample()))
        self.timing["sensors"] += time.perf_counter() - t0

    # ------------------------------------------------------------------ episode
    def reset(self, x: float, y: float, yaw: float) -> GroundTruth:
        """Put the rover at rest on the ground at (x, y) [m] heading ``yaw`` [rad], settle it.

        The body is placed so that the four wheels touch the terrain's best-fit plane, then
        ``settle_time`` of physics runs with wheels braked and steering centred; the clock
        restarts at 0.

        Returns:
            Ground truth after settling.
        """
        c = self.client
        self.terrain.drop_detail()  # the saved state has no near-ground chunks
        c.restoreState(self._state_id)
        g = self.geometry
        cy, sy = math.cos(yaw), math.sin(yaw)
        wheels = g.wheel_positions_body()[:, :2]
        wx = x + cy * wheels[:, 0] - sy * wheels[:, 1]
        wy = y + sy * wheels[:, 0] + cy * wheels[:, 1]
        wz = self.terrain.height_at(wx, wy)
        # fit z = a + b x' + c y' in the heading-aligned frame for pitch and roll
        a_mat = np.column_stack([np.ones(4), wheels[:, 0], wheels[:, 1]])
        a0, b, cc = np.linalg.lstsq(a_mat, wz, rcond=None)[0]
        pitch = -math.atan(b)
        roll = math.atan(cc)
        quat = yaw_to_quat(roll, pitch, yaw)
        rot = np.array(c.getMatrixFromQuaternion(quat.tolist())).reshape(3, 3)
        # wheel bottoms touch the plane: body origin at clearance r - axle_z along the normal
        clearance = g.wheel_radius - g.axle_z + 0.005
        pos = np.array([x, y, a0]) + rot[:, 2] * clearance
        self.rover.reset_pose(pos, quat)
        settle = int(round(self.settle_time / self.dt))
        self._steps = -settle  # the clock reads 0 when the rover has settled
        self._inbox = []
        preroll = [(n, s, e) for n, s, e in self._sensors if getattr(s, "preroll", False)]
        for _ in range(settle):
            self._substep()
            if preroll and self._steps < 0:
                self._sample_sensors(only=preroll)
        self._steps = 0
        self._sample_sensors(first=True)
        return self.ground_truth()

    def _substep(self) -> None:
        rover = self.rover
        rover.apply_passive()
        rover.apply_friction(self.terrain)
        self._step_physics()
        if self.terrain.friction.loose:  # the soil under spinning wheels gives way
            rover.update_dig(self.terrain)
        self._steps += 1

    @property
    def t(self) -> float:
        """Simulation time since the last reset [s] (whole physics steps times dt)."""
        return self._steps * self.dt

    def step(self, duration: float) -> None:
        """Advance physics by ``duration`` seconds (rounded to whole physics steps, at least one).

        Attached sensors are sampled at every substep where their period falls due. The result
        is the same whether a second is run as one call or as 240.
        """
        if self._closed:
            raise RuntimeError("this RoverSim is closed; create a new one")
        if not math.isfinite(duration) or duration < 0:
            raise ValueError(f"duration={duration!r}: give a finite, non-negative time [s]")
        sensors = bool(self._sensors)
        for _ in range(max(1, int(round(duration / self.dt)))):
            t0 = time.perf_counter()
            self._substep()
            self.timing["physics"] += time.perf_counter() - t0
            if sensors:
                self._sample_sensors()

    def capture_pair(self, camera, on_prev=None, chained: bool = False):
        """I_prev now, then one camera period of physics, then I_curr (odometry paper, Alg. 1).

        For tests and benchmarks on a bare simulation; an environment's cameras are sensors
        (:meth:`attach_sensor`) instead.

        Args:
            camera: A camera of this simulation (``rover_env.sensors.cameras``).
            on_prev: Called with I_prev before I_curr is rendered (feature selection goes here).
            chained: Reuse the camera's last frame as I_prev if it was taken now (the previous
                pair's I_curr), which halves the rendering cost.

        Returns:
            (I_prev, I_curr) frames, exactly one camera period apart in simulation time.
        """
        last = camera.last_frame
        prev = last if chained and last is not None and abs(last.t - self.t) < 1e-9 else camera.capture()
        if on_prev is not None:
            on_prev(prev)
        self.step(camera.period)
        return prev, camera.capture()

    def prepare_render(self, ground_range: float | None = None) -> None:
        """Draw the ground around the rover; call before rendering views near it.

        Args:
            ground_range: Horizontal distance from the rover [m] beyond which the views to be
                rendered see no ground (only the ground within it is drawn); None: all of it.
        """
        x, y, _ = self.client.getBasePositionAndOrientation(self.rover.body_id)[0]
        if self.renderer == "gl":
            self.backend.focus(x, y, ground_range)
        else:
            self.terrain.focus(x, y, ground_range)

    @functools.cached_property
    def shadow_caster(self) -> ShadowCaster:
        """The rover's sun-shadow caster (built on first use)."""
        return ShadowCaster(self.client, self.rover.body_id)

    def ground_truth(self) -> GroundTruth:
        """Exact state of the rover now."""
        return self.rover.ground_truth(self.t, self.terrain.body_id)

    @property
    def backend(self):
        """What the cameras render with: ``"tiny"`` or this simulation's GLRenderer (created on first use)."""
        if self.renderer == "tiny":
            return "tiny"
        if self._gl is None:
            if self._closed:
                raise RuntimeError("this RoverSim is closed; create a new one")
            from rover_env.rendering.gl import GLRenderer

            rv = self.rover
            self._gl = GLRenderer(
                self.client,
                self.terrain,
                link_textures={(rv.body_id, link): path for link, path in rv.link_textures.items()},
            )
        return self._gl

    def __deepcopy__(self, memo):
        raise TypeError("a RoverSim cannot be copied: it owns a PyBullet client; make a second RoverSim")

    def __reduce_ex__(self, protocol):
        raise TypeError("a RoverSim cannot be pickled: it owns a PyBullet client; make one where it is used")

    def close(self) -> None:
        """Disconnect this simulation's client and release its GL context; safe to call more than once."""
        if self._gl is not None:
            self._gl.release()
            self._gl = None
        if not self._closed:
            self._closed = True
            try:
                self.client.disconnect()
            except pb.error:  # already disconnected
                pass

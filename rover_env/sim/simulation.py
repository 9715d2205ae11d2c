"""RoverSim: one PyBullet client with a terrain and a rover, stepped at a fixed physics rate.

Each simulation owns its own ``BulletClient`` (never the global pybullet module), so any number
of them coexist in one process. The simulation owns the clock: every physics model (springs,
friction map, loose-soil dig; motors inside PyBullet) updates at every physics substep, so the
trajectory does not depend on how :meth:`RoverSim.step` calls are chunked. Sensors attached with
:meth:`RoverSim.attach_sensor` are sampled at their own rates, at the exact substep of each
sample, and hand out timestamped :class:`SensorMessage` objects (no simulator state).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from functools import partial
from typing import Any, Protocol, TypeVar

import numpy as np
import pybullet as pb
from pybullet_utils.bullet_client import BulletClient

from perception.rig import SensorMessage
from rover_env.config.cameras import RendererName, check_renderer
from rover_env.config.scenario import ScenarioConfig
from rover_env.sim.geometry import RoverGeometry
from rover_env.sim.ground_truth import GroundTruth
from rover_env.sim.rover import Rover
from rover_env.sim.terrain import Terrain
from rover_env.sim.transforms import quat_to_yaw, yaw_to_quat  # noqa: F401 (the simulation's names)

log = logging.getLogger(__name__)

A = TypeVar("A")


class Sensor(Protocol):
    """What :meth:`RoverSim.attach_sensor` needs of a sensor."""

    @property
    def period(self) -> float:
        """Time between samples [s]; a whole number of physics steps."""
        ...

    def sample(self) -> np.ndarray:
        """The sensor's output now (at the simulation's current time)."""
        ...


#: Most constraint-solver iterations per physics step (a step's cost grows with them).
MAX_SOLVER_ITERATIONS = 1000


class RoverSim:
    """A terrain, a rover and the physics loop.

    Args:
        scenario: Terrain, friction map and sun (the course is the task's business).
        geometry: Rover geometry.
        physics_hz: Physics rate [Hz].
        settle_time: Physics time spent at reset letting the suspension settle [s]: the rover
            stands this long before every mission (an IMU calibrates its gyro meanwhile).
        solver_iterations: Constraint-solver iterations per physics step. Cost grows with it
            (contacts dominate a step); motor accuracy under load improves as its square: a
            braked rover on an 8 deg slope creeps 19 mm in 5 s at 10, 4 mm at 20 (see the tests).
        renderer: What draws this simulation's camera views (:data:`RendererName`): ``"auto"``
            (the default), ``"gl"`` or ``"tiny"``. The simulation only keeps the choice: the
            rendering layer (:func:`rover_env.rendering.renderer_for`) resolves it and makes the
            renderer at the first render (so a simulation made before a fork renders in the
            child), and :meth:`close` releases it.

    Raises:
        ValueError: Unknown renderer name, or a physics rate or solver iteration count out of range.
    """

    def __init__(
        self,
        scenario: ScenarioConfig,
        geometry: RoverGeometry | None = None,
        physics_hz: float = 240.0,
        settle_time: float = 2.0,
        solver_iterations: int = 10,
        renderer: RendererName = "auto",
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
        #: Factor on the sun's direct light (haze) and the sky light's share (None: each
        #: camera's ``ambient``), as domain randomisation sets them per episode.
        self.haze = 1.0
        self.ambient: float | None = None
        self.geometry = geometry or RoverGeometry()
        self.dt = 1.0 / physics_hz
        self.settle_time = settle_time
        #: The renderer chosen for this simulation's views (see ``renderer`` above).
        self.renderer: RendererName = check_renderer(renderer)  # type: ignore[assignment]
        # what other layers attach (a renderer): key -> object, told of restores and of close
        self._attached: dict[str, Any] = {}
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
        if self.terrain.friction.soils:
            self.rover.attach_soil(self.terrain, self.dt)
        self._steps = 0
        self._step_physics: Callable[[], None] = partial(pb.stepSimulation, physicsClientId=c._client)
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
        for obj in self._attached.values():  # the saved state has none of what they added
            before = getattr(obj, "before_restore", None)
            if before is not None:
                before()
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
        if rover.soil is None:
            rover.apply_friction(self.terrain)
        else:  # wheels on deformable soil: its forces, not the ground's contact
            states = rover._read_wheels_with_velocity()
            rover.apply_friction(self.terrain, states)
            rover.apply_soil(self.terrain, states)
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

    def ground_truth(self) -> GroundTruth:
        """Exact state of the rover now."""
        return self.rover.ground_truth(self.t, self.terrain.body_id)

    @property
    def steps(self) -> int:
        """Physics steps since the clock last read 0 (negative while the rover settles) [-]."""
        return self._steps

    def base_pose(self) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """The rover body's pose now: position (x, y, z) [m] and quaternion (x, y, z, w), world frame."""
        pos, quat = self.client.getBasePositionAndOrientation(self.rover.body_id)
        return pos, quat

    def base_matrix(self) -> np.ndarray:
        """The rover body's pose now as a 4x4 transform, world from body [m]."""
        pos, quat = self.base_pose()
        T = np.eye(4)
        T[:3, :3] = np.array(self.client.getMatrixFromQuaternion(quat)).reshape(3, 3)
        T[:3, 3] = pos
        return T

    def link_motion(self) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Each rover link's centre of mass [m], linear [m/s] and angular velocity [rad/s] now, world frame.

        Keyed by link index (-1: the base). A point p of a link moves at v + w x (p - c).
        """
        c = self.client
        body = self.rover.body_id
        pos, _ = c.getBasePositionAndOrientation(body)
        lin, ang = c.getBaseVelocity(body)
        out = {-1: (np.array(pos), np.array(lin), np.array(ang))}
        links = list(range(c.getNumJoints(body)))
        for j, st in zip(links, c.getLinkStates(body, links, computeLinkVelocity=1), strict=True):
            out[j] = (np.array(st[0]), np.array(st[6]), np.array(st[7]))
        return out

    def base_velocity(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The rover body's linear [m/s] and angular [rad/s] velocity now, world frame."""
        lin, ang = self.client.getBaseVelocity(self.rover.body_id)
        return lin, ang

    def hold_on_stand(self, lift: float, joints: dict[str, float]) -> None:
        """Raise the rover ``lift`` [m] and set its named joints [rad or m] directly, at rest.

        What a calibration stand does: no physics runs; :meth:`reset` afterwards. Joint names are
        the URDF's (``roll_F``, ``travel_R``, ``steer_FL``, ...).

        Raises:
            ValueError: A joint name the rover does not have, or a value that is not finite.
        """
        rv = self.rover
        unknown = sorted(set(joints) - set(rv.joint))
        if unknown:
            raise ValueError(f"joints {unknown}: the rover's joints are {sorted(rv.joint)}")
        if not all(math.isfinite(v) for v in [lift, *joints.values()]):
            raise ValueError(f"lift={lift!r}, joints={joints!r}: give finite values")
        c = self.client
        if lift:
            pos, quat = self.base_pose()
            c.resetBasePositionAndOrientation(rv.body_id, [pos[0], pos[1], pos[2] + lift], quat)
        for name, value in joints.items():
            c.resetJointState(rv.body_id, rv.joint[name], value)

    def attachment(self, key: str, make: Callable[[], A]) -> A:
        """The object attached to this simulation under ``key``, made by ``make()`` on first use.

        For what a higher layer keeps per simulation (its renderer): an attached object with a
        ``before_restore()`` method is told before each :meth:`reset` restores the saved state
        (it removes any bodies it added), and one with ``release()`` is released by :meth:`close`.
        """
        obj = self._attached.get(key)
        if obj is None:
            if self._closed:
                raise RuntimeError("this RoverSim is closed; create a new one")
            obj = self._attached[key] = make()
        return obj

    def __deepcopy__(self, memo):
        raise TypeError("a RoverSim cannot be copied: it owns a PyBullet client; make a second RoverSim")

    def __reduce_ex__(self, protocol):
        raise TypeError("a RoverSim cannot be pickled: it owns a PyBullet client; make one where it is used")

    def close(self) -> None:
        """Release what is attached (a renderer) and disconnect the client; safe to call more than once."""
        attached, self._attached = self._attached, {}
        for obj in attached.values():
            release = getattr(obj, "release", None)
            if release is not None:
                release()
        if not self._closed:
            self._closed = True
            try:
                self.client.disconnect()
            except pb.error:  # already disconnected
                pass

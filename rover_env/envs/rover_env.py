"""``Rover-v0``: drive a waypoint course with a double-Ackermann rover in PyBullet."""

from __future__ import annotations

import dataclasses
import enum
import logging
import math
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from perception import observation as obs_table
from perception.estimator import qualities, state_arrays
from perception.models.drive_geometry import WHEELS as WHEEL_NAMES
from rover_env.config.imu import ImuConfig
from rover_env.config.randomize import RandomizeConfig, WorldDraw, randomize_config
from rover_env.config.rig import RIG_NAMES, PresetName, imu_config, named_rig, standard_rig, with_imu
from rover_env.config.scenario import ScenarioConfig, load_scenario, scenario_rig
from rover_env.envs.chase_view import ChaseView
from rover_env.rendering import resolve_renderer
from rover_env.sensors.cameras import blackout_windows
from rover_env.sensors.rig import PERCEPTION_PRESETS, EstimatorFactory, PerceptionPipeline
from rover_env.sim.geometry import RoverGeometry
from rover_env.sim.ground_truth import GroundTruth
from rover_env.sim.simulation import RoverSim, quat_to_yaw, yaw_to_quat
from rover_env.task.course import WaypointCourse
from rover_env.task.judge import STUCK_DISTANCE, STUCK_TREAD, Judge, RewardConfig, StepFacts, wheel_power

log = logging.getLogger(__name__)


def _imu_unit(config: ImuConfig, world: WorldDraw | None) -> ImuConfig | None:
    """This episode's IMU unit: the data sheet's noise figures times the world's factor (None: as is)."""
    if world is None:
        return None
    f = world.imu_noise

    def scaled(t):
        return dataclasses.replace(
            t,
            noise_density=t.noise_density * f,
            bias_instability=t.bias_instability * f,
            bias_random_walk=t.bias_random_walk * f,
        )

    return dataclasses.replace(config, gyro=scaled(config.gyro), accel=scaled(config.accel))


def _sensor_unit(config, world: WorldDraw | None, i: int):
    """Camera ``i``'s image sensor this episode: the data sheet's figures times the world's factors."""
    if world is None:
        return None
    fp = world.fixed_pattern[i]
    return dataclasses.replace(
        config,
        read_noise_e=config.read_noise_e * world.read_noise[i],
        full_well_e=config.full_well_e * world.full_well[i],
        prnu=min(config.prnu * fp, 0.5),
        dsnu_e=config.dsnu_e * fp,
        dark_current_e_s=config.dark_current_e_s * fp,
    )


class ActionMode(str, enum.Enum):
    """How the action vector is interpreted."""

    DRIVE = "drive"
    WHEELS = "wheels"


class ObsSource(str, enum.Enum):
    """Where the observation's state fields come from."""

    GROUND_TRUTH = "ground_truth"
    ESTIMATED = "estimated"


#: The ``action_mode`` keyword's values (:class:`ActionMode`).
ActionModeName = Literal["drive", "wheels"]
#: The ``obs_source`` keyword's values (:class:`ObsSource`).
ObsSourceName = Literal["estimated", "ground_truth"]
#: The ``camera_effects`` keyword's values: images through each camera's image sensor and lens
#: (``"field"``), or as rendered (``"ideal"``).
CameraEffectsName = Literal["field", "ideal"]


def task_values(feats) -> dict[str, float]:
    """The task fields of the observation from :class:`~rover_env.task.course.CourseFeatures`."""
    return {
        "waypoint_distance": feats.distance,
        "waypoint_bearing": feats.bearing,
        "cross_track": feats.cross_track,
        "heading_error": feats.heading_error,
    }


class RoverEnv(gym.Env):
    """Drive a four-wheel double-Ackermann rover through a waypoint course.

    Physics runs at ``physics_hz`` (240 Hz); the agent acts at ``control_hz`` (30 Hz).

    **Action** ``Box(-1, 1)`` float32. Values outside [-1, 1] are clipped; NaN or infinite
    values raise ``ValueError``.

    =====  ==================  ===========================================================
    mode   components          scaling
    =====  ==================  ===========================================================
    drive  speed, lam_F, lam_R speed * v_max [m/s] at the body centre, wheel rates from the
                               Ackermann turn centre; lam * steer_limit (30 deg) per axle
    wheels w_FL, w_FR, w_RL,   wheel surface-speed targets w * v_max [m/s] (divided by the
           w_RR, lam_F, lam_R  wheel radius for the motors); lam as in drive
    =====  ==================  ===========================================================

    **Observation** float32 vector in physical units, laid out by the table
    :func:`perception.observation.observation_fields` (name, unit, bounds, source; the
    instance's :attr:`obs_fields`): body twist, wheel rates, slip ratios, axle roll and height,
    axle steering, body roll and pitch (from the IMU, if fitted), odometry, kinematics and
    attitude quality, the on-board tracker's waypoint distance
    and bearing, cross-track and heading error, then the previous action. Read fields by name,
    never by position: ``obs[field_index(env.unwrapped.obs_fields, "v_x")]``
    (:func:`perception.observation.field_index`). Values are clipped to generous finite bounds that
    only a numerical blow-up could reach; NaN becomes 0 (its quality field says why).

    **What the observation holds** with ``obs_source="estimated"``: only what the rover could
    know. The state fields come from perception on the simulated camera images; the task
    fields from the on-board course tracker, which is fed the dead-reckoned pose (starting from
    a noisy *start fix*, scenario key ``start.fix_std``) and the course known before the
    mission; then the previous action. Nothing comes from the simulator's state: not the pose,
    not which waypoint is current, not a fault schedule (a camera fault reaches the estimator
    only as the images the camera delivers). With ``"ground_truth"`` the same fields come
    from the simulator and the tracker is fed the true pose (an ablation).

    **The judge** uses the truth: the reward terms (progress and cross-track of the true pose
    on the tracker's current segment, heading, slip, energy, time), the termination and the
    success. The episode succeeds when the tracker reaches the last waypoint (within the
    course tolerance and past it) and the true position is within the tolerance of it; if the
    true position is farther it ends with ``termination="off_target"`` (a failure), and
    ``info["miss_distance"]`` gives the true distance.

    **Reward**: the sum of the terms in ``info["reward_terms"]`` (the judge,
    :mod:`rover_env.task.judge`: its ``REWARD_TERMS`` weighted by :class:`RewardConfig`):
    progress along the course, minus cross-track, heading, slip, energy and time penalties,
    plus a success bonus, minus a failure penalty.

    **Episode end**: terminated on tipping over (body tilt > 60 deg), on leaving the terrain,
    off target or on success, the first that holds in that order
    (:data:`~rover_env.task.judge.TERMINATIONS`); truncated after the scenario's ``duration``.

    **Info**: ``ground_truth`` (exact state, and per wheel its motor torque, sinkage, drawbar
    pull and load; the soil's steady-state figures are :meth:`soil_truth`'s), ``wheel_contact``
    (friction, normal force, contact flag and point per wheel), ``reward_terms``, ``t`` [s],
    ``waypoint_index`` (the tracker's), ``start_fix`` (x, y, yaw the tracker started from),
    ``progress`` [m] and ``cross_track`` [m, left +] (of the true pose), ``is_success``, ``termination``
    (``success``, ``tipped_over``, ``left_terrain``, ``off_target``, ``time_limit`` or None),
    ``miss_distance`` [m] (once the tracker has arrived), ``wheel_power`` (drive motors'
    mechanical power [W]).

    Args:
        scenario: Preset name, YAML path or :class:`ScenarioConfig`.
        obs_source: ``"estimated"`` (default): the state fields come from perception on the
            rendered camera images (:class:`~rover_env.sensors.rig.PerceptionPipeline`: odometry
            twist, fisheye kinematics, the slip filter) and the task features from the on-board
            tracker on the dead-reckoned pose; ``info["estimate"]`` then holds the estimate
            under the keys of ``info["ground_truth"]`` (its ``pose`` dead-reckoned: x, y, the
            start height and the yaw; with an IMU, its height and tilt dead-reckoned too), plus
            ``odometry_pose`` (x, y, yaw) and ``quality`` (odometry, kinematics, attitude: the
            observation's quality fields), ``info["quality"]`` the odometry, kinematics,
            attitude and slip quality, and
            ``info["slip"]`` the slip filter's per-wheel ``valid``, ``events`` (its slip-event
            detection) and ``slip_ratio_std``.
            ``"ground_truth"``: the same layout from the simulator (for ablations).
        preset: Cameras of the estimator in the loop: ``"train"`` (low resolution, fast) or
            ``"eval"`` (the papers' 640x480 at 60 and 30 Hz); see
            :data:`~rover_env.sensors.rig.PERCEPTION_PRESETS`. Unused with ground truth.
        action_mode: ``"drive"`` or ``"wheels"``.
        render_mode: None or ``"rgb_array"`` (a composite of a third-person chase view, the
            downward camera and the fisheye; see :meth:`render`).
        control_hz: Agent rate [Hz]; must divide ``physics_hz``.
        physics_hz: Physics rate [Hz].
        v_max: Speed that action 1.0 commands [m/s].
        geometry: Rover geometry (defaults to :class:`RoverGeometry`).
        reward: Reward weights (defaults to :class:`RewardConfig`).
        render_size: (width, height) of the rendered frame [px].
        solver_iterations: Physics constraint-solver iterations per step.
        renderer: ``"auto"`` (OpenGL where a headless EGL context can be created, else
            TinyRenderer with a warning), ``"gl"`` or ``"tiny"``; resolved here
            (:func:`rover_env.rendering.resolve_renderer`). The physics is the same whatever renders.
        imu: An IMU for the estimator (with ``obs_source="estimated"``): a preset name
            (``"bmi088"``, ``"tactical"``, ``"ideal"``), a mapping (``preset`` and overrides, as
            in a scenario) or an :class:`~rover_env.sensors.imu.ImuConfig`; its errors are drawn per
            episode from the reset's seed. None (default): the scenario's ``imu``, if any. The
            standard rig carries a sun sensor (``"sun"``) with its IMU
            (:func:`~rover_env.config.rig.standard_rig`); a declared rig only what it declares.
        rig: With ``obs_source="estimated"``, a named rig in place of the scenario's sensors
            (:data:`~rover_env.config.rig.RIG_NAMES`): ``"standard"`` (the fisheye and the
            downward camera) or ``"fisheye_only"`` (the one-camera rig: the fisheye gives the
            odometry as well as the joints and wheels, :func:`~rover_env.config.rig.fisheye_only_rig`),
            each with ``imu`` (or the scenario's) and then a sun sensor, or ``"full"`` (the
            standard rig, ``imu`` or the BMI088, a sun sensor, wheel encoders, motor currents and
            the command, :func:`~rover_env.config.rig.full_rig`). None (default): the
            scenario's ``rig``, or the standard one. A scenario that declares a rig takes no name.
        estimator: With ``obs_source="estimated"``, a factory (class or callable) called once
            with the sensor rig (:attr:`rig`) that makes the estimator
            (:mod:`perception.estimator`: ``reset(start_fix)``, ``update(messages, t)``); the
            observation's state fields and ``info["estimate"]`` are what it returns. None: the
            built-in :class:`perception.RoverEstimator`. See docs/own_estimator.md.
        camera_effects: With ``obs_source="estimated"``: ``"field"`` (default) delivers each
            camera's images through its image sensor and lens (motion blur, noise,
            auto-exposure, vignetting, distortion, gamma; the camera configuration's
            ``sensor``), drawn per episode from the reset's seed; ``"ideal"`` delivers them as
            rendered (for ablations, and faster with TinyRenderer, which has no velocity buffer).
        randomize: Domain randomisation (:mod:`rover_env.config.randomize`): ``"on"`` draws each
            episode's sun, sky light, ground texture, albedo and contrast, camera mount errors,
            camera and IMU figures and friction factor from the reset's seed, within the default
            ranges; a mapping or :class:`~rover_env.config.randomize.RandomizeConfig` sets the
            ranges; ``"off"`` keeps the scenario's world. None (default): the scenario's
            ``randomize`` key (off if absent). The draw is :attr:`world` and ``info["world"]``
            at reset; the estimator keeps the nominal calibration.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        scenario: str | Path | ScenarioConfig = "flat_patches",
        obs_source: ObsSourceName = "estimated",
        action_mode: ActionModeName = "drive",
        preset: PresetName = "train",
        render_mode: str | None = None,
        control_hz: float = 30.0,
        physics_hz: float = 240.0,
        v_max: float = 2.0,
        geometry: RoverGeometry | None = None,
        reward: RewardConfig | None = None,
        render_size: tuple[int, int] = (960, 480),
        solver_iterations: int = 10,
        renderer: str = "auto",
        imu: str | dict | ImuConfig | None = None,
        estimator: EstimatorFactory | None = None,
        camera_effects: CameraEffectsName = "field",
        randomize: str | dict | RandomizeConfig | None = None,
        rig: str | None = None,
    ) -> None:
        super().__init__()
        try:
            self.action_mode = ActionMode(action_mode)
        except ValueError:
            raise ValueError(f"action_mode={action_mode!r}: use 'drive' or 'wheels'") from None
        try:
            self.obs_source = ObsSource(obs_source)
        except ValueError:
            raise ValueError(f"obs_source={obs_source!r}: use 'ground_truth' or 'estimated'") from None
        if preset not in PERCEPTION_PRESETS:
            raise ValueError(f"preset={preset!r}: use one of {sorted(PERCEPTION_PRESETS)}")
        self.preset = preset
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r}: use None or 'rgb_array'")
        for name, hz in (("physics_hz", physics_hz), ("control_hz", control_hz)):
            if isinstance(hz, bool) or not isinstance(hz, int | float) or not (math.isfinite(hz) and hz > 0):
                raise ValueError(f"{name}={hz!r}: give a rate in Hz, finite and > 0")
        substeps = physics_hz / control_hz
        if abs(substeps - round(substeps)) > 1e-9 or round(substeps) < 1:
            raise ValueError(
                f"control_hz={control_hz} must divide physics_hz={physics_hz} into whole steps "
                "(e.g. 30 of 240)"
            )
        if not (0.0 < v_max <= 5.0):
            raise ValueError(f"v_max={v_max}: use a speed in (0, 5] m/s")
        if len(render_size) != 2 or min(render_size) < 96 or max(render_size) > 4096:
            raise ValueError(f"render_size={render_size}: use (width, height) of 96 to 4096 px")
        self.scenario = load_scenario(scenario)
        if rig is not None:
            if rig not in RIG_NAMES:
                raise ValueError(f"rig={rig!r}: use one of {list(RIG_NAMES)} or None (the scenario's)")
            if self.obs_source is not ObsSource.ESTIMATED:
                raise ValueError("rig: the sensors feed the estimator; use it with obs_source='estimated'")
            if self.scenario.rig is not None:
                raise ValueError(
                    f"rig={rig!r}: scenario {self.scenario.name!r} declares its own rig; leave rig=None "
                    "or drop the scenario's rig"
                )
        #: The ranges of domain randomisation, or None (off).
        self.randomize: RandomizeConfig | None = randomize_config(
            self.scenario.randomize if randomize is None else randomize
        )
        #: This episode's world draw (None: the scenario's world).
        self.world: WorldDraw | None = None
        self.geometry = geometry or RoverGeometry()
        self.reward_cfg = reward or RewardConfig()
        self.judge = Judge(self.reward_cfg, self.scenario.duration)
        self.render_mode = render_mode
        self.render_size = (int(render_size[0]), int(render_size[1]))
        self.control_hz = float(control_hz)
        self.control_dt = 1.0 / control_hz
        self.v_max = float(v_max)
        self.metadata = {**self.metadata, "render_fps": self.control_hz}
        self.sim = RoverSim(
            self.scenario,
            self.geometry,
            physics_hz=physics_hz,
            solver_iterations=solver_iterations,
            renderer=resolve_renderer(renderer),  # type: ignore[arg-type]
        )
        self.course = WaypointCourse(self.scenario.course)
        self.pipeline: PerceptionPipeline | None = None
        if not (imu is None or isinstance(imu, str | dict | ImuConfig)):
            raise ValueError(f"imu={imu!r}: give a preset name, a mapping, an ImuConfig or None")
        if imu is not None and self.obs_source is not ObsSource.ESTIMATED:
            raise ValueError("imu: the IMU feeds the estimator; use it with obs_source='estimated'")
        if estimator is not None and self.obs_source is not ObsSource.ESTIMATED:
            raise ValueError(
                "estimator: an estimator makes the observation; use it with obs_source='estimated'"
            )
        if camera_effects not in ("field", "ideal"):
            raise ValueError(f"camera_effects={camera_effects!r}: use 'field' or 'ideal'")
        self.camera_effects = camera_effects
        #: The named rig the sensors come from (None: the scenario's rig, or the standard one).
        self.rig_name = rig
        if self.obs_source is ObsSource.ESTIMATED:
            if rig is not None:
                named = imu_config(imu) if imu is not None else self.scenario.imu
                sensors = named_rig(rig, named)
            elif imu is None:
                sensors = scenario_rig(self.scenario)
            elif self.scenario.rig is None:  # the keyword's IMU, and with it the sun sensor
                sensors = standard_rig(imu_config(imu))
            else:  # the keyword's IMU in place of the declared rig's
                sensors = with_imu(self.scenario.rig, imu_config(imu))
            declared = self.scenario.rig is not None
            try:
                self.pipeline = PerceptionPipeline(
                    self.sim,
                    preset,
                    estimator=estimator,
                    rig=sensors,
                    declared=declared,
                    camera_effects=camera_effects == "field",
                    control_hz=self.control_hz,
                )
            except BaseException:  # a bad rig or estimator: release the physics client
                self.sim.close()
                raise
            if camera_effects == "field" and self.sim.renderer == "tiny" and self.pipeline.cameras:
                log.info(
                    "field cameras with TinyRenderer: the motion blur needs a labelled render of each "
                    "view (slower); camera_effects='ideal' delivers the images as rendered"
                )
        self._est: dict[str, Any] | None = None  # the estimator's last (checked) estimate
        n_act = 3 if self.action_mode is ActionMode.DRIVE else 6
        self.action_space = spaces.Box(-1.0, 1.0, shape=(n_act,), dtype=np.float32)
        #: The observation's fields in order (name, unit, bounds, source): :mod:`perception.observation`.
        self.obs_fields = obs_table.observation_fields(self.action_mode.value)
        low, high = obs_table.bounds(self.obs_fields)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        self._prev_action = np.zeros(n_act, dtype=np.float32)
        self._gt: GroundTruth | None = None
        self._nav = np.zeros(3)  # the pose the on-board tracker is fed (x, y, yaw)
        self._start_fix = np.zeros(3)
        self._progress = 0.0
        self._stuck_track: list[tuple[float, float, float, float]] = []  # t, x, y, tread travel
        self._tread = 0.0
        self._closed = False
        self._chase: ChaseView | None = None

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode at the scenario's start pose plus random jitter from ``seed``.

        With estimated observations the rover starts from a *start fix*: the true start pose
        plus Gaussian noise of the scenario's ``start.fix_std``, drawn from the same seeded
        generator (the draw is made for both observation sources, so the true start is the same).

        ``options``: ``{"blackout": [(t0, t1), ...]}`` makes both cameras deliver black frames
        between t0 and t1 [s] of episode time (a camera fault; the estimator sees only the images).
        """
        self._check_open("reset")
        # every option is checked before anything moves: a bad one leaves the environment as it was
        if options is not None and not isinstance(options, dict):
            raise ValueError(f"reset options: {options!r}; give a dict such as {{'blackout': [(2.0, 3.0)]}}")
        options = dict(options or {})
        unknown = set(options) - {"blackout"}
        if unknown:
            raise ValueError(f"reset options {sorted(unknown)} are unknown; the only option is 'blackout'")
        blackout = blackout_windows(options.get("blackout", ()), "reset option blackout")
        if blackout and self.pipeline is None:
            raise ValueError("reset option 'blackout' needs obs_source='estimated' (there are no cameras)")
        super().reset(seed=seed)
        st = self.scenario.start
        rng = self.np_random
        r = st.jitter_position * math.sqrt(rng.uniform())
        ang = rng.uniform(-math.pi, math.pi)
        x = st.position[0] + r * math.cos(ang)
        y = st.position[1] + r * math.sin(ang)
        yaw = st.yaw + math.radians(st.jitter_yaw_deg) * rng.uniform(-1.0, 1.0)
        fix_noise = rng.normal(size=3) * np.array([st.fix_std[0], st.fix_std[0], math.radians(st.fix_std[1])])
        # the world's draw comes before the sensors' (the same whatever observes it)
        world_seed = int(rng.integers(2**63 - 1)) if self.randomize is not None else None
        cams = self.pipeline.cameras if self.pipeline is not None else []
        self.world = (
            None
            if world_seed is None
            else WorldDraw.draw(self.randomize, np.random.default_rng(world_seed), len(cams))  # type: ignore[arg-type]
        )
        self._apply_world(self.world)
        if self.pipeline is not None:
            for cam in cams:
                cam.set_blackout(blackout)
            for imu in self.pipeline.imus:  # this episode's turn-on bias, scale factors, noise
                imu.reset(int(rng.integers(2**63 - 1)), _imu_unit(imu.config, self.world))
            if self.camera_effects == "field":  # each image sensor's fixed pattern and noise
                for i, cam in enumerate(cams):
                    cam.reset_effects(
                        int(rng.integers(2**63 - 1)), _sensor_unit(cam.sensor_config, self.world, i)
                    )
            for sun in self.pipeline.sun_sensors:  # drawn after: the draws above stay as they were
                sun.reset(int(rng.integers(2**63 - 1)))
            for part in self.pipeline.proprio:  # encoders' power-up counts, current offsets
                part.reset(int(rng.integers(2**63 - 1)))
        self._gt = self.sim.reset(x, y, yaw)
        messages = self.sim.take_messages()
        if self.pipeline is not None:
            self._start_fix = np.array([x, y, yaw]) + fix_noise
            self._est = self.pipeline.start(self._start_fix, messages, self.sim.t)
            self._z0 = float(self._gt.pose[2])
        else:
            self._start_fix = np.array([x, y, yaw])
        # the mission's course starts where the rover believes it is
        self.course.reset(self._start_fix[:2])
        self._prev_action = np.zeros_like(self._prev_action)
        self._nav = self._nav_pose()
        feats = self.course.features(self._nav[:2], self._nav[2])
        judge = self._judge_features()
        self._progress = judge.progress
        self._stuck_track, self._tread = [], 0.0
        terms = Judge.zero_terms()
        info = self._info(judge, terms, False, None)
        if self.world is not None:
            info["world"] = dataclasses.asdict(self.world)
        return self._observation(feats), info

    def step(self, action):
        """Apply ``action`` for one control period and advance physics."""
        self._check_open("step")
        if self._gt is None:
            raise RuntimeError("call reset() before step()")
        act = self._validate_action(action)
        g = self.geometry
        lam_f = float(act[-2]) * g.steer_limit
        lam_r = float(act[-1]) * g.steer_limit
        if self.action_mode is ActionMode.DRIVE:
            speeds = g.drive.wheel_speeds(float(act[0]) * self.v_max, lam_f, lam_r)
        else:
            speeds = act[:4].astype(np.float64) * self.v_max
        self.sim.rover.command(speeds / g.wheel_radius, lam_f, lam_r)
        self.sim.step(self.control_dt)
        messages = self.sim.take_messages()
        if self.pipeline is not None:
            self._est = self.pipeline.update(messages, self.sim.t)
        gt = self.sim.ground_truth()
        self._gt = gt
        self._prev_action = act
        # on-board navigation: the tracker sees only the pose the rover believes
        self._nav = self._nav_pose()
        self.course.update(self._nav[:2])
        feats = self.course.features(self._nav[:2], self._nav[2])
        # the judge: the truth
        xy = gt.pose[:2]
        arrived = self.course.finished
        goal = np.asarray(self.scenario.course.waypoints[-1], dtype=np.float64)
        miss = float(np.hypot(*(xy - goal)))
        qx, qy = gt.pose[3], gt.pose[4]
        tipped = 1.0 - 2.0 * (qx * qx + qy * qy) < 0.5  # body z axis tilted more than 60 deg
        off = not self.sim.terrain.contains(xy[0], xy[1], margin=0.5)
        off_target = arrived and miss > self.scenario.course.tolerance
        stuck = self._stuck(gt)
        facts = StepFacts(
            gt=gt,
            progress_gain=0.0,
            cross_track=0.0,
            heading_error=0.0,
            wheel_radius=self.geometry.wheel_radius,
            dt=self.control_dt,
            tipped=tipped,
            left_terrain=off,
            off_target=off_target,
            arrived=arrived,
            stuck=stuck,
        )
        end = self.judge.end(facts)
        # the true pose's course features (progress at the course's end once it has succeeded)
        judged = self._judge_features(end is not None and not end.failure)
        facts = dataclasses.replace(
            facts,
            progress_gain=judged.progress - self._progress,
            cross_track=judged.cross_track,
            heading_error=judged.heading_error,
        )
        verdict = self.judge.score(facts, end)
        self._progress = judged.progress
        obs = self._observation(feats)
        info = self._info(judged, verdict.terms, verdict.success, verdict.reason)
        if arrived:
            info["miss_distance"] = miss
        return obs, verdict.reward, verdict.terminated, verdict.truncated, info

    def _apply_world(self, world: WorldDraw | None) -> None:
        """Set the simulation's world to ``world`` (None: the scenario's own)."""
        sim = self.sim
        if world is None:
            sim.scenario = self.scenario
            sim.haze, sim.ambient = 1.0, None
            sim.terrain.set_look()
            sim.terrain.friction.scale = 1.0
            mounts: list = [None] * len(self.pipeline.cameras if self.pipeline is not None else [])
        else:
            sun = dataclasses.replace(
                self.scenario.sun, elevation_deg=world.sun_elevation_deg, azimuth_deg=world.sun_azimuth_deg
            )
            sim.scenario = dataclasses.replace(self.scenario, sun=sun)
            sim.haze, sim.ambient = world.sun_transmission, world.ambient
            sim.terrain.set_look(world.texture, world.albedo, world.contrast)
            sim.terrain.friction.scale = world.friction
            mounts = list(world.mounts)
        if self.pipeline is not None:
            for cam, mount in zip(self.pipeline.cameras, mounts, strict=True):
                cam.set_mount_error(mount)

    def _stuck(self, gt: GroundTruth) -> bool:
        """The judge's ``stuck`` (scenario ``stuck_after``): moved < 0.1 m, treads turned >= 0.5 m."""
        window = self.scenario.stuck_after
        if window is None:
            return False
        self._tread += float(np.mean(np.abs(gt.wheel_rate))) * self.geometry.wheel_radius * self.control_dt
        track = self._stuck_track
        track.append((gt.t, float(gt.pose[0]), float(gt.pose[1]), self._tread))
        while len(track) > 1 and track[1][0] <= gt.t - window:
            track.pop(0)
        t0, x0, y0, tread0 = track[0]
        if gt.t - t0 < window - 1e-9:
            return False
        moved = math.hypot(gt.pose[0] - x0, gt.pose[1] - y0)
        return moved < STUCK_DISTANCE and self._tread - tread0 >= STUCK_TREAD

    def _nav_pose(self) -> np.ndarray:
        """(x, y, yaw) the on-board tracker is fed: dead-reckoned, or the truth for ground truth."""
        if self._est is not None:
            return np.asarray(self._est["pose"], dtype=np.float64).copy()
        gt = self._gt
        assert gt is not None
        return np.array([gt.pose[0], gt.pose[1], quat_to_yaw(gt.pose[3:])])

    def _judge_features(self, success: bool = False):
        """Course features of the true pose on the tracker's current segment (for reward and info)."""
        gt = self._gt
        assert gt is not None
        feats = self.course.features(gt.pose[:2], quat_to_yaw(gt.pose[3:]), clamp_finished=False)
        if success:
            feats = dataclasses.replace(feats, progress=self.course.length)
        return feats

    @property
    def rig(self):
        """The sensor rig an estimator is given, or None with ground-truth observations.

        A :class:`perception.rig.Rig`: sensor name -> kind, rate, mount, model.
        """
        return self.pipeline.rig if self.pipeline is not None else None

    @property
    def estimate_values(self) -> dict[str, Any] | None:
        """What the estimator returned at the last step, by name (checked), or None with ground truth.

        The names of :data:`perception.estimator.ESTIMATE_FIELDS` it returned (``"pose"``: a
        (3,) array, the rest floats); a name it left out is absent. A copy: changing it changes
        nothing.
        """
        if self._est is None:
            return None
        return {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in self._est.items()}

    @property
    def renderer(self) -> str:
        """What draws the cameras: ``"gl"`` or ``"tiny"`` (see the ``renderer`` argument)."""
        return self.sim.renderer

    def render(self) -> np.ndarray | None:
        """Composite frame, RGB uint8 (H, W, 3) of ``render_size`` (see :class:`ChaseView`).

        A third-person chase view on the left, the downward camera's image top right and the
        fisheye image bottom right, all rendered now, at the current simulation time.
        """
        self._check_open("render")
        if self.render_mode != "rgb_array":
            return None
        if self._chase is None:
            mounts = None  # ground truth: the standard cameras' views
            if self.pipeline is not None:  # the rig's first camera of each kind, where it has one
                down, fish = self.pipeline.downward, self.pipeline.fisheye
                mounts = {
                    "pinhole": None if down is None else down.T_body_cam,
                    "fisheye": None if fish is None else fish.T_body_cam,
                }
            self._chase = ChaseView(self.sim, self.scenario, self.render_size, mounts)
        return self._chase.frame()

    def close(self) -> None:
        """Release the physics client; safe to call more than once."""
        if not self._closed:
            self._closed = True
            self.sim.close()

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise RuntimeError(
                f"{what}() after close(): this environment's physics client is released; make a new one "
                "with gymnasium.make(...)"
            )

    # an environment owns a physics client (a process-level resource): it is not copied or pickled
    def __deepcopy__(self, memo):
        raise TypeError(
            "a RoverEnv cannot be deep-copied: it owns a PyBullet client, which a copy would share "
            "(stepping one would move the other). Make a second environment with gymnasium.make(...) "
            "and the same arguments, and reset both with the same seed"
        )

    def __reduce_ex__(self, protocol):
        raise TypeError(
            "a RoverEnv cannot be pickled: it owns a PyBullet client. Send its constructor arguments "
            "(or a function that calls gymnasium.make) to the other process and make it there, as "
            "SubprocVecEnv does"
        )

    # ------------------------------------------------------------------ helpers
    def _validate_action(self, action) -> np.ndarray:
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(
                f"action has shape {a.shape}; action_mode={self.action_mode.value!r} expects "
                f"{self.action_space.shape}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(
                f"action contains NaN or infinite values: {a.tolist()}; send finite values in [-1, 1]"
            )
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def _observation(self, feats) -> np.ndarray:
        """The observation from the state source, the tracker's features and the previous action."""
        if self._est is None:
            gt = self._gt
            assert gt is not None
            state, quality = gt.as_dict(), (1.0, 1.0, 1.0)
        else:
            state, quality = state_arrays(self._est), qualities(self._est)
        values = obs_table.state_values(state, quality, task_values(feats))
        return obs_table.assemble(self.obs_fields, values, self._prev_action)

    def soil_truth(self) -> dict[str, np.ndarray]:
        """The soil under each wheel now, from its steady state (``SOIL_CURVE_KEYS``).

        Per wheel (FL, FR, RL, RR): ``pull_ratio``, the soil's steady-state drawbar pull over
        load at the wheel's true slip and load (virgin soil); ``slip_best_pull`` and
        ``slip_best_efficiency``, the slips of the largest DP/W and of the largest tractive
        efficiency at that load. NaN for a wheel on rigid ground (and for the first, braking
        harder than -0.5). Not in ``info``: Gymnasium's checker reads NaN as nondeterminism.
        """
        if self._gt is None:
            raise RuntimeError("call reset() first")
        return self._gt.soil_dict()

    def _estimate_info(self) -> dict[str, np.ndarray]:
        """The estimate under the ground truth's keys (pose dead-reckoned; NaN where it gives none)."""
        assert self._est is not None
        v = self._est
        x, y, yaw = v["pose"]
        roll, pitch = v.get("roll", 0.0), v.get("pitch", 0.0)  # unknown without an IMU: level
        out = {"pose": np.array([x, y, self._z0 + v.get("height", 0.0), *yaw_to_quat(roll, pitch, yaw)])}
        out.update(state_arrays(v))
        out["odometry_pose"] = np.array(v["pose"], dtype=np.float64)
        out["quality"] = np.array(qualities(v), dtype=np.float64)
        return out

    def _info(self, feats, terms: dict[str, float], success: bool, reason: str | None) -> dict[str, Any]:
        gt = self._gt
        assert gt is not None
        out = {
            "ground_truth": gt.as_dict(),
            "wheel_contact": gt.contact_dict(),
            "reward_terms": terms,
            "wheel_power": wheel_power(gt),
            "t": gt.t,
            "waypoint_index": self.course.index,
            "start_fix": self._start_fix.copy(),
            "progress": feats.progress,
            "cross_track": feats.cross_track,
            "is_success": bool(success),
            "termination": reason,
        }
        if self._est is not None:
            v = self._est
            out["estimate"] = self._estimate_info()
            q_odo, q_kin, q_att = qualities(v)
            out["quality"] = {
                "odometry": q_odo,
                "kinematics": q_kin,
                "attitude": q_att,
                "slip": float(v.get("slip_quality", 0.0)),
            }
            out["slip"] = {
                "valid": np.array([v.get(f"slip_valid_{w}", 0.0) > 0.5 for w in WHEEL_NAMES]),
                "events": np.array([v.get(f"slip_event_{w}", 0.0) > 0.5 for w in WHEEL_NAMES]),
                "slip_ratio_std": np.array([v.get(f"slip_std_{w}", math.nan) for w in WHEEL_NAMES]),
            }
        return out

"""The rover on deformable soil: resting sinkage, climbing slip against the single-wheel model."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from conftest import flat_scenario

from rover_env.config.io import ConfigError
from rover_env.config.scenario import FrictionPatch
from rover_env.config.soil import load_soil
from rover_env.sim.geometry import GRAVITY
from rover_env.sim.simulation import RoverSim
from rover_env.sim.terramechanics import WheelSpec, contact_forces, rut_surface, steady_state

SOIL = "toyoura"


def _soil_sim(slope_deg=0.0, center=(10.0, 0.0), size=(40.0, 20.0)):
    patch = FrictionPatch(mu=0.5, center=center, size=size, soil=SOIL)
    sc = flat_scenario(mu=1.0, patches=[patch])
    sc = dataclasses.replace(sc, terrain=dataclasses.replace(sc.terrain, slope_deg=slope_deg))
    return RoverSim(sc)


def _mass(g) -> float:
    return g.body_mass + 4 * g.wheel_mass + 2 * g.axle_mass + 2 * g.carriage_mass + 4 * g.knuckle_mass


def _wheel(g) -> WheelSpec:
    return WheelSpec(radius=g.wheel_radius, width=g.wheel_width)


def test_a_rover_on_soil_rests_at_the_static_sinkage_and_does_not_creep():
    sim = _soil_sim()
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        load = _mass(g) * GRAVITY / 4
        lo, hi = 0.0, g.wheel_radius
        for _ in range(50):
            mid = 0.5 * (lo + hi)
            f = contact_forces(load_soil(SOIL), _wheel(g), mid, 0.0, 0.0, n_theta=24).normal
            lo, hi = (mid, hi) if f < load else (lo, mid)
        xy0 = sim.ground_truth().pose[:2].copy()
        sim.step(4.0)
        sink = sim.rover.soil.sinkage
        assert sink == pytest.approx(np.full(4, lo), rel=0.03)
        assert np.abs(sim.ground_truth().pose[:2] - xy0).max() < 5e-4
    finally:
        sim.close()


@pytest.mark.parametrize("slope_deg", [6.0, 12.0])
def test_a_rover_climbing_soil_slips_as_the_single_wheel_model_predicts(slope_deg):
    # Four wheels driven at one rate up a slope: together they pull the weight's downhill part.
    # Predicted from the single-wheel steady states at one slip: the front wheels on fresh
    # soil, the rear ones in the front wheels' ruts (their sinkage and the shear they leave),
    # each pair at the load the simulation puts on it.
    sim = _soil_sim(slope_deg)
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        sim.rover.command(np.full(4, 0.3 / g.wheel_radius), 0.0, 0.0)
        # The rear wheels meet the ruts the front ones left 3 s before, and their traction
        # follows the shear left there: the slip swings slowly about its mean (a period of
        # about two delays, decaying). Averaged over two periods.
        sim.step(10.0)
        slips, loads, sinks = [], [], []
        for _ in range(240):
            sim.step(1 / 20)
            slips.append(sim.ground_truth().slip_ratio.copy())
            loads.append(sim.rover.soil.contact.last[:, 1].copy())
            sinks.append(sim.rover.soil.sinkage.copy())
        slip = float(np.mean(slips))
        load = np.mean(loads, axis=0)
        sink = np.mean(sinks, axis=0)
        a = math.radians(slope_deg)
        assert load.sum() == pytest.approx(_mass(g) * GRAVITY * math.cos(a), rel=0.005)
        front_load, rear_load = load[:2].mean(), load[2:].mean()
        s = np.linspace(0.0, 0.5, 251)
        soil, wheel = load_soil(SOIL), _wheel(g)
        front = steady_state(soil, wheel, front_load, s, speed=0.3)
        rear = steady_state(
            soil, wheel, rear_load, s, speed=0.3, prior=front.sinkage, prior_shear=front.shear_exit
        )
        pull = (front.drawbar_pull + rear.drawbar_pull) / (front_load + rear_load)
        k = int(np.argmax(pull >= math.tan(a)))
        assert 0 < k < len(s) - 1
        assert slip == pytest.approx(s[k], abs=0.02)
        assert sink[:2] == pytest.approx(np.full(2, front.sinkage[k]), rel=0.03)
        assert sink[2:] == pytest.approx(np.full(2, rear.sinkage[k]), rel=0.03)
        assert sink[2:].min() > sink[:2].max()  # the rear wheels sink on into the ruts
    finally:
        sim.close()


def test_wheels_off_the_soil_stand_on_the_rigid_ground():
    # the soil patch under the rear wheels only (the axles are 0.8 m apart, centred on 0)
    sim = _soil_sim(center=(-2.0, 0.0), size=(4.0, 4.0))
    try:
        sim.reset(0.0, 0.0, 0.0)
        sim.step(2.0)
        sink = sim.rover.soil.sinkage
        assert np.all(sink[:2] == 0.0) and np.all(sink[2:] > 0.01)
        gt = sim.ground_truth()
        assert np.all(gt.normal_force[:2] > 50.0)  # the rigid ground carries the front wheels
        assert gt.pose[2] > 0.0
    finally:
        sim.close()


def test_a_patch_names_its_soil_and_bad_soils_are_refused():
    p = FrictionPatch(mu=0.5, center=(0.0, 0.0), soil={"preset": "lunar_regolith", "cohesion": 300})
    assert p.soil.cohesion == 300.0 and p.soil.name == "custom"
    with pytest.raises(ConfigError, match="soil.friction_deg"):
        FrictionPatch(mu=0.5, center=(0.0, 0.0), soil={"preset": "toyoura", "friction_deg": 91})
    with pytest.raises(ConfigError, match="choose one of"):
        FrictionPatch(mu=0.5, center=(0.0, 0.0), soil="quicksand")


def test_the_wheels_leave_ruts_as_deep_as_they_sank():
    sim = _soil_sim()
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        sim.rover.command(np.full(4, 0.3 / g.wheel_radius), 0.0, 0.0)
        nbytes = sim.rover.ruts.nbytes
        sinks = []
        for _ in range(40):
            sim.step(0.1)
            sinks.append(sim.rover.soil.sinkage.copy())
        rear_sink = np.mean(sinks[-10:], axis=0)[2:]
        wheels = np.array([st[4] for st in sim.rover._read_wheels()])
        # behind the rear wheels, along their tracks: pressed as deep as they sank
        behind = wheels[2:, :2] - np.array([0.3, 0.0])
        pressed = sim.rover.ruts.sample(behind)[:, 0]
        assert pressed == pytest.approx(rear_sink, rel=0.03)
        rut = rut_surface(load_soil(SOIL), _wheel(g), pressed)
        assert np.all(rut > 0.8 * rear_sink) and np.all(rut < rear_sink)  # rebounds a little
        # the map keeps that surface for the renderers
        x0, y0, depth = sim.rover.ruts.surface(float(behind[0, 0]), float(behind[0, 1]), 0.05)
        cell = sim.rover.ruts.cell
        i, j = int((behind[0, 0] - x0) / cell), int((behind[0, 1] - y0) / cell)
        assert depth[j, i] == pytest.approx(rut[0], rel=1e-5)
        # beside the tracks the soil is untouched
        assert np.all(sim.rover.ruts.sample(behind + np.array([0.0, 0.15]))[:, 0] == 0.0)
        assert sim.rover.ruts.nbytes == nbytes  # the map's memory is fixed
    finally:
        sim.close()


def test_ground_truth_on_soil_reports_the_soils_load():
    sim = _soil_sim()
    try:
        sim.reset(0.0, 0.0, 0.0)
        gt = sim.ground_truth()
        assert gt.normal_force.sum() == pytest.approx(_mass(sim.geometry) * GRAVITY, rel=0.01)
        assert np.all(np.isfinite(gt.contact_point))
        assert gt.friction == pytest.approx(np.full(4, math.tan(math.radians(load_soil(SOIL).friction_deg))))
    finally:
        sim.close()


def test_soil_contact_refuses_non_finite_or_misshapen_input():
    from rover_env.sim.soil_contact import SoilContact

    c = SoilContact(load_soil(SOIL), WheelSpec(0.1, 0.1), 4, 1 / 240)
    ok = np.zeros(4)
    with pytest.raises(ValueError, match="v_x.*NaN"):
        c.step(ok, np.array([0.0, np.nan, 0.0, 0.0]), ok, ok, ok)
    with pytest.raises(ValueError, match="sinkage: shape"):
        c.step(np.zeros(3), ok, ok, ok, ok)


def test_on_the_soft_sand_hill_traction_control_tuned_for_friction_patches_gets_stuck():
    # RoverSoftSand-v0 on the truth, seed 1: the follower without traction control climbs
    # through the loose sand at the slip the hill asks for (about 0.5); the traction control's
    # set-point (0.15, tuned on friction patches) holds the wheels to a crawl in the sand
    # pocket, where they turn while the body stops: the judge names it "stuck".
    from controllers import PathFollower, SlipAwareController
    from rover_env.envs import RoverEnv
    from rover_env.tools.mission import run_mission

    ends = {}
    for name, cls, mode in (
        ("slip_unaware", PathFollower, "drive"),
        ("slip_aware", SlipAwareController, "wheels"),
    ):
        env = RoverEnv(scenario="soft_sand", obs_source="ground_truth", action_mode=mode)
        try:
            result = run_mission(env, cls.for_env(env), seed=1)
        finally:
            env.close()
        ends[name] = (result.metrics.termination, result.metrics.progress)
    assert ends["slip_unaware"][0] == "success"
    assert ends["slip_aware"][0] == "stuck" and ends["slip_aware"][1] < 0.8 * ends["slip_unaware"][1]


def test_on_soil_the_odometrys_ground_is_the_surface_in_view_not_the_rims_lowest_points():
    """Up the soil slope the wheels sink about 2 cm: the odometry's plane rises by the measured sinkage.

    Through the wheels' lowest points the downward camera's ground lies 2 cm too low and the
    speed reads fast (measured before the lift, with the BMI088: +3.4 %); raised by each
    wheel's sinkage from the fisheye it reads within 1 %.
    """
    import gymnasium as gym

    env = gym.make("RoverSlopeLoose-v1", imu="bmi088")
    try:
        env.reset(seed=5)
        est, true, lift, sink = [], [], [], []
        for k in range(240):
            info = env.step(np.array([0.5, 0.0, 0.0], dtype=np.float32))[4]
            if k >= 90:  # on the move, the wheels sunk
                est.append(info["estimate"]["twist"][0])
                true.append(info["ground_truth"]["twist"][0])
                lift.append(env.unwrapped.pipeline.estimator._lift[0].copy())
                sink.append(info["ground_truth"]["sinkage"])
        # each wheel's ground is raised by about its true sinkage
        assert np.mean(sink) > 0.015
        np.testing.assert_allclose(np.median(lift, axis=0), np.median(sink, axis=0), atol=0.005)
        assert np.mean(est) / np.mean(true) == pytest.approx(1.0, abs=0.01)
    finally:
        env.close()

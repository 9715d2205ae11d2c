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
from rover_env.sim.terramechanics import WheelSpec, contact_forces, steady_state

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
    # Four driven wheels at one rate: each must pull tan(slope) of its load. The slip at which
    # the single-wheel steady state does so is the rover's slip (loads taken equal).
    sim = _soil_sim(slope_deg)
    try:
        sim.reset(0.0, 0.0, 0.0)
        g = sim.geometry
        sim.rover.command(np.full(4, 0.3 / g.wheel_radius), 0.0, 0.0)
        sim.step(5.0)
        slips = []
        for _ in range(120):
            sim.step(1 / 40)
            slips.append(sim.ground_truth().slip_ratio.copy())
        slip = float(np.mean(slips))
        a = math.radians(slope_deg)
        load = _mass(g) * GRAVITY * math.cos(a) / 4
        s = np.linspace(0.0, 0.6, 601)
        pull = steady_state(load_soil(SOIL), _wheel(g), load, s, speed=0.3).drawbar_pull / load
        predicted = s[np.argmax(pull >= math.tan(a))]
        assert 0.05 < predicted < 0.4
        assert slip == pytest.approx(predicted, abs=0.015)
        sink = sim.rover.soil.sinkage
        assert sink[2:].min() > sink[:2].max()  # the load shifts to the rear wheels uphill
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

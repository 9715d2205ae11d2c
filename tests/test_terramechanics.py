"""The wheel–soil contact model against known answers and the physics a test bed shows."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import quad

from rover_env.config.io import ConfigError
from rover_env.config.soil import SOIL_PRESETS, SoilConfig, load_soil
from rover_env.sim.terramechanics import WheelSpec, contact_forces, rut_surface, steady_state

WHEEL = WheelSpec(radius=0.09, width=0.11)  # Ishigami et al. 2007's test wheel
LOAD = 64.68  # their load [N]
SLIPS = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])


@pytest.mark.parametrize("n", [1.0, 1.1, 0.8])
def test_frictionless_soil_resists_with_bekkers_compaction_resistance(n):
    # Without shear strength only the normal stress acts; over a front arc (theta_m = 0, no
    # rear contact) its horizontal part integrates to Bekker's R_c = b k z^(n+1) / (n+1).
    soil = SoilConfig(k_c=2e3, k_phi=9e5, n=n, friction_deg=0.0, peak_a0=0.0, peak_a1=0.0, rear_b0=0.0)
    z = 0.012
    f = contact_forces(soil, WHEEL, z, v_x=0.1, omega=0.1 / WHEEL.radius, n_theta=400)
    k = soil.modulus(WHEEL.width)
    assert f.drawbar_pull == pytest.approx(-WHEEL.width * k * z ** (n + 1) / (n + 1), rel=2e-4)
    tf = math.acos(1 - z / WHEEL.radius)
    carried = quad(lambda t: k * (WHEEL.radius * (math.cos(t) - math.cos(tf))) ** n * math.cos(t), 0, tf)[0]
    assert f.normal == pytest.approx(WHEEL.radius * WHEEL.width * carried, rel=2e-4)
    assert f.torque == pytest.approx(0.0, abs=1e-12)


def test_at_rest_the_contact_is_symmetric_and_carries_bekkers_static_load():
    soil = load_soil("toyoura")
    z = 0.01
    f = contact_forces(soil, WHEEL, z, v_x=0.0, omega=0.0, n_theta=400)
    assert f.drawbar_pull == pytest.approx(0.0, abs=1e-9)
    assert f.torque == pytest.approx(0.0, abs=1e-12)
    k, r, n = soil.modulus(WHEEL.width), WHEEL.radius, soil.n
    tf = math.acos(1 - z / r)
    static = quad(lambda t: k * (r * (math.cos(t) - math.cos(tf))) ** n * math.cos(t), -tf, tf)[0]
    assert f.normal == pytest.approx(r * WHEEL.width * static, rel=1e-3)
    assert f.theta_r == pytest.approx(-f.theta_f)


@pytest.mark.parametrize("name", ["toyoura", "lunar_regolith", "mars_simulant", "dry_sand"])
def test_drawbar_pull_rises_with_slip_and_levels_off_below_the_shear_limit(name):
    soil = load_soil(name)
    r = steady_state(soil, WHEEL, LOAD, SLIPS)
    assert r.converged.all()
    dpw = r.drawbar_pull / LOAD
    assert abs(dpw[0]) < 0.1 < dpw[3]  # near zero at zero slip, traction after
    assert np.all(np.diff(dpw[:6]) > 0.0)
    assert dpw[9] - dpw[6] < 0.5 * (dpw[3] - dpw[0])  # it levels off
    # below the soil's shear limit: all of the contact at (c + sigma tan phi)
    area = WHEEL.width * WHEEL.radius * 2.0 * math.acos(1 - r.sinkage.max() / WHEEL.radius)
    limit = (soil.cohesion * area + LOAD * math.tan(math.radians(soil.friction_deg))) / LOAD
    assert dpw.max() < limit


@pytest.mark.parametrize("name", ["toyoura", "lunar_regolith", "dry_sand", "cmu_testbed_grousered"])
def test_sinkage_grows_with_slip_and_with_the_load(name):
    soil = load_soil(name)
    r = steady_state(soil, WHEEL, LOAD, SLIPS)
    assert np.all(np.diff(r.sinkage[1:]) > 0.0)
    assert r.sinkage[9] > 1.1 * r.sinkage[0]
    heavy = steady_state(soil, WHEEL, [LOAD, 1.5 * LOAD, 2.0 * LOAD], 0.2)
    assert np.all(np.diff(heavy.sinkage) > 0.0)


@pytest.mark.parametrize("name", ["toyoura", "dry_sand", "cmu_testbed_smooth"])
def test_braking_pulls_back(name):
    r = steady_state(load_soil(name), WHEEL, LOAD, [-0.1, -0.3, -0.6])
    dpw = r.drawbar_pull / LOAD
    assert np.all(dpw < 0.0)
    assert np.all(np.diff(dpw) < 0.0)  # harder braking, more resistance
    assert np.all(r.torque < 0.0)  # the soil drives the wheel forward: it must be held back


def test_a_wheel_in_a_rut_sinks_less_and_pulls_more():
    soil = load_soil("toyoura")
    first = steady_state(soil, WHEEL, LOAD, 0.2)
    rut = rut_surface(soil, WHEEL, first.sinkage)
    assert 0.0 < rut < first.sinkage  # the rut rebounds, but stays
    second = steady_state(soil, WHEEL, LOAD, 0.2, prior=first.sinkage, prior_shear=first.shear_exit)
    assert first.shear_exit > 0.0
    assert second.converged
    assert second.sinkage - rut < 0.5 * first.sinkage  # sinks less below the surface it meets
    assert second.drawbar_pull > first.drawbar_pull + 0.02 * LOAD


def test_reversing_mirrors_the_forces():
    soil = load_soil("dry_sand")
    fwd = contact_forces(soil, WHEEL, 0.015, v_x=0.1, omega=0.2 / WHEEL.radius)
    back = contact_forces(soil, WHEEL, 0.015, v_x=-0.1, omega=-0.2 / WHEEL.radius)
    assert back.drawbar_pull == pytest.approx(-fwd.drawbar_pull)
    assert back.torque == pytest.approx(-fwd.torque)
    assert back.normal == pytest.approx(fwd.normal)
    assert back.slip == pytest.approx(fwd.slip) == pytest.approx(0.5)


def test_side_slip_pushes_back_across_the_wheel():
    soil = load_soil("toyoura")
    f = contact_forces(soil, WHEEL, 0.015, v_x=0.1, omega=0.1 / WHEEL.radius, v_y=[0.0, 0.02, -0.02, 0.05])
    assert f.lateral[0] == pytest.approx(0.0, abs=1e-9)
    assert f.lateral[1] < 0.0 < f.lateral[2]
    assert f.lateral[3] < f.lateral[1]
    assert f.lateral[2] == pytest.approx(-f.lateral[1])


def test_grouser_tips_share_of_the_rim():
    assert WheelSpec(0.1, 0.1).tips == 1.0
    w = WheelSpec(0.1, 0.1, grousers=20, grouser_height=0.01, grouser_thickness=0.004)
    assert w.shear_radius == pytest.approx(0.11)
    assert w.tips == pytest.approx(20 * 0.004 / (2 * math.pi * 0.11))
    assert WheelSpec(0.1, 0.1, grousers=20, grouser_height=0.01, tip_ratio=0.1).tips == 0.1


def test_presets_name_their_sources():
    for name, soil in SOIL_PRESETS.items():
        assert soil.name == name
        assert len(soil.source) > 40


@pytest.mark.parametrize(
    ("change", "key"),
    [
        ({"k_phi": -1.0}, "soil.k_phi"),
        ({"k_c": -5.0}, "soil.k_c"),
        ({"friction_deg": 90.0}, "soil.friction_deg"),
        ({"n": 0.0}, "soil.n"),
        ({"n": -0.5}, "soil.n"),
        ({"shear_modulus": 0.0}, "soil.shear_modulus"),
        ({"cohesion": float("nan")}, "soil.cohesion"),
        ({"peak_a1": 0.9}, "soil.peak_a0 + soil.peak_a1"),
        ({"n_skid_power": 0.0}, "soil.n_skid_power"),
        ({"bulk": 3}, "bulk"),
    ],
)
def test_impossible_soils_are_refused_by_name(change, key):
    with pytest.raises(ConfigError, match=key.replace("+", r"\+")):
        SoilConfig.from_dict({"preset": "dry_sand", **change})


def test_a_soil_from_yaml_and_an_unknown_preset(tmp_path):
    path = tmp_path / "soil.yaml"
    path.write_text("preset: toyoura\ncohesion: 500\n")
    soil = load_soil(path)
    assert soil.cohesion == 500.0 and soil.k_phi == SOIL_PRESETS["toyoura"].k_phi
    assert soil.name == "custom"
    path.write_text("preset: toyoura\nfriction_deg: 95\n")
    with pytest.raises(ConfigError, match=r"soil.yaml.*soil.friction_deg"):
        load_soil(path)
    with pytest.raises(ConfigError, match="choose one of"):
        load_soil("quicksand")


@pytest.mark.parametrize(
    ("load", "slip", "key"),
    [
        (0.0, 0.2, "load"),
        (-5.0, 0.2, "load"),
        (20.0, 1.2, "slip"),
        (20.0, -1.5, "slip"),
        (20.0, float("nan"), "slip"),
    ],
)
def test_a_test_bed_run_refuses_impossible_loads_and_slips(load, slip, key):
    with pytest.raises(ConfigError, match=key):
        steady_state(load_soil("dry_sand"), WHEEL, load, slip)


@pytest.mark.parametrize(
    ("kw", "key"),
    [
        ({"radius": 0.0}, "wheel.radius"),
        ({"width": -0.1}, "wheel.width"),
        ({"grousers": -2}, "wheel.grousers"),
    ],
)
def test_impossible_wheels_are_refused(kw, key):
    args = {"radius": 0.1, "width": 0.1} | kw
    with pytest.raises(ConfigError, match=key):
        WheelSpec(**args)


def test_the_model_matches_a_published_single_wheel_test_bed():
    # Pavlov and Johnson's measurements (benchmarks/data; benchmarks/wheel_validation.py), slips
    # -0.5 to 0.9, each at its measured load, with their published soil parameters (the
    # slip-sinkage coefficients refit by benchmarks/wheel_fit.py): the bar.
    import csv
    from pathlib import Path

    path = Path(__file__).parents[1] / "benchmarks" / "data" / "cmu_single_wheel_beta0.csv"
    rows = list(csv.DictReader(open(path, newline="")))
    wheels = {
        "grousered": ("cmu_testbed_grousered", WheelSpec(0.058, 0.05, grouser_height=0.005, tip_ratio=0.1)),
        "smooth": ("cmu_testbed_smooth", WheelSpec(0.058, 0.05)),
    }
    for wheel, (soil, spec) in wheels.items():
        mine = [r for r in rows if r["wheel"] == wheel and float(r["slip"]) >= -0.51]
        slip, load = (np.array([float(r[k]) for r in mine]) for k in ("slip", "load_N"))
        dpw, sink = (np.array([float(r[k]) for r in mine]) for k in ("dp_over_w", "sinkage_m"))
        r = steady_state(load_soil(soil), spec, load, slip)
        assert len(mine) == 7 and r.converged.all()
        assert np.abs(r.drawbar_pull / load - dpw).mean() < 0.05
        assert np.abs(r.sinkage / sink - 1.0).max() < 0.25


def test_light_braking_barely_sinks_and_a_locked_wheel_sinks_deep():
    # Pavlov and Johnson's smooth wheel: 15.1 mm at skid -0.2 as at rest (14.4), 50 mm locked.
    # The skid law's power (1.5) keeps light braking shallow; a linear law (power 1) with the
    # same coefficients sinks it deeper there.
    soil = load_soil("cmu_testbed_smooth")
    wheel = WheelSpec(0.058, 0.05)
    z = steady_state(soil, wheel, 23.7, [0.0, -0.2, -1.0]).sinkage
    assert z[1] / z[0] < 1.2 and z[2] / z[0] > 3.0
    linear = steady_state(replace(soil, n_skid_power=1.0), wheel, 23.7, -0.2).sinkage
    assert linear > 1.1 * z[1]


def test_no_side_force_jumps_at_zero_speed():
    soil = load_soil("toyoura")
    f = contact_forces(soil, WHEEL, 0.015, v_x=0.0, omega=0.0, v_y=[-1e-7, 0.0, 1e-7])
    assert np.abs(f.lateral).max() < 1e-3  # N: a creep of 0.1 um/s is no slide


def test_a_test_bed_run_refuses_a_speed_that_is_rest():
    with pytest.raises(ConfigError, match="speed"):
        steady_state(load_soil("dry_sand"), WHEEL, LOAD, 0.2, speed=0.001)


def _rolled(contact, z: float, v: float, steps: int = 480) -> None:
    """Roll a wheel ``steps`` substeps at sinkage ``z`` [m] and ``v`` [m/s] without slip."""
    one = np.ones(1)
    for _ in range(steps):
        contact.step(z * one, v * one, v / WHEEL.radius * one, 0.0 * one, 0.0 * one)


@pytest.mark.parametrize("v", [0.3, 0.0])
def test_soil_pressed_and_relieved_springs_back_only_by_its_rebound(v):
    """A rolling wheel that rises faster than its contact meets fresh soil is not carried up Bekker's curve.

    Toyoura sand pressed to 20 mm rebounds by p/k_u = 1.7 mm: risen 3 mm in one substep (far
    faster than v sin(theta_f), 0.6 mm a substep) the wheel feels no soil; risen 0.2 mm a
    substep it stays on the loading curve. At rest the model's rest state keeps Bekker's curve
    both ways (a rover set down settles at its static sinkage).
    """
    from rover_env.sim.soil_contact import SoilContact

    soil = SOIL_PRESETS["toyoura"]
    one = np.ones(1)
    c = SoilContact(soil, WHEEL, 1, 1 / 240)
    _rolled(c, 0.020, v)
    fz = c.step(0.017 * one, v * one, v / WHEEL.radius * one, 0.0 * one, 0.0 * one)[0, 1]
    virgin = float(contact_forces(soil, WHEEL, 0.017, v, v / WHEEL.radius).normal)
    if v > 0.0:
        assert abs(fz) < 1.0 and virgin > 50.0  # (the cohesion's shear alone: -0.1 N)
        slow = SoilContact(soil, WHEEL, 1, 1 / 240)
        _rolled(slow, 0.020, v)
        for k in range(1, 16):  # 0.2 mm a substep: carried all the way up
            z = 0.020 - 0.0002 * k
            fz = slow.step(z * one, v * one, v / WHEEL.radius * one, 0.0 * one, 0.0 * one)[0, 1]
        carried = float(contact_forces(soil, WHEEL, z, v, v / WHEEL.radius).normal)
        assert fz == pytest.approx(carried, rel=0.05)
    else:
        assert fz == pytest.approx(virgin, rel=0.02)

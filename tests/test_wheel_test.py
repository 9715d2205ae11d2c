"""The single-wheel test bed in PyBullet: steady states, rest, slopes, drops, and its command."""

from __future__ import annotations

import csv
import math

import numpy as np
import pybullet as pb
import pytest

from rover_env.config.io import ConfigError
from rover_env.config.soil import load_soil
from rover_env.sim.terramechanics import WheelSpec, contact_forces, steady_state
from rover_env.sim.wheel_test import COLUMNS, _Bed, run_wheel_test
from rover_env.tools.cli import main

WHEEL = WheelSpec(radius=0.09, width=0.11)
LOAD = 64.68


@pytest.mark.parametrize(
    ("soil", "wheel", "slips"),
    [
        ("toyoura", WHEEL, [-0.4, 0.0, 0.3, 0.7]),
        (
            "cmu_testbed_grousered",
            WheelSpec(0.058, 0.05, grouser_height=0.005, tip_ratio=0.1),
            [-0.3, 0.2, 0.6],
        ),
    ],
)
def test_the_test_bed_reaches_the_models_steady_state(soil, wheel, slips):
    # a metre of travel, as a lab's bed: the soil's shear builds over a contact length or so
    load = 24.0 if wheel.radius < 0.06 else LOAD
    rows = run_wheel_test(load_soil(soil), wheel, load, slips)
    ss = steady_state(load_soil(soil), wheel, load, slips)
    for row, dp, z in zip(rows, ss.drawbar_pull, ss.sinkage, strict=True):
        assert row.load_N == pytest.approx(load, rel=1e-3)
        assert row.drawbar_pull_N / load == pytest.approx(dp / load, abs=0.01)
        assert row.sinkage_m == pytest.approx(z, rel=0.02)
    assert rows[0].drawbar_pull_N < 0.0 < rows[-2].drawbar_pull_N < rows[-1].drawbar_pull_N
    assert rows[0].torque_Nm < 0.0 < rows[-2].torque_Nm


def _static_sinkage(soil, wheel, load):
    lo, hi = 0.0, wheel.shear_radius
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if contact_forces(soil, wheel, mid, 0.0, 0.0, n_theta=24).normal < load:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _free_bed(soil_name, gravity_tilt_deg=0.0):
    soil = load_soil(soil_name)
    bed = _Bed(soil, WHEEL, LOAD, 1.0 / 240.0)
    g = 9.81
    a = math.radians(gravity_tilt_deg)
    bed.c.setGravity(g * math.sin(a), 0.0, -g * math.cos(a))
    bed.c.setJointMotorControl2(bed.body, 0, pb.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0)
    bed.c.setJointMotorControl2(bed.body, 2, pb.VELOCITY_CONTROL, targetVelocity=0.0, force=1e5)
    return soil, bed


def _carriage_x(bed):
    return bed.c.getJointState(bed.body, 0)[0]


def test_at_rest_on_level_soil_a_wheel_settles_at_the_pressure_sinkage_equilibrium_and_does_not_creep():
    soil, bed = _free_bed("toyoura")
    bed.c.setJointMotorControl2(bed.body, 2, pb.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0)
    try:
        sink = [bed._substep()[1] for _ in range(240 * 3)]
        x0 = _carriage_x(bed)
        for _ in range(240 * 5):
            bed._substep()
        assert sink[-1] == pytest.approx(_static_sinkage(soil, WHEEL, LOAD), rel=0.01)
        assert abs(_carriage_x(bed) - x0) < 1e-5  # no creep in 5 s
        assert abs(bed.c.getJointState(bed.body, 2)[1]) < 1e-4  # nor any turning
    finally:
        bed.close()


def test_a_braked_wheel_settled_on_soil_creeps_into_its_hold_when_tilted_and_stands():
    soil, bed = _free_bed("toyoura")
    try:
        for _ in range(240 * 2):  # settle on level soil, then tilt it by 15 degrees
            bed._substep()
        a = math.radians(15.0)
        bed.c.setGravity(9.81 * math.sin(a), 0.0, -9.81 * math.cos(a))
        x = []
        for _ in range(240 * 6):
            bed._substep()
            x.append(_carriage_x(bed))
        x = np.array(x)
        assert 0.0 < x[-1] < 2.0 * soil.shear_modulus  # crept into its hold, a few cm at most
        assert np.ptp(x[-480:]) < 1e-4  # then stands: under 0.1 mm in the last two seconds
        # the soil holds the downhill weight of everything the carriage carries
        carried = sum(bed.c.getDynamicsInfo(bed.body, link)[0] for link in (0, 1, 2))
        assert -bed.soil.last[0, 0] == pytest.approx(carried * 9.81 * math.sin(a), rel=0.01)
    finally:
        bed.close()


def test_a_wheel_dropped_on_soil_settles_without_bouncing_back_up():
    soil, bed = _free_bed("dry_sand")
    try:
        bed.c.resetJointState(bed.body, 1, 0.02)  # 2 cm above the surface
        z = []
        for _ in range(240 * 2):
            bed._substep()
            z.append(bed.c.getJointState(bed.body, 1)[0])
        z = np.array(z)
        landed = np.argmax(z < 0.0)
        assert z[landed:].max() < 0.002  # never back up near the drop height: no energy gained
        assert np.abs(np.diff(z[-120:])).max() * 240 < 1e-3  # at rest after two seconds
        assert -z[-1] == pytest.approx(_static_sinkage(soil, WHEEL, LOAD), rel=0.03)
    finally:
        bed.close()


def test_wheel_test_command_writes_its_table_and_plot(tmp_path, capsys):
    out = tmp_path / "bed"
    args = ["wheel-test", "--soil", "toyoura", "--radius", "0.09", "--width", "0.11", "--load", "64.68"]
    assert main([*args, "--slips", "-0.2", "0.2", "0.6", "--distance", "0.3", "--out", str(out)]) == 0
    rows = list(csv.DictReader(open(out / "wheel_test.csv", newline="")))
    assert tuple(rows[0]) == COLUMNS == ("slip", "drawbar_pull_N", "load_N", "sinkage_m", "torque_Nm")
    assert [float(r["slip"]) for r in rows] == [-0.2, 0.2, 0.6]
    dpw = [float(r["drawbar_pull_N"]) / float(r["load_N"]) for r in rows]
    assert dpw[0] < 0.0 < dpw[1] < dpw[2]
    assert (out / "wheel_test.png").stat().st_size > 10_000
    # a second run refuses to replace the first's results
    assert main([*args, "--slips", "0.2", "--out", str(out)]) == 2
    assert "earlier run" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (["--load", "0"], "load"),
        (["--load", "-10"], "load"),
        (["--slips", "1.5"], "slip"),
        (["--slips", "-1.01"], "slip"),
        (["--soil", "quicksand"], "choose one of"),
    ],
)
def test_wheel_test_command_refuses_impossible_runs(tmp_path, capsys, change, message):
    args = {"--soil": "toyoura", "--radius": "0.09", "--width": "0.11", "--load": "60", "--slips": "0.2"}
    args.update(dict(zip(change[::2], change[1::2], strict=True)))
    flat = [x for kv in args.items() for x in kv]
    assert main(["wheel-test", *flat, "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o" / "wheel_test.csv").exists()


def test_run_wheel_test_refuses_a_slip_outside_its_range():
    with pytest.raises(ConfigError, match="slip"):
        run_wheel_test(load_soil("toyoura"), WHEEL, LOAD, [0.2, -1.2])

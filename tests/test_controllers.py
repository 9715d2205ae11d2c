"""Controllers in closed loop: path following on a line and a circle, traction control on sand."""

import math
from dataclasses import replace

import gymnasium as gym
import numpy as np
import pytest
from conftest import flat_scenario

from controllers import Controller, PathFollower, PathFollowerConfig, SlipAwareController, TractionConfig
from rover_env.config.io import ConfigError
from rover_env.config.scenario import CourseConfig, StartConfig
from rover_env.envs import OBS_FIELDS


def drive(env, ctrl, seconds, seed=0):
    """Run ``ctrl`` for ``seconds``; per-step ground truth (pose xy, v_x, slip) and the energy [J]."""
    obs, info = env.reset(seed=seed)
    ctrl.reset()
    xy, vx, slip, energy = [], [], [], 0.0
    for _ in range(int(round(seconds * env.unwrapped.control_hz))):
        obs, _, term, trunc, info = env.step(ctrl.act(obs))
        gt = info["ground_truth"]
        xy.append(gt["pose"][:2])
        vx.append(gt["twist"][0])
        slip.append(gt["slip_ratio"])
        energy += info["wheel_power"] * env.unwrapped.control_dt
        if term or trunc:
            break
    return np.array(xy), np.array(vx), np.array(slip), energy, info


def test_controllers_satisfy_the_protocol_and_check_their_inputs():
    assert isinstance(PathFollower(OBS_FIELDS), Controller)
    assert isinstance(SlipAwareController(OBS_FIELDS), Controller)
    with pytest.raises(ValueError, match="cross_track"):
        PathFollower(("v_x", "heading_error"))
    with pytest.raises(ConfigError, match="bandwidth"):
        PathFollowerConfig(bandwidth=0.0)
    with pytest.raises(ConfigError, match="slip_setpoint"):
        TractionConfig(slip_setpoint=1.0)
    env = gym.make("Rover-v0", scenario=flat_scenario(), obs_source="ground_truth")
    try:
        with pytest.raises(ValueError, match="action_mode='wheels'"):
            SlipAwareController.for_env(env)
    finally:
        env.close()


def test_path_follower_converges_on_a_straight_line():
    # start 20 degrees off the line; it runs along the x axis
    sc = replace(flat_scenario(), start=StartConfig(yaw_deg=20.0), duration=30.0)
    env = gym.make("Rover-v0", scenario=sc, obs_source="ground_truth")
    try:
        xy, _, _, _, info = drive(env, PathFollower.for_env(env), 30.0)
    finally:
        env.close()
    assert info["is_success"]
    assert np.abs(xy[:, 1]).max() > 0.08  # it did start off the line
    settled = np.abs(xy[xy[:, 0] > 8.0, 1])
    assert settled.max() < 0.05, settled.max()  # steady-state cross-track [m]


@pytest.mark.parametrize("speed", [0.5, 1.0])
def test_path_follower_converges_on_a_circle(speed):
    # a 4 m circle about (0, 4) as a dense polyline, 1.25 turns, entered 15 cm and 5 degrees off
    radius = 4.0
    a = np.linspace(0.15, 2.5 * math.pi, 160)
    wps = tuple((float(radius * math.sin(t)), float(radius * (1 - math.cos(t)))) for t in a)
    sc = replace(
        flat_scenario(),
        course=CourseConfig(waypoints=wps, tolerance=0.3, speed=speed),
        start=StartConfig(position=(0.0, 0.15), yaw_deg=5.0),
        duration=80.0,
    )
    env = gym.make("Rover-v0", scenario=sc, obs_source="ground_truth")
    try:
        xy, _, _, _, info = drive(env, PathFollower.for_env(env), 80.0)
    finally:
        env.close()
    assert info["is_success"]
    err = np.hypot(xy[:, 0], xy[:, 1] - radius) - radius
    turn = np.unwrap(np.arctan2(xy[:, 0], radius - xy[:, 1]))
    settled = np.abs(err[turn > 1.25 * math.pi])  # the last turn
    assert len(settled) > 100
    print(f"circle at {speed} m/s: last turn within {100 * settled.max():.1f} cm of the circle")
    assert settled.max() < 0.05, settled.max()  # steady-state cross-track [m]


def slope_on_sand(mu=0.15, slope_deg=8.0):
    """Climbing a straight course at 1.2 m/s up an 8 degree slope of mu 0.15 (tan 8 deg = 0.14)."""
    sc = flat_scenario(mu=mu)
    return replace(
        sc,
        terrain=replace(sc.terrain, slope_deg=slope_deg),
        course=CourseConfig(waypoints=((12.0, 0.0),), speed=1.2),
        duration=25.0,
    )


def accelerating(vx, lo=0.3, hi=0.7):
    """Steps while the rover climbs from lo to hi m/s (slip is resolvable and the wheels push)."""
    return (vx > lo) & (vx < hi)


SETPOINT = 0.15


def unaware_and_aware(env_id, seconds, **make):
    """``drive`` of the slip-unaware follower (drive mode) and of traction control (wheels mode)."""
    runs = {}
    for name, mode in (("unaware", "drive"), ("aware", "wheels")):
        env = gym.make(env_id, action_mode=mode, **make)
        try:
            ctrl = (
                SlipAwareController.for_env(env, TractionConfig(slip_setpoint=SETPOINT))
                if name == "aware"
                else PathFollower.for_env(env)
            )
            runs[name] = drive(env, ctrl, seconds)
        finally:
            env.close()
    return runs


def test_traction_control_starts_within_min_slip_speed_until_the_first_trusted_estimate():
    # an episode starts at rest: before the odometry has a frame pair the wheels may not spin up
    # (on loose soil a spinning start digs in and the rover slides off), afterwards a poor
    # estimate leaves the nominal commands (the follower slows the rover instead)
    ctrl = SlipAwareController()
    c = ctrl.cfg
    fields = list(OBS_FIELDS)
    obs = np.zeros(len(fields))
    nominal = ctrl.geometry.wheel_speeds(1.0, 0.1, -0.1)
    for _ in range(3):
        cmd = ctrl.limit(obs, 1.0, 0.1, -0.1)
        assert np.all(cmd > 0) and np.all(cmd <= c.min_slip_speed + 1e-12)
    obs[fields.index("odometry_quality")] = 1.0
    obs[fields.index("v_x")] = 0.5
    cmd = ctrl.limit(obs, 1.0, 0.1, -0.1)
    assert np.all(cmd <= 0.5 * 1.05 / (1 - c.slip_setpoint)) and np.all(cmd > 0.5)
    obs[fields.index("odometry_quality")] = 0.0
    np.testing.assert_allclose(ctrl.limit(obs, 1.0, 0.1, -0.1), nominal)
    ctrl.reset()
    assert np.all(ctrl.limit(obs, 1.0, 0.1, -0.1) <= c.min_slip_speed + 1e-12)


def test_traction_control_holds_the_slip_set_point_where_the_slip_unaware_follower_spins():
    runs = unaware_and_aware("Rover-v0", 25.0, scenario=slope_on_sand(), obs_source="ground_truth")
    _, vx_u, slip_u, energy_u, _ = runs["unaware"]
    xy_a, vx_a, slip_a, energy_a, info_a = runs["aware"]
    s_u, s_a = slip_u[accelerating(vx_u)], slip_a[accelerating(vx_a)]
    assert len(s_u) > 100 and len(s_a) > 100
    print(
        f"true slip while climbing: slip-unaware median {np.median(s_u):.2f}, {energy_u:.0f} J; traction "
        f"control median {np.median(s_a):.3f}, 95th percentile {np.percentile(s_a, 95):.3f}, {energy_a:.0f} J"
    )
    assert np.median(s_u) > 0.5  # the commanded speed spins the wheels on sand
    assert abs(np.median(s_a) - SETPOINT) < 0.03
    assert np.percentile(s_a, 95) < SETPOINT + 0.03
    # the same climb: Coulomb friction gives the same force at any slip, for less work
    assert info_a["is_success"]
    assert len(vx_a) <= 1.05 * len(vx_u)
    assert energy_a < 0.9 * energy_u


def test_traction_control_on_the_estimated_slip():
    # the same climb with the estimator in the loop: the estimates drive the bounds
    runs = unaware_and_aware("Rover-v0", 25.0, scenario=slope_on_sand(), obs_source="estimated")
    slips = {name: r[2][accelerating(r[1])] for name, r in runs.items()}
    s = slips["aware"]
    p90 = np.percentile(s, 90)
    print(f"traction control on the estimated slip: median {np.median(s):.2f}, 90th percentile {p90:.2f}")
    assert np.median(slips["unaware"]) > 0.5
    assert np.median(slips["aware"]) < SETPOINT + 0.1
    assert np.percentile(slips["aware"], 90) < 0.4


def test_on_a_loose_slope_traction_control_climbs_where_the_slip_unaware_follower_slides_off():
    # RoverSlopeLoose-v0: from rest up 10 degrees of loose sand (mu 0.35, 0.105 once dug in)
    out = unaware_and_aware("RoverSlopeLoose-v0", 60.0, obs_source="ground_truth")
    xy, _, _, _, info = out["unaware"]
    assert info["termination"] == "left_terrain" and xy[-1, 0] < -15.0  # slid down the slope
    xy, _, slip, _, info = out["aware"]
    assert info["is_success"]
    assert np.abs(slip[30:]).max() < 0.3  # never dug in

"""The closed loop is honest: the physics does not depend on what observes it, and the estimated
observation is a function of perception, the on-board tracker and the previous action alone."""

import math
import subprocess
import sys

import numpy as np
import pytest

import rover_env
from perception import observation as obs_table
from rover_env.config.io import ConfigError
from rover_env.config.scenario import load_scenario
from rover_env.envs import RoverEnv
from rover_env.envs.rover_env import task_values
from rover_env.sim.simulation import RoverSim
from rover_env.task.course import WaypointCourse

SCENARIOS = ("flat_patches", "rough_slippery", "slope_loose")
GT_KEYS = ("pose", "twist", "wheel_rate", "wheel_angle", "slip_ratio", "axle_roll", "axle_height", "steering")


def _wheels_action(k: int) -> np.ndarray:
    """Varied wheel commands: speed, differential and steering all change over time."""
    base = 0.55 + 0.35 * math.sin(k / 17.0)
    diff = 0.25 * math.sin(k / 7.0)
    return np.array(
        [
            base - diff,
            base + diff,
            base - 0.5 * diff,
            base + 0.5 * diff,
            0.6 * math.sin(k / 11.0),
            -0.4 * math.sin(k / 13.0),
        ],
        dtype=np.float32,
    )


def _rollout(scenario: str, obs_source: str, steps: int, preset: str = "train", seed: int = 5) -> np.ndarray:
    env = RoverEnv(scenario=scenario, obs_source=obs_source, preset=preset, action_mode="wheels")
    try:
        _, info = env.reset(seed=seed)
        rows = [np.concatenate([info["ground_truth"][k] for k in GT_KEYS])]
        for k in range(steps):
            _, _, term, trunc, info = env.step(_wheels_action(k))
            rows.append(np.concatenate([info["ground_truth"][k] for k in GT_KEYS]))
            if term or trunc:
                break
        return np.array(rows)
    finally:
        env.close()


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_the_true_trajectory_is_bit_identical_with_ground_truth_and_estimated_observations(scenario):
    """5 s of varied wheel and steering commands: the same physics whatever observes it."""
    truth = _rollout(scenario, "ground_truth", 150)
    estimated = _rollout(scenario, "estimated", 150)
    assert len(truth) == len(estimated) == 151
    # the rover did move and slip: a trajectory worth comparing
    assert np.hypot(*(truth[-1, :2] - truth[0, :2])) > 1.0
    np.testing.assert_array_equal(truth, estimated)


@pytest.mark.parametrize(
    "scenario", [pytest.param(s, marks=pytest.mark.slow) if s != "slope_loose" else s for s in SCENARIOS]
)
def test_the_eval_preset_drives_the_same_physics(scenario):
    """The papers' 640x480 cameras in the loop change nothing in the physics (1 s)."""
    np.testing.assert_array_equal(
        _rollout(scenario, "ground_truth", 30), _rollout(scenario, "estimated", 30, "eval")
    )


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_the_trajectory_does_not_depend_on_how_the_simulation_is_stepped(scenario):
    """1/30 s calls, 1/60 s calls and 1/240 s calls give the same trajectory to the last bit."""
    sc = load_scenario(scenario)
    out = []
    for chunks in (1, 2, 8):
        sim = RoverSim(sc)
        try:
            sim.reset(*sc.start.position, sc.start.yaw)
            rows = []
            g = sim.geometry
            for k in range(150):
                a = _wheels_action(k).astype(np.float64)
                sim.rover.command(a[:4] * 1.5 / g.wheel_radius, a[4] * g.steer_limit, a[5] * g.steer_limit)
                for _ in range(chunks):
                    sim.step(1.0 / 30.0 / chunks)
                gt = sim.ground_truth()
                rows.append(np.concatenate([getattr(gt, k) for k in GT_KEYS] + [[gt.t]]))
            out.append(np.array(rows))
        finally:
            sim.close()
    assert out[0][-1, -1] == pytest.approx(5.0)
    np.testing.assert_array_equal(out[0], out[1])
    np.testing.assert_array_equal(out[0], out[2])


def _short_course(tmp_path, fix_std=(0.05, 1.0), name="short") -> str:
    path = tmp_path / f"{name}.yaml"
    path.write_text(
        f"name: {name}\n"
        "course: {waypoints: [[1.6, 0.0], [2.6, 1.0], [3.6, 1.0]], tolerance: 0.5, speed: 0.8}\n"
        "terrain: {kind: flat, size: [14.0, 14.0], texture: gravel, texture_px: 128}\n"
        "friction: {patches: [{center: [1.5, 0.0], size: [1.0, 2.0], mu: 0.15}]}\n"
        f"start: {{jitter_position: 0.2, jitter_yaw_deg: 5.0, fix_std: [{fix_std[0]}, {fix_std[1]}]}}\n"
        "duration: 14.0\n"
    )
    return str(path)


def _check_no_truth(env, controller, seed: int, steps: int) -> tuple[int, int]:
    """Drive ``steps`` and rebuild every observation from info["estimate"], an own tracker fed
    with the estimated pose, and the previous action; returns the observations rebuilt and the
    waypoints the tracker passed."""
    obs, info = env.reset(seed=seed)
    controller.reset()
    tracker = WaypointCourse(env.scenario.course)
    tracker.reset(info["start_fix"][:2])
    fields = env.obs_fields
    prev = np.zeros(env.action_space.shape, dtype=np.float32)

    def rebuild(info):
        est = info["estimate"]
        x, y, yaw = est["odometry_pose"]
        tracker.update(np.array([x, y]))
        assert tracker.index == info["waypoint_index"]
        values = obs_table.state_values(
            est, est["quality"], task_values(tracker.features(np.array([x, y]), yaw))
        )
        return obs_table.assemble(fields, values, prev)

    np.testing.assert_array_equal(obs, rebuild(info))
    rebuilt = 1
    for _ in range(steps):
        action = np.clip(np.asarray(controller.act(obs), dtype=np.float32), -1, 1)
        obs, _, term, trunc, info = env.step(action)
        prev = action
        np.testing.assert_array_equal(obs, rebuild(info))
        rebuilt += 1
        if term or trunc:
            break
    return rebuilt, tracker.index


@pytest.mark.parametrize("env_id", rover_env.ENV_IDS)
def test_the_estimated_observation_holds_no_truth(env_id):
    """On every registered mission: each observation is rebuilt exactly without the simulator."""
    import gymnasium as gym

    from controllers import PathFollower

    env = gym.make(env_id).unwrapped
    try:
        rebuilt, _ = _check_no_truth(env, PathFollower.for_env(env), seed=1, steps=60)
        assert rebuilt == 61  # the reset's observation and 60 steps' (no mission ends within 2 s)
    finally:
        env.close()


def test_with_an_imu_the_observation_holds_no_truth_and_its_tilt_is_the_imus():
    """On the loose slope with a BMI088: rebuilt from info["estimate"] alone, and the observed roll
    and pitch are the attitude filter's, off the truth by what the accelerometer's bias makes."""
    import gymnasium as gym

    from controllers import PathFollower

    env = gym.make("RoverSlopeLoose-v0", imu="bmi088").unwrapped
    try:
        rebuilt, _ = _check_no_truth(env, PathFollower.for_env(env), seed=1, steps=60)
        assert rebuilt == 61
        est = env.pipeline.estimate()
        truth = env.sim.ground_truth().tilt
        print(f"tilt: estimated {np.degrees(est.values['tilt'])}, true {np.degrees(truth)} deg")
        assert est.attitude_quality == 1.0 and abs(truth[1]) > np.radians(5.0)
        # sliding down at ~0.7 m/s^2: without the velocity's rate taken out, the pitch would be
        # 4 deg off; what is left is the accelerometer's turn-on bias drawn for this episode
        bias = env.pipeline.imu.noise.turn_on[3:5]  # x, y [m/s^2]
        print(f"accelerometer bias {bias} m/s^2")
        expected = np.array([bias[1], -bias[0]]) / 9.81  # roll, pitch error [rad]
        np.testing.assert_allclose(est.values["tilt"] - truth, expected, atol=np.radians(0.5))
    finally:
        env.close()


def test_the_tracker_passes_waypoints_on_the_estimate_alone(tmp_path):
    """A short course driven to its end by traction control: every waypoint switch is the tracker's."""
    from controllers import SlipAwareController

    env = RoverEnv(scenario=_short_course(tmp_path), action_mode="wheels")
    try:
        assert _check_no_truth(env, SlipAwareController.for_env(env), seed=2, steps=400)[1] == 3
    finally:
        env.close()


def test_the_start_fix_is_the_true_start_plus_seeded_noise(tmp_path):
    noisy, exact = [], []
    for fix_std, out in (((0.05, 1.0), noisy), ((0.0, 0.0), exact)):
        env = RoverEnv(scenario=_short_course(tmp_path, fix_std, name=f"s{len(out)}{fix_std[0]}"))
        try:
            for seed in range(12):
                _, info = env.reset(seed=seed)
                gt = info["ground_truth"]["pose"]
                x, y, yaw = info["estimate"]["odometry_pose"]
                true = np.array(
                    [
                        gt[0],
                        gt[1],
                        math.atan2(2 * (gt[6] * gt[5] + gt[3] * gt[4]), 1 - 2 * (gt[4] ** 2 + gt[5] ** 2)),
                    ]
                )
                np.testing.assert_array_equal(info["start_fix"], [x, y, yaw])
                out.append(np.array([x, y, yaw]) - true)
        finally:
            env.close()
    noisy, exact = np.array(noisy), np.array(exact)
    # the exact start is the settled pose's (x, y, yaw) to the settling's drift, the noisy one is not
    assert np.abs(exact[:, :2]).max() < 2e-3 and np.abs(exact[:, 2]).max() < 2e-3
    assert 0.02 < np.std(noisy[:, :2]) < 0.09 and math.radians(0.4) < np.std(noisy[:, 2]) < math.radians(1.8)
    # the same seed gives the same fix
    env = RoverEnv(scenario=_short_course(tmp_path, name="again"))
    try:
        a = env.reset(seed=4)[1]["start_fix"]
        b = env.reset(seed=4)[1]["start_fix"]
        np.testing.assert_array_equal(a, b)
    finally:
        env.close()


def test_arrival_far_from_the_truth_ends_off_target(tmp_path):
    """A 0.6 m start-fix error: the tracker reaches the goal, the judge does not count it."""
    from controllers import SlipAwareController

    env = RoverEnv(scenario=_short_course(tmp_path, fix_std=(0.6, 0.0)), action_mode="wheels")
    try:
        ctrl = SlipAwareController.for_env(env)
        for seed in range(10):
            obs, info = env.reset(seed=seed)
            if np.hypot(*(info["start_fix"][:2] - info["ground_truth"]["pose"][:2])) > 0.9:
                break
        else:
            pytest.fail("no seed gave a start fix 0.9 m off")
        ctrl.reset()
        for _ in range(600):
            obs, reward, term, trunc, info = env.step(ctrl.act(obs))
            if term or trunc:
                break
        assert term and info["termination"] == "off_target" and not info["is_success"]
        assert info["miss_distance"] > env.scenario.course.tolerance
        assert info["reward_terms"]["failure"] == -env.reward_cfg.failure
        assert info["reward_terms"]["success"] == 0.0
    finally:
        env.close()


@pytest.mark.parametrize("value, message", [("-0.1", "out of range"), (".nan", "finite")])
def test_a_bad_start_fix_std_is_a_config_error_naming_file_and_key(tmp_path, value, message):
    path = _short_course(tmp_path)
    text = open(path).read().replace("fix_std: [0.05, 1.0]", f"fix_std: [{value}, 1.0]")
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=rf"bad\.yaml.*start\.fix_std\[0\].*{message}"):
        load_scenario(bad)
    bad.write_text(text.replace(f"fix_std: [{value}, 1.0]", f"fix_std: [0.05, {value}]"))
    with pytest.raises(ConfigError, match=rf"bad\.yaml.*start\.fix_std\[1\].*{message}"):
        load_scenario(bad)


def test_layering_controllers_and_perception_import_no_simulator():
    code = (
        "import sys\n"
        "import perception, perception.observation, perception.models.drive_geometry\n"
        "sim = ('pybullet', 'gymnasium', 'rover_env', 'controllers')\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in sim]\n"
        "assert not bad, ('perception', bad)\n"
        "import controllers, controllers.path_follower, controllers.traction, controllers.pure_pursuit\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('pybullet', 'rover_env')]\n"
        "assert not bad, ('controllers', bad)\n"
        "import controllers.rl\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('pybullet', 'rover_env')]\n"
        "assert not bad, ('controllers.rl', bad)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


def test_bench_physics_row_is_a_ground_truth_environment_ten_times_faster_than_the_estimated_one():
    """``rover bench``'s physics-only row: no camera attached, and >= 10x the estimated steps/s."""
    import cv2

    from rover_env.tools.bench import bench_env, bench_physics

    cv2.setNumThreads(1)
    physics = bench_physics("flat_patches", steps=150)
    estimated = bench_env("flat_patches", "estimated", "train", steps=45)
    assert physics.steps_per_s > 10.0 * estimated.steps_per_s, (physics.steps_per_s, estimated.steps_per_s)


def test_docs_observation_table_matches_the_declared_table():
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "observation.md").read_text()
    for mode in ("drive", "wheels"):
        assert obs_table.markdown_table(obs_table.observation_fields(mode)) in text

"""A user's estimator in the loop: gym.make(..., estimator=FACTORY) with any object of the interface."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import rover_env  # noqa: F401
from perception.estimator import EstimatorError
from perception.observation import OBS_FIELDS, field_index

ACTIONS = [np.array([0.6, 0.2 * math.sin(k / 5), -0.1], dtype=np.float32) for k in range(30)]


class Scripted:
    """Returns a few fields, a pose that walks 1 cm a step, and records every message it gets."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self.seen: list[tuple[str, float]] = []
        self.resets = 0

    def reset(self, start_fix) -> None:
        self.pose = np.array(start_fix, dtype=np.float64)
        self.resets += 1

    def update(self, messages, t):
        self.seen += [(m.sensor, m.t) for m in messages]
        self.pose = self.pose + [0.01, 0.0, 0.0]
        return {"pose": self.pose.copy(), "v_x": 0.5, "slip_FL": 0.25, "odometry_quality": 0.7}


class FailsAt:
    """A faulty estimator: at update number ``n`` (after a reset) it returns ``bad`` or raises."""

    def __init__(self, rig, n=2, bad=None) -> None:
        self.n, self.bad = n, bad

    def reset(self, start_fix) -> None:
        self.k = 0
        self.pose = np.array(start_fix, dtype=np.float64)

    def update(self, messages, t):
        self.k += 1
        if self.k == self.n:
            if self.bad is None:
                raise ZeroDivisionError("a bug in the user's code")
            return self.bad
        return {"pose": self.pose}


def test_the_observation_is_what_the_estimator_returned_and_the_tracker_follows_its_pose():
    env = gym.make("Rover-v0", estimator=Scripted, imu="bmi088", renderer="tiny")
    try:
        obs, _ = env.reset(seed=3)
        u = env.unwrapped
        est = u.pipeline.estimator
        for a in ACTIONS:
            obs, _, _, _, info = env.step(a)
        names = u.obs_fields
        assert obs[field_index(names, "v_x")] == pytest.approx(0.5)
        assert obs[field_index(names, "slip_FL")] == pytest.approx(0.25)
        assert obs[field_index(names, "odometry_quality")] == pytest.approx(0.7)
        for unknown in ("axle_roll_F", "kinematics_quality", "attitude_quality", "omega"):
            assert obs[field_index(names, unknown)] == 0.0  # not returned: unknown, 0
        # the tracker's features come from the pose it returned
        feats = u.course.features(est.pose[:2], est.pose[2])
        assert obs[field_index(names, "waypoint_distance")] == pytest.approx(feats.distance, abs=1e-5)
        assert obs[field_index(names, "cross_track")] == pytest.approx(feats.cross_track, abs=1e-5)
        np.testing.assert_allclose(info["estimate"]["odometry_pose"], est.pose)
        assert math.isnan(info["estimate"]["axle_roll"][0]) and info["estimate"]["twist"][0] == 0.5
        # every sensor's messages reach it, at the rig's rates: 1 s of 30 Hz cameras, a 240 Hz IMU
        rig = u.rig
        assert set(rig) == {"fisheye", "downward", "imu", "sun"} and rig["imu"].rate_hz == 240.0
        after = [(s, t) for s, t in est.seen if t > 1e-9]
        counts = {name: sum(s == name for s, _ in after) for name in rig}
        assert counts == {"fisheye": 30, "downward": 30, "imu": 240, "sun": 5}
        for name in rig:
            ts = np.array([t for s, t in est.seen if s == name])
            np.testing.assert_allclose(np.diff(ts[ts > 1e-9]), rig[name].period, atol=1e-9)
    finally:
        env.close()


def test_the_true_trajectory_is_the_same_whatever_estimates():
    def truth(**kw):
        env = gym.make("RoverShadows-v0", renderer="tiny", **kw)
        try:
            env.reset(seed=5)
            poses = [env.step(a)[4]["ground_truth"]["pose"] for a in ACTIONS[:20]]
        finally:
            env.close()
        return np.array(poses)

    np.testing.assert_array_equal(truth(), truth(estimator=Scripted))


def test_builtin_estimator_is_the_default_unchanged_and_its_changes_take_effect():
    from perception.fusion.slip import SlipConfig
    from rover_env.sensors.rig import builtin_estimator

    def observations(**kw):
        env = gym.make("RoverRoughSlippery-v0", renderer="tiny", **kw)
        try:
            env.reset(seed=3)
            return np.array([env.step(a)[0] for a in ACTIONS[:20]])
        finally:
            env.close()

    default = observations()
    np.testing.assert_array_equal(default, observations(estimator=builtin_estimator("train")))
    # without the gripping wheels' zero-slip prior the slip estimates differ
    slips = [field_index(OBS_FIELDS, f"slip_{w}") for w in ("FL", "FR", "RL", "RR")]
    other = observations(estimator=builtin_estimator("train", slip=SlipConfig(grip_std=0.0)))
    assert np.abs(other[:, slips] - default[:, slips]).max() > 1e-3
    with pytest.raises(rover_env.ConfigError, match="preset"):
        builtin_estimator("fast")
    # the odometry's ground in view keeps the wheels' plane's height at the front axle
    env = gym.make("Rover-v0", renderer="tiny")
    try:
        env.reset(seed=0)
        geom = env.unwrapped.geometry
        anchor = env.unwrapped.pipeline.estimator.odometry.config.plane_anchor
        np.testing.assert_allclose(anchor, (geom.wheelbase / 2, 0.0), atol=1e-9)
    finally:
        env.close()


@pytest.mark.parametrize(
    ("bad", "names"),
    [
        ({"pose": [0.0, 0.0, 0.0], "speed": 1.0}, ["unknown key 'speed'", "step 2"]),
        ({"pose": [0.0, 0.0, 0.0], "v_x": math.nan}, ["'v_x' is nan", "step 2"]),
        ({"pose": [0.0, 0.0]}, ["'pose'", "three finite numbers", "step 2"]),
        ([1, 2, 3], ["not a mapping", "step 2"]),
        (None, ["ZeroDivisionError", "a bug in the user's code", "step 2"]),
    ],
)
def test_a_faulty_estimator_is_named_with_the_key_and_step_and_reset_recovers(bad, names):
    def factory(rig):
        return FailsAt(rig, n=3, bad=bad)  # update 1 is the reset's, 2 and 3 are steps 1 and 2

    env = gym.make("Rover-v0", estimator=factory, renderer="tiny")
    try:
        env.reset(seed=0)
        env.step(ACTIONS[0])
        with pytest.raises(EstimatorError) as exc:
            env.step(ACTIONS[1])
        msg = str(exc.value)
        assert "test_own_estimator.FailsAt" in msg and all(n in msg for n in names), msg
        env.reset(seed=1)  # usable again
        obs, *_ = env.step(ACTIONS[0])
        assert np.all(np.isfinite(obs))
    finally:
        env.close()


def test_an_estimator_without_the_interface_is_refused():
    class NoUpdate:
        def __init__(self, rig):
            pass

        def reset(self, start_fix):
            pass

    with pytest.raises(TypeError, match="has no update"):
        gym.make("Rover-v0", estimator=NoUpdate, renderer="tiny")
    with pytest.raises(ValueError, match="obs_source='estimated'"):
        gym.make("Rover-v0", estimator=Scripted, obs_source="ground_truth")


def test_a_user_estimator_runs_in_vector_environments():
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import SubprocVecEnv

    venv = gym.make_vec(
        "Rover-v0", num_envs=2, vectorization_mode="async", estimator=Scripted, renderer="tiny"
    )
    try:
        obs, _ = venv.reset(seed=0)
        for a in ACTIONS[:3]:
            obs, *_ = venv.step(np.stack([a, a]))
        assert obs.shape[0] == 2 and np.allclose(obs[:, 0], 0.5)  # v_x is the first field
    finally:
        venv.close()
    sb3 = make_vec_env(
        "Rover-v0",
        n_envs=2,
        vec_env_cls=SubprocVecEnv,
        env_kwargs={"estimator": Scripted, "renderer": "tiny"},
    )
    try:
        sb3.seed(0)
        sb3.reset()
        obs, *_ = sb3.step(np.stack([ACTIONS[0], ACTIONS[0]]))
        assert np.allclose(obs[:, 0], 0.5)
    finally:
        sb3.close()


def test_the_example_estimator_drives_a_mission_and_rover_eval_takes_it(
    tiny_scenario, tmp_path, capsys, monkeypatch
):
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(root)  # `examples.own_estimator` resolves from the project's root, as for a user
    sys.path.insert(0, str(root))
    try:
        from examples.own_estimator import run
    finally:
        sys.path.remove(str(root))
    res = run(steps=60)
    assert res["mae_v_x"] < 0.05 and res["final_position_error"] < 0.1, res
    from rover_env.tools.cli import main

    out = tmp_path / "eval"
    argv = [
        "eval",
        "--controllers",
        "pure_pursuit",
        "--missions",
        tiny_scenario,
        "--seeds",
        "0",
        "--workers",
        "1",
    ]
    argv += ["--estimator", "examples.own_estimator:LucasKanadeEstimator", "--out", str(out)]
    assert main(argv) == 0
    report = (out / "report.md").read_text()
    assert (
        "Estimator on the estimated-observation runs: examples.own_estimator:LucasKanadeEstimator" in report
    )
    assert (
        "| pure_pursuit | examples.own_estimator:LucasKanadeEstimator | 1 | 1 |" in report
    )  # it reached the goal
    bad = ["eval", "--missions", tiny_scenario, "--seeds", "0", "--out", str(tmp_path / "x")]
    assert main([*bad, "--estimator", "examples.own_estimator:Nope"]) == 2
    assert "has no callable 'Nope'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()

"""Reinforcement learning: the residual wrapper, the mission cycle, training and the policy loader."""

import json

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from controllers import PathFollower  # noqa: E402
from controllers.rl import MissionCycle, PolicyController, ResidualDrive, TrainConfig, make_env, train  # noqa: E402
from rover_env.evaluation import EvalJob, run_sweep  # noqa: E402


def test_residual_drive_adds_the_scaled_residual_to_the_follower():
    env = ResidualDrive(gym.make("Rover-v0", obs_source="ground_truth"), scale=(0.5, 0.3, 0.3))
    follower = PathFollower.for_env(env)
    try:
        obs, _ = env.reset(seed=0)
        base = follower.act(obs)
        np.testing.assert_allclose(env.residual.compose(obs, np.zeros(3)), base, atol=1e-7)
        np.testing.assert_allclose(
            env.residual.compose(obs, np.array([-0.2, 1.0, -1.0])),
            np.clip(base + np.array([-0.1, 0.3, -0.3]), -1, 1),
            atol=1e-6,
        )
        assert np.all(np.abs(env.residual.compose(obs, np.full(3, 10.0))) <= 1.0)  # clipped
        _, _, _, _, info = env.step(np.zeros(3, np.float32))
        assert "ground_truth" in info
    finally:
        env.close()
    with pytest.raises(ValueError, match="action_mode='drive'"):
        ResidualDrive(gym.make("Rover-v0", obs_source="ground_truth", action_mode="wheels"))


def test_mission_cycle_runs_each_mission_in_turn():
    env = make_env(["Rover-v0", "RoverSlopeLoose-v0"], obs_source="ground_truth")
    try:
        names = []
        for _ in range(3):
            env.reset(seed=0)
            cycle = env.unwrapped
            assert isinstance(cycle, MissionCycle)
            names.append(cycle.current.unwrapped.scenario.name)
            _, _, _, _, info = env.step(np.zeros(3, np.float32))
        assert names == ["flat_patches", "slope_loose", "flat_patches"]
    finally:
        env.close()


def test_train_writes_a_policy_that_the_loader_and_rover_eval_drive(tmp_path, tiny_scenario):
    cfg = TrainConfig(
        missions=(tiny_scenario,),
        total_steps=256,
        n_envs=1,
        obs_source="ground_truth",
        eval_every=10**9,
        checkpoint_every=10**9,
        hyper=dict(n_steps=128, batch_size=64, n_epochs=1),
    )
    out = train(cfg, tmp_path / "run")
    meta = json.loads((out / "policy.json").read_text())
    assert meta["algo"] == "ppo" and meta["residual"] == [0.5, 0.3, 0.3]
    assert (out / "tb").is_dir()
    env = gym.make("Rover-v0", scenario=tiny_scenario, obs_source="ground_truth")
    try:
        ctrl = PolicyController(out, env)
        obs, _ = env.reset(seed=0)
        ctrl.reset()
        a = ctrl.act(obs)
        assert a.shape == (3,) and a.dtype == np.float32 and np.all(np.abs(a) <= 1)
    finally:
        env.close()
    # barely trained: the residual is near zero, so the policy follows the course like its follower
    (row,) = run_sweep([EvalJob(f"policy:{out}@ground_truth", tiny_scenario, 0)], workers=1)
    assert row["success"]
    with pytest.raises(FileNotFoundError, match="policy.zip"):
        PolicyController(tmp_path, env)
    wheels = gym.make("Rover-v0", scenario=tiny_scenario, obs_source="ground_truth", action_mode="wheels")
    with pytest.raises(ValueError, match="action_mode"):
        PolicyController(out, wheels)
    wheels.close()


def test_the_shipped_policy_loads_and_drives():
    from controllers.rl import shipped_policy

    env = gym.make("Rover-v0", obs_source="ground_truth")
    try:
        ctrl = PolicyController(shipped_policy(), env)
        assert ctrl.meta["reward"] == {"slip_speed": 5.0} and ctrl.residual is not None
        obs, _ = env.reset(seed=0)
        ctrl.reset()
        for _ in range(60):  # two seconds: it drives off along the course
            obs, _, _, _, info = env.step(ctrl.act(obs))
        assert info["progress"] > 1.0
    finally:
        env.close()

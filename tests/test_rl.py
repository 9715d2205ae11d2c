"""Reinforcement learning: the residual wrapper, the mission cycle, training and the policy loader."""

import copy
import json
import logging
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from controllers import PathFollower, SlipAwareController  # noqa: E402
from controllers.rl import PolicyController, policy_action_mode  # noqa: E402
from rover_env.tools.evaluation import EvalJob, run_sweep  # noqa: E402
from rover_env.tools.training import (  # noqa: E402
    EpisodeSeeds,
    MissionCycle,
    ResidualDrive,
    TrainConfig,
    make_env,
    train,
)

DATA = Path(__file__).parent / "data"


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
        # the policy can slow the rover to the follower's lowest speed, not stop or reverse it
        f = follower.cfg
        assert env.residual.compose(obs, np.array([-1.0, 0.0, 0.0]))[0] == pytest.approx(
            f.min_speed / f.v_max
        )
        _, _, _, _, info = env.step(np.zeros(3, np.float32))
        assert "ground_truth" in info
    finally:
        env.close()


def test_traction_residual_is_the_slip_aware_controller_plus_a_drive_change_within_the_slip_bounds():
    """Wheels mode: a zero residual drives exactly like SlipAwareController. A policy that always
    asks for more speed (residual +1) spins the wheels on the loose slope through the path
    follower alone, but not through the traction base."""
    env = ResidualDrive(gym.make("RoverSlopeLoose-v0", obs_source="ground_truth", action_mode="wheels"))
    ref = SlipAwareController.for_env(env)
    try:
        assert env.action_space.shape == (3,)
        obs, _ = env.reset(seed=0)
        ref.reset()
        for _ in range(90):
            # a copy: compose advances the base controller, and step composes again
            action = copy.deepcopy(env.residual).compose(obs, np.zeros(3))
            np.testing.assert_allclose(action, ref.act(obs), atol=1e-6)
            obs, *_ = env.step(np.zeros(3, np.float32))
    finally:
        env.close()
    median_slip, progress = {}, {}
    for mode in ("drive", "wheels"):
        env = ResidualDrive(gym.make("RoverSlopeLoose-v0", obs_source="ground_truth", action_mode=mode))
        try:
            env.reset(seed=0)
            slips = []
            for _ in range(240):  # 8 s, speed residual +1 (the follower's 0.8 m/s + 1 m/s)
                _, _, term, _, info = env.step(np.array([1.0, 0.0, 0.0], np.float32))
                slips.append(np.abs(info["ground_truth"]["slip_ratio"]).mean())
                if term:
                    break
            median_slip[mode] = float(np.median(slips))
            progress[mode] = float(info["progress"])
        finally:
            env.close()
    print(f"median slip with +1 m/s asked for on the loose slope: {median_slip}")
    assert median_slip["drive"] > 0.5, median_slip
    assert median_slip["wheels"] < 0.1, median_slip
    assert progress["wheels"] > 5.0 > progress["drive"], progress  # and it climbs


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


def test_episode_seeds_give_every_episode_a_known_seed_and_world():
    env = make_env("Rover-v0", obs_source="ground_truth", randomize="on", episode_seeds=(5, 3))
    plain = gym.make("Rover-v0", obs_source="ground_truth", randomize="on")
    try:
        worlds = [env.reset(seed=123)[1]["world"] for _ in range(2)]  # the given seed is overridden
        assert worlds[0] != worlds[1]
        for seed, world in zip((5, 8), worlds, strict=True):
            assert plain.reset(seed=seed)[1]["world"] == world
        assert isinstance(env.env, EpisodeSeeds) and env.env.episodes == 2
    finally:
        env.close()
        plain.close()

    class Two(gym.Env):  # ends after two steps
        observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
        action_space = gym.spaces.Box(-1.0, 1.0, (1,))

        def reset(self, *, seed=None, options=None):
            self.k, self.seed_given = 0, seed
            return np.zeros(1, np.float32), {}

        def step(self, action):
            self.k += 1
            return np.zeros(1, np.float32), 0.0, self.k == 2, False, {}

    wrapped = EpisodeSeeds(Two(), first=7, stride=2)
    for seed in (7, 9):
        wrapped.reset()
        assert wrapped.unwrapped.seed_given == seed
        assert "episode_seed" not in wrapped.step(np.zeros(1))[4]
        assert wrapped.step(np.zeros(1))[4]["episode_seed"]["seed"] == seed
    with pytest.raises(ValueError, match="stride"):
        EpisodeSeeds(Two(), first=0, stride=0)
    with pytest.raises(ValueError, match="episode_seeds"):
        TrainConfig(episode_seeds=-1)


def test_train_writes_a_policy_that_the_loader_and_rover_eval_drive(tmp_path, tiny_scenario, caplog):
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
    assert meta["base"] == "traction" and policy_action_mode(out) == "wheels"
    assert (out / "tb").is_dir()
    # episodes.csv: every finished episode's mission and seed, from episode_seeds on
    rows = (out / "episodes.csv").read_text().splitlines()
    assert rows[0].startswith("step,mission,seed,success")
    assert [int(r.split(",")[2]) for r in rows[1:]] == list(range(10_000, 10_000 + len(rows) - 1))
    env = gym.make("Rover-v0", scenario=tiny_scenario, obs_source="ground_truth", action_mode="wheels")
    try:
        ctrl = PolicyController(out, env)
        obs, _ = env.reset(seed=0)
        ctrl.reset()
        a = ctrl.act(obs)
        assert a.shape == (6,) and a.dtype == np.float32 and np.all(np.abs(a) <= 1)
        # a fresh folder loads without unpickling: the one warning is the trust note of any outside policy
        assert [r.message for r in caplog.records if "outside the package" not in r.message] == []
        assert (out / "obs_stats.npz").is_file() and not (out / "vecnormalize.pkl").exists()
        assert meta["obs_dim"] == obs.size and meta["action_low"] == [-1.0] * 3
        caplog.clear()
        # trained on ground truth, the quality fields were always 1: an estimator's 0.5 gets a warning
        q = [f.name for f in env.unwrapped.obs_fields].index("odometry_quality")
        ctrl.act(np.where(np.arange(obs.size) == q, 0.5, obs).astype(np.float32))
        assert "odometry_quality" in caplog.text and "never saw" in caplog.text
    finally:
        env.close()
    # barely trained: the residual is near zero, so the policy follows the course like its follower
    (row,) = run_sweep([EvalJob(f"policy:{out}@ground_truth", tiny_scenario, 0)], workers=1)
    assert row["success"]
    with pytest.raises(FileNotFoundError, match="policy.zip"):
        PolicyController(tmp_path, env)
    drive = gym.make("Rover-v0", scenario=tiny_scenario, obs_source="ground_truth", action_mode="drive")
    with pytest.raises(ValueError, match="action_mode"):
        PolicyController(out, drive)
    drive.close()


def test_the_shipped_policy_loads_and_drives():
    """The shipped policy: residual over traction control, trained on estimates with field cameras,
    randomised worlds and the BMI088; it drives off along the course."""
    from controllers.rl import shipped_policy

    env = gym.make("Rover-v0", obs_source="ground_truth", action_mode=policy_action_mode(shipped_policy()))
    try:
        ctrl = PolicyController(shipped_policy(), env)
        meta = ctrl.meta
        assert meta["reward"] == {"slip_speed": 5.0} and ctrl.residual is not None
        assert meta["obs_source"] == "estimated" and meta["base"] == "traction"
        assert (meta["camera_effects"], meta["randomize"], meta["imu"]) == ("field", "on", "bmi088")
        assert meta["obs_fields"] == [f.name for f in env.unwrapped.obs_fields][: len(meta["obs_fields"])]
        obs, _ = env.reset(seed=0)
        ctrl.reset()
        for _ in range(60):  # two seconds: it drives off along the course
            obs, _, _, _, info = env.step(ctrl.act(obs))
        assert info["progress"] > 1.0
    finally:
        env.close()


def test_a_policy_trained_before_fields_were_added_reads_its_own_by_name():
    """The policy shipped before roll, pitch and attitude quality were observed
    (``tests/data/policy_before_attitude``) reads its own fields by name: a change of the roll
    it never saw leaves its action as it was."""
    folder = DATA / "policy_before_attitude"
    env = gym.make("Rover-v0", obs_source="ground_truth", action_mode=policy_action_mode(folder))
    try:
        ctrl = PolicyController(folder, env)
        names = [f.name for f in env.unwrapped.obs_fields]
        assert set(ctrl.meta["obs_fields"]) < set(names) and "roll" not in ctrl.meta["obs_fields"]
        obs, _ = env.reset(seed=0)
        ctrl.reset()
        a0 = ctrl.act(obs)
        ctrl.reset()
        tilted = np.where(np.arange(obs.size) == names.index("roll"), 0.3, obs).astype(np.float32)
        np.testing.assert_array_equal(ctrl.act(tilted), a0)
        ctrl.reset()
        for _ in range(60):
            obs, _, _, _, info = env.step(ctrl.act(obs))
        assert info["progress"] > 1.0
    finally:
        env.close()


def test_a_policy_trained_on_a_field_the_environment_lacks_is_refused(tmp_path):
    import shutil

    from controllers.rl import shipped_policy

    folder = shutil.copytree(shipped_policy(), tmp_path / "policy")
    meta = json.loads((folder / "policy.json").read_text())
    meta["obs_fields"].append("soil_moisture")
    (folder / "policy.json").write_text(json.dumps(meta))
    env = gym.make("Rover-v0", obs_source="ground_truth", action_mode="wheels")
    try:
        with pytest.raises(ValueError, match="soil_moisture.*retrain"):
            PolicyController(folder, env)
    finally:
        env.close()


def test_policy_action_mode_reads_the_policy_folder_and_names_what_is_wrong(tmp_path):
    with pytest.raises(FileNotFoundError, match="policy.json"):
        policy_action_mode(tmp_path)
    (tmp_path / "policy.json").write_text("{not json")
    with pytest.raises(ValueError, match="malformed"):
        policy_action_mode(tmp_path)
    (tmp_path / "policy.json").write_text(json.dumps({"action_mode": "torque"}))
    with pytest.raises(ValueError, match="'torque'"):
        policy_action_mode(tmp_path)
    (tmp_path / "policy.json").write_text(json.dumps({"action_mode": "wheels"}))
    assert policy_action_mode(tmp_path) == "wheels"


def test_an_unknown_residual_base_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="'torque'.*follower.*traction"):
        TrainConfig(base="torque")
    with pytest.raises(ValueError, match="'torque'"):
        make_env("Rover-v0", base="torque")


def test_training_with_an_imu_puts_one_on_the_rover_and_a_bad_preset_is_refused(tiny_scenario):
    """``rover train --imu PRESET``: every training environment has that IMU (its gyro then feeds
    the observation's yaw rate, roll and pitch); an unknown preset is named."""
    env = make_env(tiny_scenario, imu="bmi088")
    try:
        env.reset(seed=0)
        assert env.unwrapped.pipeline.imu is not None
        obs = env.step(np.zeros(env.action_space.shape, np.float32))[0]
        assert np.all(np.isfinite(obs))
    finally:
        env.close()
    env = make_env(tiny_scenario)
    try:
        assert env.unwrapped.pipeline.imu is None
    finally:
        env.close()
    with pytest.raises(ValueError, match="imu 'bmi99'"):
        TrainConfig(imu="bmi99")
    assert TrainConfig(imu="bmi088").imu == "bmi088"


def test_a_policy_trained_with_an_imu_warns_when_driven_without_one(tmp_path, tiny_scenario, caplog):
    """A policy trained on an IMU's yaw rate, roll and pitch, driven on a rover without one, is
    named with the fix (``@imu:PRESET``); with the IMU it was trained with, nothing is said."""
    import shutil

    from controllers.rl import shipped_policy

    folder = shutil.copytree(shipped_policy(), tmp_path / "policy")
    meta = json.loads((folder / "policy.json").read_text())
    meta["imu"] = "bmi088"
    (folder / "policy.json").write_text(json.dumps(meta))
    for imu, warned in ((None, True), ("bmi088", False)):
        env = make_env(tiny_scenario, imu=imu)
        try:
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="controllers.rl"):
                PolicyController(folder, env)
            said = [r.getMessage() for r in caplog.records if "trained with an IMU" in r.getMessage()]
            assert bool(said) is warned
            if warned:
                assert "@imu:bmi088" in said[0]
        finally:
            env.close()

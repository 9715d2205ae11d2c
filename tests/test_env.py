"""The Gymnasium environment: API conformance, determinism, isolation, vectorisation, bad input."""

import warnings

import cv2
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import rover_env
from rover_env.envs import OBS_FIELDS, RoverEnv
from rover_env.sim.ground_truth import GROUND_TRUTH_KEYS, SOIL_TRUTH_KEYS


def rollout(env, seed, actions):
    obs, _ = env.reset(seed=seed)
    out = [np.append(obs, 0.0)]
    for a in actions:
        obs, r, term, trunc, info = env.step(a)
        out.append(np.append(obs, r))
    return np.array(out)


#: The vector-env machinery does not depend on the mission: the soil missions' runs of it are slow.
MACHINERY_IDS = [
    pytest.param(e, marks=pytest.mark.slow) if e in ("RoverSlopeLoose-v1", "RoverSoftSand-v0") else e
    for e in rover_env.ENV_IDS
]

ACTIONS = [np.array([0.6, 0.3 * np.sin(k / 10), -0.2], dtype=np.float32) for k in range(40)]


def test_registration_is_idempotent():
    before = len(gym.registry)
    rover_env.register_envs()
    rover_env.register_envs()
    assert len(gym.registry) == before
    assert "Rover-v0" in rover_env.ENV_IDS
    for env_id in rover_env.ENV_IDS:
        assert env_id in gym.registry


@pytest.mark.parametrize("env_id", rover_env.ENV_IDS)
@pytest.mark.parametrize("action_mode", ["drive", "wheels"])
@pytest.mark.parametrize("obs_source", ["estimated", "ground_truth"])
def test_check_env_passes_without_warnings(env_id, action_mode, obs_source):
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(env_id, action_mode=action_mode, obs_source=obs_source, render_mode="rgb_array")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(env.unwrapped)
            sb3_check_env(env.unwrapped)
        messages = [str(w.message) for w in caught]
        assert messages == []
        n_act = 3 if action_mode == "drive" else 6
        assert env.observation_space.shape == (len(OBS_FIELDS) + n_act,)
        env.reset(seed=0)
        frame = env.render()
        assert frame.shape == (480, 960, 3) and frame.dtype == np.uint8
        assert frame.std() > 5  # a real picture, not a blank frame
    finally:
        env.close()


def test_same_seed_same_rollout_fresh_and_reused():
    a = RoverEnv()
    b = RoverEnv()
    try:
        ra = rollout(a, 7, ACTIONS)
        rb = rollout(b, 7, ACTIONS)
        np.testing.assert_array_equal(ra, rb)
        rollout(a, 3, ACTIONS[:10])  # a different episode in between
        np.testing.assert_array_equal(rollout(a, 7, ACTIONS), ra)
        rc = rollout(b, 8, ACTIONS)
        assert not np.array_equal(rc, ra)  # the seed matters (start jitter)
    finally:
        a.close()
        b.close()


@pytest.mark.parametrize("env_id", rover_env.ENV_IDS)
@pytest.mark.parametrize("obs_source", ["estimated", "ground_truth"])
def test_same_seed_same_rollout_on_every_mission(env_id, obs_source):
    a = gym.make(env_id, obs_source=obs_source)
    b = gym.make(env_id, obs_source=obs_source)
    try:
        ra = rollout(a, 11, ACTIONS[:12])
        np.testing.assert_array_equal(rollout(b, 11, ACTIONS[:12]), ra)
        np.testing.assert_array_equal(rollout(a, 11, ACTIONS[:12]), ra)  # reused
    finally:
        a.close()
        b.close()


def test_two_envs_in_one_process_do_not_interfere():
    ref_env = RoverEnv()
    ref = rollout(ref_env, 1, ACTIONS)
    ref_env.close()
    a, b = RoverEnv(), RoverEnv(scenario="rough")
    try:
        a.reset(seed=1)
        b.reset(seed=2)
        out = [np.append(a.reset(seed=1)[0], 0.0)]
        for act in ACTIONS:
            b.step(np.array([1.0, -1.0, 1.0], dtype=np.float32))
            obs, r, *_ = a.step(act)
            out.append(np.append(obs, r))
        np.testing.assert_array_equal(np.array(out), ref)
    finally:
        a.close()
        b.close()


def test_reward_terms_sum_to_reward_and_info_keys():
    env = RoverEnv()
    try:
        _, info = env.reset(seed=0)
        assert tuple(info["ground_truth"]) == GROUND_TRUTH_KEYS
        assert info["ground_truth"]["pose"].shape == (7,)
        progress = 0.0
        for _ in range(60):
            _, reward, term, trunc, info = env.step(np.array([0.5, 0.0, 0.0]))
            assert reward == pytest.approx(sum(info["reward_terms"].values()), abs=1e-12)
            progress += info["reward_terms"]["progress"]
        assert set(info["wheel_contact"]) == {"friction", "normal_force", "in_contact", "contact_point"}
        assert info["t"] == pytest.approx(2.0)
        # 2 s at half of 2 m/s toward the first waypoint: about 1.5-2 m of progress
        assert 1.2 < progress < 2.1
        assert info["ground_truth"]["twist"][0] == pytest.approx(1.0, abs=0.05)
    finally:
        env.close()


def test_bad_actions_raise_and_out_of_range_is_clipped():
    env = RoverEnv()
    try:
        env.reset(seed=0)
        with pytest.raises(ValueError, match="NaN or infinite"):
            env.step(np.array([np.nan, 0.0, 0.0]))
        with pytest.raises(ValueError, match="NaN or infinite"):
            env.step(np.array([0.0, np.inf, 0.0]))
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros(6))
        obs, *_ = env.step(np.array([3.0, -7.0, 0.5]))
        np.testing.assert_allclose(obs[-3:], [1.0, -1.0, 0.5])
        assert env.sim.rover.steer_cmd[0] == pytest.approx(-env.geometry.steer_limit)
    finally:
        env.close()
    env.close()  # closing twice is safe


def test_bad_constructor_arguments_are_explained():
    with pytest.raises(ValueError, match="action_mode"):
        RoverEnv(action_mode="tank")
    with pytest.raises(ValueError, match="obs_source"):
        RoverEnv(obs_source="camera")
    with pytest.raises(ValueError, match="preset"):
        RoverEnv(preset="fast")
    with pytest.raises(ValueError, match="blackout"):
        RoverEnv(obs_source="ground_truth").reset(seed=0, options={"blackout": [(0.0, 1.0)]})
    with pytest.raises(ValueError, match="control_hz"):
        RoverEnv(control_hz=7.0)
    with pytest.raises(rover_env.ConfigError, match="unknown scenario preset"):
        RoverEnv(scenario="moon_base")


@pytest.mark.parametrize("env_id", MACHINERY_IDS)
@pytest.mark.parametrize("obs_source", ["estimated", "ground_truth"])
def test_make_vec_sync_and_async_give_the_same_rollouts(env_id, obs_source):
    """In worker processes (the estimator in the loop or not): the same seeds give the same observations."""
    from rover_env.rendering.gl import gl_status

    out = {}
    for mode in ("sync", "async"):
        # this test process has rendered with OpenGL already, and Mesa's EGL does not survive a
        # fork: async workers start from a fork server (the default fork would fall back to
        # TinyRenderer, with a warning)
        kwargs = {"context": "forkserver"} if mode == "async" else {}
        venv = gym.make_vec(
            env_id, num_envs=2, vectorization_mode=mode, vector_kwargs=kwargs, obs_source=obs_source
        )
        try:
            if obs_source == "estimated" and gl_status()[0]:
                assert list(venv.get_attr("renderer")) == ["gl", "gl"]
            obs, _ = venv.reset(seed=[3, 4])
            assert obs.shape == (2, len(OBS_FIELDS) + 3)
            rows = [obs]
            for k in range(6):
                obs, rew, term, trunc, info = venv.step(np.tile([0.5, 0.2 * (k % 2), 0.0], (2, 1)))
                rows.append(obs)
            rates = [OBS_FIELDS.index(f"wheel_rate_{w}") for w in ("FL", "FR", "RL", "RR")]
            assert np.all(np.isfinite(obs)) and obs[:, rates].min() > 1.0  # wheels turning forward
            assert not np.array_equal(obs[0], obs[1])  # two seeds, two start poses
            out[mode] = np.stack(rows)
        finally:
            venv.close()
    np.testing.assert_array_equal(out["sync"], out["async"])


def _make(env_id, obs_source):
    """A module-level factory: a worker process unpickles it by importing this module (and rover_env)."""
    return gym.make(env_id, obs_source=obs_source)


@pytest.mark.parametrize("env_id", MACHINERY_IDS)
@pytest.mark.parametrize(
    "obs_source", ["estimated", pytest.param("ground_truth", marks=pytest.mark.slow)]
)  # the estimated source's workers run the whole pipeline; the truth's only its simpler part
def test_subproc_vec_env(env_id, obs_source):
    import functools

    from stable_baselines3.common.vec_env import SubprocVecEnv

    make = functools.partial(_make, env_id, obs_source)
    sb3 = SubprocVecEnv([make, make])
    try:
        # seeded: unseeded starts put the rover's shadow on a tread in about 1 % of RoverShadows-v0
        # starts, and that wheel's rate is then unmeasured for the first frames
        sb3.seed(0)
        obs = sb3.reset()
        for _ in range(5):
            obs, rew, done, infos = sb3.step(np.tile([0.5, 0.0, 0.0], (2, 1)))
        rates = [OBS_FIELDS.index(f"wheel_rate_{w}") for w in ("FL", "FR", "RL", "RR")]
        assert obs.shape == (2, len(OBS_FIELDS) + 3) and obs[:, rates].min() > 1.0  # wheels turning
        assert "ground_truth" in infos[0]
    finally:
        sb3.close()


def test_episode_succeeds_when_the_last_waypoint_is_reached(tmp_path):
    yaml_text = """
name: short
course: {waypoints: [[1.5, 0.0]], tolerance: 0.5}
terrain: {kind: flat, size: [10.0, 10.0], texture: concrete, texture_px: 64}
duration: 10.0
"""
    path = tmp_path / "short.yaml"
    path.write_text(yaml_text)
    env = RoverEnv(scenario=path)
    try:
        env.reset(seed=0)
        for _ in range(300):
            _, reward, term, trunc, info = env.step(np.array([0.4, 0.0, 0.0]))
            if term or trunc:
                break
        assert term and info["is_success"] and info["termination"] == "success"
        assert info["reward_terms"]["success"] == pytest.approx(10.0)
        assert 0.9 < info["t"] < 3.0
    finally:
        env.close()


def test_composite_render_records_with_gymnasium_record_video(tmp_path):
    """The composite frame (chase view, downward image, fisheye) goes through RecordVideo."""
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(
        gym.make("Rover-v0", render_mode="rgb_array", render_size=(480, 240)),
        video_folder=str(tmp_path / "videos"),
        episode_trigger=lambda _: True,
        disable_logger=True,
    )
    try:
        env.reset(seed=1)
        for _ in range(12):
            env.step(np.array([0.6, 0.2, -0.2], dtype=np.float32))
        frame = env.render()
    finally:
        env.close()
    assert frame.shape == (240, 480, 3)
    # right column: the downward image (top) and the fisheye circle with black corners (bottom)
    fisheye = frame[120:, 320:]
    assert fisheye[2:6, 2:6].max() < 10 and fisheye[55:65, 75:85].std() > 2
    assert frame[:120, 320:].std() > 5
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1
    cap = cv2.VideoCapture(str(videos[0]))
    ok, first = cap.read()
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    assert ok and first.shape == (240, 480, 3) and n >= 12


def test_estimated_observation_tracks_the_truth_and_survives_a_blackout():
    env = RoverEnv(preset="train")
    try:
        env.reset(seed=2, options={"blackout": [(1.0, 1.5)]})
        frames = env.pipeline.frames
        rows = []
        for _ in range(75):  # 2.5 s at 0.5 of v_max, straight
            windowed = frames["fisheye_windowed"]
            obs, _, term, trunc, info = env.step(np.array([0.5, 0.0, 0.0], dtype=np.float32))
            assert not (term or trunc)
            # the fisheye renders windows about the tracked joints, not after a black frame (and a
            # black frame is not rendered at all)
            prev_dark = 1.0 - 1e-9 <= info["t"] - 1 / 30 < 1.5 - 1e-9
            dark = 1.0 - 1e-9 <= info["t"] < 1.5 - 1e-9
            assert frames["fisheye_windowed"] == windowed + (not (prev_dark or dark)), info["t"]
            state = [k for k in info["ground_truth"] if k not in SOIL_TRUTH_KEYS]
            assert sorted(info["estimate"]) == sorted([*state, "odometry_pose", "quality"])
            assert np.all(np.isfinite(obs))
            sl = info["slip"]
            assert sorted(sl) == ["events", "slip_ratio_std", "valid"]
            assert all(sl[k].shape == (4,) for k in sl) and not np.any(sl["events"] & ~sl["valid"])
            rows.append((info["t"], obs.copy(), info["ground_truth"]["twist"][0], info["quality"], sl))
        i = {name: k for k, name in enumerate(OBS_FIELDS)}
        slips = [i[f"slip_{w}"] for w in ("FL", "FR", "RL", "RR")]
        dark = [r for r in rows if 1.1 <= r[0] < 1.5]
        assert dark and all(
            r[1][i["odometry_quality"]] == 0.0 and r[1][i["kinematics_quality"]] == 0.0 for r in dark
        )
        stale = [r for r in dark if r[0] >= 1.25]  # after max_age: no slip valid, none reported
        assert all(r[3]["slip"] == 0.0 and not r[4]["valid"].any() for r in stale)
        assert all(np.all(r[1][slips] == 0.0) and np.all(np.isinf(r[4]["slip_ratio_std"])) for r in stale)
        # before and well after the blackout the estimated forward speed follows the truth
        lit = [r for r in rows if 0.6 <= r[0] < 1.0 or r[0] >= 2.0]
        err = np.array([r[1][i["v_x"]] - r[2] for r in lit])
        assert np.mean(np.abs(err)) < 0.1, err
        assert all(r[1][i["kinematics_quality"]] > 0.5 for r in rows if r[0] >= 2.0)  # the fisheye is back
    finally:
        env.close()


def test_ground_truth_tilt_is_the_z_y_x_roll_and_pitch_of_the_pose():
    import dataclasses

    from scipy.spatial.transform import Rotation

    from rover_env.sim.ground_truth import GroundTruth

    fields = {f.name: np.zeros(4) for f in dataclasses.fields(GroundTruth)}
    for roll, pitch, yaw in ((0.2, -0.3, 1.0), (-0.05, 0.4, -2.5), (0.0, 0.0, 3.0)):
        q = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()  # x, y, z, w
        gt = GroundTruth(**(fields | {"t": 0.0, "pose": np.array([0.0, 0.0, 0.3, *q])}))
        np.testing.assert_allclose(gt.tilt, [roll, pitch], atol=1e-12)
    # pitch + is nose down: the body x axis then points below the horizon
    q = Rotation.from_euler("ZYX", [0.0, 0.1, 0.0])
    assert q.apply([1.0, 0.0, 0.0])[2] < 0

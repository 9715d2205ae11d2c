"""The sensor rig a scenario declares: add, drop or move a sensor without code; bad rigs named."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import yaml

import rover_env  # noqa: F401
from rover_env.config.io import ConfigError, to_dict
from rover_env.config.rig import STANDARD_RPY, mount_matrix
from rover_env.config.scenario import load_scenario
from rover_env.sensors.cameras import R_BODY_DOWNCAM, R_BODY_FISHEYE
from rover_env.sim.geometry import RoverGeometry


class Recorder:
    """An estimator that keeps every message's sensor, time and image."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self.seen: list[tuple[str, float]] = []
        self.last: dict[str, np.ndarray] = {}

    def reset(self, start_fix) -> None:
        self.pose = np.array(start_fix, dtype=np.float64)

    def update(self, messages, t):
        for m in messages:
            self.seen.append((m.sensor, m.t))
            self.last[m.sensor] = m.data
        return {"pose": self.pose}


def scenario_file(tmp_path, rig, name="flat_patches", **extra):
    """A copy of a shipped scenario with ``rig`` (and other keys) set, as a YAML file."""
    data = to_dict(load_scenario(name)) | {"rig": rig} | extra
    data.pop("imu", None)
    path = tmp_path / "rigged.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_standard_rig_is_the_one_the_sensors_are_built_with():
    env = gym.make("Rover-v0", renderer="tiny", imu="bmi088")
    try:
        rig = env.unwrapped.rig
        assert list(rig) == ["fisheye", "downward", "imu", "sun"]
        assert [rig[n].kind for n in rig] == ["fisheye", "pinhole", "imu", "sun"]
        assert [rig[n].rate_hz for n in rig] == [30.0, 30.0, 240.0, 5.0]
        g = RoverGeometry()
        # the sun sensor on the mast's post, above its boom, looking up
        np.testing.assert_array_equal(rig["sun"].mount[:3, :3], np.eye(3))
        assert rig["sun"].mount[2, 3] > g.mast_camera_position[2] and rig["sun"].mount[0, 3] == g.mast_x
        np.testing.assert_array_equal(rig["downward"].mount[:3, :3], R_BODY_DOWNCAM)
        np.testing.assert_array_equal(rig["downward"].mount[:3, 3], g.mast_camera_position)
        np.testing.assert_array_equal(rig["fisheye"].mount[:3, :3], R_BODY_FISHEYE)
        np.testing.assert_array_equal(rig["fisheye"].mount[:3, 3], g.fisheye_origin)
        # the standard orientations as roll-pitch-yaw are the same rotations
        for kind, R in (("pinhole", R_BODY_DOWNCAM), ("fisheye", R_BODY_FISHEYE)):
            np.testing.assert_allclose(mount_matrix((0, 0, 0), STANDARD_RPY[kind])[:3, :3], R, atol=1e-12)
        # the models are those the simulation renders through, as the estimator's own read-only copies
        pipe = env.unwrapped.pipeline
        for name, cam in (("downward", pipe.downward), ("fisheye", pipe.fisheye)):
            assert rig[name].model is not cam.model
            np.testing.assert_array_equal(rig[name].model.T_body_cam, cam.model.T_body_cam)
            assert not rig[name].model.T_body_cam.flags.writeable
        np.testing.assert_array_equal(rig["downward"].model.K, pipe.downward.model.K)
        assert rig["fisheye"].model.poly == pipe.fisheye.model.poly
    finally:
        env.close()


def test_a_scenario_adds_moves_and_drops_sensors_and_their_messages_arrive_at_their_rates(tmp_path):
    front = [0.45, 0.05, 0.55]
    rig = [
        {"name": "front", "kind": "pinhole", "rate_hz": 60, "mount": {"position": front},
         "camera": {"width": 96, "height": 72}},
        {"name": "downward", "kind": "pinhole", "rate_hz": 20},
        {"name": "imu", "kind": "imu", "rate_hz": 120, "imu": "tactical",
         "mount": {"position": [0.1, 0.0, 0.05], "rpy": [0.0, 0.0, math.pi / 2]}},
    ]  # fmt: skip
    env = gym.make(
        "Rover-v0", scenario=str(scenario_file(tmp_path, rig)), estimator=Recorder, renderer="tiny"
    )
    try:
        u = env.unwrapped
        env.reset(seed=1)
        for _ in range(30):  # 1 s
            env.step(np.array([0.5, 0.0, 0.0], dtype=np.float32))
        spec = u.rig
        assert list(spec) == ["front", "downward", "imu"]  # no fisheye: dropped
        assert (spec["front"].kind, spec["front"].rate_hz) == ("pinhole", 60.0)
        np.testing.assert_allclose(spec["front"].mount[:3, 3], front)
        np.testing.assert_allclose(spec["front"].mount[:3, :3], R_BODY_DOWNCAM, atol=1e-12)
        assert spec["front"].model.image_size == (96, 72)
        np.testing.assert_allclose(spec["imu"].mount[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
        assert spec["imu"].rate_hz == 120.0
        est = u.pipeline.estimator
        after = [(s, t) for s, t in est.seen if t > 1e-9]
        assert {n: sum(s == n for s, _ in after) for n in spec} == {"front": 60, "downward": 20, "imu": 120}
        for name in spec:
            ts = np.array([t for s, t in est.seen if s == name and t > 1e-9])
            np.testing.assert_allclose(np.diff(ts), spec[name].period, atol=1e-9)
        assert est.last["front"].shape == (72, 96, 3)
        assert est.last["downward"].shape[:2] == (120, 160)  # the train preset's size
        # the moved camera sees other ground than the mast camera
        assert est.last["front"].std() > 5.0
    finally:
        env.close()


def test_the_built_in_estimator_says_what_a_rig_lacks(tmp_path):
    path = scenario_file(tmp_path, [{"name": "downward", "kind": "pinhole"}])
    with pytest.raises(ConfigError, match="RoverEstimator needs a 'fisheye' sensor"):
        gym.make("Rover-v0", scenario=str(path), renderer="tiny")


def test_the_imu_keyword_takes_the_place_of_the_rig_s_imu(tmp_path):
    rig = [
        {"name": "fisheye", "kind": "fisheye"},
        {"name": "down", "kind": "pinhole"},
        {"name": "body_imu", "kind": "imu", "rate_hz": 80, "imu": "bmi088"},
    ]
    env = gym.make("Rover-v0", scenario=str(scenario_file(tmp_path, rig)), imu="ideal", renderer="tiny")
    try:
        spec = env.unwrapped.rig
        assert list(spec) == ["fisheye", "down", "body_imu"] and spec["body_imu"].rate_hz == 80.0
        assert spec["body_imu"].model.gyro.noise_density == 0.0  # the ideal IMU's data sheet
    finally:
        env.close()


STRETCH = [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # not a rotation
SHEAR = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]  # not rigid: a bad last row


@pytest.mark.parametrize(
    ("rig", "message"),
    [
        ([{"name": "a", "kind": "lidar"}], r"rig\[0\]\.kind: 'lidar' is not one of"),
        ([{"name": "a", "kind": "pinhole", "mount": STRETCH}],
         r"rig\[0\]\.mount: .*not a rotation.*rigid"),
        ([{"name": "a", "kind": "pinhole", "mount": SHEAR}],
         r"rig\[0\]\.mount: last row"),
        ([{"name": "a", "kind": "fisheye"}, {"name": "a", "kind": "pinhole"}], r"rig\[1\]\.name: 'a'"),
        ([{"name": "a", "kind": "pinhole", "camera": {"widht": 64}}],
         r"unknown key 'rig\[0\]\.camera\.widht'"),
        ([{"name": "a", "kind": "imu", "camera": {"width": 64}}],
         r"rig\[0\]\.camera: sensor 'a' is of kind imu; give its settings as imu"),
        ([{"name": "e", "kind": "wheel_encoders", "encoder": {"counts_per_rev": 2}}],
         r"rig\[0\]\.wheel_encoders\.counts_per_rev"),
        ([{"name": "e", "kind": "wheel_encoders", "encoder": {"counts_per_rev": 4096, "counter_bits": 12}}],
         r"counter must hold at least 4 revolutions"),
        ([{"name": "m", "kind": "motor_current", "motor": {"efficiency": 1.5}}],
         r"rig\[0\]\.motor_current\.efficiency"),
        ([{"name": "m", "kind": "motor_current", "motor": {"torque_konstant": 1}}],
         r"rig\[0\]\.motor_current: unknown key 'torque_konstant'"),
        ([{"name": "c", "kind": "command", "motor": "dcx26"}],
         r"rig\[0\]\.motor: sensor 'c' is of kind command; it takes only rate_hz"),
        ([{"name": "c", "kind": "command", "mount": {"position": [0, 0, 1]}}],
         r"rig\[0\]\.mount: sensor 'c' is command, which reads the joints"),
        ([{"name": "a", "kind": "pinhole", "mount": {"place": [0, 0, 1]}}], r"rig\[0\]\.mount: unknown key"),
    ],
)  # fmt: skip
def test_a_bad_rig_is_a_config_error_naming_the_key(tmp_path, rig, message):
    with pytest.raises(ConfigError, match=message):
        load_scenario(scenario_file(tmp_path, rig))


@pytest.mark.parametrize(
    ("index", "sensor"),
    [
        (0, {"kind": "pinhole", "rate_hz": 70}),
        (1, {"kind": "imu", "rate_hz": 100}),
        (1, {"kind": "wheel_encoders", "rate_hz": 7}),
        (1, {"kind": "motor_current", "rate_hz": 50}),
        (1, {"kind": "command", "rate_hz": 50}),
    ],
)
def test_a_rate_that_does_not_divide_the_physics_rate_is_named(tmp_path, index, sensor):
    rig = [{"name": "fisheye", "kind": "fisheye"}, {"name": "down", "kind": "pinhole"}]
    rig[index] = {"name": "odd"} | sensor
    path = scenario_file(tmp_path, rig)
    with pytest.raises(
        ConfigError,
        match=rf"rig\[{index}\]\.rate_hz: .* \(sensor 'odd'\) does not divide the physics rate 240",
    ):
        gym.make("Rover-v0", scenario=str(path), estimator=Recorder, renderer="tiny")


def test_a_scenario_with_both_a_rig_and_an_imu_is_refused(tmp_path):
    data = to_dict(load_scenario("flat_patches")) | {
        "rig": [{"name": "f", "kind": "fisheye"}],
        "imu": "bmi088",
    }
    path = tmp_path / "both.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="imu: this scenario declares a rig"):
        load_scenario(path)


def test_a_turned_only_mount_keeps_the_imu_s_place_and_the_keyword_replaces_its_settings(tmp_path):
    rig = [
        {"name": "fisheye", "kind": "fisheye"},
        {"name": "downward", "kind": "pinhole"},
        {"name": "imu", "kind": "imu", "imu": {"preset": "bmi088", "position": [0.1, 0.2, 0.05]},
         "mount": {"rpy": [0.0, 0.0, math.pi / 2]}},
    ]  # fmt: skip
    path = scenario_file(tmp_path, rig)
    scenario = load_scenario(path)
    assert load_scenario(scenario) == scenario  # a configuration passes through unchanged
    env = gym.make("Rover-v0", scenario=str(path), renderer="tiny")
    try:
        mount = env.unwrapped.rig["imu"].mount
        np.testing.assert_allclose(mount[:3, 3], [0.1, 0.2, 0.05])  # the IMU's own place ...
        np.testing.assert_allclose(mount[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # ... turned
    finally:
        env.close()
    # the keyword's settings take the place of the rig's (its name, rate and mount stay)
    env = gym.make("Rover-v0", scenario=str(path), imu="ideal", renderer="tiny")
    try:
        spec = env.unwrapped.rig["imu"]
        np.testing.assert_allclose(spec.mount[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
        assert spec.model.gyro.noise_density == 0.0
    finally:
        env.close()


def test_the_scenario_s_imu_rate_is_named_where_it_was_written(tmp_path):
    data = to_dict(load_scenario("flat_patches")) | {"imu": {"preset": "bmi088", "rate_hz": 100}}
    path = tmp_path / "imu100.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"^imu\.rate_hz: 100 Hz \(sensor 'imu'\) does not divide"):
        gym.make("Rover-v0", scenario=str(path), renderer="tiny")
    rig = [{"name": "f", "kind": "fisheye"}, {"name": "d", "kind": "pinhole"},
           {"name": "i", "kind": "imu", "imu": {"preset": "bmi088", "rate_hz": 100}}]  # fmt: skip
    with pytest.raises(ConfigError, match=r"^rig\[2\]\.imu\.rate_hz: 100 Hz"):
        gym.make("Rover-v0", scenario=str(scenario_file(tmp_path, rig)), renderer="tiny")

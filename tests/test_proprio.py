"""Proprioceptive sensors in the rig: encoders, motor currents, the command; the soil's truth per wheel."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from test_rig import Recorder, scenario_file

import rover_env  # noqa: F401
from perception.rig import EncoderModel, MotorModel
from rover_env.config.io import ConfigError
from rover_env.config.proprio import MotorCurrentConfig, encoder_config, motor_config
from rover_env.sim.ground_truth import GROUND_TRUTH_KEYS, SOIL_CURVE_KEYS, SOIL_TRUTH_KEYS
from rover_env.sim.terramechanics import steady_state


class Keeper(Recorder):
    """A recorder that keeps every message."""

    def update(self, messages, t):
        self.messages = [*getattr(self, "messages", []), *messages]
        return super().update(messages, t)


def _drive(tmp_path, rig, steps, action=(0.8, 0.0, 0.0), name="flat_patches", seed=3):
    env = gym.make(
        "Rover-v0", scenario=str(scenario_file(tmp_path, rig, name)), estimator=Keeper, renderer="tiny"
    )
    infos = []
    try:
        _, info = env.reset(seed=seed)
        infos.append(info)
        for _ in range(steps):
            infos.append(env.step(np.asarray(action, dtype=np.float32))[4])
        return env.unwrapped.pipeline.estimator, infos, env.unwrapped.rig
    finally:
        env.close()


def test_encoders_count_the_true_wheel_angle_to_a_count_through_the_counters_wrap(tmp_path):
    rig = [{"name": "enc", "kind": "wheel_encoders", "encoder": {"counter_bits": 14}}]
    est, infos, spec = _drive(tmp_path, rig, 150)  # 5 s at about 14 rad/s: 11 revolutions, 2 wraps
    model = spec["enc"].model
    assert isinstance(model, EncoderModel) and model.counts_per_rev == 4096 and model.wrap == 2**14
    msgs = [m for m in est.messages if m.sensor == "enc"]
    assert len(msgs) == 1 + 150 * 4  # 120 Hz from t = 0
    counts = np.array([m.data for m in msgs])
    assert np.all(counts == np.round(counts)) and counts.min() >= 0 and counts.max() < 2**14
    assert np.any(np.diff(counts, axis=0) < -(2**13))  # the counter wrapped
    unwrapped = counts[0] + np.cumsum(
        np.vstack([0 * counts[0], (np.diff(counts, axis=0) + 2**13) % 2**14 - 2**13]), 0
    )
    by_t = {round(m.t, 6): i for i, m in enumerate(msgs)}
    truth = np.array([info["ground_truth"]["wheel_angle"] for info in infos])
    rows = [by_t[round(info["t"], 6)] for info in infos]
    angle = (unwrapped[rows] - unwrapped[rows[0]]) * 2 * math.pi / 4096
    err = angle - (truth - truth[0])
    assert np.abs(err).max() <= 2 * math.pi / 4096 + 1e-9  # one count
    assert (truth[-1] - truth[0]).min() > 2 * math.pi * 9


def test_motor_currents_give_back_the_true_wheel_torque_through_the_data_sheet(tmp_path):
    exact = {"offset_std": 0.0, "noise_std": 0.0, "lsb": 0.0}
    rig = [{"name": "cur", "kind": "motor_current", "rate_hz": 30, "motor": exact}]
    est, infos, spec = _drive(tmp_path, rig, 40)
    model = spec["cur"].model
    assert isinstance(model, MotorModel) and model.gear_ratio == 100.0
    by_t = {round(m.t, 6): m.data for m in est.messages if m.sensor == "cur"}
    torque = np.array([info["ground_truth"]["wheel_torque"] for info in infos])
    rate = np.array([info["ground_truth"]["wheel_rate"] for info in infos])
    current = np.array([by_t[round(info["t"], 6)] for info in infos])
    back = model.wheel_torque(current, rate)
    np.testing.assert_allclose(back, torque, atol=1e-9)
    # speeding up at the 8 N m limit: 8 / (100 * 0.75) / 0.0283 A and the friction's 60 mA
    np.testing.assert_allclose(torque[1:3], 8.0)
    np.testing.assert_allclose(
        current[1:3], 8.0 / 75 / 0.0283 + 0.06 * np.tanh(rate[1:3] * 100 / 5), rtol=1e-9
    )
    cfg = MotorCurrentConfig()
    i8 = 8.0 / (cfg.gear_ratio * cfg.efficiency) / cfg.torque_constant + cfg.no_load_current * math.tanh(
        1000 / 5
    )
    assert float(model.wheel_torque(i8, 10.0)) == pytest.approx(8.0, abs=1e-9)
    # braking: the wheel drives the motor, which sees the torque times the efficiency
    assert float(
        model.wheel_torque(-2.0 * 0.75 / 100 / 0.0283 + 0.06 * math.tanh(1000 / 5), 10.0)
    ) == pytest.approx(-2.0)


def test_motor_current_noise_and_offset_have_their_data_sheet_spread(tmp_path):
    rig = [{"name": "cur", "kind": "motor_current", "rate_hz": 240, "motor": {"lsb": 0.0}}]
    est, infos, spec = _drive(tmp_path, rig, 60, action=(0.0, 0.0, 0.0))  # standing, braked
    msgs = [m for m in est.messages if m.sensor == "cur" and m.t > 0.5]  # settled at rest
    data = np.array([m.data for m in msgs])
    noise = data - data.mean(axis=0)
    assert noise.std() == pytest.approx(0.02, rel=0.1)


def test_the_command_is_what_the_rover_was_told_after_its_limits(tmp_path):
    rig = [{"name": "cmd", "kind": "command"}]
    est, infos, spec = _drive(tmp_path, rig, 10, action=(1.0, 1.0, -0.5))
    assert spec["cmd"].rate_hz == 30.0 and spec["cmd"].model is None
    last = [m for m in est.messages if m.sensor == "cmd"][-1]
    assert last.data.shape == (6,)
    assert last.data[4] == pytest.approx(math.radians(30)) and last.data[5] == pytest.approx(
        -math.radians(15)
    )
    assert np.all(last.data[:4] > 0)


def test_the_full_rig_is_the_standard_one_with_the_bmi088_and_proprioception():
    env = gym.make("Rover-v0", rig="full", renderer="tiny")
    try:
        rig = env.unwrapped.rig
        assert [(n, rig[n].kind, rig[n].rate_hz) for n in rig] == [
            ("fisheye", "fisheye", 30.0),
            ("downward", "pinhole", 30.0),
            ("imu", "imu", 240.0),
            ("sun", "sun", 5.0),
            ("encoders", "wheel_encoders", 120.0),
            ("currents", "motor_current", 120.0),
            ("command", "command", 30.0),
        ]
    finally:
        env.close()


def test_proprio_settings_from_presets_and_mappings():
    assert encoder_config("as5047p").counts_per_rev == 4096
    assert motor_config({"preset": "dcx26", "gear_ratio": 50}).name == "custom"
    with pytest.raises(ConfigError, match="choose one of"):
        encoder_config("nonesuch")
    with pytest.raises(ConfigError, match="counts_per_rev"):
        EncoderModel(counts_per_rev=2.5)


def test_the_truth_on_soil_is_the_soils_sinkage_pull_and_load(tmp_path):
    """Up a slope of sand the truth's sinkage, load and pull are the soil's; its curves, steady states'."""
    rig = [{"name": "cmd", "kind": "command"}]
    est, infos, spec = _drive(tmp_path, rig, 30, action=(0.3, 0.0, 0.0))
    gt = infos[-1]["ground_truth"]  # flat_patches has no soil: the truth reads rigid ground
    assert tuple(gt) == GROUND_TRUTH_KEYS and set(SOIL_TRUTH_KEYS) <= set(gt)
    assert np.all(gt["sinkage"] == 0.0)
    np.testing.assert_allclose(gt["load"].sum(), 42.6 * 9.81, rtol=0.03)
    path = scenario_file(tmp_path, rig, "slope_soil")
    env = gym.make("Rover-v0", scenario=str(path), estimator=Keeper, renderer="tiny")
    try:
        env.reset(seed=0)
        for _ in range(150):
            info = env.step(np.array([0.3, 0.0, 0.0], dtype=np.float32))[4]
        soil = env.unwrapped.sim.rover.soil
        soil_truth = env.unwrapped.soil_truth()
        assert tuple(soil_truth) == SOIL_CURVE_KEYS
        gt = info["ground_truth"] | soil_truth
        np.testing.assert_array_equal(gt["sinkage"], soil.sinkage)
        np.testing.assert_array_equal(gt["drawbar_pull"], soil.contact.last[:, 0])
        assert 0.010 < gt["sinkage"].min() and gt["sinkage"].max() < 0.05
        # the slope's weight component is what the four wheels pull (steady climb)
        mg = 42.6 * 9.81
        assert gt["drawbar_pull"].sum() == pytest.approx(mg * math.sin(math.radians(10)), rel=0.1)
        assert gt["load"].sum() == pytest.approx(mg * math.cos(math.radians(10)), rel=0.05)
        # the front wheels on virgin soil: their curves are the test bed's steady state at their load
        s_grid = np.linspace(0.0, 0.95, 96)
        for i in (0, 1):
            assert gt["slip_ratio"][i] > 0.05
            ss = steady_state(soil.curves[0].soil, soil.wheel, gt["load"][i], s_grid, n_theta=48)
            dpw = ss.drawbar_pull / ss.load
            assert gt["slip_best_pull"][i] == pytest.approx(s_grid[np.argmax(dpw)], abs=0.03)
            assert gt["pull_ratio"][i] == pytest.approx(np.interp(gt["slip_ratio"][i], s_grid, dpw), abs=0.01)
            assert 0.0 < gt["slip_best_efficiency"][i] < gt["slip_best_pull"][i]
    finally:
        env.close()


def test_the_full_rig_gives_the_builtin_estimator_encoder_rates_and_wheel_torques():
    """With encoders the slip filter's wheel rates follow the truth closely; the currents give the torques."""
    env = gym.make("Rover-v0", rig="full")
    try:
        _, info = env.reset(seed=4)
        err_rate, err_torque, sinkage = [], [], []
        wheels = ("FL", "FR", "RL", "RR")
        for k in range(60):
            info = env.step(np.array([0.5, 0.0, 0.0], dtype=np.float32))[4]
            if k >= 20:
                gt, est, v = info["ground_truth"], info["estimate"], env.unwrapped.estimate_values
                err_rate.append(est["wheel_rate"] - gt["wheel_rate"])
                err_torque.append([v[f"wheel_torque_{w}"] for w in wheels] - gt["wheel_torque"])
                sinkage += [v[f"sinkage_{w}"] for w in wheels if f"sinkage_{w}" in v]
        assert np.abs(err_rate).mean() < 0.05  # rad/s, at about 8 rad/s
        # the current sense's 20 mA of noise and 10 mA offset: about 0.05 N m at the wheel
        assert np.abs(err_torque).mean() < 0.15
        # on rigid ground the fisheye sees each wheel's face reach the ground: (almost) no sinkage
        # (measured: 138 readings of 160, mean 0.4 mm, 95 % at 0, the largest 11 mm)
        assert len(sinkage) > 80 and np.mean(np.abs(sinkage)) < 0.002 and np.percentile(sinkage, 95) < 0.006
    finally:
        env.close()


def test_encoder_counters_unwrap_and_refuse_what_is_not_a_reading():
    from perception.fusion.encoders import EncoderRates

    enc = EncoderRates("enc", 4096, 16, 1 / 120, window=1 / 30)
    rate = 12.0  # rad/s on every wheel, from a count near the counter's top: it wraps
    counts = lambda t: np.mod(np.floor(65000 + rate * t * 4096 / (2 * math.pi)), 65536) * np.ones(4)  # noqa: E731
    windows = [w for k in range(121) if (w := enc.add(counts(k / 120), k / 120)) is not None]
    assert len(windows) == 30
    got = np.array([w.rate for w in windows])
    assert np.abs(got - rate).max() <= 2 * math.pi / 4096 * 30 + 1e-9  # a count over the window
    with pytest.raises(ValueError, match="enc: a wheel-encoder sample is \\(4,\\) counts"):
        enc.add(np.zeros(3), 2.0)
    before = enc.rejected
    assert enc.add(np.array([1.5, 0, 0, 0]), 1.01) is None  # not a whole count
    assert enc.add(np.array([70000.0, 0, 0, 0]), 1.02) is None  # beyond the counter
    assert enc.add(counts(0.5), 0.5) is None  # out of order
    assert enc.rejected == before + 3
    # after a gap the window restarts: no rate spans it
    enc.reset()
    assert enc.add(counts(0.0), 0.0) is None
    assert enc.add(counts(0.5), 0.5) is None and enc.rejected == 1
    # a counter that stands still while the fisheye sees its wheel turn is stuck, and left out
    enc.reset()
    stuck = lambda t: np.array([*counts(t)[:3], 123.0])  # noqa: E731
    out = None
    for k in range(61):
        t = k / 120
        out = enc.add(stuck(t), t) or out
        if k % 4 == 0:
            enc.check_stuck(np.full(4, rate), np.ones(4, bool), t)
    assert out is not None and list(out.valid) == [True, True, True, False]
    assert np.all(np.isfinite(out.rate[:3]))


def test_a_current_spike_is_outvoted_and_a_clipped_or_missing_reading_is_no_torque():
    model = MotorModel()
    rate = np.full(4, 10.0)
    i = 2.0 / (100 * 0.75) / 0.0283 + 0.06 * math.tanh(1000 / 5)  # 2 N m driving
    batch = np.full((4, 4), i)
    batch[1, 0] = 9.0  # a spike on FL
    batch[:3, 1] = 10.0  # FR clipped at full scale three times of four: not enough readings
    batch[0, 2] = np.nan  # one reading of RL lost
    batch[:, 3] = np.nan  # RR: none
    torque = model.step_torque(batch, rate)
    np.testing.assert_allclose(torque[[0, 2]], 2.0, atol=1e-9)
    assert np.isnan(torque[1]) and np.isnan(torque[3])
    assert np.all(np.isnan(model.step_torque(np.zeros((0, 4)), rate)))


def test_rover_record_refuses_sensors_it_cannot_log_before_writing(tmp_path):
    from rover_env.tools.record import record

    with pytest.raises(ValueError, match="encoders, motor currents and command have no log format"):
        record("Rover-v0", "slip_aware", 1.0, tmp_path / "out", rig="full")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_on_rigid_ground_the_wheels_pull_is_the_mass_times_the_acceleration(tmp_path):
    """Speeding up on level rigid ground: the four drawbar pulls (contact friction along each
    wheel's heading) sum to the rover's mass times its acceleration."""
    rig = [{"name": "cmd", "kind": "command"}]
    _, infos, _ = _drive(tmp_path, rig, 8, action=(0.8, 0.0, 0.0))
    v = np.array([info["ground_truth"]["twist"][0] for info in infos])
    pull = np.array([info["ground_truth"]["drawbar_pull"].sum() for info in infos])
    accel = np.diff(v) * 30.0  # the control rate
    mid = 0.5 * (pull[1:] + pull[:-1])
    assert accel[2:6].min() > 3.0  # at the motors' torque limit
    np.testing.assert_allclose(mid[2:6], 42.6 * accel[2:6], rtol=0.05)


def test_the_soil_identification_reads_the_loads_off_the_accelerometer():
    """With currents and an IMU the soil is identified; its loads carry the weight like the truth."""
    env = gym.make("Rover-v0", rig="full", renderer="tiny")
    try:
        env.reset(seed=2)
        est = env.unwrapped.pipeline.estimator
        assert est.soil is not None and est.soil.mass == pytest.approx(42.6)
        seen = []
        orig = est.soil.add

        def spy(distance, slip, valid, torque, sinkage, force, velocity, xy):
            if force is not None:
                seen.append(est.soil.loads(force))
            orig(distance, slip, valid, torque, sinkage, force, velocity, xy)

        est.soil.add = spy
        truth = []
        for _ in range(45):
            info = env.step(np.array([0.4, 0.0, 0.0], dtype=np.float32))[4]
            truth.append(info["ground_truth"]["load"])
        W, T = np.array(seen[15:]), np.array(truth[-len(seen[15:]) :])
        np.testing.assert_allclose(W.sum(axis=1), T.sum(axis=1), rtol=0.03)
        # each axle's share: the front's within 5 % of the truth's on average
        assert W[:, :2].sum(axis=1).mean() == pytest.approx(T[:, :2].sum(axis=1).mean(), rel=0.05)
        # rigid ground, one slip: no pull curve to identify, and none is reported
        assert not est.soil.last.identified
        assert "slip_best_pull" not in env.unwrapped.estimate_values
    finally:
        env.close()
    # without motor currents there is no identification
    env = gym.make("Rover-v0", imu="bmi088", renderer="tiny")
    try:
        env.reset(seed=2)
        assert env.unwrapped.pipeline.estimator.soil is None
    finally:
        env.close()

"""The IMU: its error model against its configured Allan terms, and its truth against the simulator."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from conftest import flat_scenario

from perception.fusion.allan import allan_deviation, fit_allan
from rover_env.config.imu import G, ImuConfig, TriadNoise
from rover_env.config.io import ConfigError
from rover_env.sensors.imu import Imu, ImuNoise
from rover_env.sim.simulation import RoverSim
from rover_env.sim.transforms import quat_to_matrix


def stationary_fit(cfg: ImuConfig, hours: float, seed: int, bin_samples: int = 12):
    """Allan fits of each axis over ``hours`` of stationary error output (generated a minute at a time)."""
    noise = ImuNoise(cfg, seed)
    per_minute = int(round(60 * cfg.rate_hz))
    means = []
    for _ in range(int(round(hours * 60))):
        e = noise.errors(per_minute)
        means.append(e.reshape(-1, bin_samples, 6).mean(axis=1))  # exact cluster sums for tau >= a bin
    x = np.vstack(means)
    dt = noise.dt * bin_samples
    taus, adev = allan_deviation(x, dt)
    return [fit_allan(taus, adev[:, a], len(x) * dt) for a in range(6)]


def ratios(cfg: ImuConfig, fits, attr_fit: str, attr_cfg: str) -> np.ndarray:
    return np.array(
        [
            getattr(f, attr_fit) / getattr(cfg.gyro if a < 3 else cfg.accel, attr_cfg)
            for a, f in enumerate(fits)
        ]
    )


@pytest.mark.slow  # ten hours of samples: 24 s
def test_allan_terms_of_the_tactical_unit_match_its_configuration_over_10_hours():
    cfg = ImuConfig.preset("tactical")
    fits = stationary_fit(cfg, 10.0, seed=7)
    n = ratios(cfg, fits, "random_walk", "noise_density")
    b = ratios(cfg, fits, "bias_instability", "bias_instability")
    print(f"tactical, 10 h: N/N_cfg {np.round(n, 3)}, B/B_cfg {np.round(b, 3)}")
    assert np.all(np.abs(n - 1) <= 0.10)
    assert np.all(np.abs(b - 1) <= 0.10)


def test_allan_terms_of_the_mems_unit_over_one_hour():
    cfg = ImuConfig.preset("bmi088")
    fits = stationary_fit(cfg, 1.0, seed=11)
    n = ratios(cfg, fits, "random_walk", "noise_density")
    print(f"bmi088, 1 h: N/N_cfg {np.round(n, 3)}")
    assert np.all(np.abs(n - 1) <= 0.10)
    # its gyro's 2 deg/h floor lies under the white noise until ~1,400 s, so it is checked alone
    flicker = dataclasses.replace(
        cfg,
        gyro=TriadNoise(bias_instability=cfg.gyro.bias_instability),
        accel=TriadNoise(bias_instability=cfg.accel.bias_instability),
    )
    b = ratios(flicker, stationary_fit(flicker, 1.0, seed=12), "bias_instability", "bias_instability")
    print(f"bmi088 bias instability alone, 1 h: B/B_cfg {np.round(b, 3)}")
    assert np.all(np.abs(b - 1) <= 0.10)


def test_per_episode_constants_follow_the_seed_and_their_configured_spread():
    cfg = ImuConfig.preset("bmi088")
    a, b = ImuNoise(cfg, 3), ImuNoise(cfg, 3)
    assert np.array_equal(a.errors(100), b.errors(100))
    draws = np.array([ImuNoise(cfg, s).turn_on for s in range(400)])
    sd = draws.std(axis=0)
    assert np.allclose(sd[:3], cfg.gyro.turn_on_bias, rtol=0.15)
    assert np.allclose(sd[3:], cfg.accel.turn_on_bias, rtol=0.15)
    scale = np.array([np.diag(ImuNoise(cfg, s).matrices[0]) - 1 for s in range(400)])
    assert np.allclose(scale.std(axis=0), cfg.gyro.scale_factor, rtol=0.15)


def test_saturation_and_quantisation():
    cfg = ImuConfig.preset("bmi088")
    noise = ImuNoise(cfg, 0)
    y, sat = noise.measure(np.array([[20.0, 0.0, 0.0]]), np.array([[0.0, 0.0, G]]))
    assert sat[0, 0] and not sat[0, 1:].any()
    assert y[0, 0] == pytest.approx(cfg.gyro.range)
    steps = y[0, 3:] / cfg.accel.resolution
    assert np.allclose(steps, np.rint(steps), atol=1e-6)


def settled_sim(cfg: ImuConfig, seed: int):
    sim = RoverSim(flat_scenario(mu=1.0))
    imu = Imu(sim, cfg, seed=seed)
    sim.attach_sensor("imu", imu)
    sim.reset(0.0, 0.0, 0.4)
    return sim, imu


def imu_samples(sim: RoverSim) -> np.ndarray:
    """The IMU's samples since the last call, from t = 0 on (the settling's come before)."""
    return np.array([m.data for m in sim.take_messages() if m.sensor == "imu" and m.t >= 0])


def test_ideal_imu_at_rest_reads_gravity_and_the_mems_unit_its_bias():
    sim, imu = settled_sim(ImuConfig.preset("ideal"), 0)
    try:
        pre = [m.t for m in sim.take_messages() if m.sensor == "imu"]
        # sampled while settling (2 s before t = 0), then at t = 0
        n = round(sim.settle_time * 240)
        assert sim.settle_time == 2.0
        assert len(pre) == n and pre[0] == pytest.approx(-(n - 1) / 240) and pre[-1] == 0.0
        sim.rover.command(np.zeros(4), 0.0, 0.0)
        sim.step(2.0)
        s = imu_samples(sim)
        assert len(s) == 480  # 240 Hz, after t = 0
        R_wb = quat_to_matrix(sim.ground_truth().pose[3:])
        up = R_wb.T @ np.array([0.0, 0.0, G])  # the mount frame is the body frame here
        assert np.allclose(s[-240:, 3:6].mean(axis=0), up, atol=2e-3)
        assert np.abs(s[-240:, :3]).max() < 2e-3
        assert not s[:, 6].any()
    finally:
        sim.close()
    cfg = ImuConfig.preset("bmi088")
    sim, imu = settled_sim(cfg, 5)
    try:
        sim.rover.command(np.zeros(4), 0.0, 0.0)
        sim.step(2.0)
        s = imu_samples(sim)[-240:]
        R_wb = quat_to_matrix(sim.ground_truth().pose[3:])
        err = s[:, 3:6].mean(axis=0) - R_wb.T @ np.array([0.0, 0.0, G])
        # within the configured turn-on bias (3 sigma) plus scale and misalignment of 1 g
        bound = 3 * cfg.accel.turn_on_bias + 3 * (cfg.accel.scale_factor + cfg.accel.misalignment) * G
        assert np.all(np.abs(err) <= bound)
        # and it is this episode's bias, to the noise of a one-second mean
        drawn = imu.noise.turn_on[3:] + (imu.noise.matrices[1] - np.eye(3)) @ (R_wb.T @ [0.0, 0.0, G])
        assert np.allclose(err, drawn, atol=5 * cfg.accel.noise_density + 2 * cfg.accel.bias_instability)
    finally:
        sim.close()


def test_gyro_reads_a_steady_turn_within_its_scale_factor_error():
    for name in ("ideal", "bmi088"):
        cfg = ImuConfig.preset(name)
        sim, imu = settled_sim(cfg, 9)
        try:
            g = sim.geometry
            lam = 0.3
            sim.rover.command(g.drive.wheel_speeds(1.0, lam, -lam) / g.wheel_radius, lam, -lam)
            sim.step(4.0)
            imu_samples(sim)
            rates = []
            for _ in range(240):
                sim.step(1 / 240)
                rates.append(sim.ground_truth().twist[2])
            s = imu_samples(sim)
            true = float(np.mean(rates))
            meas = float(s[:, 2].mean())
            print(f"{name}: true yaw rate {true:.4f} rad/s, gyro z {meas:.4f} rad/s")
            assert abs(true) > 0.3
            if name == "ideal":
                assert meas == pytest.approx(true, abs=2e-3)
            else:
                sf = cfg.gyro.scale_factor + cfg.gyro.misalignment
                assert abs(meas - true) <= 3 * sf * abs(true) + 3 * cfg.gyro.turn_on_bias
        finally:
            sim.close()


@pytest.mark.parametrize(
    "change, key",
    [
        (dict(rate_hz=-1.0), "rate_hz"),
        (dict(position=(0.0, math.nan, 0.0)), "position"),
        (dict(gyro=TriadNoise(noise_density=-1e-3)), "gyro.noise_density"),
        (dict(accel=TriadNoise(bias_instability=math.inf)), "accel.bias_instability"),
        (dict(gyro=TriadNoise(range=0.0)), "gyro.range"),
    ],
)
def test_bad_parameters_name_the_key(change, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        dataclasses.replace(ImuConfig(), **change)


def test_config_from_a_mapping_and_bad_mappings():
    cfg = ImuConfig.from_dict({"preset": "tactical", "rate_hz": 120, "gyro": {"noise_density": 1e-5}})
    assert cfg.rate_hz == 120 and cfg.gyro.noise_density == 1e-5
    assert cfg.accel == ImuConfig.preset("tactical").accel
    with pytest.raises(ConfigError, match="unknown keys"):
        ImuConfig.from_dict({"rate": 100})
    with pytest.raises(ConfigError, match="imu preset"):
        ImuConfig.from_dict({"preset": "adxl"})
    with pytest.raises(ConfigError, match=r"imu\.gyro"):
        ImuConfig.from_dict({"gyro": {"noise": 1.0}})
    sim = RoverSim(flat_scenario())
    try:
        with pytest.raises(ConfigError, match="does not divide"):
            Imu(sim, ImuConfig(rate_hz=200.0))
    finally:
        sim.close()


def quat_to_roll_pitch(q) -> tuple[float, float]:
    R = quat_to_matrix(q)
    return math.atan2(R[2, 1], R[2, 2]), -math.asin(R[2, 0])


def drive_circle(imu, seconds: float, env_id: str = "RoverRoughSlippery-v0", seed: int = 3):
    import gymnasium as gym

    import rover_env  # noqa: F401
    from rover_env.sim.simulation import quat_to_yaw

    env = gym.make(env_id, obs_source="estimated", preset="train", imu=imu)
    try:
        obs, info = env.reset(seed=seed)
        first = env.unwrapped.pipeline.estimate()
        yaw0 = info["estimate"]["odometry_pose"][2] - quat_to_yaw(info["ground_truth"]["pose"][3:])
        fields = [f.name for f in env.unwrapped.obs_fields]
        att = [fields.index(n) for n in ("roll", "pitch", "attitude_quality")]
        rows = []  # the observation's roll, pitch and attitude quality, and the true tilt
        for _ in range(int(seconds * 30)):
            obs, _, term, trunc, info = env.step(np.array([0.25, 0.5, -0.5], np.float32))
            assert not (term or trunc)
            rows.append([*obs[att], *info["ground_truth"]["tilt"]])
        est = info["estimate"]["odometry_pose"]
        yaw_err = math.remainder(est[2] - quat_to_yaw(info["ground_truth"]["pose"][3:]) - yaw0, 2 * math.pi)
        tilt = [quat_to_roll_pitch(info[k]["pose"][3:]) for k in ("estimate", "ground_truth")]
        return env.unwrapped.pipeline, first, math.degrees(yaw_err), np.array(rows), np.degrees(tilt)
    finally:
        env.close()


@pytest.mark.slow  # a 40 s drive on rough ground: 50 s
def test_gyro_calibrated_at_standstill_and_heading_held_on_rough_ground():
    base, _, err_none, att_none, _ = drive_circle(None, 15.0)
    pipe, first, err_imu, att_imu, tilt = drive_circle("bmi088", 15.0)
    cfg = pipe.imu.config
    bias, std = first.gyro_bias
    # the standstill before t = 0 gives the episode's turn-on bias to a few hundredths of a degree/s
    assert abs(bias - pipe.imu.noise.turn_on[2]) <= 3 * std + 3e-4
    print(f"gyro bias {bias:.5f} +- {std:.5f} rad/s, turn-on {pipe.imu.noise.turn_on[2]:.5f}")
    assert std < 0.1 * cfg.gyro.turn_on_bias
    assert first.imu_saturated == 0
    print(
        f"15 s circle on rough ground: heading error {err_none:+.2f} deg without IMU, {err_imu:+.2f} deg with"
    )
    assert abs(err_imu) < 0.5 * abs(err_none)
    assert abs(err_imu) < 2.0
    print(f"roll, pitch: estimated {np.round(tilt[0], 2)} deg, true {np.round(tilt[1], 2)} deg")
    assert np.all(np.abs(tilt[0] - tilt[1]) < 1.0)
    # the observation's roll and pitch follow the truth over the drive (it rolls by up to about 6.5 deg);
    # without an IMU they read 0 with attitude quality 0: unknown, not level
    err = np.degrees(np.abs(att_imu[:, :2] - att_imu[:, 3:]))
    print(f"observed roll, pitch: error max {err.max(axis=0)} deg, true |tilt| max "
          f"{np.degrees(np.abs(att_imu[:, 3:]).max(axis=0))} deg")  # fmt: skip
    assert np.degrees(np.abs(att_imu[:, 3:]).max()) > 2.0
    assert err.max() < 1.0 and np.all(att_imu[:, 2] == 1.0)
    assert np.all(att_none[:, :3] == 0.0)


def test_imu_option_errors():
    import gymnasium as gym

    import rover_env  # noqa: F401

    with pytest.raises(ValueError, match="obs_source='estimated'"):
        gym.make("Rover-v0", obs_source="ground_truth", imu="bmi088")
    with pytest.raises(ValueError, match="imu="):
        gym.make("Rover-v0", imu=3)
    with pytest.raises(ConfigError, match="imu preset"):
        gym.make("Rover-v0", imu="mpu6050")


def test_an_imu_in_the_scenario_file(tmp_path):
    import gymnasium as gym
    import yaml

    import rover_env  # noqa: F401
    from rover_env.config.scenario import load_scenario

    shipped = Path(rover_env.__file__).parent / "config" / "scenarios" / "flat_patches.yaml"
    base = yaml.safe_load(shipped.read_text())
    base["imu"] = {"preset": "tactical", "rate_hz": 120}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(base))
    env = gym.make("Rover-v0", scenario=str(tmp_path / "s.yaml"))
    try:
        imu = env.unwrapped.pipeline.imu
        assert imu.config.rate_hz == 120 and imu.config.gyro == ImuConfig.preset("tactical").gyro
    finally:
        env.close()
    base["imu"] = {"preset": "bmi088", "gyro": {"noise_density": -1.0}}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(base))
    with pytest.raises(ConfigError, match=r"imu\.gyro\.noise_density"):
        load_scenario(tmp_path / "bad.yaml")
    base["imu"] = "mpu6050"
    (tmp_path / "bad2.yaml").write_text(yaml.safe_dump(base))
    with pytest.raises(ConfigError, match="imu preset 'mpu6050'"):
        load_scenario(tmp_path / "bad2.yaml")

"""The IMU: its error model against its configured Allan terms, and its truth against the simulator."""

import dataclasses
import math

import numpy as np
import pytest
from conftest import flat_scenario

from perception.allan import allan_deviation, fit_allan
from rover_env.config_io import ConfigError
from rover_env.imu import G, Imu, ImuConfig, ImuNoise, TriadNoise
from rover_env.rover import quat_to_matrix
from rover_env.sim import RoverSim


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
    return np.array([m.data for m in sim.take_messages() if m.sensor == "imu"])


def test_ideal_imu_at_rest_reads_gravity_and_the_mems_unit_its_bias():
    sim, imu = settled_sim(ImuConfig.preset("ideal"), 0)
    try:
        sim.rover.command(np.zeros(4), 0.0, 0.0)
        sim.step(2.0)
        s = imu_samples(sim)
        assert len(s) == 481  # 240 Hz, both ends
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

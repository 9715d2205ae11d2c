"""The simulated sun sensor against the simulator's pose and sun, and the heading it gives in the loop."""

import dataclasses
import math

import numpy as np
import pytest
from conftest import flat_scenario

from rover_env.config.io import ConfigError
from rover_env.config.rig import SensorConfig, standard_rig
from rover_env.config.scenario import StartConfig, SunConfig
from rover_env.config.sun_sensor import SunSensorConfig
from rover_env.envs.rover_env import RoverEnv
from rover_env.sensors.sun_sensor import SunSensor
from rover_env.sim.simulation import RoverSim
from rover_env.sim.transforms import quat_to_yaw


def sim_with_sun(**sun) -> RoverSim:
    scenario = dataclasses.replace(flat_scenario(), sun=SunConfig(**sun))
    return RoverSim(scenario, renderer="tiny")


def test_ideal_reading_is_the_sun_seen_from_the_sensor_frame():
    sim = sim_with_sun(azimuth_deg=30.0, elevation_deg=50.0, azimuth_rate_deg_s=1.0)
    try:
        sensor = SunSensor(sim, SunSensorConfig.preset("ideal"))
        sim.reset(1.0, -2.0, math.radians(40.0))
        sim.step(0.5)
        out = sensor.sample()
        R_ws = sim.base_matrix()[:3, :3] @ sensor.T_body_sensor[:3, :3]
        e = sim.scenario.sun.direction(sim.t)
        assert out[6] == 0.0
        np.testing.assert_allclose(out[3:6], e, atol=1e-12)  # the ephemeris at the reading's time
        np.testing.assert_allclose(R_ws @ out[:3], e, atol=1e-9)
        # the sun 50 deg up at azimuth 30.5 deg, the rover heading 40 deg: 9.5 deg to its right
        level_az = math.degrees(math.atan2(out[1], out[0]))
        assert level_az == pytest.approx(
            30.0 + sim.t - math.degrees(quat_to_yaw(sim.ground_truth().pose[3:])), abs=0.5
        )
    finally:
        sim.close()


def test_fixed_error_has_the_configured_spread():
    sim = sim_with_sun(azimuth_deg=0.0, elevation_deg=60.0)
    try:
        sensor = SunSensor(sim, SunSensorConfig(accuracy_deg=0.5, noise_deg=0.0))
        sim.reset(0.0, 0.0, 0.0)
        truth = sensor.truth()
        angles = []
        for seed in range(400):
            sensor.reset(seed)
            s = sensor.sample()[:3]
            angles.append(math.degrees(math.acos(min(1.0, float(s @ truth)))))
        # a rotation of per-axis spread sigma moves a direction by sigma * sqrt(2) (rms)
        assert math.sqrt(np.mean(np.square(angles))) == pytest.approx(0.5 * math.sqrt(2.0), rel=0.1)
    finally:
        sim.close()


@pytest.mark.parametrize(
    "sun, seen",
    [
        ({"elevation_deg": 15.0}, False),  # 75 deg off its boresight: outside its 70 deg
        ({"elevation_deg": 25.0}, True),
        ({"elevation_deg": 45.0, "clouds": ((0.0, 100.0, 0.3, 0.0),)}, False),  # too dim
        ({"elevation_deg": 45.0, "clouds": ((0.0, 100.0, 0.8, 0.0),)}, True),
    ],
)
def test_no_reading_without_the_sun_in_view(sun, seen):
    sim = sim_with_sun(**sun)
    try:
        sensor = SunSensor(sim)
        sim.reset(0.0, 0.0, 0.0)
        out = sensor.sample()
        assert bool(out[6] == 0.0) == seen
        assert bool(np.all(np.isfinite(out[:3]))) == seen
        assert np.all(np.isfinite(out[3:6]))  # the ephemeris is always there
    finally:
        sim.close()


def test_bad_sun_sensor_settings_name_the_key():
    with pytest.raises(ConfigError, match="fov_deg"):
        SunSensorConfig(fov_deg=0.0)
    with pytest.raises(ConfigError, match=r"sun\.noise_deg"):
        SensorConfig("sun", "sun", sun={"noise_deg": -1.0})
    with pytest.raises(ConfigError, match="unknown keys"):
        SensorConfig("sun", "sun", sun={"fov": 60.0})
    with pytest.raises(ConfigError, match="preset"):
        SensorConfig("sun", "sun", sun="nope")
    with pytest.raises(ConfigError, match="camera"):
        SensorConfig("sun", "sun", camera={"width": 100})
    with pytest.raises(ConfigError, match="sun: sensor .* is of kind imu; give its settings as imu"):
        SensorConfig("imu", "imu", sun="nfss411")


def test_standard_rig_carries_the_sun_sensor_with_the_imu():
    assert [s.kind for s in standard_rig(None)] == ["fisheye", "pinhole"]
    assert [s.kind for s in standard_rig("bmi088")] == ["fisheye", "pinhole", "imu", "sun"]


def test_sun_corrects_a_start_fix_heading_error_in_the_loop():
    # a 3 deg start fix on flat ground at rest; ideal IMU (its tilt exact): the sun brings the
    # dead-reckoned heading to within a few tenths of a degree within two seconds
    scenario = dataclasses.replace(
        flat_scenario(),
        sun=SunConfig(azimuth_deg=120.0, elevation_deg=40.0),
        start=StartConfig(fix_std=(0.0, 3.0)),
    )
    env = RoverEnv(
        scenario=scenario, obs_source="estimated", imu="ideal", renderer="tiny", camera_effects="ideal"
    )
    try:
        assert "sun" in env.rig and env.rig["sun"].kind == "sun"
        for seed in range(20):
            _, info = env.reset(seed=seed)
            fix_error = info["start_fix"][2] - quat_to_yaw(env.sim.ground_truth().pose[3:])
            if abs(fix_error) > math.radians(2.0):
                break
        assert abs(fix_error) > math.radians(2.0)
        for _ in range(60):
            _, _, _, _, info = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        est = env.pipeline.estimator.last_step
        error = est.values["odometry_pose"][2] - quat_to_yaw(env.sim.ground_truth().pose[3:])
        assert est.sun_readings >= 5
        assert abs(math.degrees(error)) < 0.3
        assert est.heading_std < math.radians(0.3)
    finally:
        env.close()

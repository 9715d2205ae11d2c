"""Axle roll, height and steering measured from rendered fisheye images, against the simulator."""

import dataclasses
import math

import numpy as np
from test_fisheye import feasible_states, lifted_sim, set_joints  # noqa: F401  (fixture)

from perception.kinematics.markers import MarkerConfig, assign_markers, measure_axles, segment_magenta
from rover_env.sensors.cameras import FisheyeCamera


def test_markers_in_rendered_images_give_roll_height_and_steering(lifted_sim):  # noqa: F811
    sim = lifted_sim
    g = sim.geometry
    cam = FisheyeCamera(sim)
    model = g.kinematic_model(cam.T_body_cam)
    cfg = MarkerConfig()
    T_cb = np.linalg.inv(model.T_body_cam)
    rng = np.random.default_rng(11)
    errors = []
    for lam, psi, d in feasible_states(g, 30, rng):
        set_joints(sim, lam, psi, d, rng.uniform(-math.pi, math.pi, 4))
        cent, _, _ = segment_magenta(cam.capture().image, cfg)
        depth = -(g.axle_z + np.asarray(d))
        delta = g.ackermann_angles(*lam)
        # the previous frame's state, some way off, predicts where each marker is
        prev = model.marker_positions(np.asarray(psi) * 0.9, depth + 0.004, delta * 0.9)
        pred = {m: cam.model.world2cam(T_cb[:3, :3] @ p + T_cb[:3, 3]) for m, p in prev.items()}
        found = assign_markers(pred, cent, cfg.gate_frac * cam.model.image_size[0])
        assert len(found) == 8
        meas = measure_axles(model, cam.model, {m: cent[j] for m, j in found.items()}, psi, depth)
        errors.append(
            np.r_[
                np.degrees(meas.psi - psi),
                1000 * (meas.depth - depth),
                np.degrees(meas.lam - np.asarray(lam)),
            ]
        )
    mae = np.abs(np.array(errors)).mean(axis=0)
    print(f"roll MAE {mae[:2].round(3)} deg, depth {mae[2:4].round(2)} mm, steering {mae[4:].round(3)} deg")
    assert mae[:2].max() < 0.2 and mae[2:4].max() < 1.0 and mae[4:].max() < 0.5


def test_steering_sweep_calibration_in_the_simulator(tmp_path):
    """The paper's steering calibration, on rendered images, then used on held-out poses."""
    from conftest import flat_scenario
    from test_fisheye import set_joints

    from perception.kinematics.markers import SteeringCalibration
    from rover_env.sim.simulation import RoverSim
    from rover_env.tools.calibrate import write_steering_calibration

    sim = RoverSim(flat_scenario(mu=1.0))
    try:
        sim.reset(2.0, -1.0, 0.4)
        path = write_steering_calibration(tmp_path / "steering.yaml", sim, limit_deg=24.0, steps=17)
        cal = SteeringCalibration.load(path)
        g = sim.geometry
        cam = FisheyeCamera(sim)
        model = g.kinematic_model(cam.T_body_cam)
        cfg = MarkerConfig()
        T_cb = np.linalg.inv(model.T_body_cam)
        errors = []
        for lam in np.radians([-19.0, -7.5, 4.0, 13.0, 21.5]):  # between the swept poses
            set_joints(sim, (lam, -lam), (0.0, 0.0), (0.0, 0.0), (0.0,) * 4)
            cent, _, _ = segment_magenta(cam.capture().image, cfg)
            depth = np.full(2, -g.axle_z)
            delta = g.ackermann_angles(lam, -lam)
            pred = model.marker_positions((0.0, 0.0), depth, delta)
            pix = {m: cam.model.world2cam(T_cb[:3, :3] @ p + T_cb[:3, 3]) for m, p in pred.items()}
            found = assign_markers(pix, cent, cfg.gate_frac * 640)
            meas = measure_axles(model, cam.model, {m: cent[j] for m, j in found.items()}, (0, 0), depth, cal)
            errors.append(np.degrees(meas.lam - [lam, -lam]))
    finally:
        sim.close()
    err = np.abs(np.array(errors))
    print(f"ratio-calibrated steering on held-out poses: MAE {err.mean():.3f} deg, max {err.max():.3f} deg")
    assert err.max() < 0.75


def test_wheel_rates_from_rendered_treads_within_3_percent_rms_at_half_and_two_metres_per_second():
    """A steady turn under a low sun, the estimator on every frame.

    On flat ground: on rough ground the marker noise moves the modelled wheel centres by a few
    tenths of a millimetre between frames, which the treads read as 2-3 % of rotation at
    0.5 m/s (see ``benchmarks/kinematics_table1.py`` for rough ground).
    """
    from conftest import flat_scenario

    from perception.kinematics.fisheye import KinematicStateEstimator
    from rover_env.config.scenario import SunConfig
    from rover_env.sim.simulation import RoverSim

    scenario = dataclasses.replace(flat_scenario(), sun=SunConfig(azimuth_deg=200.0, elevation_deg=35.0))
    for speed in (0.5, 2.0):
        sim = RoverSim(scenario)
        try:
            sim.reset(0.0, 0.0, 0.0)
            g = sim.geometry
            cam = FisheyeCamera(sim)
            est = KinematicStateEstimator(cam.model, g.kinematic_model(cam.T_body_cam))
            lam = math.radians(8.0)
            sim.rover.command(g.drive.wheel_speeds(speed, lam, -lam) / g.wheel_radius, lam, -lam)
            sim.step(1.0)
            errors, valid, last = [], [], None
            for _ in range(16):
                frame = cam.capture()
                gt = sim.ground_truth()
                s = est.update(frame.image, frame.t)
                if last is not None:  # the true rate over the frame interval
                    true = (gt.wheel_angle - last[0]) / (frame.t - last[1])
                    errors.append((s.theta_dot - true) / np.abs(true))
                    valid.append([s.valid[f"theta_{w}"] for w in ("FL", "FR", "RL", "RR")])
                last = (gt.wheel_angle.copy(), frame.t)
                sim.step(cam.period)
        finally:
            sim.close()
        rms = 100 * np.sqrt((np.array(errors[1:]) ** 2).mean(axis=0))  # after the first rotation
        print(f"{speed} m/s: wheel-rate RMS error {rms.round(2)} %, valid {np.mean(valid):.3f}")
        assert rms.max() <= 3.0 and np.mean(valid) >= 0.95

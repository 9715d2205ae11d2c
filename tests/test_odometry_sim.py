"""The odometry paper's shadow ablation in the simulator, on a short stretch of the 5 m arc."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import odometry_shadow_ablation as ablation  # noqa: E402


@pytest.mark.slow
def test_mask_and_ransac_track_the_arc_where_no_robustness_fails(tmp_path):
    camera, frames, poses, planes, shadow, _ = ablation.record(1.5, "full", 30.0, 225.0)
    truth, results = ablation.evaluate(camera, frames, poses, planes)
    a = results["(a) no robustness"]
    c = results["(c) mask + RANSAC + validity gate"]
    print(
        {
            k: (round(v["speed_rms"], 4), round(v["zero_share"], 3), round(v["locked_share"], 2))
            for k, v in results.items()
        }
    )
    assert shadow > 0.15  # the rover's shadow is in view
    assert a["end_error_share"] > 0.2 and a["bad_share"] > 0.5  # fails
    assert c["valid_share"] == 1.0 and c["zero_share"] == 0.0
    assert c["speed_rms"] <= 0.02 * 2.0 and c["yaw_rate_rms"] <= 0.02
    assert c["end_error_share"] <= 0.01
    assert c["locked_share"] < 0.05 < results["(b) RANSAC only"]["locked_share"]  # the mask's doing
    assert ablation.plot(tmp_path, poses[1:, 0], truth, poses, results).stat().st_size > 10_000


def test_downward_camera_pose_calibrated_on_the_checkerboard_scenario():
    """Eq. (9) on rendered images: corners found by cornerSubPix from a deliberately wrong guess."""
    import cv2
    import numpy as np

    from perception.models.calibration import calibrate_ground_camera
    from perception.models.cameras import PinholeCamera
    from rover_env.config.cameras import DownwardCameraConfig
    from rover_env.config.scenario import load_scenario
    from rover_env.sensors.cameras import DownwardCamera
    from rover_env.sim.simulation import RoverSim

    scenario = load_scenario("calibration")
    sim = RoverSim(scenario)
    try:
        sim.reset(0.013, 0.021, 0.3)
        cam = DownwardCamera(sim, DownwardCameraConfig(shadows=False))
        image = cv2.cvtColor(cam.capture().image, cv2.COLOR_RGB2GRAY)
        pos, quat = sim.client.getBasePositionAndOrientation(sim.rover.body_id)
        R_wb = np.array(sim.client.getMatrixFromQuaternion(quat)).reshape(3, 3)
    finally:
        sim.close()
    true = cam.model
    # a mount guess 5 mm and 0.5 deg off, as a tape measure would give
    guess_T = true.T_body_cam.copy()
    guess_T[:3, :3] = guess_T[:3, :3] @ cv2.Rodrigues(np.radians([0.5, -0.4, 0.3]))[0]
    guess_T[:3, 3] += (0.005, -0.004, 0.003)
    guess = PinholeCamera(
        K=true.K, distortion=true.distortion, image_size=true.image_size, T_body_cam=guess_T
    )
    s = scenario.terrain.checker_square
    i, j = np.meshgrid(np.arange(-40, 41), np.arange(-40, 41))
    world = np.column_stack([i.ravel() * s, j.ravel() * s, np.zeros(i.size)])
    body = (world - pos) @ R_wb  # exact: the simulator's pose
    on_ground = np.isfinite(body).all(axis=1)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    current = guess
    for win in (9, 5, 5):  # detect around the predictions, fit, predict again with a tighter window
        T_cb = np.linalg.inv(current.T_body_cam)
        start = current.project(body @ T_cb[:3, :3].T + T_cb[:3, 3])
        inside = on_ground & (start > 15).all(axis=1) & (start[:, 0] < 625) & (start[:, 1] < 465)
        found = cv2.cornerSubPix(
            image, start[inside].astype(np.float32).reshape(-1, 1, 2), (win, win), (-1, -1), crit
        )
        fit = calibrate_ground_camera(current, found.reshape(-1, 2), body[inside])
        current = fit.camera
    got, want = fit.camera.T_body_cam, true.T_body_cam
    angle = np.degrees(np.arccos(np.clip((np.trace(got[:3, :3].T @ want[:3, :3]) - 1) / 2, -1, 1)))
    offset = np.abs(got[:3, 3] - want[:3, 3]).max()
    n = int(fit.inliers.sum())
    print(
        f"calibration: {n} of {len(found)} corners, RMS {fit.rms_px:.3f} px, "
        f"off {1000 * offset:.2f} mm, {angle:.3f} deg"
    )
    assert n > 300 and fit.rms_px < 0.2
    assert offset < 0.002 and angle < 0.05
    # the fitted ground plane is the ground under the parked rover, in the body frame
    a, b, c = fit.camera.ground_plane
    assert abs(c + pos[2] / R_wb[2, 2]) < 0.002 and abs(a) < 0.01 and abs(b) < 0.01


def test_pair_mode_selects_on_the_first_frame_before_the_second_exists():
    import math

    import numpy as np
    from conftest import flat_scenario

    from perception.odometry.flow import FlowOdometry
    from rover_env.config.cameras import DownwardCameraConfig
    from rover_env.sensors.cameras import DownwardCamera
    from rover_env.sim.simulation import RoverSim

    sim = RoverSim(flat_scenario(mu=1.0))
    try:
        sim.reset(0.0, 0.0, 0.2)
        g = sim.geometry
        sim.rover.command(np.full(4, 1.0 / g.wheel_radius), 0.0, 0.0)
        sim.step(1.0)
        cam = DownwardCamera(sim, DownwardCameraConfig.preset("half"))
        odo = FlowOdometry(cam.model)
        selections = []
        prev, curr = sim.capture_pair(cam, on_prev=lambda f: selections.append(odo.select(f.image, f.t)))
        est = odo.track(selections[0], curr.image, curr.t - prev.t, curr.t)
        truth = sim.ground_truth().twist
    finally:
        sim.close()
    assert selections[0].t == prev.t and est.valid
    assert math.hypot(est.v_x - truth[0], est.v_y - truth[1]) < 0.02 * 1.0

"""Examples and the command line, run with small budgets."""

import json
import runpy
from pathlib import Path

import numpy as np
import pytest

from rover_env.tools.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_drive_course_example_makes_progress():
    run = runpy.run_path(str(ROOT / "examples" / "drive_course.py"))["run"]
    out = run(max_steps=150)  # 5 s
    assert out["t"] == 5.0  # exact: whole physics steps
    assert 2.0 < out["progress_m"] < 5.0  # cruise 0.8 m/s after accelerating


def test_rover_demo_writes_video_plots_metrics_and_tum(tmp_path):
    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(
        "name: tiny\n"
        "course: {waypoints: [[2.5, 0.0], [3.5, 1.0]], tolerance: 0.5, speed: 0.8}\n"
        "terrain: {kind: flat, size: [12.0, 12.0], texture: gravel, texture_px: 128}\n"
        "friction: {patches: [{center: [1.5, 0.0], size: [1.0, 2.0], mu: 0.15}]}\n"
        "duration: 12.0\n"
    )
    out = tmp_path / "out"
    assert main(["demo", "--out", str(out), "--scenario", str(scenario)]) == 0
    for name in ("demo.mp4", "slip.png", "metrics.json"):
        assert (out / name).stat().st_size > 300, name
    for run in ("slip_unaware", "slip_aware"):  # both drivers, each with its plots and trajectories
        for name in ("trajectory.png", "velocity_slip.png", "joints.png", "metrics.json", "trajectory.tum"):
            assert (out / run / name).stat().st_size > 300, (run, name)
    data = json.loads((out / "metrics.json").read_text())
    assert set(data["runs"]) == {"slip_unaware", "slip_aware"} and data["seed"] == 0
    metrics, est = data["runs"]["slip_aware"]["metrics"], data["runs"]["slip_aware"]["estimator"]
    assert metrics["success"] is True
    assert 3.0 < metrics["path_length"] < 5.0
    # the demo drives on estimates: their errors against the truth are reported, and small
    assert est["mae_v_x"] < 0.05 and est["mae_steering"] < 0.02
    assert est["position_error_final"] < 0.3
    run = out / "slip_aware"
    tum, tum_est = np.loadtxt(run / "trajectory.tum"), np.loadtxt(run / "estimate.tum")
    assert tum.shape[1] == tum_est.shape[1] == 8 and len(tum) == len(tum_est)
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-6)
    assert np.abs(tum[-1, 1:3] - tum_est[-1, 1:3]).max() < 0.3
    assert abs(tum[0, 3] - tum_est[0, 3]) < 0.01  # one z convention: the body origin's height
    # units beside every key, counts as integers, and no F1 without events
    sub = json.loads((run / "metrics.json").read_text())
    assert sub["units"]["metrics"]["energy"] == "J" and sub["units"]["estimator"]["mae_v_x"] == "m/s"
    assert set(sub["units"]["estimator"]) == set(sub["estimator"])
    assert isinstance(sub["estimator"]["slip_events"], int)
    if sub["estimator"]["slip_events"] == 0 and sub["estimator"]["slip_events_false"] == 0:
        assert sub["estimator"]["slip_f1"] is None and sub["estimator"]["slip_precision"] is None
    import av

    from rover_env.tools.video import overlay_box

    with av.open(str(out / "demo.mp4")) as container:  # H.264, as browsers play it
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
    frame = frames[len(frames) // 2]
    # both runs one above the other, each under a 22 px label: chase view + both cameras
    assert frame.shape == (2 * (480 + 22), 960, 3) and frame.std() > 5
    # the overlay: white text on a dark band at the top left of each run, and the time in it changes
    x0, y0, x1, y1 = overlay_box(5)
    y0, y1 = y0 + 22, y1 + 22
    band = frame[y0:y1, x0:x1].max(axis=2)
    assert np.median(band) < 90 and (band > 200).sum() > 300
    assert np.abs(frames[5][y0:y1, x0:x1].astype(int) - frames[-5][y0:y1, x0:x1]).max() > 100


def test_cli_reports_bad_scenario(capsys):
    assert main(["demo", "--out", "/tmp/never", "--scenario", "no_such_preset"]) == 2
    assert "unknown scenario preset" in capsys.readouterr().err


def test_camera_bench_rows_and_table():
    from rover_env.tools.bench import bench_cameras, format_camera_table

    rows = bench_cameras("flat_patches", presets=("train",), frames=1, renderers=("tiny",))
    assert [(r.camera, r.shadows) for r in rows] == [
        ("downward", True),
        ("fisheye", True),
        ("downward", False),
        ("fisheye", False),
    ]
    fish = rows[1]
    assert fish.face_pixels > 160 * 120 and 0 < fish.ms_remap < fish.ms_per_frame
    table = format_camera_table(rows)
    assert table.count("\n") == 5 and "| fisheye | train | tiny | on |" in table


def test_rover_odometry_cli_on_a_folder_of_images(tmp_path):
    from test_odometry import make_ground, mast_camera, write_arc_images

    ground = make_ground()
    write_arc_images(tmp_path / "imgs", ground, (0.8, 0.0, 0.2), 8, 1 / 30)
    calib = mast_camera().save(tmp_path / "calib.yaml")
    out = tmp_path / "out"
    code = main(["odometry", str(tmp_path / "imgs"), "--calib", str(calib), "--fps", "30", "--out", str(out)])
    assert code == 0
    rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(rows) == 7 and rows["valid"].all()
    np.testing.assert_allclose(rows["v_x"], 0.8, rtol=0.01)
    assert np.loadtxt(out / "trajectory.tum").shape == (8, 8)
    # with an IMU mounted turned 90 deg about z (its z still the body's): the gyro's yaw too
    t = np.arange(-1.0, 7 / 30 + 1e-9, 1 / 240)
    lines = ["t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"]
    lines += [f"{ti:.6f},0,0,{0.2 * (ti > 0) + 0.01:.6f},0,0,9.81" for ti in t]
    (tmp_path / "imu.csv").write_text("\n".join(lines) + "\n")
    args = ["--imu", str(tmp_path / "imu.csv"), "--imu-rpy", "0", "0", "90", "--imu-still", "1"]
    out2 = tmp_path / "out2"
    assert (
        main(
            [
                "odometry",
                str(tmp_path / "imgs"),
                "--calib",
                str(calib),
                "--fps",
                "30",
                "--out",
                str(out2),
                *args,
            ]
        )
        == 0
    )
    rows = np.genfromtxt(out2 / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    np.testing.assert_allclose(rows["omega_imu"], 0.2, atol=1e-5)
    assert np.loadtxt(out2 / "trajectory_imu.tum").shape == (8, 8)
    # errors are reported, not raised
    assert (
        main(["odometry", str(tmp_path / "nowhere"), "--calib", str(calib), "--fps", "30", "--out", str(out)])
        == 2
    )


def test_rover_kinematics_cli_on_a_folder_of_fisheye_images(tmp_path, capsys):
    import csv
    import math

    import cv2
    from test_markers import fisheye, render_markers, rover_model

    model = rover_model()
    cam = fisheye(model)
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    psis = [(0.02 * k, -0.01 * k) for k in range(4)]
    for k, psi in enumerate(psis):
        rgb = render_markers(model, cam, psi, (0.15, 0.15), model.wheel_angles(0.1, -0.1))
        cv2.imwrite(str(imgs / f"f{k:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    (imgs / "f004.png").write_bytes(b"not an image")
    cam_yaml, rover_yaml = cam.save(tmp_path / "omni.yaml"), model.save(tmp_path / "rover.yaml")
    out = tmp_path / "out"
    args = ["kinematics", str(imgs), "--camera", str(cam_yaml), "--rover", str(rover_yaml), "--fps", "30"]
    assert main([*args, "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "kinematics.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(rows) == 5
    np.testing.assert_allclose(rows["psi_F"][:4], [p[0] for p in psis], atol=math.radians(0.2))
    np.testing.assert_allclose(rows["psi_R"][:4], [p[1] for p in psis], atol=math.radians(0.2))
    assert rows["valid_psi_F"][:4].all() and not rows["valid_psi_F"][4]
    assert "not a readable image" in rows["note"][4] and np.isfinite(rows["psi_F"][4])
    with open(out / "kinematics.csv", newline="") as fh:
        assert list(csv.DictReader(fh))[4]["sinkage_FL"] == ""  # no image: no sinkage
    # a malformed geometry file: the error names the key, nothing is raised
    (tmp_path / "bad.yaml").write_text(rover_yaml.read_text().replace("wheel_radius", "wheel_radiu"))
    args[args.index(str(rover_yaml))] = str(tmp_path / "bad.yaml")
    assert main([*args, "--out", str(out)]) == 2
    assert "wheel_radiu" in capsys.readouterr().err


def test_rover_kinematics_cli_writes_each_wheels_sinkage(tmp_path):
    """Images ray-cast with the wheels 25 mm deep in soil, then on rigid ground: 25 mm, then 0 in the CSV.

    The sinkage is the track over the last 0.8 s of frames: none on the first frame alone.
    """
    import cv2
    from test_markers import fisheye, render_markers, rover_model
    from test_sinkage import cast

    model = rover_model()
    cam = fisheye(model)
    imgs = tmp_path / "imgs"
    imgs.mkdir()
    depth = (model.nominal_depth, model.nominal_depth)
    for k, z in enumerate([0.025] * 4 + [0.0] * 10):
        soil = cast(model, cam, z, seed=k)
        rgb = render_markers(model, cam, (0.0, 0.0), depth, np.zeros(4), background=soil)
        cv2.imwrite(str(imgs / f"f{k:03d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cam_yaml, rover_yaml = cam.save(tmp_path / "omni.yaml"), model.save(tmp_path / "rover.yaml")
    out = tmp_path / "out"
    args = ["kinematics", str(imgs), "--camera", str(cam_yaml), "--rover", str(rover_yaml), "--fps", "10"]
    assert main([*args, "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "kinematics.csv", delimiter=",", names=True, dtype=None, encoding=None)
    sink = np.stack([rows[f"sinkage_{w}"] for w in ("FL", "FR", "RL", "RR")], -1)
    assert np.all(np.isnan(sink[0])) and rows["sinkage_quality"][0] == 0.0
    np.testing.assert_allclose(sink[1:4], 0.025, atol=0.002)
    np.testing.assert_allclose(sink[-5:], 0.0, atol=0.002)  # rigid ground: the faces reach the rims
    assert np.all(rows["sinkage_quality"][1:] >= 0.5)


def test_every_option_has_help_without_markup_and_pybullet_prints_no_banner():
    import subprocess
    import sys

    from rover_env.tools.cli import build_parser

    parser = build_parser()
    for name, sub in parser._subparsers._group_actions[0].choices.items():
        text = sub.format_help()
        assert "``" not in text and ":class:" not in text, name
        for action in sub._actions:
            assert action.help, (name, action.dest)
    helps = {
        n: " ".join(s.format_help().split()) for n, s in parser._subparsers._group_actions[0].choices.items()
    }
    assert "(default: 0-2)" in helps["eval"] and "(default: slope_loose)" in helps["demo"]
    code = "import gymnasium as gym, rover_env; gym.make('Rover-v0', obs_source='ground_truth').reset(seed=0)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "pybullet build time" not in out.stdout + out.stderr and "argv[0]" not in out.stdout + out.stderr


@pytest.mark.slow  # a second demo run: 14 s
def test_rover_demo_logs_both_runs_to_rerun(tmp_path):
    pytest.importorskip("rerun", reason="the rerun extra is not installed: pip install 'rover-vision[rerun]'")
    import subprocess
    import sys

    scenario = tmp_path / "tiny.yaml"
    scenario.write_text(
        "name: tiny\ncourse: {waypoints: [[1.5, 0.0]], tolerance: 0.5, speed: 0.8}\n"
        "terrain: {kind: flat, size: [12.0, 12.0], texture: gravel, texture_px: 128}\nduration: 6.0\n"
    )
    rrd = tmp_path / "out" / "mission.rrd"
    argv = [
        "demo",
        "--out",
        str(tmp_path / "out"),
        "--scenario",
        str(scenario),
        "--no-video",
        "--rerun",
        str(rrd),
    ]
    assert main(argv) == 0
    dump = subprocess.run(
        [sys.executable, "-m", "rerun", "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120
    )
    assert dump.returncode == 0, dump.stderr
    for run in ("slip_unaware", "slip_aware"):
        for entity in ("cameras/downward", "cameras/fisheye", "world/truth_path", "world/estimate_path",
                       "twist/v_x/estimate", "slip/FL/truth", "joints/steering_F/estimate"):  # fmt: skip
            assert f"/{run}/{entity}" in dump.stdout, (run, entity)


def test_rover_odometry_cli_on_a_folder_of_fisheye_images(tmp_path, capsys):
    from dataclasses import replace

    from test_fisheye_odometry import ROVER_PLANE, _fisheye_folder

    cam, folder = _fisheye_folder(tmp_path, twist=(0.3, 0.05, -0.1))
    calib = replace(cam, ground_plane=ROVER_PLANE).save(tmp_path / "omni.yaml")
    out = tmp_path / "out"
    code = main(["odometry", str(folder), "--camera", str(calib), "--fps", "30", "--out", str(out)])
    assert code == 0
    rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert len(rows) == 7 and rows["valid"].all()
    np.testing.assert_allclose(rows["v_x"], 0.3, atol=0.015)
    np.testing.assert_allclose(rows["omega"], -0.1, atol=0.015)
    assert (out / "trajectory.tum").is_file() and (out / "odometry.mcap").is_file()
    # a fisheye calibration without its ground plane: one line that says how to measure it
    cam.save(tmp_path / "bare.yaml")
    code = main(
        [
            "odometry",
            str(folder),
            "--camera",
            str(tmp_path / "bare.yaml"),
            "--fps",
            "30",
            "--out",
            str(tmp_path / "o2"),
        ]
    )
    err = capsys.readouterr().err
    assert code != 0 and "ground_plane: not set" in err and "measure" in err
    assert not (tmp_path / "o2").exists()


def test_rover_odometry_cli_says_which_option_takes_a_fisheye_calibration(tmp_path, capsys):
    from test_fisheye_odometry import _rover_fisheye

    calib = _rover_fisheye().save(tmp_path / "omni.yaml")
    (tmp_path / "imgs").mkdir()
    code = main(
        [
            "odometry",
            str(tmp_path / "imgs"),
            "--calib",
            str(calib),
            "--fps",
            "30",
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert code != 0 and "give it as --camera" in capsys.readouterr().err

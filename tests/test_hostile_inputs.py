"""Hostile and careless input: each case gets a one-line error naming the input, or a flagged
result, never a traceback, a silently wrong answer or lost work."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rover_env.tools.cli import build_parser


def _cli_error(capsys, argv: list[str]) -> str:
    """The one-line error argparse prints for ``argv`` (exit status 2)."""
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "error:" in ln]
    assert len(lines) == 1
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["eval", "--out", "o", "--seeds", "5-2"], ["--seeds", "'5-2'", "empty range"]),
        (["eval", "--out", "o", "--seeds", "0-100000000"], ["--seeds", "100000001 seeds", "10000"]),
        (["eval", "--out", "o", "--seeds", "x"], ["--seeds", "N or N-M"]),
        (["eval", "--out", "o", "--workers", "0"], ["--workers", "from 1 to"]),
        (["eval", "--out", "o", "--workers", "1000"], ["--workers", "1000"]),
        (["train", "--out", "o", "--eval-every", "0"], ["--eval-every", ">= 1"]),
        (["train", "--out", "o", "--eval-every", "-5"], ["--eval-every", ">= 1"]),
        (["train", "--out", "o", "--steps", "0"], ["--steps"]),
        (["train", "--out", "o", "--reward", "foo=1"], ["--reward", "'foo'", "slip"]),
        (["train", "--out", "o", "--reward", "slip=nan"], ["--reward", "0 to 1e6"]),
        (["train", "--out", "o", "--reward", "slip"], ["--reward", "TERM=NUMBER"]),
        (["bench", "--steps", "0"], ["--steps", "from 1"]),
        (["demo", "--out", "o", "--seed", "-1"], ["--seed", "from 0"]),
        (["odometry", "imgs", "--calib", "c.yaml", "--out", "o", "--fps", "1e300"], ["--fps", "1e300"]),
        (["odometry", "imgs", "--calib", "c.yaml", "--out", "o", "--fps", "0"], ["--fps", "above 0"]),
        (["kinematics", "imgs", "--camera", "c", "--rover", "r", "--out", "o", "--fps", "nan"], ["--fps"]),
    ],
)
def test_cli_rejects_out_of_range_arguments(capsys, argv, names):
    msg = _cli_error(capsys, argv)
    for name in names:
        assert name in msg, msg


def test_cli_accepts_the_edges():
    p = build_parser()
    assert p.parse_args(["eval", "--out", "o", "--seeds", "3-3", "7"]).seeds == [[3], [7]]
    assert p.parse_args(["eval", "--out", "o", "--seeds", "0-9999"]).seeds[0][-1] == 9999
    assert p.parse_args(["train", "--out", "o", "--reward", "slip=5", "time=0"]).reward == [
        ("slip", 5.0),
        ("time", 0.0),
    ]
    assert p.parse_args(["eval", "--out", "o", "--workers", "1"]).workers == 1


# ---------------------------------------------------------------- estimators


def _textured(size=(160, 120), seed=0):
    import cv2

    rng = np.random.default_rng(seed)
    w, h = size
    img = cv2.GaussianBlur(rng.normal(0, 1, (h, w)).astype(np.float32), (0, 0), 2.0)
    return np.clip(128 + 40 * img / img.std(), 0, 255).astype(np.uint8)


def _odometry(**cfg):
    from test_odometry import mast_camera

    from perception.odometry.flow import FlowOdometry, FlowOdometryConfig

    return FlowOdometry(mast_camera((160, 120)), FlowOdometryConfig.for_camera(160, 30.0, **cfg))


def test_a_frozen_camera_is_no_motion_observable_not_a_confident_zero():
    img = _textured()
    odo = _odometry()
    assert odo.update(img, 0.0) is None
    est = odo.update(img.copy(), 1 / 30)
    assert not est.valid and "no motion observable" in est.reason
    assert np.isnan(est.v_x) and est.quality == 0.0
    # a frame that moved is tracked again
    moved = np.roll(img, 2, axis=0)
    assert odo.update(moved, 2 / 30).valid
    # a noise-free simulated camera says a repeat is a standstill: a valid zero
    still = _odometry(repeated_frames="still")
    still.update(img, 0.0)
    est = still.update(img.copy(), 1 / 30)
    assert est.valid and abs(est.v_x) < 1e-9 and abs(est.v_y) < 1e-9
    with pytest.raises(ValueError, match="repeated_frames"):
        _odometry(repeated_frames="maybe")


def test_the_kinematics_estimator_refuses_a_non_finite_or_backward_time():
    from test_markers import fisheye, rover_model

    from perception.kinematics.fisheye import KinematicStateEstimator

    model = rover_model()
    est = KinematicStateEstimator(fisheye(model), model)
    frame = np.zeros((480, 640, 3), np.uint8)
    for bad in (math.inf, -math.inf, math.nan):
        with pytest.raises(ValueError, match="finite"):
            est.update(frame, bad)
    s = est.update(frame, 0.0)
    assert not any(s.valid.values())  # a black frame: nothing measured
    with pytest.raises(ValueError, match="increasing"):
        est.update(frame, 0.0)
    assert not any(est.update(frame, 0.1).valid.values())


def test_the_slip_filter_validates_odometry_noise_and_leaves_out_impossible_readings():
    from perception.fusion.slip import SlipEstimator

    xy = np.array([[0.4, 0.3], [0.4, -0.3], [-0.4, 0.3], [-0.4, -0.3]])
    f = SlipEstimator(xy, 0.115)
    with pytest.raises(ValueError, match="not a covariance"):
        f.add_odometry(0.1, (1.0, 0.0, 0.0), 1 / 30, cov=-np.eye(3))
    with pytest.raises(ValueError, match="not a covariance"):
        f.add_odometry(0.1, (1.0, 0.0, 0.0), 1 / 30, cov=[[1e-4, 1.0, 0], [0, 1e-4, 0], [0, 0, 1e-4]])
    with pytest.raises(ValueError, match="quality"):
        f.add_odometry(0.1, (1.0, 0.0, 0.0), 1 / 30, quality=1e9)
    for k in range(1, 11):  # 1 m/s, wheels rolling
        t = k / 30
        f.add_odometry(t, (1.0, 0.0, 0.0), 1 / 30, 1.0)
        f.add_wheels(t, np.full(4, 1.0 / 0.115), 1 / 30)
    f.add_odometry(11 / 30, (1e300, 0.0, 0.0), 1 / 30, 1.0)
    f.add_wheels(11 / 30, np.array([1e300, 8.7, 8.7, 8.7]), 1 / 30)
    est = f.estimate(11 / 30)
    assert f.rejected == 2
    assert np.all(np.isfinite(est.twist)) and est.twist[0] == pytest.approx(1.0, abs=0.02)
    assert np.all(np.isfinite(est.wheel_rate)) and est.wheel_rate[0] == pytest.approx(8.7, abs=0.1)


def test_16_bit_images_are_scaled_by_the_logs_bit_depth_so_a_glint_costs_nothing(tmp_path):
    import cv2
    from test_odometry import START, make_ground, mast_camera, pose_after, render

    from perception.logs.offline import bit_depth, run_folder_odometry

    ground = make_ground()
    folder = tmp_path / "imgs"
    folder.mkdir()
    twist, fps, n = (1.0, 0.0, 0.0), 60.0, 10
    pose = START
    for k in range(n):
        if k:
            pose = pose_after(pose, twist, 1 / fps)
        img = (
            render(mast_camera(), ground, pose, rng=np.random.default_rng(k)).astype(np.uint16) * 16
        )  # 12 bits
        if k % 3 == 1:
            img[5, 5] = 65535  # a glint: one saturated pixel at the container's top
        cv2.imwrite(str(folder / f"f{k:02d}.png"), img)
    assert bit_depth(cv2.imread(str(folder / "f00.png"), cv2.IMREAD_UNCHANGED)) == 12
    calib = mast_camera().save(tmp_path / "calib.yaml")
    res = run_folder_odometry(folder, calib, fps, tmp_path / "out")
    rows = np.genfromtxt(res.csv_path, delimiter=",", names=True, dtype=None, encoding=None)
    assert res.valid == n - 1
    np.testing.assert_allclose(rows["v_x"], twist[0], rtol=0.02)
    with pytest.raises(ValueError, match="float32"):
        bit_depth(np.zeros((4, 4), np.float32))


# ---------------------------------------------------------------- environment


@pytest.mark.parametrize(
    "options",
    [
        {"blackout": 5},
        {"blackout": "1-2"},
        {"blackout": [(1.0,)]},
        {"blackout": [(2.0, 1.0)]},
        {"blackout": [("a", "b")]},
        {"blackout": [(0.0, math.inf)]},
        {"fault": 1},
        ["blackout"],
    ],
)
def test_a_bad_reset_option_is_refused_before_anything_moves_and_the_episode_goes_on(options):
    import gymnasium as gym

    import rover_env  # noqa: F401

    env = gym.make("Rover-v0", obs_source="estimated")
    try:
        env.reset(seed=3)
        for _ in range(3):
            env.step(np.array([0.5, 0.0, 0.0], np.float32))
        sim = env.unwrapped.sim
        before, t = sim.ground_truth().pose.copy(), sim.t
        with pytest.raises(ValueError, match="blackout|options"):
            env.reset(seed=4, options=options)
        assert sim.t == t
        np.testing.assert_array_equal(sim.ground_truth().pose, before)
        _, _, term, trunc, info = env.step(np.array([0.5, 0.0, 0.0], np.float32))
        assert info["t"] > t and not term
        env.reset(seed=4, options={"blackout": [(0.5, 1.0)]})  # a good one works after it
    finally:
        env.close()


# ---------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    ("size", "cell", "points"), [((80.0, 80.0), 0.02, "16,008,001"), ((500.0, 500.0), 0.1, "25,010,001")]
)
def test_a_heightfield_beyond_the_memory_budget_is_refused_with_the_numbers(size, cell, points):
    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import MAX_HEIGHTFIELD_POINTS, TerrainConfig

    with pytest.raises(ConfigError, match=points) as exc:
        TerrainConfig(kind="rough", size=size, cell=cell, roughness=0.03, wavelength=1.0)
    assert f"{MAX_HEIGHTFIELD_POINTS:,}" in str(exc.value) and "cell" in str(exc.value)
    ok = TerrainConfig(kind="rough", size=(20.0, 20.0), cell=0.02, roughness=0.03, wavelength=1.0)
    assert ok.grid_points == MAX_HEIGHTFIELD_POINTS  # the budget's edge is accepted


def test_yaml_that_is_not_utf8_or_mixes_key_types_names_the_file(tmp_path):
    from perception.models.calib_io import CalibrationError, read_mapping
    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import load_scenario

    latin = tmp_path / "latin1.yaml"
    latin.write_bytes("name: caf\xe9\ncourse: {waypoints: [[5, 0]]}\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=r"latin1\.yaml: not UTF-8"):
        load_scenario(latin)
    with pytest.raises(CalibrationError, match=r"latin1\.yaml: not UTF-8"):
        read_mapping(latin, {"K"}, set())
    mixed = tmp_path / "mixed.yaml"
    mixed.write_text("name: x\n1: 2\nzz: 3\ncourse: {waypoints: [[5, 0]]}\n")
    with pytest.raises(ConfigError, match=r"mixed\.yaml: unknown key '1'"):
        load_scenario(mixed)
    with pytest.raises(CalibrationError, match=r"mixed\.yaml: unknown key 1"):
        read_mapping(mixed, {"name", "course"}, set())


@pytest.mark.parametrize("hz", [0, -30, math.nan, math.inf, "30"])
def test_a_control_rate_that_is_not_a_positive_rate_is_refused(hz):
    from rover_env.envs.rover_env import RoverEnv

    with pytest.raises(ValueError, match="control_hz"):
        RoverEnv(control_hz=hz)


@pytest.mark.parametrize("n", [-1, 0, 10**9, 2.5, True])
def test_solver_iterations_out_of_range_are_refused_before_a_simulation_is_built(n):
    from conftest import flat_scenario

    from rover_env.sim.simulation import RoverSim

    with pytest.raises(ValueError, match="solver_iterations"):
        RoverSim(flat_scenario(), solver_iterations=n)


def test_a_rover_geometry_with_an_impossible_marker_arc_is_refused(tmp_path):
    from test_markers import rover_model

    from perception.models.calib_io import CalibrationError
    from perception.models.rover import RoverKinematicModel

    text = rover_model().save(tmp_path / "rover.yaml").read_text()
    for bad in (".inf", ".nan", "-0.2", "4.0"):
        lines = [
            f"correction_marker_arc: {bad}" if ln.startswith("correction_marker_arc") else ln
            for ln in text.splitlines()
        ]
        (tmp_path / "bad.yaml").write_text("\n".join(lines) + "\n")
        with pytest.raises(CalibrationError, match=r"bad\.yaml: correction_marker_arc"):
            RoverKinematicModel.load(tmp_path / "bad.yaml")


# ---------------------------------------------------------------- policy folders


@pytest.fixture
def policy_copy(tmp_path):
    import shutil

    from controllers.rl import shipped_policy

    return shutil.copytree(shipped_policy(), tmp_path / "policy")


def _drive_env():
    import gymnasium as gym

    import rover_env  # noqa: F401

    return gym.make("Rover-v0", obs_source="ground_truth", action_mode="wheels")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda m: m | {"algo": "dqn"}, "algo 'dqn'"),
        (lambda m: {k: v for k, v in m.items() if k != "obs_fields"}, "missing obs_fields"),
        (lambda m: m | {"residual": [0.5, "x", 0.3]}, "residual"),
        (lambda m: [m], "JSON object"),
    ],
)
def test_a_malformed_policy_json_names_the_file_and_the_key(policy_copy, edit, message):
    import json

    from controllers.rl import PolicyController

    meta = json.loads((policy_copy / "policy.json").read_text())
    (policy_copy / "policy.json").write_text(json.dumps(edit(meta)))
    env = _drive_env()
    try:
        with pytest.raises(ValueError, match=message) as exc:
            PolicyController(policy_copy, env)
        assert "policy.json" in str(exc.value)
    finally:
        env.close()


def test_policy_folders_load_without_unpickling_and_garbage_statistics_are_named(
    policy_copy, caplog, monkeypatch
):
    import pickle

    import cloudpickle

    from controllers.rl import PolicyController

    def refuse(*_a, **_k):
        raise AssertionError("unpickled")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(cloudpickle, "loads", refuse)
    import stable_baselines3.common.save_util as su

    monkeypatch.setattr(su.cloudpickle, "loads", refuse)
    env = _drive_env()
    try:
        ctrl = PolicyController(policy_copy, env)  # nothing unpickled
        obs, _ = env.reset(seed=0)
        assert np.all(np.isfinite(ctrl.act(obs)))
        assert any("outside" in r.message or "trust" in r.message for r in caplog.records)
        monkeypatch.undo()
        (policy_copy / "obs_stats.npz").write_bytes(b"garbage")
        with pytest.raises(ValueError, match=r"obs_stats\.npz: not observation statistics"):
            PolicyController(policy_copy, env)
        (policy_copy / "obs_stats.npz").unlink()
        (policy_copy / "vecnormalize.pkl").write_bytes(b"\x80\x04garbage")
        with pytest.raises(ValueError, match=r"vecnormalize\.pkl: not a VecNormalize"):
            PolicyController(policy_copy, env)
    finally:
        env.close()


# ---------------------------------------------------------------- calibration geometry


def test_a_calibration_that_cannot_see_the_ground_is_refused_at_load_and_per_estimate(tmp_path):
    import yaml
    from test_odometry import mast_camera

    from perception.models.calib_io import CalibrationError
    from perception.models.cameras import PinholeCamera

    good = mast_camera((160, 120)).save(tmp_path / "calib.yaml")
    data = yaml.safe_load(good.read_text())
    above = dict(data, ground_plane=[0.0, 0.0, 0.9])  # the ground 0.37 m above the camera
    (tmp_path / "above.yaml").write_text(yaml.safe_dump(above))
    with pytest.raises(CalibrationError, match="below the ground plane"):
        PinholeCamera.load(tmp_path / "above.yaml")
    up = np.array(data["T_body_cam"])
    up[:3, :3] = up[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # turned over: looking at the sky
    (tmp_path / "up.yaml").write_text(yaml.safe_dump(dict(data, T_body_cam=up.tolist())))
    with pytest.raises(CalibrationError, match="optical axis"):
        PinholeCamera.load(tmp_path / "up.yaml")
    # per estimate: a wheels' plane above the camera makes the pair invalid, not a wrong speed
    odo = _odometry()
    img = _textured()
    odo.update(img, 0.0, ground_plane=(0.0, 0.0, -0.265))
    est = odo.update(np.roll(img, 2, axis=0), 1 / 30, ground_plane=(0.0, 0.0, 0.9))
    assert not est.valid and "not in view in this frame" in est.reason
    est = odo.update(np.roll(img, 4, axis=0), 2 / 30, ground_plane=(0.0, 0.0, -0.265))
    assert not est.valid and "not in view in the last frame" in est.reason
    assert odo.update(np.roll(img, 6, axis=0), 3 / 30, ground_plane=(0.0, 0.0, -0.265)).valid


# ---------------------------------------------------------------- rover eval and output folders


def _fake_run_job(calls, stop_after=None):
    """A stand-in for one mission run (this tests the sweep's bookkeeping, not the missions)."""

    def run(job):
        if stop_after is not None and len(calls) == stop_after:
            raise KeyboardInterrupt
        calls.append(job.name)
        return {
            "controller": job.controller, "mission": job.mission, "seed": job.seed, "preset": job.preset,
            "obs_source": "ground_truth", "estimator": "none", "camera_effects": "none", "randomize": "off",
            "success": True, "termination": "success", "time": 10.0 + job.seed,
        }  # fmt: skip

    return run


def test_rover_eval_checks_every_input_first_reports_what_finished_and_resumes(tmp_path, monkeypatch, capsys):
    import json

    import rover_env.tools.evaluation as ev
    from rover_env.tools.cli import main

    out = tmp_path / "eval"
    base = ["eval", "--controllers", "slip_aware@ground_truth", "--workers", "1", "--out", str(out)]
    # a bad mission after a good one: refused before anything runs or is written
    assert main([*base, "--missions", "Rover-v0", "no_such_mission", "--seeds", "0-2"]) == 2
    assert "no_such_mission" in capsys.readouterr().err and not out.exists()
    # Ctrl-C after two of four runs: their report is written, the rest --resume runs
    calls = []
    monkeypatch.setattr(ev, "run_job", _fake_run_job(calls, stop_after=2))
    argv = [*base, "--missions", "Rover-v0", "--seeds", "0-3"]
    assert main(argv) == 130
    assert "--resume" in capsys.readouterr().err
    assert len(json.loads((out / "results.json").read_text())) == 2
    assert "partial: 2 of 4" in (out / "report.md").read_text()
    # the same command again would replace those results: refused without --resume or --overwrite
    assert main(argv) == 2
    assert "--overwrite" in capsys.readouterr().err
    monkeypatch.setattr(ev, "run_job", _fake_run_job(calls))
    assert main([*argv, "--resume"]) == 0
    assert len(calls) == 4  # two before the interruption, two resumed
    rows = json.loads((out / "results.json").read_text())
    assert sorted(r["seed"] for r in rows) == [0, 1, 2, 3]
    assert main([*argv, "--overwrite"]) == 0 and len(calls) == 8  # all four again


def test_output_folders_are_checked_before_work_and_never_silently_replaced(tmp_path, capsys):
    from rover_env.tools.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["demo", "--out", str(blocker), "--no-video"]) == 2
    assert "not a folder" in capsys.readouterr().err
    done = tmp_path / "done"
    done.mkdir()
    (done / "metrics.json").write_text("{}")
    assert main(["demo", "--out", str(done), "--no-video"]) == 2
    err = capsys.readouterr().err
    assert "metrics.json" in err and "--overwrite" in err
    # an unwritable folder (a read-only mount; root ignores file modes, so the check is faked)
    import tempfile

    def refuse(*_a, **_k):
        raise PermissionError(13, "Permission denied")

    real = tempfile.NamedTemporaryFile
    tempfile.NamedTemporaryFile = refuse
    try:
        assert main(["demo", "--out", str(tmp_path / "ro"), "--no-video"]) == 2
    finally:
        tempfile.NamedTemporaryFile = real
    assert "cannot write there (Permission denied)" in capsys.readouterr().err


def test_an_image_bomb_is_refused_from_its_header_before_decoding(tmp_path):
    import struct
    import zlib

    from perception.models.validation import MAX_IMAGE_PIXELS, image_file_size
    from rover_env.config.io import ConfigError
    from rover_env.sim.textures import read_texture

    def png_header(w, h):  # a valid PNG signature and IHDR claiming w x h, no pixel data
        ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
        chunk = b"IHDR" + ihdr
        head = b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))
        return head + struct.pack(">I", 0) + b"IEND" + struct.pack(">I", zlib.crc32(b"IEND"))

    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png_header(100_000, 100_000))
    assert bomb.stat().st_size < 100
    with pytest.raises(ValueError, match="bomb.png: .*pixel budget"):
        image_file_size(bomb)
    bomb.write_bytes(png_header(9000, 9000))  # 81 Mpx: within Pillow's limit, beyond ours
    with pytest.raises(ValueError, match="9000 x 9000 px"):
        image_file_size(bomb)
    with pytest.raises(ConfigError, match="terrain.texture: .*bomb.png.*budget"):
        read_texture(bomb)
    assert image_file_size(tmp_path / "bomb.png", max_pixels=10**8) == (9000, 9000)
    (tmp_path / "text.png").write_text("not an image")
    assert image_file_size(tmp_path / "text.png") is None
    assert MAX_IMAGE_PIXELS >= 8192 * 8192  # a texture at texture_px's limit fits


# ---------------------------------------------------------------- textures and geometry


def test_a_texture_file_that_is_not_an_image_is_a_config_error(tmp_path):
    import dataclasses

    from conftest import flat_scenario

    from rover_env.config.io import ConfigError
    from rover_env.sim.simulation import RoverSim

    bad = tmp_path / "ground.png"
    bad.write_text("not an image")
    scenario = flat_scenario()
    scenario = dataclasses.replace(scenario, terrain=dataclasses.replace(scenario.terrain, texture=str(bad)))
    with pytest.raises(ConfigError, match="ground.png.*not a readable image"):
        RoverSim(scenario, renderer="gl")


def test_a_corrupt_cached_texture_is_rebuilt(tmp_path, monkeypatch, caplog):
    import logging

    from rover_env.sim.textures import read_texture, texture_file

    monkeypatch.setenv("ROVER_CACHE_DIR", str(tmp_path))
    path = texture_file("regolith", 64, 5)
    good = read_texture(path)
    path.write_bytes(path.read_bytes()[:40])  # truncated
    with caplog.at_level(logging.WARNING):
        again = texture_file("regolith", 64, 5)
    assert again == path and "rebuilding" in caplog.text
    np.testing.assert_array_equal(read_texture(again), good)


@pytest.mark.parametrize("key", ["wheel_radius", "track", "body_mass"])
def test_non_finite_rover_geometry_names_the_key(key):
    from rover_env.config.io import ConfigError
    from rover_env.sim.geometry import RoverGeometry

    for bad in (math.nan, math.inf):
        with pytest.raises(ConfigError, match=key):
            RoverGeometry(**{key: bad})


# ---------------------------------------------------------------- numbers that are not numbers


@pytest.mark.parametrize(
    ("imu", "names"),
    [
        ("{gyro: {range: inf}}", ["imu.gyro.range", "'inf' is text", ".inf"]),  # YAML 1.1: a string
        ("{rate_hz: true}", ["imu.rate_hz", "True is a true/false value"]),
        ("{accel: {noise_density: '1e-3'}}", ["imu.accel.noise_density", "is text"]),
        ("{position: [0, 0, yes]}", ["imu.position[2]"]),
    ],
)
def test_a_scenario_number_given_as_text_or_a_bool_is_refused_where_it_is_read(tmp_path, imu, names):
    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import load_scenario

    path = tmp_path / "s.yaml"
    path.write_text(f"name: s\ncourse: {{waypoints: [[5, 0]]}}\nimu: {imu}\n")
    with pytest.raises(ConfigError) as exc:
        load_scenario(path)
    msg = str(exc.value)
    assert str(path) in msg and all(n in msg for n in names), msg
    ok = tmp_path / "ok.yaml"  # the same key with a real number, infinity written the YAML way
    ok.write_text("name: s\ncourse: {waypoints: [[5, 0]]}\nimu: {gyro: {range: .inf}, rate_hz: 120}\n")
    assert load_scenario(ok).imu == {"gyro": {"range": math.inf}, "rate_hz": 120}


def test_rover_eval_on_a_scenario_with_a_text_number_is_one_line_not_a_traceback(tmp_path, capsys):
    from rover_env.tools.cli import main

    path = tmp_path / "s.yaml"
    path.write_text("name: s\ncourse: {waypoints: [[5, 0]]}\nimu: {gyro: {range: inf}}\n")
    argv = ["eval", "--missions", str(path), "--controllers", "slip_aware", "--seeds", "0"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "imu.gyro.range" in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("K", [[600.0, 0, 320], [0, "600", 240], [0, 0, 1]]),
        ("ground_plane", [0, 0, True]),
        ("distortion", "0"),
    ],
)
def test_a_calibration_number_given_as_text_or_a_bool_names_the_key(tmp_path, key, value):
    import yaml
    from test_odometry import mast_camera

    from perception.models.calib_io import CalibrationError
    from perception.models.cameras import PinholeCamera

    data = yaml.safe_load(mast_camera().save(tmp_path / "c.yaml").read_text())
    data[key] = value
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(CalibrationError, match=rf"bad\.yaml: {key}: expected numbers"):
        PinholeCamera.load(tmp_path / "bad.yaml")


def test_a_rover_geometry_number_given_as_text_names_the_key(tmp_path):
    import yaml
    from test_markers import rover_model

    from perception.models.calib_io import CalibrationError
    from perception.models.rover import RoverKinematicModel

    data = yaml.safe_load(rover_model().save(tmp_path / "r.yaml").read_text())
    data["track"] = "1.2"
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(CalibrationError, match=r"bad\.yaml: track: expected a number, got '1\.2' is text"):
        RoverKinematicModel.load(tmp_path / "bad.yaml")


# ---------------------------------------------------------------- environment copies


def test_an_environment_is_not_copied_or_pickled_and_is_unusable_after_close():
    import copy
    import pickle

    import gymnasium as gym

    env = gym.make("Rover-v0", obs_source="ground_truth")
    env.reset(seed=0)
    with pytest.raises(TypeError, match="gymnasium.make"):
        copy.deepcopy(env)
    with pytest.raises(TypeError, match="cannot be pickled"):
        pickle.dumps(env)
    with pytest.raises(TypeError, match="cannot be copied"):
        copy.deepcopy(env.unwrapped.sim)
    obs, *_ = env.step(np.zeros(3))  # the original is untouched by the attempts
    assert np.all(np.isfinite(obs))
    env.close()
    for call in (lambda: env.step(np.zeros(3)), env.reset, env.unwrapped.render):
        with pytest.raises(RuntimeError, match=r"after close\(\).*gymnasium\.make"):
            call()
    env.close()  # closing twice is fine

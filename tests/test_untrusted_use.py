"""The tools under hostile use: every number right or absent, every file kept, every fault named.

Each case here was found by trying the tools as a user would with bad input; each test fails on
the code before its fix. The simulator is needed only where the case is about it (the rig given
to an estimator, rover eval, rover train); the logs are written here.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_bags import LogWriter  # noqa: E402

from perception.logs.replay import load_rig, replay  # noqa: E402
from perception.models.cameras import PinholeCamera  # noqa: E402
from rover_env.tools.cli import main  # noqa: E402

FPS, N, IMU_HZ = 30.0, 20, 240.0
T_CAM = 100.0  # the camera's first stamp [s]
T_BODY_CAM = np.array([[0.0, -1.0, 0.0, 0.9], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.8], [0, 0, 0, 1.0]])


def one_error(capsys) -> str:
    """The one error line of a command; no traceback."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


def write_log(
    path: Path, imu_start: float = T_CAM - 0.5, imu_hz: float = IMU_HZ, imu_n: int | None = None
) -> Path:
    """An MCAP log: N grey frames at FPS from T_CAM, and an IMU at ``imu_hz`` from ``imu_start``."""
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur((rng.random((48, 64)) * 255).astype(np.uint8), (3, 3), 0)
    with LogWriter(path, "mcap") as lw:
        for k in range(N):
            lw.image("/cam/image_raw", T_CAM + k / FPS, np.roll(texture, k, axis=1), encoding="mono8")
        n = imu_n if imu_n is not None else int((N / FPS + 0.5) * imu_hz)
        for j in range(n):
            lw.imu("/imu/data", imu_start + j / imu_hz, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
    return path


def write_rig(folder: Path, imu_rate: float = IMU_HZ, cam_topic: str | None = "/cam/image_raw") -> Path:
    cam = PinholeCamera.from_fov((64, 48), math.radians(70), T_body_cam=T_BODY_CAM, ground_plane=(0, 0, -0.3))
    folder.mkdir(parents=True, exist_ok=True)
    cam.save(folder / "cam.yaml")
    topic = f"\n    topic: {cam_topic}" if cam_topic else ""
    text = (
        "sensors:\n"
        f"  - name: cam\n    kind: pinhole\n    rate_hz: {FPS}\n    calibration: cam.yaml{topic}\n"
        f"  - name: imu\n    kind: imu\n    rate_hz: {imu_rate:.6e}\n    topic: /imu/data\n"
    )
    (folder / "rig.yaml").write_text(text)
    return folder / "rig.yaml"


class Still:
    """An estimator that stays where it started, and counts what it is given."""

    def __init__(self, rig) -> None:
        self.given: list = []

    def reset(self, start_fix) -> None:
        self.pose = np.array(start_fix, dtype=float)

    def update(self, messages, t):
        self.given.append((t, [(m.sensor, m.t) for m in messages]))
        return {"pose": self.pose, "v_x": 0.0}


# ------------------------------------------------------------------ logs in replay


def test_sensors_on_clocks_that_do_not_overlap_are_named_with_their_spans(tmp_path):
    rig = load_rig(write_rig(tmp_path / "rig"))
    for start, hint in (
        (T_CAM + 3600.0, "--time-offset imu=-3600.262"),  # an IMU stamped an hour late
        (1.7e9, "--time-offset imu=-1699999900.262"),  # the epoch clock against the camera's boot time
        (T_CAM - 50.5, "--time-offset imu=50.237"),  # 50 s early
    ):
        log = write_log(tmp_path / f"l{start:.0f}.mcap", imu_start=start)
        with pytest.raises(ValueError, match="time spans do not overlap") as exc:
            replay(log, rig, Still(rig.rig))
        msg = str(exc.value)
        assert "cam (/cam/image_raw) 100.000 to 100.633 s" in msg and f"imu (/imu/data) {start:.3f}" in msg
        if hint:
            assert hint in msg, msg
    # the offset the error names puts it right: every tick gets its IMU samples, none is late
    log = write_log(tmp_path / "late.mcap", imu_start=T_CAM + 3600.0 - 0.5)
    est = Still(rig.rig)
    steps = list(replay(log, rig, est, time_offsets={"imu": -3600.0}))
    assert len(steps) == N and steps[-1].t_log == pytest.approx(T_CAM + (N - 1) / FPS)
    assert all(any(s == "imu" for s, _ in given) for _, given in est.given)


def test_a_declared_rate_far_from_the_logs_is_refused_naming_both(tmp_path):
    log = write_log(tmp_path / "l.mcap")
    for rate in (24.0, 1e-12):
        rig = load_rig(write_rig(tmp_path / f"rig{rate:g}", imu_rate=rate))
        with pytest.raises(ValueError, match=rf"rate_hz {rate:g}, but its messages come at 240 Hz"):
            replay(log, rig, Still(rig.rig))
    rig = load_rig(write_rig(tmp_path / "ok", imu_rate=230.0))  # within 10 %: taken
    assert len(list(replay(log, rig, Still(rig.rig)))) == N


def test_work_is_bounded_by_the_log_and_no_row_is_past_its_end(tmp_path, capsys):
    log = write_log(tmp_path / "l.mcap", imu_n=int(5 * IMU_HZ))  # the IMU goes on 4 s after the camera
    rig_file = write_rig(tmp_path / "rig")
    rig = load_rig(rig_file)
    steps = list(replay(log, rig, Still(rig.rig), control_hz=30.0))
    assert len(steps) == N and max(s.t_log for s in steps) <= T_CAM + (N - 1) / FPS + 1e-6
    with pytest.raises(ValueError, match="control rate from 1 to 1000 Hz"):
        replay(log, rig, Still(rig.rig), control_hz=0.001)
    argv = ["replay", str(log), "--rig", str(rig_file), "--control-hz", "0.001", "--out", str(tmp_path / "o")]
    with pytest.raises(SystemExit) as exc:  # argparse's refusal
        main(argv)
    assert exc.value.code == 2 and "--control-hz" in capsys.readouterr().err and not (tmp_path / "o").exists()
    assert main(["replay", str(log), "--rig", str(rig_file), "--out", ""]) == 2
    assert "--out: empty" in one_error(capsys)


def test_several_topics_of_a_kind_are_chosen_in_the_rig_file(tmp_path, capsys):
    log = tmp_path / "two.mcap"
    with LogWriter(log, "mcap") as lw:
        for k in range(3):
            for topic in ("/a/image_raw", "/b/image_raw"):
                lw.image(topic, T_CAM + k / FPS, np.zeros((48, 64), np.uint8), encoding="mono8")
    rig_file = write_rig(tmp_path / "rig", cam_topic=None)
    still = tmp_path / "still.py"
    still.write_text(
        "class Still:\n    def __init__(self, rig): pass\n    def reset(self, fix): pass\n"
        "    def update(self, m, t): return {'pose': [0.0, 0.0, 0.0]}\n"
    )
    argv = ["replay", str(log), "--rig", str(rig_file), "--estimator", f"{still}:Still"]
    assert main([*argv, "--out", str(tmp_path / "o")]) == 2
    line = one_error(capsys)
    assert "rig file (its `topic:` key)" in line and "--topic" not in line


# ------------------------------------------------------------------ the estimator interface


@pytest.mark.parametrize(
    ("bad", "words"),
    [
        ({"v_x": "1.5"}, ["'v_x' is '1.5'", "not a number"]),
        ({"odometry_quality": 1.7}, ["'odometry_quality' is 1.7", "quality is in [0, 1]"]),
        ({"slip_event_FL": 0.5}, ["'slip_event_FL' is 0.5", "flag"]),
        ({"slip_std_RR": -1.0}, ["'slip_std_RR'", ">= 0"]),
    ],
)
def test_an_estimate_that_is_not_a_number_in_range_is_named(bad, words):
    from perception.estimator import EstimatorError, check_estimate

    with pytest.raises(EstimatorError) as exc:
        check_estimate({"pose": [0.0, 0.0, 0.0], **bad}, "mine.Est", 7)
    assert all(w in str(exc.value) for w in ["estimator mine.Est, step 7", *words]), str(exc.value)

    class Odd:
        def __float__(self):
            raise RuntimeError("no float here")

    with pytest.raises(EstimatorError, match=r"step 7: 'v_x' is .*RuntimeError: no float here"):
        check_estimate({"pose": [0.0, 0.0, 0.0], "v_x": Odd()}, "mine.Est", 7)
    with pytest.raises(EstimatorError, match="'pose'"):
        check_estimate({"pose": ["1", "2", "3"]}, "mine.Est", 7)


def test_an_estimator_that_exits_or_lacks_update_is_exit_2_and_writes_nothing(tmp_path, capsys):
    log = write_log(tmp_path / "l.mcap")
    rig_file = write_rig(tmp_path / "rig")
    src = tmp_path / "mine.py"
    src.write_text(
        "import sys\n"
        "class Exits:\n    def __init__(self, rig): pass\n    def reset(self, fix): pass\n"
        "    def update(self, messages, t): sys.exit(0)\n"
        "class NoUpdate:\n    def __init__(self, rig): pass\n    def reset(self, fix): pass\n"
        "def refuses(rig): raise ValueError('I need a stereo pair')\n"
    )
    for factory, words in (
        ("Exits", "estimator mine.Exits, step 0: SystemExit"),
        ("NoUpdate", "has no update() method"),
        ("refuses", "I need a stereo pair"),
    ):
        out = tmp_path / f"o_{factory}"
        argv = [
            "replay",
            str(log),
            "--rig",
            str(rig_file),
            "--estimator",
            f"{src}:{factory}",
            "--out",
            str(out),
        ]
        assert main(argv) == 2, factory
        assert words in one_error(capsys)
        assert not out.exists()


def test_the_rig_an_estimator_is_given_cannot_change_the_simulation():
    import gymnasium as gym

    import rover_env  # noqa: F401
    from perception.estimator import EstimatorError

    def vandal(rig):
        rig["downward"].model.K[0, 0] *= 2.0  # a "calibration tweak" in place
        raise AssertionError("unreachable: the array is read-only")

    with pytest.raises(EstimatorError, match="assignment destination is read-only"):
        gym.make("Rover-v0", estimator=vandal, renderer="tiny")

    seen = {}

    class Snoop(Still):
        def __init__(self, rig):
            super().__init__(rig)
            seen["rig"] = rig
            with pytest.raises(ValueError, match="read-only"):
                rig["fisheye"].mount[0, 3] += 1.0

    env = gym.make("Rover-v0", estimator=Snoop, renderer="tiny", camera_effects="ideal")
    try:
        env.reset(seed=0)
        u = env.unwrapped
        # the estimator's rig is its own: the simulated cameras keep their models
        assert seen["rig"]["downward"].model is not u.pipeline.sensors["downward"].model
        np.testing.assert_array_equal(seen["rig"]["downward"].model.K, u.pipeline.sensors["downward"].model.K)
        img = u.pipeline.last_images["downward"]
        with pytest.raises(ValueError, match="read-only"):
            img[0, 0] = 0  # the samples it is given are read-only too
    finally:
        env.close()


def test_odometry_overrides_are_honoured_or_refused_on_every_rig():
    import gymnasium as gym

    import rover_env  # noqa: F401
    from perception.estimator import EstimatorError
    from perception.models.validation import ConfigError
    from rover_env.sensors.rig import builtin_estimator

    with pytest.raises(ConfigError, match="'max_featurez' is not a FlowOdometryConfig field"):
        builtin_estimator("train", odometry_overrides={"max_featurez": 50})
    factory = builtin_estimator("train", odometry_overrides={"max_features": 50})
    with pytest.raises(EstimatorError, match="no downward camera .* fisheye_odometry"):
        gym.make("Rover-v0", rig="fisheye_only", estimator=factory, renderer="tiny")
    env = gym.make("Rover-v0", estimator=factory, renderer="tiny")
    try:
        assert env.unwrapped.pipeline.estimator.odometry.config.max_features == 50
    finally:
        env.close()


# ------------------------------------------------------------------ outputs


def wheel_test_argv(out, *extra, soil="toyoura"):
    return ["wheel-test", "--soil", str(soil), "--radius", "0.1", "--width", "0.1", "--load", "100",
            "--slips", "0.2", "--distance", "0.2", "--out", str(out), *extra]  # fmt: skip


def test_wheel_test_never_writes_through_a_link_or_loses_its_earlier_results(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(wheel_test_argv(out)) == 0
    earlier = {p.name: p.read_bytes() for p in out.iterdir()}
    # a symbolic link where the CSV goes: refused, the user's file it points to untouched
    mine = tmp_path / "mine.csv"
    mine.write_text("the user's data")
    (out / "wheel_test.csv").unlink()
    (out / "wheel_test.csv").symlink_to(mine)
    assert main(wheel_test_argv(out, "--overwrite")) == 2
    assert "symbolic link" in one_error(capsys) and mine.read_text() == "the user's data"
    # a folder where the plot goes: refused before any work, the earlier CSV as it was
    (out / "wheel_test.csv").unlink()
    (out / "wheel_test.csv").write_bytes(earlier["wheel_test.csv"])
    (out / "wheel_test.png").unlink()
    (out / "wheel_test.png").mkdir()
    assert main(wheel_test_argv(out, "--overwrite")) == 2
    assert "wheel_test.png is a folder" in one_error(capsys)
    assert (out / "wheel_test.csv").read_bytes() == earlier["wheel_test.csv"]


@pytest.mark.parametrize(
    ("command", "message"),
    [
        (lambda out: wheel_test_argv(out, soil="no_such_soil"), "no_such_soil"),
        (lambda out: ["eval", "--missions", "Rover-v99", "--out", str(out)], "Rover-v99"),
        (lambda out: ["train", "--missions", "Rover-v99", "--out", str(out)], "Rover-v99"),
        (lambda out: ["record", "Rover-v99", "--controller", "slip_aware", "--seconds", "1",
                      "--out", str(out)], "Rover-v99"),
        (lambda out: ["record", "Rover-v0", "--controller", "slip_aware@ground_truth", "--seconds", "1",
                      "--out", str(out)], "no sensor runs"),
        (lambda out: ["demo", "--scenario", "no_such_scenario", "--out", str(out)], "no_such_scenario"),
    ],
)  # fmt: skip
def test_a_refused_input_leaves_no_output_folder(tmp_path, capsys, command, message):
    out = tmp_path / "new" / "out"
    assert main(command(out)) == 2
    assert message in one_error(capsys)
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize(
    "command", ["wheel-test", "eval", "train", "record", "demo", "odometry", "kinematics"]
)
def test_an_empty_out_is_refused_not_the_current_folder(tmp_path, monkeypatch, capsys, command):
    monkeypatch.chdir(tmp_path)
    argv = {
        "wheel-test": wheel_test_argv(""),
        "eval": ["eval", "--out", ""],
        "train": ["train", "--out", ""],
        "record": ["record", "Rover-v0", "--controller", "slip_aware", "--seconds", "1", "--out", ""],
        "demo": ["demo", "--out", ""],
        "odometry": ["odometry", str(tmp_path), "--calib", "c.yaml", "--fps", "30", "--out", ""],
        "kinematics": ["kinematics", str(tmp_path), "--camera", "c.yaml", "--rover", "r.yaml", "--fps", "30",
                       "--out", ""],
    }[command]  # fmt: skip
    assert main(argv) == 2
    assert "--out" in one_error(capsys)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ physics that cannot be


@pytest.mark.parametrize(
    ("soil", "words"),
    [
        ({"preset": "toyoura", "n": 0.01}, "too fast for the 240 Hz physics step"),  # sank -24 m before
        ({"preset": "toyoura", "k_phi": 1.0e11}, "too fast for the 240 Hz physics step"),  # -164 m
        ({"preset": "toyoura", "k_c": 0.0, "k_phi": 1.0e-3}, "buried past its axle"),  # 4.5 m deep, quietly
    ],
)
def test_a_soil_whose_steady_state_cannot_be_is_refused_before_the_run(tmp_path, capsys, soil, words):
    import yaml

    path = tmp_path / "soil.yaml"
    path.write_text(yaml.safe_dump(soil))
    out = tmp_path / "out"
    assert main(wheel_test_argv(out, soil=path)) == 2
    assert words in one_error(capsys) and not out.exists()


def test_a_test_bed_run_too_long_or_not_physical_is_an_error(tmp_path, capsys):
    assert main(wheel_test_argv(tmp_path / "o", "--speed", "1e-6")) == 2  # hung for hours before
    assert "give a speed above" in one_error(capsys) and not (tmp_path / "o").exists()
    from rover_env.config.io import ConfigError
    from rover_env.config.soil import load_soil
    from rover_env.sim.terramechanics import WheelSpec
    from rover_env.sim.wheel_test import WheelTestRow, _check_row

    soil, wheel = load_soil("toyoura"), WheelSpec(0.1, 0.1)
    _check_row(WheelTestRow(0.2, 10.0, 100.0, 0.02, 1.0), 100.0, wheel, soil)  # a physical one passes
    for row, words in (
        (WheelTestRow(0.2, 10.0, 100.0, -12.56, 1.0), "negative sinkage"),
        (WheelTestRow(0.2, math.nan, 0.0, 0.02, 1.0), "non-finite"),
        (WheelTestRow(0.2, 0.0, 0.0, 0.02, 1.0), "carrying 0 N of the 100 N load"),
        (WheelTestRow(0.2, 10.0, 100.0, 0.2, 1.0), "past the wheel's axle"),
    ):
        with pytest.raises(ConfigError, match=words):
            _check_row(row, 100.0, wheel, soil)


# ------------------------------------------------------------------ calibrations that cannot be


def _fisheye_calibration(tmp_path, **changes) -> Path:
    import dataclasses

    from perception.models.cameras import OmniCamera

    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = (0.0, 0.0, 0.6)
    cam = OmniCamera.equidistant((320, 240), math.radians(190.0), 150.0, T_body_cam=T)
    cam = dataclasses.replace(cam, ground_plane=(0.0, 0.0, -0.3))
    path = cam.save(tmp_path / "omni.yaml")
    text = path.read_text()
    for key, value in changes.items():
        import yaml

        data = yaml.safe_load(text)
        data[key] = value
        text = yaml.safe_dump(data)
    path.write_text(text)
    return path


def test_the_fisheye_odometry_refuses_a_calibration_that_cannot_be(tmp_path, capsys):
    from perception.models.calib_io import CalibrationError
    from perception.models.cameras import OmniCamera
    from perception.odometry.fisheye import FisheyeOdometry

    good = OmniCamera.load(_fisheye_calibration(tmp_path))
    assert good.model_error() == "" and FisheyeOdometry(good).camera is good
    with pytest.raises(CalibrationError, match="tilted 89.0 deg"):
        OmniCamera.load(
            _fisheye_calibration(tmp_path, ground_plane=[math.tan(math.radians(89.0)), 0.0, -0.3])
        )
    scaled = _fisheye_calibration(tmp_path, poly=[100.0 * a for a in good.poly])
    with pytest.raises(ValueError, match="the polynomial is scaled or wrong"):
        FisheyeOdometry(OmniCamera.load(scaled))
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "0.png"), np.zeros((240, 320, 3), np.uint8))
    out = tmp_path / "out"
    assert main(["odometry", str(images), "--camera", str(scaled), "--fps", "30", "--out", str(out)]) == 2
    assert "polynomial" in one_error(capsys) and not out.exists()


# ------------------------------------------------------------------ rover train's arguments


@pytest.mark.parametrize(
    ("extra", "words"),
    [
        (["--missions", "Rover-v99"], "mission 'Rover-v99'"),
        (["--residual", "-1", "0.3", "0.3"], "residual [-1.0, 0.3, 0.3]"),
        (["--residual", "nan", "0.3", "0.3"], "give three numbers from 0 to 2"),
        (["--imu", "bmi088", "--obs-source", "ground_truth"], "the IMU feeds the estimator"),
        (["--imu", "mems"], "imu 'mems'"),
    ],
)
def test_rover_train_checks_every_argument_before_any_worker_starts(tmp_path, capsys, extra, words):
    out = tmp_path / "out"
    assert main(["train", "--out", str(out), "--steps", "10", *extra]) == 2
    assert words in one_error(capsys) and not out.exists()


def test_rover_train_says_what_it_trains_when_steps_are_below_one_rollout(
    tmp_path, capsys, monkeypatch, tiny_scenario
):
    import rover_env.tools.training as training

    trained = {}

    def fake_train(cfg, out, progress=False):  # the check, not the hour of training
        trained["steps"] = cfg.steps_trained()
        out.commit()
        return out.path

    monkeypatch.setattr(training, "train", fake_train)
    argv = ["train", "--out", str(tmp_path / "o"), "--steps", "10", "--missions", tiny_scenario,
            "--obs-source", "ground_truth"]  # fmt: skip
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert (
        "--steps 10 is below one rollout of PPO (1024 steps: 512 on each of 2 environments): it trains 1024"
        in err
    )
    assert trained["steps"] == 1024
    argv[argv.index("10")] = "200000"  # the default: a whole number of rollouts and more, no note
    argv[argv.index(str(tmp_path / "o"))] = str(tmp_path / "o2")
    assert main(argv) == 0
    assert "below one rollout" not in capsys.readouterr().err


# ------------------------------------------------------------------ Ctrl-C


def test_ctrl_c_while_the_command_loads_is_one_line(monkeypatch, capsys):
    import rover_env.tools.cli as cli

    def interrupted():
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert cli.main(["eval", "--out", "x"]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "rover: interrupted" and "Traceback" not in err


# ------------------------------------------------------------------ reports: only what was returned


PARTIAL = """
import numpy as np


class PoseSpeedYaw:
    '''Returns only the pose, v_x and omega (dead reckoning on the true start fix, a fixed speed).'''

    def __init__(self, rig):
        pass

    def reset(self, start_fix):
        self.pose = np.array(start_fix, dtype=float)

    def update(self, messages, t):
        return {"pose": self.pose, "v_x": 0.5, "omega": 0.0}


def refuses(rig):
    raise ValueError("this estimator needs a stereo pair")
"""


def test_rover_eval_scores_only_what_an_estimator_returned_and_puts_estimators_side_by_side(
    tmp_path, capsys, tiny_scenario
):
    import csv
    import json

    src = tmp_path / "partial.py"
    src.write_text(PARTIAL)
    out = tmp_path / "eval"
    argv = ["eval", "--controllers", "slip_unaware", "--missions", tiny_scenario, "--seeds", "0",
            "--workers", "1", "--preset", "train", "--camera-effects", "ideal", "--out", str(out),
            "--estimator", f"mine={src}:PoseSpeedYaw", "--estimator", "built-in"]  # fmt: skip
    assert main(argv) == 0
    with open(out / "results.csv") as fh:
        rows = {r["estimator"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {"mine", "built-in"}
    mine, builtin = rows["mine"], rows["built-in"]
    for key in ("est_mae_slip", "est_slip_mae_slipping", "est_mae_wheel_rate", "est_mae_axle_height",
                "est_mae_steering", "est_slip_f1", "est_slip_events"):  # fmt: skip
        assert mine[key] == "nan", (key, mine[key])  # not a score for a zero it never claimed
        assert math.isfinite(float(builtin[key])) or key == "est_slip_f1", (key, builtin[key])
    assert float(mine["est_mae_v_x"]) > 0.0 and math.isfinite(float(mine["est_mae_omega"]))
    data = {r["estimator"]: r for r in json.loads((out / "results.json").read_text())}
    assert data["mine"]["est_mae_slip"] is None and data["built-in"]["est_mae_slip"] is not None
    report = (out / "report.md").read_text()
    table = [ln for ln in report.splitlines() if ln.startswith("| slip_unaware |")]
    assert len(table) == 4  # both estimators, in the mission table and the errors table
    errors = [ln for ln in table if ln.startswith("| slip_unaware | mine |") and "–" in ln]
    assert errors and errors[-1].count("–") >= 4
    assert f"`mine`: `{src}:PoseSpeedYaw`" in report
    # a factory that refuses the rig: found before the sweep, exit 2, no folder
    bad = tmp_path / "bad"
    argv2 = ["eval", "--controllers", "slip_unaware", "--missions", tiny_scenario, "--seeds", "0",
             "--out", str(bad), "--estimator", f"{src}:refuses"]  # fmt: skip
    assert main(argv2) == 2
    assert "needs a stereo pair" in one_error(capsys) and not bad.exists()


# ------------------------------------------------------------------ rover record and replay


def test_a_recorded_mission_replays_to_the_estimates_of_the_loop(tmp_path, capsys):
    from perception.logs import bags
    from perception.logs.truth import read_estimates, read_truth

    rec = tmp_path / "rec"
    assert (
        main(["record", "Rover-v0", "--controller", "slip_aware", "--seconds", "3", "--out", str(rec)]) == 0
    )
    assert {p.name for p in rec.iterdir()} == {"log.mcap", "rig.yaml", "rover.yaml", "fisheye.yaml",
                                               "downward.yaml", "truth.csv", "truth.tum",
                                               "estimates_in_loop.csv"}  # fmt: skip
    with bags.open_log(rec / "log.mcap") as lg:
        topics = lg.topics()
    assert topics == {
        "/fisheye/image_raw/compressed": ("sensor_msgs/msg/CompressedImage", 91),
        "/downward/image_raw/compressed": ("sensor_msgs/msg/CompressedImage", 91),
    }
    truth = read_truth(rec / "truth.csv")
    assert truth["t_log"][0] == pytest.approx(2.0) and len(truth["t_log"]) == 91  # stamps valid from 0
    rig = load_rig(rec / "rig.yaml")
    assert rig.starts_at_rest and rig.topics["fisheye"] == "/fisheye/image_raw/compressed"
    out = tmp_path / "replay"
    argv = [
        "replay",
        str(rec / "log.mcap"),
        "--rig",
        str(rec / "rig.yaml"),
        "--truth",
        str(rec / "truth.csv"),
    ]
    assert main([*argv, "--out", str(out)]) == 0
    loop, again = read_estimates(rec / "estimates_in_loop.csv"), read_estimates(out / "estimates.csv")
    np.testing.assert_allclose(again["t_log"], loop["t_log"], atol=1e-6)
    # the fisheye's images are the loop's to the bit: its kinematics gives the same numbers
    for key in ("steering_F", "axle_roll_R", "axle_height_F", "wheel_angle_FL"):
        np.testing.assert_allclose(again[key], loop[key], rtol=0, atol=1e-12)
    errors = {r.split(",")[0]: r.split(",") for r in (out / "errors.csv").read_text().splitlines()[1:]}
    mae = float(errors["v_x"][3])
    vx_loop = np.nanmean(np.abs(loop["v_x"] - np.interp(loop["t_log"], truth["t_log"], truth["v_x"]))[30:])
    assert abs(mae - vx_loop) < 0.005, (mae, vx_loop)


# ------------------------------------------------------------------ the docs, as a user follows them

ROOT = Path(__file__).resolve().parents[1]


def _yaml_block_after(doc: Path, heading: str) -> str:
    text = doc.read_text()
    rest = text[text.index(heading) :]
    start = rest.index("```yaml\n") + len("```yaml\n")
    return rest[start : rest.index("```", start)]


def test_the_docs_rig_example_moves_the_camera_forward_and_sees_the_ground(tmp_path):
    import gymnasium as gym

    import rover_env  # noqa: F401
    from rover_env.sensors.cameras import DownwardCamera

    rig = _yaml_block_after(ROOT / "docs" / "rover_and_scenarios.md", "### The sensor rig")
    path = tmp_path / "moved.yaml"
    path.write_text("base: flat_patches\n" + rig)  # the docs' way to change only the rig of a preset
    env = gym.make("Rover-v0", scenario=str(path), renderer="tiny", camera_effects="ideal")
    try:
        u = env.unwrapped
        cam = u.rig["downward"].model
        standard = DownwardCamera.standard_mount(u.geometry)
        assert cam.T_body_cam[0, 3] > standard[0, 3]  # "moved forward"
        # the rearmost ground it sees lies ahead of the body's front: the rover is not in view
        w, h = cam.image_size
        ground = cam.pixels_to_ground(np.array([[0.0, h - 1.0], [w - 1.0, h - 1.0]]), (0.0, 0.0, -0.265))
        assert ground[:, 0].min() > u.geometry.body_size[0] / 2
        assert u.scenario.course == rover_env.load_scenario("flat_patches").course  # the rest: the preset's
    finally:
        env.close()


def test_the_readme_quick_start_runs_on_a_current_id_without_a_warning():
    import warnings

    readme = (ROOT / "README.md").read_text()
    start = readme.index("## Quick start")
    block = readme[start:][readme[start:].index("```python\n") + len("```python\n") :]
    code = block[: block.index("```")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scope: dict = {}
        exec(compile(code, "README quick start", "exec"), scope)  # noqa: S102
    env, info = scope["env"], scope["info"]
    try:
        import rover_env

        assert env.spec.id in rover_env.ENV_IDS
        assert info["ground_truth"]["slip_ratio"].shape == info["estimate"]["slip_ratio"].shape == (4,)
        assert np.all(np.isfinite(scope["obs"]))
    finally:
        env.close()


def test_scenario_files_can_start_from_a_preset_and_name_it_wrongly(tmp_path):
    from rover_env.config.io import ConfigError
    from rover_env.config.scenario import load_scenario

    path = tmp_path / "s.yaml"
    path.write_text("base: flat_patchez\n")
    with pytest.raises(ConfigError, match="base: 'flat_patchez'; name a shipped scenario preset"):
        load_scenario(path)
    path.write_text("base: rough\nduration: 12\n")
    got, preset = load_scenario(path), load_scenario("rough")
    assert got.duration == 12 and got.terrain == preset.terrain and got.friction == preset.friction


def test_a_module_estimator_that_does_not_import_suggests_its_path(tmp_path, monkeypatch):
    from rover_env.tools.evaluation import load_estimator

    monkeypatch.chdir(tmp_path)  # a folder from which the module is not importable
    with pytest.raises(ValueError, match=r"give the file's path instead: path/to/my_estimators/lk\.py:Lk"):
        load_estimator("my_estimators.lk:Lk")
    factory = load_estimator(f"lk={ROOT / 'examples' / 'own_estimator.py'}:LucasKanadeEstimator")
    assert factory.__name__ == "LucasKanadeEstimator"


# ------------------------------------------------------------------ found in review


def test_ctrl_c_stops_a_sweep_run_in_this_process_and_workers_leave_it_to_the_parent():
    import signal

    from rover_env.tools import evaluation

    before = signal.getsignal(signal.SIGINT)
    try:
        evaluation._init_worker()  # the sweep's own process: Ctrl-C still interrupts it
        assert signal.getsignal(signal.SIGINT) is before
        evaluation._init_pool_worker()  # a pool worker: the parent stops it (SIGTERM)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is evaluation._exit_terminated
    finally:
        signal.signal(signal.SIGINT, before)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def test_a_resumed_sweep_takes_only_its_own_runs_and_estimators(tmp_path):
    import json

    from rover_env.tools.evaluation import EvalJob, finished_row

    job = EvalJob("slip_aware", "Rover-v0", 0, out=str(tmp_path), estimator="mine=a.py:F")
    row = {"controller": "slip_aware", "mission": "Rover-v0", "seed": 0, "preset": "train",
           "camera_effects": "field", "estimator": "mine", "estimator_spec": "a.py:F", "randomize": "off",
           "rig": "mission", "sweep": "s1"}  # fmt: skip
    (tmp_path / "row.json").write_text(json.dumps(row))
    assert finished_row(job, "s1")["seed"] == 0 and "sweep" not in finished_row(job, "s1")
    assert finished_row(job, "s2") is None  # an earlier sweep's run in a folder given with --overwrite
    other = EvalJob("slip_aware", "Rover-v0", 0, out=str(tmp_path), estimator="mine=b.py:G")
    assert finished_row(other, "s1") is None  # the same name for another estimator


def test_a_run_over_before_its_start_up_leaves_the_event_scores_of_the_others(tmp_path):
    from rover_env.tools.estimator_metrics import slip_metrics

    def run(t_end):
        t = np.arange(0.0, t_end, 1 / 30)
        n = len(t)
        return {"t": t, "est": np.zeros((n, 19)), "tru": np.zeros((n, 19)), "events": np.zeros((n, 4)),
                "speed": np.ones((n, 4)), "frame": 1 / 30, "radius": 0.115}  # fmt: skip

    m = slip_metrics([run(0.5), run(5.0)])  # the first ends within the filters' start-up
    assert m["events"] == 0 and m["false"] == 0 and m["missed"] == 0


def test_an_imu_saturation_flag_is_read_only_where_the_rig_file_says_so(tmp_path):
    from perception.logs.bags import McapWriter, log_imu

    log = tmp_path / "sat.mcap"
    with McapWriter(log) as w:
        for j in range(50):
            w.imu(1.0 + j / 200, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81), "/imu/data", "imu", saturated=j == 10)
    rows, _ = log_imu(log, flags=True)
    assert rows[10, 7] == 1.0 and rows[:, 7].sum() == 1.0
    folder = tmp_path / "rig"
    folder.mkdir()
    base = "sensors:\n  - {name: imu, kind: imu, rate_hz: 200.0, topic: /imu/data%s}\n"
    for extra, flagged in (("", 0.0), (", saturation: covariance", 1.0)):
        (folder / "rig.yaml").write_text(base % extra)
        rig = load_rig(folder / "rig.yaml")
        est = Still(rig.rig)
        got = []
        est.update = lambda messages, t, got=got: (
            got.extend(m.data[6] for m in messages) or {"pose": [0, 0, 0]}
        )
        list(replay(log, rig, est))
        assert sum(got) == flagged


def test_a_replayed_rig_refuses_odometry_settings_it_cannot_use(tmp_path):
    from perception.models.validation import ConfigError

    rig_file = tmp_path / "rig.yaml"
    rig_file.write_text(
        "builtin_estimator: {odometry: {max_features: 50}}\n"
        "sensors:\n  - {name: imu, kind: imu, rate_hz: 240.0}\n"
    )
    with pytest.raises(ConfigError, match="no downward camera"):
        load_rig(rig_file)


def test_a_sweeps_run_folder_is_never_a_link(tmp_path):
    from perception.logs.outputs import OutputFolder

    runs = tmp_path / "runs"
    runs.mkdir()
    (tmp_path / "elsewhere").mkdir()
    (runs / "slip_aware_Rover-v0_0").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(ValueError, match="symbolic link .* keeps its own folder"):
        OutputFolder(runs / "slip_aware_Rover-v0_0", ("row.json",), True, within=runs)


def test_a_test_bed_travel_too_short_to_average_is_refused():
    from rover_env.config.io import ConfigError
    from rover_env.config.soil import load_soil
    from rover_env.sim.terramechanics import WheelSpec
    from rover_env.sim.wheel_test import check_wheel_test

    with pytest.raises(ConfigError, match="physics steps of travel a slip"):
        check_wheel_test(load_soil("toyoura"), WheelSpec(0.1, 0.1), 100.0, [0.2], speed=1.0, distance=0.001)
    slips, total = check_wheel_test(load_soil("toyoura"), WheelSpec(0.1, 0.1), 100.0, [0.2], 0.01, 0.2)
    assert slips == [0.2] and total == 4800 + 240


def test_complex_values_are_not_estimates():
    from perception.estimator import EstimatorError, check_estimate

    with pytest.raises(EstimatorError, match="not a number"):
        check_estimate({"pose": [0.0, 0.0, 0.0], "v_x": np.complex128(1 + 2j)}, "mine.Est", 3)
    with pytest.raises(EstimatorError, match="'pose'"):
        check_estimate({"pose": [1 + 0j, 0.0, 0.0]}, "mine.Est", 3)

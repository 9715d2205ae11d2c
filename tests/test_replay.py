"""An estimator developed in the simulation runs unchanged on a robot log (`rover replay`)."""

from __future__ import annotations

import csv
import dataclasses
import math
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import rover_env  # noqa: F401
from perception.logs.replay import CSV_COLUMNS, load_rig, save_rig
from perception.models.validation import ConfigError

sys.path.insert(0, str(Path(__file__).parent))
from test_bags import LogWriter  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
T0 = 100.0  # the log's first stamp [s]
TOPICS = {"fisheye": "/fisheye/image_raw", "downward": "/down/image_raw", "imu": "/imu"}
STEPS = 45


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A mission driven on the example estimator in the loop, its messages written to an MCAP log."""
    sys.path.insert(0, str(ROOT))
    try:
        from examples.own_estimator import LucasKanadeEstimator
    finally:
        sys.path.remove(str(ROOT))

    class Tap(LucasKanadeEstimator):
        def __init__(self, rig) -> None:
            super().__init__(rig)
            self.messages: list = []
            self.out: list[tuple[float, dict]] = []

        def update(self, messages, t):
            self.messages += messages
            values = super().update(messages, t)
            self.out.append((t, {k: np.array(v, dtype=float) for k, v in values.items()}))
            return values

    env = gym.make("Rover-v0", estimator=Tap, imu="bmi088", renderer="tiny")
    truth = []
    try:
        _, info = env.reset(seed=0)
        start = info["start_fix"]
        for k in range(STEPS):
            _, _, _, _, info = env.step(np.array([0.7, 0.3 * math.sin(k / 8), 0.0], dtype=np.float32))
            truth.append(info["ground_truth"]["twist"][0])
        rig, tap = env.unwrapped.rig, env.unwrapped.pipeline.estimator
    finally:
        env.close()
    folder = tmp_path_factory.mktemp("replay")
    log_path = folder / "mission.mcap"
    with LogWriter(log_path, "mcap") as lw:
        for m in tap.messages:
            t = T0 + m.t
            if m.sensor == "imu":
                lw.imu(TOPICS["imu"], t, m.data[:3], m.data[3:6])
            elif m.sensor == "sun":  # logs carry cameras and IMUs (the example estimator ignores it)
                continue
            else:
                lw.image(TOPICS[m.sensor], t, m.data, encoding="rgb8")
    rig_file = save_rig(rig, folder / "rig", TOPICS)
    return log_path, rig_file, tap.out, np.array(truth), start


def read_csv(path: Path) -> dict[str, np.ndarray]:
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return {c: np.array([float(r[c]) if r[c] else math.nan for r in rows]) for c in CSV_COLUMNS}


def test_a_rig_file_round_trips_the_simulation_s_rig(recorded):
    _, rig_file, *_ = recorded
    lr = load_rig(rig_file)
    assert list(lr.rig) == ["fisheye", "downward", "imu"] and lr.topics == TOPICS
    assert [s.kind for s in lr.rig.values()] == ["fisheye", "pinhole", "imu"]
    assert lr.rig["downward"].rate_hz == 30.0 and lr.rig["imu"].rate_hz == 240.0
    assert not lr.rig["fisheye"].readout_window  # a log's images are recorded: no windows to ask for
    assert lr.rig.vehicle is not None
    K = lr.rig["downward"].model.K
    assert K[0, 0] > 0 and lr.rig["downward"].model.image_size == (160, 120)
    # writing it again over the same files is refused, and nothing is changed
    before = {p.name: p.read_bytes() for p in rig_file.parent.iterdir()}
    with pytest.raises(FileExistsError, match="rig.yaml"):
        save_rig(lr.rig, rig_file.parent)
    assert {p.name: p.read_bytes() for p in rig_file.parent.iterdir()} == before
    assert (lr.rig["fisheye"].gamma, lr.rig["fisheye"].bayer) == (2.2, "RGGB")  # field cameras
    # a camera's photometry (its output gamma and colour-filter array) is kept: an ideal one's too
    from perception.rig import Rig, SensorSpec

    specs = [
        dataclasses.replace(s_, gamma=1.0, bayer=None) if s_.kind != "imu" else s_ for s_ in lr.rig.values()
    ]
    again = load_rig(save_rig(Rig(specs, lr.rig.vehicle, lr.rig.steer_max_rate), rig_file.parent / "ideal"))
    assert [(s_.gamma, s_.bayer) for s_ in again.rig.values()] == [(1.0, None), (1.0, None), (1.0, None)]
    assert isinstance(again.rig["imu"], SensorSpec)


def test_the_estimator_gives_on_the_log_what_it_gave_in_the_loop(recorded, tmp_path, monkeypatch):
    from rover_env.tools.cli import main

    log_path, rig_file, in_loop, _, start = recorded
    monkeypatch.chdir(ROOT)
    out = tmp_path / "lk"
    argv = [
        "replay",
        str(log_path),
        "--rig",
        str(rig_file),
        "--out",
        str(out),
        "--start",
        str(start[0]),
        str(start[1]),
        str(math.degrees(start[2])),
    ]
    assert main([*argv, "--estimator", "examples.own_estimator:LucasKanadeEstimator"]) == 0
    got = read_csv(out / "estimates.csv")
    assert len(got["t"]) == STEPS + 1  # the reset's tick and one per control step
    np.testing.assert_allclose(got["t"], [t for t, _ in in_loop], atol=1e-6)
    np.testing.assert_allclose(got["t_log"], T0 + got["t"], atol=1e-6)  # the log's clock
    pose = np.array([v["pose"] for _, v in in_loop])
    np.testing.assert_allclose(np.c_[got["x"], got["y"], got["yaw"]], pose, atol=1e-5)
    for name in ("v_x", "omega"):
        expected = np.array([v.get(name, math.nan) for _, v in in_loop], dtype=float)
        np.testing.assert_allclose(got[name], expected, atol=1e-5, equal_nan=True)
    assert np.isnan(got["slip_FL"]).all()  # it estimates no slip: the column stays empty


def test_the_built_in_estimator_replays_the_log(recorded, tmp_path):
    from rover_env.tools.cli import main

    log_path, rig_file, _, truth, _ = recorded
    out = tmp_path / "builtin"
    assert main(["replay", str(log_path), "--rig", str(rig_file), "--out", str(out)]) == 0
    got = read_csv(out / "estimates.csv")
    v = got["v_x"][1:]
    ok = np.isfinite(v) & (got["odometry_quality"][1:] > 0)
    assert ok.mean() > 0.8
    assert np.mean(np.abs(v[ok] - truth[ok])) < 0.05  # [m/s]
    assert np.isfinite(got["axle_roll_F"][5:]).all()  # the fisheye's kinematics from the log's images


def test_bad_input_is_named_and_writes_nothing(recorded, tmp_path, capsys):
    from rover_env.tools.cli import main

    log_path, rig_file, *_ = recorded
    # a calibration of another size than the log's images
    text = rig_file.read_text()
    other = rig_file.parent / "downward.yaml"
    small = tmp_path / "small.yaml"
    small.write_text(other.read_text().replace("- 160\n- 120", "- 80\n- 60"))
    bad_rig = rig_file.parent / "bad_rig.yaml"
    bad_rig.write_text(text.replace("calibration: downward.yaml", f"calibration: {small}"))
    out = tmp_path / "o1"
    assert main(["replay", str(log_path), "--rig", str(bad_rig), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "160x120 px image" in err and "'downward'" in err and "80x60 px" in err
    assert not out.exists()
    # a factory that fails on the rig: named, exit status 2, nothing written
    picky = tmp_path / "picky.py"
    picky.write_text("class Picky:\n    def __init__(self, rig): self.cam = rig['front']\n")
    out = tmp_path / "o0"
    assert (
        main(
            [
                "replay",
                str(log_path),
                "--rig",
                str(rig_file),
                "--estimator",
                f"{picky}:Picky",
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "KeyError: 'front'" in capsys.readouterr().err and not out.exists()
    # an estimator that fails at its third update: named, with the step
    bad = tmp_path / "bad_estimator.py"
    bad.write_text(
        "class Boom:\n    def __init__(self, rig): self.k = 0\n    def reset(self, fix): pass\n"
        "    def update(self, messages, t):\n        self.k += 1\n"
        "        if self.k == 3: raise RuntimeError('boom')\n        return {'pose': [0.0, 0.0, 0.0]}\n"
    )
    out = tmp_path / "o2"
    assert (
        main(
            ["replay", str(log_path), "--rig", str(rig_file), "--estimator", f"{bad}:Boom", "--out", str(out)]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "estimator bad_estimator.Boom, step 2: RuntimeError: boom" in err
    assert not (out / "estimates.csv").exists()


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda t: t.replace("kind: imu", "kind: lidar"), r"sensors\[2\]\.kind: 'lidar'"),
        (
            lambda t: t.replace("kind: imu", "kind: wheel_encoders"),
            r"sensors\[2\]\.kind: 'wheel_encoders'; proprioceptive sensors are not read from logs yet",
        ),
        (lambda t: t.replace("rate_hz: 240.0", "rate_hz: -5"), r"sensors\[2\]: imu.rate_hz"),
        (lambda t: t.replace("calibration: downward.yaml", "calibration: nowhere.yaml"), "nowhere.yaml"),
        (lambda t: t.replace("- name: imu", "- name: downward"), "two sensors named 'downward'"),
    ],
)
def test_a_malformed_rig_file_is_a_config_error_naming_the_key(recorded, tmp_path, edit, message):
    _, rig_file, *_ = recorded
    path = rig_file.parent / "edited.yaml"
    path.write_text(edit(rig_file.read_text()))
    with pytest.raises(ConfigError, match=message):
        load_rig(path)

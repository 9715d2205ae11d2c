"""Messy real logs: glitched clocks, damaged files, odd encodings and units, careless output folders.

Every log here is written by the test (ROS 1 bags, ROS 2 SQLite bags and MCAP files with
rosbags) from frames rendered of a known planar motion, then damaged the way robots and disks
damage them. Each case ends in a result as accurate as the undamaged log's where the data
allows, or a one-line error naming the file, the key or the message, never a traceback, and
never a user's file lost.
"""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")

from test_bags import LogWriter  # noqa: E402
from test_odometry import START, make_ground, mast_camera, pose_after, render  # noqa: E402

from perception.logs import bags  # noqa: E402
from rover_env.tools.cli import main  # noqa: E402

T0 = 1_700_000_000.25
FPS, N = 60.0, 60
TWIST = (0.8, 0.05, 0.2)
TOPIC = "/down/image_raw"


@pytest.fixture(scope="module")
def frames():
    ground = make_ground()
    pose, out = START, []
    for k in range(N):
        if k:
            pose = pose_after(pose, TWIST, 1 / FPS)
        out.append(render(mast_camera(), ground, pose, rng=np.random.default_rng(k)))
    return out


def write_log(
    path: Path, kind: str, frames, stamps=None, info: bool = False, imu: bool = False, compression=None
) -> Path:
    """A log of ``frames`` received at T0 + k / FPS, stamped ``stamps`` (default: the same)."""
    with LogWriter(path, kind, compression) as lw:
        for k, img in enumerate(frames):
            t = T0 + k / FPS
            lw.image(TOPIC, t, img, encoding="mono8", stamp=None if stamps is None else stamps[k])
            if info:
                lw.camera_info("/down/camera_info", t, mast_camera())
        if imu:
            for j in range(int(len(frames) / FPS * 200) + 20):
                lw.imu("/imu/data", T0 - 0.05 + j / 200, (0.0, 0.0, TWIST[2] + 0.01), (0.0, 0.0, 9.81))
    return path


def calib(tmp_path: Path) -> Path:
    return mast_camera().save(tmp_path / "calib.yaml")


def odometry(tmp_path, source, out="out", *extra):
    """``rover odometry`` on ``source``: (exit status, rows or None)."""
    argv = ["odometry", str(source), "--calib", str(calib(tmp_path)), "--out", str(tmp_path / out), *extra]
    rc = main(argv)
    csv = tmp_path / out / "odometry.csv"
    rows = np.genfromtxt(csv, delimiter=",", names=True, dtype=None, encoding=None) if csv.exists() else None
    return rc, rows


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def clean_rows(frames, tmp_path_factory):
    """The undamaged log's rows: what every damaged log is held to."""
    tmp = tmp_path_factory.mktemp("clean")
    rc, rows = odometry(tmp, write_log(tmp / "clean.mcap", "mcap", frames))
    assert rc == 0 and len(rows) == N - 1 and rows["valid"].all()
    np.testing.assert_allclose(rows["v_x"], TWIST[0], rtol=0.01)
    np.testing.assert_allclose(rows["t"], T0 + np.arange(1, N) / FPS, atol=1e-6, rtol=0)
    return rows


def same_as_clean(rows, clean, skip=(), offset=0.0):
    """The valid rows are the clean log's at the same times (plus ``offset``), to the last digit written."""
    good = rows[rows["valid"] == 1]
    ref = clean[~np.isin(np.arange(1, len(clean) + 1), list(skip))]  # row k: the pair ending at frame k
    np.testing.assert_allclose(good["t"], ref["t"] + offset, atol=1e-6, rtol=0)
    for key in ("v_x", "v_y", "omega"):
        np.testing.assert_allclose(good[key], ref[key], atol=2e-6)


# ------------------------------------------------------------------ clocks


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_one_frame_stamped_1000_s_late_costs_only_the_pairs_touching_it(tmp_path, frames, clean_rows, kind):
    stamps = T0 + np.arange(N) / FPS
    stamps[30] += 1000.0  # one header clock glitch; the receive times are right
    name = {"ros1": "g.bag", "ros2": "g_ros2", "mcap": "g.mcap"}[kind]
    rc, rows = odometry(tmp_path, write_log(tmp_path / name, kind, frames, stamps))
    assert rc == 0
    assert len(rows) >= 57 and len(rows) == N - 1
    bad = rows[rows["valid"] == 0]
    assert len(bad) == 1  # frame 30's row: its pairs (29, 30) and (30, 31) are not measured
    assert "frame 30: header stamp steps 1000.017 s where the receive time steps 0.017 s" in bad["reason"][0]
    np.testing.assert_allclose(bad["t"], T0 + 30 / FPS, atol=1e-6, rtol=0)  # placed by the receive clock
    same_as_clean(np.delete(rows, [29, 30]), clean_rows, skip=(30, 31))
    # frame 31's pair spans the glitch (29 to 31), as accurate as the pairs around it
    row31 = rows[30]
    assert row31["valid"] and abs(row31["v_x"] - TWIST[0]) < 0.01 * TWIST[0]


def test_a_clock_that_jumps_back_10_s_keeps_every_frame_after_the_jump(tmp_path, frames, clean_rows):
    stamps = T0 + np.arange(N) / FPS
    stamps[30:] -= 10.0  # the camera's clock is set back part-way through, and stays there
    rc, rows = odometry(tmp_path, write_log(tmp_path / "jump.bag", "ros1", frames, stamps))
    assert rc == 0 and len(rows) == N - 1
    bad = rows[rows["valid"] == 0]
    assert "frame 30: header stamp" in bad["reason"][0] and "goes back 9.983 s" in bad["reason"][0]
    assert "the clock jumps here" in bad["reason"][0]
    assert len(bad) == 1  # the pair across the jump; frame 31 pairs with frame 30
    # the frames after the jump are processed, on one time line: the clock in effect at the end
    np.testing.assert_allclose(rows["t"], T0 - 10.0 + np.arange(1, N) / FPS, atol=1e-6, rtol=0)
    assert rows["valid"][30:].all()
    same_as_clean(np.delete(rows, [30]), clean_rows, skip=(30, 31), offset=-10.0)  # 31 pairs with the anchor
    assert abs(rows["v_x"][30] - TWIST[0]) < 0.01 * TWIST[0]
    tum = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    assert np.all(np.diff(tum[:, 0]) > 0)


@pytest.mark.parametrize("kind", ["ros2", "mcap"])
def test_frames_stored_out_of_order_are_put_back_in_stamp_order(tmp_path, frames, clean_rows, kind):
    path = tmp_path / ("swap_ros2" if kind == "ros2" else "swap.mcap")
    order = list(range(N))
    order[20], order[21] = 21, 20  # the recorder stored frame 21 first
    order[40], order[41], order[42] = 42, 40, 41
    with LogWriter(path, kind) as lw:
        for k, j in enumerate(order):  # frame j received in the k-th place, stamped at its own time
            lw.image(TOPIC, T0 + k / FPS, frames[j], encoding="mono8", stamp=T0 + j / FPS)
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and len(rows) == N - 1 and rows["valid"].all()
    same_as_clean(rows, clean_rows)


def test_a_repeated_stamp_is_flagged_as_such(tmp_path, frames):
    stamps = T0 + np.arange(12) / FPS
    stamps[6] = stamps[5]
    rc, rows = odometry(tmp_path, write_log(tmp_path / "rep.mcap", "mcap", frames[:12], stamps))
    assert rc == 0 and len(rows) == 11
    assert (
        "frame 6: header stamp" in rows["reason"][5]
        and "repeats the last good message's" in rows["reason"][5]
    )
    assert rows["valid"].sum() == 10  # frame 7 pairs with frame 5


def _placed(pairs, **kw):
    from perception.logs.log_time import in_stamp_order, place

    items = [SimpleNamespace(stamp=s, recv=r) for s, r in pairs]
    return place(in_stamp_order(items), **kw)


def test_stamp_clock_trusts_continuous_stamps_over_a_hiccuping_receive_clock():
    p = 1 / 30
    base = [(100 + k * p, 500 + k * p) for k in range(20)]
    # the recorder's host clock steps +10 s, or the recorder stalls 0.7 s and catches up in a burst
    step = [(s, r + (10.0 if k >= 8 else 0.0)) for k, (s, r) in enumerate(base)]
    stall = [(s, max(r, base[10][1] + 0.7) if 5 <= k <= 10 else r) for k, (s, r) in enumerate(base)]
    jitter = [(s, r + 0.7 * np.random.default_rng(k).random()) for k, (s, r) in enumerate(base)]
    for case in (step, stall, jitter):
        out = _placed(case)
        assert all(not x.why for x in out), [x.why for x in out if x.why]
        np.testing.assert_allclose([x.t for x in out], [s for s, _ in base], atol=1e-9, rtol=0)


def test_stamp_clock_flags_a_glitch_and_follows_a_jump():
    p = 1 / 30
    base = [(100 + k * p, 500 + k * p) for k in range(20)]
    first = [(s + (1000.0 if k == 0 else 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(first)  # the first stamp is the glitch: it does not start the time line
    assert math.isnan(out[0].t) and "disagrees with the next" in out[0].why
    np.testing.assert_allclose([x.t for x in out[1:]], [s for s, _ in base[1:]], atol=1e-9, rtol=0)
    small = [(s + (0.3 if k == 7 else 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(small)  # 0.3 s late: within the receive clock's tolerance, out of line all the same
    bad = [x for x in out if x.why]
    assert len(bad) == 1 and bad[0].item.stamp == small[7][0] and "out of line" in bad[0].why
    good = sorted((x.item.stamp, x.t) for x in out if not x.why)
    np.testing.assert_allclose(
        [t for _, t in good], [s for k, (s, _) in enumerate(base) if k != 7], atol=1e-9, rtol=0
    )
    assert np.all(np.diff([x.t for x in out]) > 0)  # rows in time order, the flagged one among them
    fwd = [(s + (10.0 if k >= 9 else 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(fwd)  # the camera's clock steps 10 s ahead and stays: one anchor, the rest on the line
    assert [k for k, x in enumerate(out) if x.why] == [9] and out[9].anchor
    np.testing.assert_allclose(
        [x.t for x in out], [s + 10.0 for s, _ in base], atol=1e-9, rtol=0
    )  # the end's clock
    const = [(100.0, r) for _, r in base]  # a driver that never sets the stamp: the receive times
    out = _placed(const)
    assert all(not x.why for x in out)
    np.testing.assert_allclose([x.t for x in out], [r for _, r in base], atol=1e-9, rtol=0)


# ------------------------------------------------------------------ damaged files


@pytest.mark.parametrize("compression", [None, "bz2"])
def test_a_ros1_bag_whose_last_chunk_is_damaged_keeps_every_frame_before_it(
    tmp_path, frames, clean_rows, caplog, compression
):
    from rosbags.rosbag1 import Reader

    path = write_log(tmp_path / "cut.bag", "ros1", frames, compression=compression)
    with Reader(path) as r:
        chunks = sorted(r.chunk_infos, key=lambda c: c.pos)
        last = chunks[-1]
        datapos = r.chunks[last.pos].datapos
        before = sum(1 for c, t, _ in r.messages() if t < last.start_time)
    data = bytearray(path.read_bytes())
    data[datapos : datapos + 64] = b"\xff" * 64  # the last chunk's first record header
    path.write_bytes(bytes(data))
    assert 10 < before < N
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and len(rows) == before - 1 and rows["valid"].all()
    same_as_clean(rows, clean_rows[: before - 1])
    msg = " ".join(r.getMessage() for r in caplog.records if "damaged" in r.getMessage())
    assert str(path) in msg and f"after {TOPIC} message {before - 1}" in msg and "reading ends there" in msg


def _pages(db: Path, kind: str) -> list[int]:
    con = sqlite3.connect(db)
    try:
        rows = con.execute(
            "SELECT pageno FROM dbstat WHERE name = 'messages' AND pagetype = ? ORDER BY pageno", (kind,)
        ).fetchall()
    except sqlite3.OperationalError:
        pytest.skip("this SQLite has no dbstat table to find a page by")
    finally:
        con.close()
    return [r[0] for r in rows]


def _damage_page(db: Path, page: int) -> None:
    data = bytearray(db.read_bytes())
    size = 4096
    data[(page - 1) * size : page * size] = (
        np.random.default_rng(1).integers(0, 256, size, np.uint8).tobytes()
    )
    db.write_bytes(bytes(data))


def test_a_ros2_bag_with_a_damaged_table_page_loses_only_that_pages_rows(
    tmp_path, frames, clean_rows, caplog
):
    path = write_log(tmp_path / "page_ros2", "ros2", frames)
    db = next(path.glob("*.db3"))
    leaves = _pages(db, "leaf")
    assert len(leaves) >= 3
    con = sqlite3.connect(db)  # the rows the damaged page holds
    lost = con.execute("SELECT ncell FROM dbstat WHERE pageno = ?", (leaves[1],)).fetchone()[0]
    con.close()
    _damage_page(db, leaves[1])
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and 0 < lost < 20
    assert len(rows) == N - 1 - lost  # every frame but the damaged page's
    good = rows[rows["valid"] == 1]
    assert len(good) >= len(rows) - 1  # at most the pair across the gap is invalid
    np.testing.assert_allclose(good["v_x"], TWIST[0], rtol=0.01)
    msg = " ".join(r.getMessage() for r in caplog.records if "damaged page" in r.getMessage())
    assert str(db) in msg and "are lost; every other row is read" in msg


def test_a_ros2_bag_with_one_damaged_message_page_loses_only_that_message(
    tmp_path, frames, clean_rows, caplog
):
    path = write_log(tmp_path / "row_ros2", "ros2", frames)
    db = next(path.glob("*.db3"))
    overflow = _pages(db, "overflow")
    _damage_page(db, overflow[len(overflow) // 2])  # one page inside one image's data
    rc, rows = odometry(tmp_path, path)
    assert rc == 0
    lost = [r.getMessage() for r in caplog.records if "is damaged" in r.getMessage()]
    assert len(lost) == 1 and TOPIC in lost[0] and str(db) in lost[0]
    k = int(lost[0].split(f"{TOPIC} message ")[1].split()[0])
    assert 20 < k < 40
    # the frame is skipped: its neighbours pair across it, two frame periods apart
    assert len(rows) == N - 2 and rows["valid"].all()
    assert rows["t"][k - 1] == pytest.approx(T0 + (k + 1) / FPS, abs=1e-6, rel=0)
    np.testing.assert_allclose(rows["v_x"], TWIST[0], rtol=0.01)


def test_a_ros2_bag_cut_in_half_is_read_through_a_repaired_copy(tmp_path, frames, clean_rows, caplog):
    path = write_log(tmp_path / "half_ros2", "ros2", frames)
    db = next(path.glob("*.db3"))
    data = db.read_bytes()
    db.write_bytes(data[: len(data) // 2 + 1234])  # a copy that stopped half-way, mid-page
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and len(rows) >= 15 and rows["valid"].all()
    same_as_clean(rows, clean_rows[: len(rows)])
    assert any(
        "reading a repaired copy" in r.getMessage() and str(db) in r.getMessage() for r in caplog.records
    )
    assert db.read_bytes() == data[: len(data) // 2 + 1234]  # the user's file is not touched


def test_a_split_ros2_bag_without_its_metadata_is_read_in_its_files_order(tmp_path, frames, clean_rows):
    """A recorder killed before it wrote metadata.yaml, after splitting into 11 files."""
    folder = tmp_path / "split"
    folder.mkdir()
    parts = np.array_split(np.arange(N), 11)
    for i, idx in enumerate(parts):
        part = tmp_path / f"part{i}"
        with LogWriter(part, "ros2") as lw:
            for k in idx:
                lw.image(TOPIC, T0 + k / FPS, frames[k], encoding="mono8")
        next(part.glob("*.db3")).replace(folder / f"rosbag2_{i}.db3")
    assert bags.is_log(folder)
    rc, rows = odometry(tmp_path, folder)
    assert rc == 0 and len(rows) == N - 1 and rows["valid"].all()  # bag_2 before bag_10
    same_as_clean(rows, clean_rows)


def test_a_cut_off_mcap_keeps_every_frame_before_the_cut(tmp_path, frames, clean_rows, caplog):
    path = write_log(tmp_path / "cut.mcap", "mcap", frames)
    data = path.read_bytes()
    path.write_bytes(data[: int(0.6 * len(data))])  # the recorder died: no summary, no footer
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and 30 < len(rows) < N - 1 and rows["valid"].all()
    same_as_clean(rows, clean_rows[: len(rows)])
    msg = " ".join(r.getMessage() for r in caplog.records if "cut off" in r.getMessage())
    assert str(path) in msg and "at byte" in msg and f"after the {TOPIC} message at log time" in msg


def test_a_damaged_definition_inside_an_mcap_chunk_costs_no_message(tmp_path, frames, clean_rows, caplog):
    """The schema record at the head of the first chunk is damaged; the summary still defines it."""
    path = write_log(tmp_path / "schema.mcap", "mcap", frames)
    data = bytearray(path.read_bytes())
    at = data.index(b"sensor_msgs/msg/Image")  # the first chunk's copy of the image schema
    data[at : at + 16] = b"\xab" * 16
    path.write_bytes(bytes(data))
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and len(rows) == N - 1 and rows["valid"].all()
    same_as_clean(rows, clean_rows)
    assert any(
        "is damaged" in r.getMessage() and "other records are read" in r.getMessage() for r in caplog.records
    )


def test_a_cut_inside_the_only_chunk_keeps_the_messages_before_it(tmp_path, capsys):
    """A short recording is one chunk: a cut through it keeps the frames before the cut."""
    small = mast_camera((160, 120))
    ground = make_ground()
    pose, path = START, tmp_path / "one_chunk.mcap"
    with LogWriter(path, "mcap") as lw:
        for k in range(20):
            if k:
                pose = pose_after(pose, TWIST, 1 / FPS)
            lw.image(
                TOPIC,
                T0 + k / FPS,
                render(small, ground, pose, rng=np.random.default_rng(k)),
                encoding="mono8",
            )
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    out = tmp_path / "o"
    argv = ["odometry", str(path), "--calib", str(small.save(tmp_path / "small.yaml")), "--out", str(out)]
    assert main(argv) == 0
    rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    assert (
        8 <= len(rows) <= 10 and rows["valid"].all()
    )  # 19,200 px a frame: 9 or 10 whole frames before the cut


def test_damaged_camera_info_and_imu_messages_are_skipped_with_their_topic_index_and_time(
    tmp_path, frames, caplog
):
    path = tmp_path / "msgs.mcap"
    cam = mast_camera()
    with LogWriter(path, "mcap") as lw:
        for k, img in enumerate(frames[:20]):
            t = T0 + k / FPS
            if k == 0:  # the first CameraInfo is garbage; the later ones are fine
                lw.write_raw("/down/camera_info", "sensor_msgs/msg/CameraInfo", b"\x00\x01\x00\x00garbage", t)
            else:
                lw.camera_info("/down/camera_info", t, cam)
            lw.image(TOPIC, t, img, encoding="mono8")
        for j in range(100):
            t = T0 - 0.05 + j / 200
            if j == 40:
                lw.write_raw("/imu/data", "sensor_msgs/msg/Imu", b"\x00\x01\x00\x00\x07", t)
            else:
                lw.imu("/imu/data", t, (0.0, 0.0, TWIST[2] + 0.01), (0.0, 0.0, 9.81))
    data = yaml.safe_load(cam.save(tmp_path / "full.yaml").read_text())
    (tmp_path / "mount.yaml").write_text(yaml.safe_dump({k: data[k] for k in ("T_body_cam", "ground_plane")}))
    argv = ["odometry", str(path), "--calib", str(tmp_path / "mount.yaml"), "--out", str(tmp_path / "o")]
    assert main([*argv, "--imu-topic", "/imu/data"]) == 0
    rows = np.genfromtxt(
        tmp_path / "o" / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    assert len(rows) == 19 and rows["valid"].all()
    np.testing.assert_allclose(rows["omega_imu"], TWIST[2], atol=2e-3)
    msgs = [r.getMessage() for r in caplog.records if "does not deserialise" in r.getMessage()]
    assert any("/down/camera_info message 0 (log time 1700000000.250000 s)" in m for m in msgs)
    assert any("/imu/data message 40 (log time 1700000000.400000 s)" in m for m in msgs)


@pytest.mark.parametrize("kind", ["ros1", "ros2", "mcap"])
def test_damage_anywhere_gives_a_result_or_one_line_never_a_traceback(tmp_path, frames, kind, capsys):
    """Damage at many places of each kind of log: the frames before it are kept where the
    format allows, or a one-line error; never a traceback or an unforeseen error."""
    n = 24
    name = {"ros1": "f.bag", "ros2": "f_ros2", "mcap": "f.mcap"}[kind]
    src = write_log(tmp_path / name, kind, frames[:n], info=True)
    target = next(src.glob("*.db3")) if src.is_dir() else src
    original = target.read_bytes()
    rng = np.random.default_rng(7)
    for trial, frac in enumerate(np.linspace(0.0, 1.0, 9)):
        data = bytearray(original)
        at = min(int(frac * len(data)), len(data) - 64)
        cut = bool(trial % 2)
        if cut:  # the recording stops there
            data = data[: max(at, 1)]
        else:  # 64 bytes overwritten there
            data[at : at + 64] = rng.integers(0, 256, 64, np.uint8).tobytes()
        target.write_bytes(bytes(data))
        out = tmp_path / f"o{trial}"
        rc = main(["odometry", str(src), "--calib", str(calib(tmp_path)), "--out", str(out)])
        err = capsys.readouterr().err
        assert "Traceback" not in err and rc in (0, 1, 2), (trial, frac, rc, err)
        assert rc == 0 or len([ln for ln in err.splitlines() if "error:" in ln]) == 1
        # where the data before the damage is intact and findable, it is used: MCAP always; ROS 2
        # (SQLite) and ROS 1 where only data was overwritten (ROS 1's index is at its end, SQLite's
        # b-tree pages anywhere)
        keeps = kind == "mcap" or (not cut and (kind == "ros2" or frac < 0.9))
        if keeps and frac >= 0.5:
            assert rc == 0, (trial, frac, err)
            rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
            assert len(rows) >= int(frac * n) - 4, (trial, frac, len(rows))


# ------------------------------------------------------------------ output folders


def test_nothing_the_user_put_in_out_is_removed_whatever_its_name(tmp_path, frames, capsys):
    out = tmp_path / "out"
    user_frames = out / "odometry"  # a frames folder of the name the old MCAP writer cleared
    user_frames.mkdir(parents=True)
    for k, img in enumerate(frames[:4]):
        cv2.imwrite(str(user_frames / f"{k:03d}.png"), img)
    (out / "notes.txt").write_text("mine")
    (out / "kinematics").mkdir()
    (out / "kinematics" / "keep.txt").write_text("mine too")
    from test_markers import fisheye, render_markers, rover_model

    model = rover_model()
    cam = fisheye(model)
    rgb = render_markers(model, cam, (0.0, 0.0), (0.15, 0.15), model.wheel_angles(0.0, 0.0))
    cv2.imwrite(str(out / "kinematics" / "000.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # the input inside --out is refused before anything is written
    argv = ["odometry", str(user_frames), "--calib", str(calib(tmp_path)), "--fps", "60", "--out", str(out)]
    assert main(argv) == 2
    assert "holds the input" in one_error_line(capsys)
    # a log elsewhere, into the same folder: the results go in beside the user's files
    assert main(["odometry", str(write_log(tmp_path / "l.mcap", "mcap", frames[:6])), "--calib",
                 str(calib(tmp_path)), "--out", str(out)]) == 0  # fmt: skip
    # rover kinematics on a folder of that name inside --out: refused, the folder untouched
    from test_markers import fisheye, rover_model

    model = rover_model()
    argv = [
        "kinematics",
        str(out / "kinematics"),
        "--camera",
        str(fisheye(model).save(tmp_path / "omni.yaml")),
    ]
    argv += ["--rover", str(model.save(tmp_path / "rover.yaml")), "--fps", "30", "--out", str(out)]
    assert main(argv) == 2
    assert "holds the input" in one_error_line(capsys)
    after = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert all(after.get(p) == b for p, b in before.items())
    assert set(after) - set(before) == {out / n for n in ("odometry.csv", "trajectory.tum", "odometry.mcap")}


def test_overwrite_replaces_only_what_this_run_writes(tmp_path, frames, capsys, caplog):
    log_path = write_log(tmp_path / "i.mcap", "mcap", frames[:12], imu=True)
    base = ["odometry", str(log_path), "--calib", str(calib(tmp_path)), "--out", str(tmp_path / "out")]
    assert main(base) == 0
    (tmp_path / "out" / "mine.csv").write_text("keep")
    (tmp_path / "out" / "trajectory_imu.tum").write_text("my own trajectory")  # a user's file of that name
    before = (tmp_path / "out" / "odometry.csv").read_bytes()
    assert main(base) == 2 and "--overwrite" in one_error_line(capsys)
    assert main([*base, "--overwrite"]) == 0  # no IMU this run: the file of the IMU path's name is kept
    names = {p.name for p in (tmp_path / "out").iterdir()}
    assert names == {"odometry.csv", "trajectory.tum", "odometry.mcap", "mine.csv", "trajectory_imu.tum"}
    assert (tmp_path / "out" / "trajectory_imu.tum").read_text() == "my own trajectory"
    assert (tmp_path / "out" / "odometry.csv").read_bytes() == before  # remade, the same
    assert "trajectory_imu.tum is not from this run" in caplog.text
    assert main([*base, "--imu-topic", "/imu/data", "--overwrite"]) == 0  # this run writes it: replaced
    assert (tmp_path / "out" / "trajectory_imu.tum").read_text() != "my own trajectory"


def test_a_full_disk_names_the_file_and_leaves_the_earlier_results_or_nothing(
    tmp_path, frames, monkeypatch, capsys
):
    from perception.logs.outputs import OutputFolder

    if not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    log_path = write_log(tmp_path / "d.mcap", "mcap", frames[:6])
    argv = ["odometry", str(log_path), "--calib", str(calib(tmp_path))]
    assert main([*argv, "--out", str(tmp_path / "old")]) == 0
    earlier = {p.name: p.read_bytes() for p in (tmp_path / "old").iterdir()}
    stage = OutputFolder.stage

    def full(self, name):  # the staged file is a disk with no space left (ENOSPC on write)
        tmp = stage(self, name)
        tmp.unlink()
        tmp.symlink_to("/dev/full")
        return tmp

    monkeypatch.setattr(OutputFolder, "stage", full)
    assert main([*argv, "--out", str(tmp_path / "new" / "run")]) == 2
    line = one_error_line(capsys)
    assert str(tmp_path / "new" / "run" / "odometry.csv") in line and "No space left" in line
    assert not (tmp_path / "new").exists()  # the folders this run made are gone again
    assert main([*argv, "--out", str(tmp_path / "old"), "--overwrite"]) == 2
    assert {p.name: p.read_bytes() for p in (tmp_path / "old").iterdir()} == earlier


# ------------------------------------------------------------------ images, calibration, IMU


def _image_msg(img: np.ndarray, encoding: str) -> SimpleNamespace:
    h, w = img.shape[:2]
    return SimpleNamespace(
        encoding=encoding, height=h, width=w, step=img.nbytes // h, is_bigendian=0, data=img.tobytes()
    )


def test_bayer_and_yuv_images_decode_to_the_scene_and_other_encodings_are_named():
    rng = np.random.default_rng(2)
    small = rng.integers(0, 256, (30, 40, 3), np.uint8)
    bgr = cv2.resize(small, (320, 240), interpolation=cv2.INTER_CUBIC)  # smooth: demosaicing can recover it
    b, g, r = bgr[..., 0], bgr[..., 1], bgr[..., 2]
    mosaic = np.empty(bgr.shape[:2], np.uint8)  # RGGB: R at (0, 0), B at (1, 1)
    mosaic[0::2, 0::2], mosaic[0::2, 1::2] = r[0::2, 0::2], g[0::2, 1::2]
    mosaic[1::2, 0::2], mosaic[1::2, 1::2] = g[1::2, 0::2], b[1::2, 1::2]
    img, why = bags.decode_image(_image_msg(mosaic, "bayer_rggb8"), "sensor_msgs/msg/Image")
    assert why == "" and img.shape == bgr.shape
    err = np.abs(img[4:-4, 4:-4].astype(float) - bgr[4:-4, 4:-4]).mean(axis=(0, 1))
    assert err.max() < 6, err  # every channel in its place (a wrong pattern swaps red and blue: ~40)
    for enc, code in (("yuv422", cv2.COLOR_BGR2YUV_UYVY), ("yuyv", cv2.COLOR_BGR2YUV_YUY2)):
        packed = cv2.cvtColor(bgr, code)  # two bytes a pixel, chroma shared by pixel pairs
        img, why = bags.decode_image(_image_msg(packed, enc), "sensor_msgs/msg/Image")
        assert why == "" and np.abs(img.astype(float) - bgr).mean() < 8
    _, why = bags.decode_image(_image_msg(np.zeros((4, 4), np.float32), "32FC1"), "sensor_msgs/msg/Image")
    assert "'32FC1' is not a camera image" in why and "bayer_rggb8" in why


def test_a_log_of_depth_images_is_refused_with_its_encoding(tmp_path, capsys):
    path = tmp_path / "depth.mcap"
    with LogWriter(path, "mcap") as lw:
        for k in range(5):
            lw.image(TOPIC, T0 + k / 30, np.ones((480, 640), np.float32), encoding="32FC1")
    rc, rows = odometry(tmp_path, path)
    assert rc == 2 and rows is None
    assert "'32FC1' is not a camera image" in one_error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_a_log_without_a_single_valid_pair_exits_non_zero_with_the_reason(tmp_path, frames, capsys):
    rc, rows = odometry(tmp_path, write_log(tmp_path / "one.mcap", "mcap", frames[:1]))
    assert rc == 1 and "no valid estimate in 0 pairs" in one_error_line(capsys)
    black = [np.zeros_like(f) for f in frames[:5]]
    rc, rows = odometry(tmp_path, write_log(tmp_path / "black.mcap", "mcap", black), "out2")
    assert rc == 1 and len(rows) == 4 and not rows["valid"].any()
    assert "most often" in one_error_line(capsys)


def test_a_rational_polynomial_camera_info_is_modelled_not_truncated(tmp_path):
    """Frames of a strongly distorted lens (k4..k6 of the rational model): with all 8 coefficients
    the odometry is as accurate as on an ideal lens; cut to 5 it is not."""
    base = mast_camera()
    d = np.array([-0.25, 0.08, 0.001, -0.001, 0.01, 0.2, 0.02, 0.003])
    from perception.models.cameras import PinholeCamera

    lens = PinholeCamera(K=base.K, distortion=d, image_size=base.image_size, T_body_cam=base.T_body_cam,
                         ground_plane=base.ground_plane)  # fmt: skip
    ground = make_ground()
    pose, path = START, tmp_path / "rational.mcap"
    with LogWriter(path, "mcap") as lw:
        for k in range(8):
            if k:
                pose = pose_after(pose, TWIST, 1 / FPS)
            t = T0 + k / FPS
            lw.image(TOPIC, t, render(lens, ground, pose, rng=np.random.default_rng(k)), encoding="mono8")
            lw.camera_info("/down/camera_info", t, lens, model="rational_polynomial")
    info = bags.camera_info(path, TOPIC)
    np.testing.assert_array_equal(info["distortion"], d)
    data = yaml.safe_load(lens.save(tmp_path / "full.yaml").read_text())
    (tmp_path / "mount.yaml").write_text(yaml.safe_dump({k: data[k] for k in ("T_body_cam", "ground_plane")}))
    out = tmp_path / "o"
    assert main(["odometry", str(path), "--calib", str(tmp_path / "mount.yaml"), "--out", str(out)]) == 0
    rows = np.genfromtxt(out / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None)
    np.testing.assert_allclose(rows["v_x"], TWIST[0], rtol=0.01)
    # the same frames through the first five coefficients only: the speed is visibly wrong
    data["distortion"] = d[:5].tolist()
    (tmp_path / "five.yaml").write_text(yaml.safe_dump(data))
    assert (
        main(["odometry", str(path), "--calib", str(tmp_path / "five.yaml"), "--out", str(tmp_path / "f")])
        == 0
    )
    five = np.genfromtxt(
        tmp_path / "f" / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    assert np.nanmedian(np.abs(five["v_x"] / TWIST[0] - 1)) > 0.05


def test_a_pinhole_of_eight_coefficients_round_trips_and_matches_opencv():
    from perception.models.calib_io import CalibrationError
    from perception.models.cameras import PinholeCamera

    K = np.array([[400.0, 0, 320], [0, 400, 240], [0, 0, 1]])
    d = np.array([-0.25, 0.08, 0.001, -0.001, 0.01, 0.2, 0.02, 0.003])
    cam = PinholeCamera(K=K, distortion=d, image_size=(640, 480))
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-0.7, 0.7, 200), rng.uniform(-0.5, 0.5, 200), np.ones(200)])
    ref, _ = cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, d)
    np.testing.assert_allclose(cam.project(P), ref[:, 0], atol=1e-9)
    np.testing.assert_allclose(cam.normalized(cam.project(P)), P[:, :2], atol=1e-12)
    for bad in (np.zeros(12), np.zeros(3), np.zeros(6)):  # thin prism, too short, no model of 6
        with pytest.raises(CalibrationError, match="rational_polynomial"):
            PinholeCamera(K=K, distortion=bad, image_size=(640, 480))


@pytest.mark.parametrize(
    ("model", "K", "message"),
    [
        ("equidistant", None, "distortion model 'equidistant' is not one the pinhole camera models"),
        ("plumb_bob", np.zeros((3, 3)), "has no positive focal lengths"),
    ],
)
def test_a_bad_camera_info_is_blamed_on_the_log_not_the_calibration(
    tmp_path, frames, capsys, model, K, message
):
    cam = mast_camera()
    fish = _with_distortion(cam, np.array([0.1, -0.02, 0.003, -0.001, 0.0]))
    path = tmp_path / "info.mcap"
    with LogWriter(path, "mcap") as lw:
        for k, img in enumerate(frames[:4]):
            lw.image(TOPIC, T0 + k / FPS, img, encoding="mono8")
            lw.camera_info("/down/camera_info", T0 + k / FPS, fish, model=model, K=K)
    data = yaml.safe_load(cam.save(tmp_path / "full.yaml").read_text())
    mount = tmp_path / "mount.yaml"
    mount.write_text(yaml.safe_dump({k: data[k] for k in ("T_body_cam", "ground_plane")}))
    assert main(["odometry", str(path), "--calib", str(mount), "--out", str(tmp_path / "o")]) == 2
    line = one_error_line(capsys)
    assert message in line and f"{path}: /down/camera_info" in line and "mount.yaml" not in line
    # a calibration with every intrinsic does not need the CameraInfo: the run goes on
    assert (
        main(["odometry", str(path), "--calib", str(tmp_path / "full.yaml"), "--out", str(tmp_path / "p")])
        == 0
    )


def _with_distortion(cam, distortion):
    from perception.models.cameras import PinholeCamera

    return PinholeCamera(K=cam.K, distortion=distortion, image_size=cam.image_size)


def _imu_csv(path: Path, t, gyro_z, accel_z=9.81, bias=0.004) -> Path:
    rows = ["t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"]
    rows += [f"{ti:.6f},0.001,-0.002,{w + bias:.6f},0.02,-0.01,{accel_z:.5f}" for ti, w in zip(t, gyro_z)]
    path.write_text("\n".join(rows) + "\n")
    return path


def _folder(tmp_path: Path, frames) -> Path:
    d = tmp_path / "imgs"
    d.mkdir()
    for k, img in enumerate(frames):
        cv2.imwrite(str(d / f"{k:03d}.png"), img)
    return d


def test_imu_files_in_other_units_are_refused_before_any_image_with_the_likely_unit(tmp_path, frames, capsys):
    imgs = _folder(tmp_path, frames[:20])
    t = np.arange(-1.0, 20 / FPS, 1 / 200)
    w = np.where(t > 0, TWIST[2], 0.0)
    argv = [
        "odometry",
        str(imgs),
        "--calib",
        str(calib(tmp_path)),
        "--fps",
        "60",
        "--out",
        str(tmp_path / "o"),
    ]
    cases = [
        (
            _imu_csv(tmp_path / "deg.csv", t, np.degrees(w), bias=0.5),
            ["--imu-still", "1"],
            "looks like deg/s",
        ),
        (_imu_csv(tmp_path / "g.csv", t, w, accel_z=1.0), ["--imu-still", "1"], "looks like g"),
        (_imu_csv(tmp_path / "mms.csv", t, w, accel_z=9810.0), [], "looks like mm/s^2"),
        (_imu_csv(tmp_path / "fast.csv", t, w * 1000), [], "beyond any gyro's range"),
        (_imu_csv(tmp_path / "clock.csv", t + 1000.0, w), [], "no overlap"),
    ]
    for path, extra, message in cases:
        assert main([*argv, "--imu", str(path), *extra]) == 2
        line = one_error_line(capsys)
        assert message in line and str(path) in line, line
        assert not (tmp_path / "o").exists()  # refused before an image was read or a folder made


def test_a_gyro_in_deg_s_without_a_standstill_is_found_by_the_odometry(tmp_path, frames, capsys):
    imgs = _folder(tmp_path, frames[:30])
    t = np.arange(0.0, 30 / FPS, 1 / 200)
    w = np.full(len(t), TWIST[2])
    deg = _imu_csv(tmp_path / "deg.csv", t, np.degrees(w), bias=0.0)
    ok = _imu_csv(tmp_path / "ok.csv", t, w, bias=0.0)
    argv = ["odometry", str(imgs), "--calib", str(calib(tmp_path)), "--fps", "60"]
    # the frames turn at TWIST[2]; a gyro that says 57 times that is in deg/s
    assert main([*argv, "--out", str(tmp_path / "a"), "--imu", str(deg)]) == 2
    line = one_error_line(capsys)
    assert "times the odometry's" in line and "looks like deg/s" in line
    # the odometry itself is kept, without the IMU's columns
    names = {p.name for p in (tmp_path / "a").iterdir()}
    assert names == {"odometry.csv", "trajectory.tum", "odometry.mcap"}
    assert main([*argv, "--out", str(tmp_path / "b"), "--imu", str(ok)]) == 0
    rows = np.genfromtxt(
        tmp_path / "b" / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    np.testing.assert_allclose(rows["omega_imu"], TWIST[2], atol=5e-3)  # the bias fitted to the odometry


def test_a_mono_fisheye_log_exits_non_zero_with_the_reason(tmp_path, capsys):
    from test_markers import fisheye, rover_model

    model = rover_model()
    cam = fisheye(model)
    w, h = cam.image_size
    path = tmp_path / "mono.mcap"
    with LogWriter(path, "mcap") as lw:
        for k in range(3):
            lw.image("/fisheye/image_raw", T0 + k / 30, np.full((h, w), 90, np.uint8), encoding="mono8")
    argv = ["kinematics", str(path), "--camera", str(cam.save(tmp_path / "omni.yaml"))]
    argv += ["--rover", str(model.save(tmp_path / "rover.yaml")), "--out", str(tmp_path / "k")]
    assert main(argv) == 1
    line = one_error_line(capsys)
    assert "no degree of freedom measured on any of 3 frames" in line and "give 8-bit colour images" in line


# ------------------------------------------------------------------ review findings


def test_a_camera_and_imu_clock_that_jump_together_keep_the_imu_on_the_pairs(tmp_path, frames):
    """The robot's clock is set back 10 s part-way: the IMU's stamps follow the camera's."""
    path = tmp_path / "jump_imu.mcap"
    jump = T0 + 30 / FPS - 0.001  # the receive time from which every stamp is 10 s early
    with LogWriter(path, "mcap") as lw:
        for k, img in enumerate(frames):
            t = T0 + k / FPS
            lw.image(TOPIC, t, img, encoding="mono8", stamp=t - (10.0 if t >= jump else 0.0))
        T = lw.store.types
        for j in range(int(N / FPS * 200) + 20):
            t = T0 - 0.05 + j / 200
            V3 = T["geometry_msgs/msg/Vector3"]
            msg = T["sensor_msgs/msg/Imu"](
                header=lw.header(t - (10.0 if t >= jump else 0.0)),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=V3(x=0.0, y=0.0, z=TWIST[2] + 0.01),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=V3(x=0.0, y=0.0, z=9.81),
                linear_acceleration_covariance=np.zeros(9),
            )
            lw.write("/imu/data", "sensor_msgs/msg/Imu", msg, t)
    rc, rows = odometry(tmp_path, path, "out", "--imu-topic", "/imu/data")
    assert rc == 0 and len(rows) == N - 1
    after = rows[31:]  # the pairs after the jump have their IMU samples, on the same time line
    assert np.all(after["imu_samples"] >= 3)
    np.testing.assert_allclose(after["omega_imu"], TWIST[2], atol=5e-3)


def test_a_camera_drop_out_is_not_filled_with_made_up_motion(tmp_path, frames):
    """10 s without frames (the log goes on): the path holds the last twist 0.5 s at most."""
    stamps = T0 + np.arange(12) / FPS
    stamps[6:] += 10.0
    path = tmp_path / "drop.mcap"
    with LogWriter(path, "mcap") as lw:
        for k, img in enumerate(frames[:12]):
            img = img if k != 6 else np.zeros_like(img)  # the first frame after the gap is black
            lw.image(TOPIC, stamps[k], img, encoding="mono8")
    rc, rows = odometry(tmp_path, path)
    assert rc == 0
    tum = np.loadtxt(tmp_path / "out" / "trajectory.tum")
    travelled = np.sum(np.hypot(np.diff(tum[:, 1]), np.diff(tum[:, 2])))
    true = TWIST[0] * 10 / FPS  # the frames' own motion (they are consecutive views)
    assert travelled < true + TWIST[0] * 0.5 + 0.05, travelled  # at most 0.5 s of hold, not 10 s


def test_sigterm_mid_run_leaves_nothing_half_written(tmp_path, frames, monkeypatch, capsys):
    import os
    import signal

    from perception.odometry.flow import FlowOdometry

    calls = {"n": 0}
    update = FlowOdometry.update

    def update_then_kill(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 5:
            os.kill(os.getpid(), signal.SIGTERM)  # what timeout, docker stop and Slurm send
        return update(self, *a, **k)

    monkeypatch.setattr(FlowOdometry, "update", update_then_kill)
    path = write_log(tmp_path / "k.mcap", "mcap", frames[:12])
    out = tmp_path / "out"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    rc = main(["odometry", str(path), "--calib", str(calib(tmp_path)), "--out", str(out)])
    assert rc == 143 and "terminated" in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["mine.txt"]  # no staged file, no stray folder


def test_results_get_the_usual_file_permissions(tmp_path, frames):
    import os
    import stat

    rc, _ = odometry(tmp_path, write_log(tmp_path / "p.mcap", "mcap", frames[:4]))
    mask = os.umask(0)
    os.umask(mask)
    for name in ("odometry.csv", "trajectory.tum", "odometry.mcap"):
        mode = stat.S_IMODE((tmp_path / "out" / name).stat().st_mode)
        assert mode == 0o666 & ~mask, (name, oct(mode))


def test_camera_info_binning_roi_and_a_compressed_topic_beside_it(tmp_path, frames):
    """The sensor is 1280x960; the driver bins 2x2: K is the sensor's, the images half its size."""
    cam = mast_camera()
    full_K = cam.K.copy()
    full_K[:2] *= 2.0  # the same lens on the full sensor
    path = tmp_path / "binned.mcap"
    with LogWriter(path, "mcap") as lw:
        T = lw.store.types
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        for k, img in enumerate(frames[:8]):
            t = T0 + k / FPS
            lw.image("/down/image_raw/compressed", t, img, compressed="png")
            msg = T["sensor_msgs/msg/CameraInfo"](
                header=lw.header(t), height=960, width=1280, distortion_model="plumb_bob", binning_x=2,
                binning_y=2, roi=roi, k=full_K.ravel(), d=np.zeros(5), r=np.eye(3).ravel(), p=np.zeros(12),
            )  # fmt: skip
            lw.write("/down/camera_info", "sensor_msgs/msg/CameraInfo", msg, t)
        lw.camera_info("/other/camera_info", T0, cam)  # a second camera's: not beside the images
    info = bags.camera_info(path, "/down/image_raw/compressed")
    assert info["topic"] == "/down/camera_info" and info["image_size"] == cam.image_size
    np.testing.assert_allclose(info["K"], cam.K, atol=1e-9)
    data = yaml.safe_load(cam.save(tmp_path / "full.yaml").read_text())
    (tmp_path / "mount.yaml").write_text(yaml.safe_dump({k: data[k] for k in ("T_body_cam", "ground_plane")}))
    assert (
        main(["odometry", str(path), "--calib", str(tmp_path / "mount.yaml"), "--out", str(tmp_path / "o")])
        == 0
    )
    rows = np.genfromtxt(
        tmp_path / "o" / "odometry.csv", delimiter=",", names=True, dtype=None, encoding=None
    )
    np.testing.assert_allclose(rows["v_x"], TWIST[0], rtol=0.01)


def test_odd_yuv_a_bom_and_a_missing_source_are_one_line_each(tmp_path, frames, capsys):
    img, why = bags.decode_image(_image_msg(np.zeros((4, 5, 2), np.uint8), "yuv422"), "sensor_msgs/msg/Image")
    assert img is None and "odd width 5 px" in why
    from perception.fusion.inertial import read_imu_csv

    bom = tmp_path / "bom.csv"
    bom.write_text(
        "\ufefft,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z\n0.0,0,0,0.1,0,0,9.81\n", encoding="utf-8"
    )
    assert read_imu_csv(bom).gyro[0, 2] == 0.1
    assert (
        main(
            [
                "odometry",
                str(tmp_path / "nope.bag"),
                "--calib",
                str(calib(tmp_path)),
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "nope.bag: no such file or folder" in one_error_line(capsys)


# ------------------------------------------------------------------ two things wrong at once


def _stream(n=90, p=1 / 30, t0=100.0, r0=500.0):
    return [(t0 + k * p, r0 + k * p) for k in range(n)]


def test_a_stepped_receive_clock_then_a_drop_out_costs_only_the_dropped_frames():
    base = _stream()
    case = [(s, r + (1.0 if k >= 20 else 0.0)) for k, (s, r) in enumerate(base) if k not in (25, 26, 27, 28)]
    out = _placed(case)
    assert not [x.why for x in out if x.why]
    np.testing.assert_allclose([x.t for x in out], [s for s, _ in case], atol=1e-9, rtol=0)


@pytest.mark.parametrize(("rate", "stall"), [(10.0, 2.0), (30.0, 0.6), (30.0, 2.0)])
def test_a_drop_out_while_the_recorder_stalls_is_no_clock_jump(rate, stall):
    """Frames 30-33 dropped; the recorder stalls and writes the queued frames in a burst."""
    p = 1 / rate
    base = _stream(120, p)
    queued_until = base[34][1] + stall
    case = []
    for k, (s, r) in enumerate(base):
        if 30 <= k < 34:
            continue
        burst = base[34][1] + stall + 0.001 * (k - 34)
        case.append((s, max(r, burst) if r < queued_until else r))
    out = _placed(case)
    assert not [x.why for x in out if x.why] and not any(x.anchor for x in out)
    np.testing.assert_allclose([x.t for x in out], [s for s, _ in case], atol=1e-9, rtol=0)


def test_a_clock_set_back_by_less_than_the_tolerance_gives_no_wrong_pair():
    base = _stream(60)
    case = [(s - (0.2 if k >= 30 else 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(case)
    accepted = [x for x in out if not x.why]
    assert len(out) - len(accepted) <= 7  # below the tolerance: the 0.2 s the clock went back over is flagged
    t = np.array([x.t for x in out])
    assert np.all(np.diff(t) > 0)
    # every accepted pair spans its true time: the stamps' steps, the step itself taken out
    truth = {round(x.item.recv, 6): x.item.recv - 400.0 for x in out}
    for a, b in zip(accepted, accepted[1:]):
        if not b.anchor:
            true_dt = truth[round(b.item.recv, 6)] - truth[round(a.item.recv, 6)]
            assert b.t - a.t == pytest.approx(true_dt, abs=1e-9)


def test_a_camera_and_an_imu_on_one_clock_share_the_time_line_whatever_each_drops():
    """An NTP step at boot lands between the IMU's first samples and the camera's first frame."""
    cam = [(100.5 + k / 30 - 1000.0, 500.5 + k / 30) for k in range(60)]  # all after the step
    imu = [(100.0 + j / 200 - (1000.0 if j >= 60 else 0.0), 500.0 + j / 200) for j in range(600)]
    pc, pi = _placed(cam), _placed(imu)
    assert not [x.why for x in pc if x.why]
    # on one clock the two streams' times at one receive time agree
    ti = np.interp(
        [x.item.recv for x in pc], [x.item.recv for x in pi if not x.why], [x.t for x in pi if not x.why]
    )
    np.testing.assert_allclose([x.t for x in pc], ti, atol=1e-6, rtol=0)


def test_three_equal_stamps_at_the_start_do_not_turn_the_stamps_off():
    base = _stream(60)
    case = [(base[0][0] if k < 3 else s, r) for k, (s, r) in enumerate(base)]
    out = _placed(case)
    np.testing.assert_allclose([x.t for x in out[3:]], [s for s, _ in base[3:]], atol=1e-9, rtol=0)


def test_two_glitches_in_a_row_keep_the_rows_in_time_order():
    base = _stream(40)
    case = [(s + {12: 1.0, 13: 0.7}.get(k, 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(case)
    assert {round(x.item.stamp - 100.0, 6) for x in out if x.why} == {
        round(12 / 30 + 1.0, 6),
        round(13 / 30 + 0.7, 6),
    }
    assert np.all(np.diff([x.t for x in out]) > 0)


def test_a_folder_in_the_way_of_a_result_is_refused_before_any_work(tmp_path, frames, capsys):
    log_path = write_log(tmp_path / "c.mcap", "mcap", frames[:6])
    argv = ["odometry", str(log_path), "--calib", str(calib(tmp_path)), "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    earlier = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    (tmp_path / "out" / "trajectory.tum").unlink()
    (tmp_path / "out" / "trajectory.tum").mkdir()  # something the new result cannot replace
    del earlier["trajectory.tum"]
    assert main([*argv, "--overwrite"]) == 2  # refused before any work
    assert "trajectory.tum is a folder where this tool writes a file" in one_error_line(capsys)
    assert {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir() if p.is_file()} == earlier
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]


def test_a_forward_step_within_the_tolerance_makes_its_pair_unsure():
    """The camera's clock steps 0.3 s ahead: the stamps keep the frames, the pair across is not trusted."""
    base = _stream(60)
    case = [(s + (0.3 if k >= 30 else 0.0), r) for k, (s, r) in enumerate(base)]
    out = _placed(case)
    odd = [k for k, x in enumerate(out) if x.why]
    assert odd == [30] and out[30].anchor and "unsure pair" in out[30].why
    assert np.all(np.diff([x.t for x in out]) > 0)


def test_a_flipped_byte_in_the_mcap_summary_costs_nothing(tmp_path, frames, clean_rows):
    """One bit of the summary's image schema name flipped: the data section's own record is used."""
    path = write_log(tmp_path / "summary.mcap", "mcap", frames)
    data = bytearray(path.read_bytes())
    at = data.rindex(b"sensor_msgs/msg/Image")  # the summary's copy, at the end
    data[at + 2] ^= 0x01
    path.write_bytes(bytes(data))
    rc, rows = odometry(tmp_path, path)
    assert rc == 0 and len(rows) == N - 1 and rows["valid"].all()
    same_as_clean(rows, clean_rows)

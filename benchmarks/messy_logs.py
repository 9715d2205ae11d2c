"""What glitched and damaged logs cost: `rover odometry` on a 60-frame log, clean and messed up.

Frames of a known planar motion (0.8 m/s, 0.05 m/s, 0.2 rad/s at 60 fps, rendered as in the
tests) are written as ROS 1, ROS 2 SQLite and MCAP logs, then glitched or damaged the way real
logs are. Each row gives the exit status, the rows written, the valid ones, how many valid rows
are the clean log's numbers to the last digit written (matched by time since the first row: a
clock set back moves the whole time line), the largest speed error of the rest, and the
frames lost.

    python benchmarks/messy_logs.py
"""

from __future__ import annotations

import contextlib
import io
import logging
import sqlite3
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_bags import LogWriter  # noqa: E402
from test_odometry import START, make_ground, mast_camera, pose_after, render  # noqa: E402

from rover_env.tools.cli import main  # noqa: E402

T0, FPS, N, TWIST, TOPIC = 1_700_000_000.25, 60.0, 60, (0.8, 0.05, 0.2), "/down/image_raw"


def write(path: Path, kind: str, frames, stamps=None, recv=None) -> Path:
    with LogWriter(path, kind) as lw:
        for k, img in enumerate(frames):
            t = T0 + k / FPS if recv is None else recv[k]
            lw.image(TOPIC, t, img, encoding="mono8", stamp=None if stamps is None else stamps[k])
    return path


def run(tmp: Path, src: Path, name: str):
    calib = mast_camera().save(tmp / "calib.yaml")
    out = tmp / f"out_{name}"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        rc = main(["odometry", str(src), "--calib", str(calib), "--out", str(out)])
    csv = out / "odometry.csv"
    rows = np.genfromtxt(csv, delimiter=",", names=True, dtype=None, encoding=None) if csv.exists() else None
    return rc, rows


def damage_page(db: Path, kind: str, which: int) -> None:
    con = sqlite3.connect(db)
    pages = [
        r[0]
        for r in con.execute(
            "SELECT pageno FROM dbstat WHERE name = 'messages' AND pagetype = ? ORDER BY pageno", (kind,)
        )
    ]
    con.close()
    data = bytearray(db.read_bytes())
    page = pages[which]
    data[(page - 1) * 4096 : page * 4096] = (
        np.random.default_rng(1).integers(0, 256, 4096, np.uint8).tobytes()
    )
    db.write_bytes(bytes(data))


def main_() -> None:
    logging.disable(logging.WARNING)
    ground = make_ground()
    pose, frames = START, []
    for k in range(N):
        if k:
            pose = pose_after(pose, TWIST, 1 / FPS)
        frames.append(render(mast_camera(), ground, pose, rng=np.random.default_rng(k)))
    truth = T0 + np.arange(N) / FPS
    cases = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rc, clean = run(tmp, write(tmp / "clean.mcap", "mcap", frames), "clean")
        ref_t, ref_v = clean["t"] - clean["t"][0], clean["v_x"]  # rows' times from the first row's

        glitch = truth.copy()
        glitch[30] += 1000.0
        for kind, name in (("ros1", "g.bag"), ("ros2", "g_ros2"), ("mcap", "g.mcap")):
            cases.append((f"{kind}: frame 30 stamped 1000 s late", write(tmp / name, kind, frames, glitch)))
        back = truth.copy()
        back[30:] -= 10.0
        cases.append(
            ("ros1: camera clock set back 10 s at frame 30", write(tmp / "b.bag", "ros1", frames, back))
        )
        step = truth.copy()
        step[30:] += 10.0
        cases.append(
            (
                "mcap: recorder clock steps +10 s at frame 30",
                write(tmp / "s.mcap", "mcap", frames, truth, step),
            )
        )
        jitter = truth + 0.7 * np.random.default_rng(3).random(N)
        cases.append(("ros1: receive delays of 0-0.7 s", write(tmp / "j.bag", "ros1", frames, truth, jitter)))

        from rosbags.rosbag1 import Reader

        bag = write(tmp / "c.bag", "ros1", frames)
        with Reader(bag) as r:
            last = max(r.chunk_infos, key=lambda c: c.pos)
            datapos = r.chunks[last.pos].datapos
        data = bytearray(bag.read_bytes())
        data[datapos : datapos + 64] = b"\xff" * 64
        bag.write_bytes(bytes(data))
        cases.append(("ros1: last chunk damaged", bag))
        for what, kind, which in (
            ("a b-tree leaf page", "leaf", 1),
            ("one image's data page", "overflow", 700),
        ):
            folder = write(tmp / f"p_{kind}_ros2", "ros2", frames)
            damage_page(next(folder.glob("*.db3")), kind, which)
            cases.append((f"ros2: {what} damaged", folder))
        cut = write(tmp / "cut.mcap", "mcap", frames)
        cut.write_bytes(cut.read_bytes()[: int(0.6 * cut.stat().st_size)])
        cases.append(("mcap: cut off at 60 % (no summary)", cut))

        print(f"clean log: exit {rc}, {len(clean)} rows, {int(clean['valid'].sum())} valid")
        print()
        print("| log | exit | rows | valid | valid = clean | largest v_x error of the rest [m/s] | lost |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for i, (label, src) in enumerate(cases):
            rc, rows = run(tmp, src, str(i))
            if rows is None:
                print(f"| {label} | {rc} | 0 | 0 | 0 | - | {N} |")
                continue
            good = rows[rows["valid"] == 1]
            same, err = 0, 0.0
            for t, vx in zip(good["t"] - rows["t"][0], good["v_x"], strict=True):
                j = int(np.argmin(np.abs(ref_t - t)))
                if abs(ref_t[j] - t) < 1e-4 and abs(ref_v[j] - vx) < 2e-6:
                    same += 1
                else:
                    err = max(err, abs(vx - TWIST[0]))
            lost = N - 1 - len(rows)
            print(f"| {label} | {rc} | {len(rows)} | {len(good)} | {same} | {err:.4f} | {lost} |")


if __name__ == "__main__":
    main_()

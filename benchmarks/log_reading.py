"""Reading speed of robot logs: perception.logs.bags against rosbags' AnyReader, per kind of log.

perception.logs.bags reads ROS 2 SQLite bags row by row (sqlite3) and MCAP files record by record
(mcap) so that damage loses only itself; ROS 1 bags go through rosbags as before. This prints,
for each kind, the time to read every image message of a log and turn it into an image array,
both ways, side by side in one process (one thread), and their ratio.

    python benchmarks/log_reading.py [--frames 300] [--size 640x480] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_bags import LogWriter  # noqa: E402

from perception.logs import bags  # noqa: E402

T0 = 1_700_000_000.0


def write(path: Path, kind: str, n: int, size: tuple[int, int]) -> Path:
    rng = np.random.default_rng(0)
    w, h = size
    with LogWriter(path, kind) as lw:
        for k in range(n):
            lw.image("/cam", T0 + k / 30, rng.integers(0, 256, (h, w), np.uint8), encoding="mono8")
            lw.imu("/imu", T0 + k / 30, (0.0, 0.0, 0.1), (0.0, 0.0, 9.81))
    return path


def read_ours(path: Path) -> int:
    return sum(f.image is not None for f in bags.log_images(path, "/cam").frames())


def read_rosbags(path: Path) -> int:
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    n = 0
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
        conns = [c for c in r.connections if c.topic == "/cam"]
        for c, _t, raw in r.messages(connections=conns):
            img, _ = bags.decode_image(r.deserialize(raw, c.msgtype), c.msgtype)
            n += img is not None
    return n


def best(fn, path: Path, repeat: int) -> tuple[float, int]:
    times, n = [], 0
    for _ in range(repeat):
        t = time.perf_counter()
        n = fn(path)
        times.append(time.perf_counter() - t)
    return min(times), n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    size = tuple(int(v) for v in args.size.split("x"))
    w, h = size
    print(f"{args.frames} mono8 frames of {w}x{h} px and as many IMU messages; best of {args.repeat}")
    print()
    print("| log | perception.logs.bags [ms/frame] | rosbags AnyReader [ms/frame] | ratio |")
    print("|---|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for kind, name in (("ros1", "a.bag"), ("ros2", "b_ros2"), ("mcap", "c.mcap")):
            path = write(Path(tmp) / name, kind, args.frames, size)
            ours, n1 = best(read_ours, path, args.repeat)
            theirs, n2 = best(read_rosbags, path, args.repeat)
            assert n1 == n2 == args.frames, (n1, n2)
            a, b = 1e3 * ours / n1, 1e3 * theirs / n2
            print(f"| {kind} | {a:.2f} | {b:.2f} | {a / b:.2f} |")


if __name__ == "__main__":
    main()

"""The fisheye odometry over a relief it assumes flat: synthetic views, known motion.

The fisheye hangs 0.145 m above the ground under the rover's body; the odometry meets its rays
with a plane. Here the ground is that plane plus a relief A sin(2 pi x / L) sin(2 pi 0.8 y / L + 1)
(L 1.5 m, the rough missions' dominant wavelength), rendered through an equidistant fisheye of
the train preset's size (320 x 240, 185 degrees) with the test suite's texture, and driven at
(0.4 m/s, 0, 0.2 rad/s) for 30 frames at 30 Hz. Prints the MAE of (v_x, v_y, omega) per
amplitude, of the rigid fit on the plane alone and of the two-view fit (the default).

    python benchmarks/fisheye_relief.py [--amplitudes 0 0.015 0.03]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))

import test_fisheye_odometry as T  # noqa: E402  (the test suite's texture and motion helpers)

from perception.models.cameras import OmniCamera  # noqa: E402
from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig  # noqa: E402


def camera() -> OmniCamera:
    """The rover's fisheye mount at the train preset's size: 0.145 m above the ground, looking down."""
    return T._rover_fisheye((320, 240))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--amplitudes", type=float, nargs="+", default=[0.0, 0.015, 0.03])
    args = ap.parse_args(argv)
    tex = T._texture(3)
    twist, dt = (0.4, 0.0, 0.2), 1.0 / 30.0
    print("| relief amplitude [m] | fit | v_x MAE [m/s] | v_y MAE [m/s] | omega MAE [rad/s] | valid pairs |")
    print("|---:|---|---:|---:|---:|---:|")
    cam = camera()
    for amp in args.amplitudes:
        frames, pose = [], np.array([0.3, 0.2, 0.1])
        for _ in range(30):
            frames.append(T.render_relief(cam, tex, tuple(pose), amp))
            dx, dy, da = T._after(twist, dt)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            pose = pose + np.array([c * dx - s * dy, s * dx + c * dy, da])
        for two_view in (False, True):
            odo = FisheyeOdometry(cam, FisheyeOdometryConfig(two_view=two_view), ground_plane=T.ROVER_PLANE)
            errs, n = [], 0
            for k, img in enumerate(frames):
                est = odo.update(img, k * dt)
                if est is not None:
                    n += 1
                    if est.valid:
                        errs.append(np.abs(est.twist - np.array(twist)))
            mae = np.array(errs).mean(axis=0)
            name = "two-view" if two_view else "plane"
            print(f"| {amp:.3f} | {name} | {mae[0]:.4f} | {mae[1]:.4f} | {mae[2]:.4f} | {len(errs)}/{n} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The fisheye odometry over a relief it assumes flat: synthetic views, known motion.

The fisheye hangs 0.145 m above the ground under the rover's body; the odometry meets its rays
with a plane. Here the ground is that plane plus a relief A sin(2 pi x / L) sin(2 pi 0.8 y / L + 1)
(L 1.5 m, the rough missions' dominant wavelength), rendered through an equidistant fisheye of
the train preset's size (320 x 240, 185 degrees) with the test suite's texture, and driven at
(0.4 m/s, 0, 0.2 rad/s) for 30 frames at 30 Hz. Prints the MAE of (v_x, v_y, omega) per
amplitude.

    python benchmarks/fisheye_relief.py [--amplitudes 0 0.015 0.03]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests"))

import test_fisheye_odometry as T  # noqa: E402  (the test suite's texture and motion helpers)

from perception.cameras import OmniCamera  # noqa: E402
from perception.fisheye_odometry import FisheyeOdometry  # noqa: E402

W, H = 320, 240
PLANE = (0.0, 0.0, -0.265)  # the rover's: body origin 0.265 m above the ground


def camera() -> OmniCamera:
    """The rover's fisheye mount: 0.12 m below the body origin, looking down."""
    m = np.eye(4)
    m[:3, :3] = np.diag([1.0, -1.0, -1.0])
    m[:3, 3] = (0.0, 0.0, -0.12)
    return OmniCamera.equidistant((W, H), math.radians(185.0), 150.0, T_body_cam=m)


def render(cam: OmniCamera, tex: np.ndarray, pose, amplitude: float, wavelength: float = 1.5) -> np.ndarray:
    """The fisheye view of the textured relief with the body at pose (x, y, yaw) [m, m, rad]."""
    yy, xx = np.mgrid[0:H, 0:W]
    rays = cam.cam2world(np.column_stack([xx.ravel(), yy.ravel()]).astype(float))
    R, o = cam.T_body_cam[:3, :3], cam.T_body_cam[:3, 3]
    d = rays @ R.T
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)

    def world(dist):
        p = o + dist[:, None] * d
        return x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]

    with np.errstate(divide="ignore", invalid="ignore"):
        dist = (PLANE[2] - o[2]) / d[:, 2]
        for _ in range(8):  # the ray's meeting with the relief, by fixed-point iteration
            wx, wy = world(dist)
            z = PLANE[2] + amplitude * np.sin(2 * math.pi * wx / wavelength) * np.sin(
                2 * math.pi * 0.8 * wy / wavelength + 1.0
            )
            dist = (z - o[2]) / d[:, 2]
    wx, wy = world(dist)
    u = ((wx + T.TEX_M / 2) / T.TEX_M * T.TEX_PX).reshape(H, W).astype(np.float32)
    v = ((wy + T.TEX_M / 2) / T.TEX_M * T.TEX_PX).reshape(H, W).astype(np.float32)
    bad = ~(np.isfinite(u) & (d[:, 2] < -0.05).reshape(H, W))
    u[bad], v[bad] = -1.0, -1.0
    img = cv2.remap(tex, u, v, cv2.INTER_LINEAR, borderValue=0.0)
    return np.clip(img * 255.0, 0, 255).astype(np.uint8)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--amplitudes", type=float, nargs="+", default=[0.0, 0.015, 0.03])
    args = ap.parse_args(argv)
    tex = T._texture(3)
    twist, dt = (0.4, 0.0, 0.2), 1.0 / 30.0
    print("| relief amplitude [m] | v_x MAE [m/s] | v_y MAE [m/s] | omega MAE [rad/s] | valid pairs |")
    print("|---:|---:|---:|---:|---:|")
    for amp in args.amplitudes:
        cam = camera()
        odo = FisheyeOdometry(cam, ground_plane=PLANE)
        pose = np.array([0.3, 0.2, 0.1])
        errs, n = [], 0
        for k in range(30):
            dx, dy, da = T._after(twist, dt)
            c, s = math.cos(pose[2]), math.sin(pose[2])
            est = odo.update(render(cam, tex, tuple(pose), amp), k * dt)
            pose = pose + np.array([c * dx - s * dy, s * dx + c * dy, da])
            if est is not None:
                n += 1
                if est.valid:
                    errs.append(np.abs(est.twist - np.array(twist)))
        e = np.array(errs)
        mae = e.mean(axis=0)
        print(f"| {amp:.3f} | {mae[0]:.4f} | {mae[1]:.4f} | {mae[2]:.4f} | {len(e)}/{n} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

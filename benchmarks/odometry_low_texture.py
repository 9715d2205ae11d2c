"""The odometry's share of valid pairs on low-contrast, shadowed ground, and its accuracy there.

A synthetic ground (Gaussian blobs at 2, 6 and 20 mm, 1 mm/px) is seen by the mast camera at
640 x 480 and 60 Hz while the rover drives an arc at 1 m/s and 0.2 rad/s: each frame is the
ground warped by the known motion, its contrast scaled about mid-grey, the rover's body shadow
(a sharp dark region from the image's bottom edge) multiplied in, and shot and read noise added
(4 electrons per grey level, ``--noise`` grey levels of read noise). No simulator is involved, so
the motion is exact. For each contrast and each odometry variant it prints the valid pairs of
59, the v_x MAE of the valid ones [m/s] and the RMS of their errors over their own standard
deviations (the covariance's calibration: about 1 when honest), and the reasons of the invalid.

Variants: the shipped configuration, and one per ``--variant KEY=VALUE[,KEY=VALUE]`` (any
:class:`perception.odometry.flow.FlowOdometryConfig` fields).

Run: python benchmarks/odometry_low_texture.py [--contrast 0.15 0.1 0.08 0.06] \\
    [--variant max_std=0.03 --variant harris_width=640,fb_levels=3]
"""

from __future__ import annotations

import argparse
import ast
import collections
import math
import re
from dataclasses import replace

import cv2
import numpy as np

from perception import PinholeCamera
from perception.odometry.flow import FlowOdometry, FlowOdometryConfig, integrate_twist

MM = 0.001  # ground texture resolution [m/px]


def mast_camera(size=(640, 480)) -> PinholeCamera:
    """The rover's mast camera: 0.8 m above flat ground, looking down, image up = body forward."""
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
    T[:3, 3] = (0.95, 0.0, 0.535)
    return PinholeCamera.from_fov(
        size, math.radians(77.0), math.radians(57.0), T_body_cam=T, ground_plane=(0.0, 0.0, -0.265)
    )


def ground(n: int = 3000, seed: int = 5) -> np.ndarray:
    """An n x n mm ground of Gaussian blobs at three scales, grey about 130 (float32)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.float32)
    for sigma, weight in ((2.0, 1.0), (6.0, 1.4), (20.0, 1.6)):
        layer = cv2.GaussianBlur(rng.normal(size=(n, n)).astype(np.float32), (0, 0), sigma)
        img += weight * layer / layer.std()
    return 130 + 30 * img / img.std()


def body_shadow(size=(640, 480)) -> np.ndarray:
    """A sharp-edged dark region fixed in the image: the rover's body and mast, from the bottom edge."""
    w, h = size
    m = np.zeros((h, w), np.uint8)
    cv2.rectangle(m, (int(0.3 * w), int(0.45 * h)), (int(0.7 * w), h), 1, -1)
    cv2.rectangle(m, (int(0.47 * w), 0), (int(0.53 * w), h), 1, -1)
    cv2.fillPoly(
        m, [np.array([[0, int(0.7 * h)], [int(0.3 * w), int(0.55 * h)], [int(0.3 * w), h], [0, h]])], 1
    )
    return m.astype(bool)


def frames(cam, tex, twist, n, dt, shade, noise, seed=0) -> list[np.ndarray]:
    """n frames of ``tex`` along the constant ``twist`` from the texture's centre."""
    rng = np.random.default_rng(seed)
    w, h = cam.image_size
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    body = cam.pixels_to_ground(np.stack([xs, ys], -1).reshape(-1, 2))
    poses = integrate_twist(np.arange(n) * dt, np.tile(twist, (n, 1)), pose0=(-0.95, 0.0, 0.0))
    shadow = body_shadow((w, h))
    out = []
    for x, y, th in poses:
        c, s = math.cos(th), math.sin(th)
        mx = ((x + c * body[:, 0] - s * body[:, 1]) / MM + tex.shape[1] / 2).reshape(h, w).astype(np.float32)
        my = (tex.shape[0] / 2 - (y + s * body[:, 0] + c * body[:, 1]) / MM).reshape(h, w).astype(np.float32)
        img = cv2.remap(tex, mx, my, cv2.INTER_LINEAR)
        img = np.where(shadow, img * shade, img)
        img = (
            img
            + rng.normal(size=img.shape) * np.sqrt(np.maximum(img, 0.0) / 4.0)
            + rng.normal(scale=noise, size=img.shape)
        )
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--contrast", type=float, nargs="+", default=[0.15, 0.1, 0.08, 0.06])
    ap.add_argument("--shade", type=float, default=0.25, help="light in the shadow, share of the sunlit")
    ap.add_argument("--noise", type=float, default=3.0, help="read noise [grey levels]")
    ap.add_argument("--variant", action="append", default=[], metavar="KEY=VALUE[,KEY=VALUE]")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    variants = {"shipped": {}}
    for group in args.variant:
        variants[group] = {k: ast.literal_eval(v) for k, _, v in (i.partition("=") for i in group.split(","))}
    cam, tex, twist, dt = mast_camera(), ground(), np.array([1.0, 0.0, 0.2]), 1 / 60
    print(
        "| contrast | variant | valid of 59 | v_x MAE [m/s] | RMS error / own deviation | invalid: reasons |"
    )
    print("|---:|---|---:|---:|---:|---|")
    for contrast in args.contrast:
        imgs = frames(cam, 130 + contrast * (tex - 130), twist, 60, dt, args.shade, args.noise)
        for name, kw in variants.items():
            odo = FlowOdometry(cam, replace(FlowOdometryConfig(), **kw))
            err, z, why = [], [], collections.Counter()
            for k, img in enumerate(imgs):
                e = odo.update(img, k * dt)
                if k == 0:
                    continue
                if e.valid:
                    err.append(e.v_x - twist[0])
                    z.append(err[-1] / math.sqrt(e.twist_cov[0, 0]))
                else:
                    why[re.sub(r"[0-9.]+", "x", e.reason)] += 1
            mae = f"{np.mean(np.abs(err)):.4f}" if err else "–"
            rz = f"{np.sqrt(np.mean(np.square(z))):.2f}" if z else "–"
            reasons = ", ".join(f"{r}: {c}" for r, c in why.most_common()) or "–"
            print(f"| {contrast} | {name} | {len(err)} | {mae} | {rz} | {reasons} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

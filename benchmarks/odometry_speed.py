"""FlowOdometry's time per frame against a naive OpenCV pipeline, on the same frames, one thread.

The frames are a 640x480, 60 Hz sequence of the downward camera (eval preset) while the rover
drives a curve over shadowed regolith on ``flat_patches``, rendered once up front. Both
estimators then run frame by frame in this process, interleaved (frame k by one, then by the
other, which one goes first alternating), with ``cv2.setNumThreads(1)``:

* FlowOdometry in chained mode (:meth:`perception.FlowOdometry.update`: the shadow mask,
  feature selection, forward-backward Lucas-Kanade, RANSAC and the least-squares twist);
* the naive pipeline: ``goodFeaturesToTrack`` (50 corners), ``calcOpticalFlowPyrLK`` (21 px
  window, 3 levels) and ``estimateAffinePartial2D``, no shadow handling.

Run: python benchmarks/odometry_speed.py [--frames 120] [--width 640]
"""

from __future__ import annotations

import argparse
import math
import time

import cv2
import numpy as np


def render_frames(n: int, width: int, renderer: str = "auto") -> tuple[list[np.ndarray], object, float]:
    """``n`` downward frames while driving, the camera model and the frame period [s]."""
    from rover_env.config.cameras import DownwardCameraConfig
    from rover_env.config.scenario import load_scenario
    from rover_env.sensors.cameras import DownwardCamera
    from rover_env.sim.simulation import RoverSim

    sim = RoverSim(load_scenario("flat_patches"), renderer=renderer)
    try:
        sim.reset(0.0, 0.0, 0.3)
        cam = DownwardCamera(sim, DownwardCameraConfig(width=width, height=width * 3 // 4, rate_hz=60.0))
        sim.rover.command(np.full(4, 8.0), 0.15, -0.15)
        sim.step(0.5)
        frames = []
        for _ in range(n):
            frames.append(cam.capture().image)
            sim.step(cam.period)
        return frames, cam.model, cam.period
    finally:
        sim.close()


def naive_step(prev: np.ndarray, curr: np.ndarray):
    """The naive pipeline on one pair of grey images: a similarity transform or None."""
    p0 = cv2.goodFeaturesToTrack(prev, maxCorners=50, qualityLevel=0.01, minDistance=10)
    if p0 is None:
        return None
    p1, st, _ = cv2.calcOpticalFlowPyrLK(prev, curr, p0, None, winSize=(21, 21), maxLevel=3)
    ok = st.ravel() == 1
    if ok.sum() < 3:
        return None
    m, _ = cv2.estimateAffinePartial2D(p0[ok], p1[ok])
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--width", type=int, default=640)
    args = ap.parse_args(argv)
    from perception.odometry.flow import FlowOdometry, FlowOdometryConfig

    cv2.setNumThreads(1)
    frames, model, period = render_frames(args.frames, args.width)
    odo = FlowOdometry(model, FlowOdometryConfig.for_camera(args.width, 1.0 / period))
    grays = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY) for f in frames]
    t_flow, t_naive, valid = [], [], 0
    for k, img in enumerate(frames):
        # alternate which pipeline runs first on a frame: the second finds warmer caches
        order = (0, 1) if k % 2 else (1, 0)
        dt = [0.0, 0.0]
        for which in order:
            t0 = time.perf_counter()
            if which == 0:
                est = odo.update(img, k * period)
            elif k:
                naive_step(grays[k - 1], grays[k])
            dt[which] = time.perf_counter() - t0
        if k:  # the first frame only selects (no pair yet)
            t_flow.append(dt[0])
            t_naive.append(dt[1] + _gray_time(img))
            valid += bool(est is not None and est.valid)
    f, n = float(np.median(t_flow)) * 1e3, float(np.median(t_naive)) * 1e3
    h = args.width * 3 // 4
    print(f"{len(t_flow)} frame pairs, {args.width}x{h} px, one thread (cv2.setNumThreads(1))")
    print("| pipeline | median ms/frame | p90 ms/frame | valid estimates |")
    print("|---|---:|---:|---:|")
    print(f"| FlowOdometry (shadow mask, Harris at 320 px, FB-checked LK, RANSAC) | {f:.2f} | "
          f"{np.percentile(t_flow, 90) * 1e3:.2f} | {valid}/{len(t_flow)} |")  # fmt: skip
    print(f"| naive (goodFeaturesToTrack 50 + LK 21 px, 3 levels + estimateAffinePartial2D) | {n:.2f} | "
          f"{np.percentile(t_naive, 90) * 1e3:.2f} | - |")  # fmt: skip
    print(f"\nFlowOdometry / naive: {f / n:.2f}")
    return 0 if math.isfinite(f) else 1


def _gray_time(img: np.ndarray) -> float:
    """The naive pipeline's grey conversion (FlowOdometry converts inside ``update``) [s]."""
    t = time.perf_counter()
    cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    return time.perf_counter() - t


if __name__ == "__main__":
    raise SystemExit(main())

"""Your own estimator in the loop: Lucas-Kanade on the downward camera plus the IMU's gyro.

The kind of estimator a user writes in an afternoon, with OpenCV and nothing from
``perception``'s estimators: corners tracked between consecutive downward frames, mapped to the
ground through the camera's calibration (the rig gives it), a rigid 2-D fit of the ground's
motion (RANSAC), and the yaw rate from the gyro where there is one. It returns the body twist,
a quality and the dead-reckoned pose; everything else stays unknown (0 in the observation).

Run it (a short closed-loop mission, its errors against the truth):

    python examples/own_estimator.py

Evaluate it against the built-in estimator on the same missions and seeds:

    rover eval --controllers slip_unaware --missions Rover-v0 RoverShadows-v0 --seeds 0-2 \\
        --estimator examples.own_estimator:LucasKanadeEstimator --out own
"""

from __future__ import annotations

import math

import cv2
import numpy as np


class LucasKanadeEstimator:
    """Visual odometry from the rig's downward camera, the gyro's yaw rate if there is an IMU.

    Args:
        rig: The rover's sensors (``perception.rig.Rig``): the ``"pinhole"`` camera's model maps
            pixels to the ground, the ``"imu"``'s mount turns its rates into the body frame.
    """

    def __init__(self, rig) -> None:
        cams = rig.of_kind("pinhole")
        if not cams:
            raise ValueError("LucasKanadeEstimator needs a downward pinhole camera in the rig")
        self.cam = cams[0]
        imus = rig.of_kind("imu")
        self.imu = imus[0] if imus else None
        self.reset((0.0, 0.0, 0.0))

    def reset(self, start_fix) -> None:
        self.pose = np.array(start_fix, dtype=np.float64)
        self.prev = None  # (grey image, time) of the last downward frame
        self.twist = np.zeros(3)
        self.quality = 0.0
        self.t = None
        self.gyro: list[float] = []  # body-z rates since the last frame [rad/s]
        self.bias = 0.0

    def update(self, messages, t):
        if self.t is None:  # the first call: its IMU samples before t are the standstill
            still = [
                self._yaw_rate(m.data) for m in messages if self.imu and m.sensor == self.imu.name and m.t < t
            ]
            self.bias = float(np.mean(still)) if still else 0.0
            messages = [m for m in messages if m.t >= t - 1e-9]
            self.t = t
        for m in messages:
            if self.imu is not None and m.sensor == self.imu.name:
                self.gyro.append(self._yaw_rate(m.data) - self.bias)
            elif m.sensor == self.cam.name:
                self._advance(m.t)
                self._frame(m.data, m.t)
        self._advance(t)
        return {
            "pose": self.pose.copy(),
            "v_x": float(self.twist[0]),
            "v_y": float(self.twist[1]),
            "omega": float(self.twist[2]),
            "odometry_quality": self.quality,
        }

    def _yaw_rate(self, data) -> float:
        return float(self.imu.mount[2, :3] @ np.asarray(data[:3], dtype=np.float64))

    def _advance(self, t: float) -> None:
        """Dead reckoning to ``t`` with the last twist."""
        dt = t - self.t
        if dt > 0:
            vx, vy, w = self.twist
            yaw = self.pose[2] + 0.5 * w * dt
            self.pose += [
                dt * (vx * math.cos(yaw) - vy * math.sin(yaw)),
                dt * (vx * math.sin(yaw) + vy * math.cos(yaw)),
                w * dt,
            ]
            self.t = t

    def _frame(self, rgb: np.ndarray, t: float) -> None:
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        prev, self.prev = self.prev, (grey, t)
        if prev is None or not grey.any():
            self.quality = 0.0
            return
        img0, t0 = prev
        dt = t - t0
        p0 = cv2.goodFeaturesToTrack(img0, maxCorners=120, qualityLevel=0.01, minDistance=5)
        if p0 is None or dt <= 0:
            self.quality = 0.0
            return
        p1, status, _ = cv2.calcOpticalFlowPyrLK(img0, grey, p0, None, winSize=(15, 15), maxLevel=3)
        ok = status.ravel() == 1
        if ok.sum() < 8:
            self.quality = 0.0
            return
        g0 = self.cam.model.pixels_to_ground(p0[ok, 0].astype(np.float64))  # body frame at t0 [m]
        g1 = self.cam.model.pixels_to_ground(p1[ok, 0].astype(np.float64))  # body frame at t
        A, inliers = cv2.estimateAffinePartial2D(g0, g1, method=cv2.RANSAC, ransacReprojThreshold=0.005)
        if A is None:
            self.quality = 0.0
            return
        # the ground moved by g1 = R(-dyaw) (g0 - d): the body turned by dyaw and moved by d
        dyaw = -math.atan2(A[1, 0], A[0, 0])
        d = -A[:, :2].T @ A[:, 2]
        omega = dyaw / dt
        if self.gyro:
            omega = float(np.mean(self.gyro))  # the gyro's yaw rate is far less noisy
            self.gyro = []
        self.twist = np.array([d[0] / dt, d[1] / dt, omega])
        self.quality = float(inliers.mean()) if inliers is not None else 0.0


def run(mission: str = "Rover-v0", seed: int = 0, steps: int = 300, imu: str | None = "bmi088") -> dict:
    """Drive ``mission`` with the path follower on this estimator; its errors against the truth."""
    import gymnasium as gym

    import rover_env  # noqa: F401  (registers the missions)
    from controllers import PurePursuit
    from perception.observation import OBS_FIELDS

    env = gym.make(mission, estimator=LucasKanadeEstimator, imu=imu)
    ctrl = PurePursuit(OBS_FIELDS)
    try:
        obs, info = env.reset(seed=seed)
        err_v, err_pos = [], []
        for _ in range(steps):
            obs, _, terminated, truncated, info = env.step(ctrl.act(obs))
            truth, est = info["ground_truth"], info["estimate"]
            err_v.append(abs(est["twist"][0] - truth["twist"][0]))
            err_pos.append(float(np.hypot(*(est["pose"][:2] - truth["pose"][:2]))))
            if terminated or truncated:
                break
    finally:
        env.close()
    return {
        "mission": mission,
        "t": round(float(info["t"]), 2),
        "termination": info["termination"],
        "mae_v_x": round(float(np.mean(err_v)), 4),
        "final_position_error": round(err_pos[-1], 3),
    }


if __name__ == "__main__":
    print(run())

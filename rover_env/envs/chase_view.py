"""The chase view of :meth:`RoverEnv.render`: a third-person view beside the simulated cameras.

For people watching a mission (videos, the ``rgb_array`` render mode); nothing in it reaches the
observation. The insets show the simulated cameras at the inset's resolution, with the sun's
shadows; the chase view outlines the friction patches, which no camera sees.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from perception.models.cameras import PinholeCamera
from rover_env.config.cameras import DownwardCameraConfig, FisheyeCameraConfig
from rover_env.config.scenario import ScenarioConfig
from rover_env.rendering import focus_on_rover
from rover_env.rendering.base import Lighting, look_at
from rover_env.sensors.cameras import DownwardCamera, FisheyeCamera
from rover_env.sim.simulation import RoverSim
from rover_env.sim.transforms import quat_to_yaw


class ChaseView:
    """Composite frames of one simulation: the chase view on the left, the cameras on the right.

    Args:
        sim: The simulation.
        scenario: Its scenario (the sun and the friction patches).
        size: (width, height) of a frame [px].
        mounts: The insets' camera mounts (4 x 4, body from camera) by kind, ``"pinhole"`` and
            ``"fisheye"``: the rig's first camera of each kind; a kind given as None is left
            out (a black inset). None: both at their standard mounts.
    """

    def __init__(
        self,
        sim: RoverSim,
        scenario: ScenarioConfig,
        size: tuple[int, int],
        mounts: dict[str, np.ndarray | None] | None = None,
    ) -> None:
        self.sim = sim
        self.scenario = scenario
        self.size = size
        std = {
            "pinhole": DownwardCamera.standard_mount(sim.geometry),
            "fisheye": FisheyeCamera.standard_mount(sim.geometry),
        }
        self.mounts = std if mounts is None else {k: mounts.get(k) for k in std}
        self._views: dict | None = None
        self._outlines: list | None = None  # the friction patches drawn in the chase view

    def frame(self) -> np.ndarray:
        """The composite frame now, RGB uint8 (H, W, 3) of ``size``."""
        w, h = self.size
        side = w // 3
        left = w - side
        pos, quat = self.sim.base_pose()
        yaw = quat_to_yaw(quat)
        eye = [
            pos[0] - 2.6 * math.cos(yaw) + 0.8 * math.sin(yaw),
            pos[1] - 2.6 * math.sin(yaw) - 0.8 * math.cos(yaw),
            pos[2] + 1.6,
        ]
        views = self._render_views(left, h, side, h // 2)
        renderer = focus_on_rover(self.sim)
        T_world_chase = look_at(eye, [pos[0], pos[1], pos[2] - 0.1])
        sun = self.sim.scenario.sun  # where the sun is now, and how much of it the clouds let through
        t = self.sim.t
        sx, sy, sz = (float(v) for v in sun.direction(t))
        diffuse = sun.transmission(t) * self.sim.haze
        lighting = Lighting(
            (sx, sy, sz), ambient=0.35, diffuse=diffuse, shadows=True, clouds=sun.cloud_bands(t)
        )
        chase = renderer.render_pinhole(views["chase"], T_world_chase, lighting, far=60.0)
        frame = np.zeros((h, w, 3), dtype=np.uint8)
        frame[:, :left] = chase.rgb
        if chase.segmentation is not None:  # past the terrain's edge: a dark sky, not the clear colour
            void = chase.segmentation < 0
            frame[:, :left][void] = views["sky"][void]
        # the friction patches, outlined and labelled in the chase view only (no camera sees them)
        self._draw_patches(frame[:, :left], views["chase"], T_world_chase)
        for row, cam, label in ((0, views["downward"], "downward camera"), (1, views["fisheye"], "fisheye")):
            if cam is None:
                img = np.zeros((h // 2, side, 3), np.uint8)
                label = f"no {label} in the rig"
            else:
                img = cv2.resize(cam.capture().image, (side, h // 2), interpolation=cv2.INTER_AREA)
            cv2.putText(img, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
            frame[row * (h // 2) : (row + 1) * (h // 2), left:] = img
        return frame

    def _draw_patches(self, img: np.ndarray, camera: PinholeCamera, T_world_cam: np.ndarray) -> None:
        """Outline each low-friction patch on the ground of a rendered view and label it with its mu."""
        T_cam_world = np.linalg.inv(T_world_cam)

        def project(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            q = T_cam_world[:3, :3] @ p.T + T_cam_world[:3, 3:4]
            front = q[2] > 0.2
            return ((camera.K @ q)[:2] / np.where(front, q[2], 1.0)).T, front

        for outline, centre, label, colour in self._patch_outlines():
            uv, front = project(outline)
            for i in range(len(uv) - 1):
                if front[i] and front[i + 1]:
                    p0, p1 = (tuple(int(round(v)) for v in uv[j]) for j in (i, i + 1))
                    cv2.line(img, p0, p1, colour, 2, cv2.LINE_AA)
            (c_uv,), (c_front,) = project(centre[None])
            if c_front and 0 <= c_uv[0] < img.shape[1] and 0 <= c_uv[1] < img.shape[0]:
                org = (int(c_uv[0]) - 24, int(c_uv[1]))
                cv2.putText(img, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
                cv2.putText(img, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)

    def _patch_outlines(self) -> list[tuple[np.ndarray, np.ndarray, str, tuple[int, int, int]]]:
        """Per friction patch, once: its outline on the ground (N, 3) and centre [m, world], label, colour."""
        if self._outlines is None:
            terrain = self.sim.terrain
            self._outlines = []
            for patch in self.scenario.friction.patches:
                cx, cy = patch.center
                if patch.shape == "circle":
                    a = np.linspace(0.0, 2 * math.pi, 73)
                    xy = np.column_stack([cx + patch.radius * np.cos(a), cy + patch.radius * np.sin(a)])
                else:
                    hx, hy = patch.size[0] / 2, patch.size[1] / 2
                    s = np.linspace(-1.0, 1.0, 17)
                    one = np.ones_like(s)
                    local = np.concatenate([
                        np.column_stack([hx * s, -hy * one]), np.column_stack([hx * one, hy * s]),
                        np.column_stack([-hx * s, hy * one]), np.column_stack([-hx * one, -hy * s]),
                    ])  # fmt: skip
                    c, sn = math.cos(math.radians(patch.yaw_deg)), math.sin(math.radians(patch.yaw_deg))
                    xy = local @ np.array([[c, sn], [-sn, c]]) + (cx, cy)
                xy = np.vstack([xy, [cx, cy]])
                z = np.asarray(terrain.height_at(xy[:, 0], xy[:, 1]), dtype=np.float64).reshape(-1) + 0.01
                pts = np.column_stack([xy, z])
                label = f"mu {patch.mu:g}" + (" loose" if patch.slip_loss > 0 else "")
                colour = (255, 170, 0) if patch.mu < 0.5 else (120, 200, 255)
                self._outlines.append((pts[:-1], pts[-1], label, colour))
        return self._outlines

    def _render_views(self, left: int, h: int, inset_w: int, inset_h: int) -> dict:
        """Cameras of the composite frame, built on first use (the fisheye precomputes its remap)."""
        if self._views is None:
            shadows = True
            # insets at about their display size (even sizes, the camera's 4:3 aspect)
            iw = max(16, 2 * (inset_w // 2))
            ih = max(16, 2 * (iw * 3 // 8))
            self._views = {
                "chase": PinholeCamera.from_fov((left, h), math.radians(55.0 * left / h), math.radians(55.0)),
                "downward": None
                if (m := self.mounts["pinhole"]) is None
                else DownwardCamera(self.sim, DownwardCameraConfig(width=iw, height=ih, shadows=shadows), m),
                "fisheye": None
                if (m := self.mounts["fisheye"]) is None
                else FisheyeCamera(self.sim, FisheyeCameraConfig(width=iw, height=ih, shadows=shadows), m),
                # what the chase view shows past the terrain: a dark sky, lighter at the top
                "sky": np.broadcast_to(
                    (np.linspace(70, 20, h)[:, None, None] * np.array([0.8, 0.9, 1.2])).astype(np.uint8),
                    (h, left, 3),
                ),
            }
        return self._views

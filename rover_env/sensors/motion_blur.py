"""Exposure blur and rolling shutter along each pixel's actual motion.

A camera exposes each row over ``exposure`` seconds ending at its readout; whatever moves
across the image meanwhile is smeared along its path. :class:`MotionField` computes, from a
rendered view's per-pixel 3-D points and body labels and the simulator's link velocities, the
image velocity of every pixel [px/s]: the ground is still, the rover's links move rigidly (the
wheels turn, the body carries the camera); the GL renderer draws the same field in its colour
pass instead (a velocity buffer, :class:`rover_env.rendering.base.MotionSpec`). :func:`blur`
then averages the rendered image along those paths (a gather along each pixel's motion
vector, as renderers' velocity-buffer motion blur does), and a rolling shutter shifts each
row by its velocity times its readout delay.

The image velocity is the camera model's exact derivative at each pixel: for a point at
distance ``rho`` along the pixel's ray ``r`` moving at ``p_dot`` in the camera frame,
``x_dot = J (I - r r^T) p_dot / rho``, with ``J`` the projection's derivative on the unit
sphere, found once per camera by finite differences of its model.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import cv2
import numpy as np

LINK_SHIFT = 24  # segmentation label: body id + ((link + 1) << 24)


class MotionField:
    """Per-pixel image velocity of one camera from its rendered views.

    Args:
        rays: (H, W, 3) unit ray of each pixel in the camera's optical frame (NaN outside the
            field of view).
        project: Pixels (N, 2) of points (N, 3) in the optical frame: the camera's model.
    """

    def __init__(self, rays: np.ndarray, project: Callable[[np.ndarray], np.ndarray]) -> None:
        h, w, _ = rays.shape
        r = rays.reshape(-1, 3)
        ok = np.all(np.isfinite(r), axis=1)
        # two unit tangents of the sphere at each ray
        helper = np.where(np.abs(r[:, [0]]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        e1 = np.cross(r, helper)
        e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
        e2 = np.cross(r, e1)
        eps = 1e-4
        jac = np.zeros((h * w, 2, 3))
        base = np.full((h * w, 2), np.nan)
        base[ok] = project(r[ok])
        for e in (e1, e2):
            moved = np.full((h * w, 2), np.nan)
            moved[ok] = project(r[ok] + eps * e[ok])
            d = (moved - base) / eps  # pixel change per radian along e
            jac += d[:, :, None] * e[:, None, :]
        jac[~ok] = 0.0
        self.rays = rays.astype(np.float32)
        self.jacobian = np.nan_to_num(jac).reshape(h, w, 2, 3).astype(np.float32)
        self.size = (w, h)

    def velocity(
        self,
        points_cam: np.ndarray,
        labels: np.ndarray | None,
        T_world_cam: np.ndarray,
        links: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
        body_id: int,
        camera_link: int = -1,
    ) -> np.ndarray:
        """Image velocity (H, W, 2) [px/s] of every pixel now.

        Args:
            points_cam: (H, W, 3) each pixel's surface point in the optical frame [m] (NaN: none).
            labels: (H, W) segmentation (body id + ((link + 1) << 24), -1 none), or None: a still world.
            T_world_cam: The camera's pose [m].
            links: :meth:`rover_env.sim.simulation.RoverSim.link_motion`.
            body_id: The rover's body id (its links move; every other body is still).
            camera_link: The link the camera is fixed to (-1: the base).
        """
        R = T_world_cam[:3, :3].astype(np.float32)
        c_cam = T_world_cam[:3, 3]
        com, v_l, w_l = links[camera_link]
        v_cam = v_l + np.cross(w_l, c_cam - com)  # the camera's own velocity, world frame
        h, w = points_cam.shape[:2]
        out = np.zeros((h, w, 2), np.float32)
        flat = points_cam.reshape(-1, 3)
        idx = np.flatnonzero(np.isfinite(flat[:, 0]))
        if len(idx) == 0:
            return out
        p = flat[idx].astype(np.float32)
        # velocity of each surface point relative to the camera, in the camera frame:
        # R^T (v_p - v_cam) - (R^T w_cam) x p_cam
        wx, wy, wz = (R.T @ w_l).astype(np.float32)
        rel = -(R.T @ v_cam).astype(np.float32) - np.stack(
            [wy * p[:, 2] - wz * p[:, 1], wz * p[:, 0] - wx * p[:, 2], wx * p[:, 1] - wy * p[:, 0]], axis=1
        )
        if labels is not None:
            lab = labels.reshape(-1)[idx]
            rover = np.flatnonzero((lab & ((1 << LINK_SHIFT) - 1)) == body_id)
            if len(rover):
                link_of = (lab[rover] >> LINK_SHIFT) - 1
                p_world = p[rover] @ R.T + c_cam.astype(np.float32)
                for link in np.unique(link_of):
                    if int(link) not in links:
                        continue
                    sel = link_of == link
                    c_l, v, w_ = links[int(link)]
                    v_p = v + np.cross(w_, p_world[sel] - c_l)
                    rel[rover[sel]] += (v_p @ R).astype(np.float32)
        rel /= np.maximum(np.sqrt(np.einsum("ij,ij->i", p, p)), 1e-6)[:, None]
        jac = self.jacobian.reshape(-1, 2, 3)[idx]
        out.reshape(-1, 2)[idx] = np.einsum("nij,nj->ni", jac, rel)
        return out


@functools.lru_cache(maxsize=64)  # a fisheye's windows change size from frame to frame
def _grid(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel x and y coordinates (H, W) float32 of an image, made once per size (read-only)."""
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    xs.flags.writeable = ys.flags.writeable = False
    return xs, ys


def _rgb8(image: np.ndarray) -> bool:
    """Whether ``image`` is (H, W, 3) uint8: resampled through four channels (see :func:`remap_image`)."""
    return image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8


def remap_image(image: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """``cv2.remap`` (bilinear, edges replicated) of an image, an RGB uint8 one through four channels.

    OpenCV's remap has a vector path for four channels, about 2.5 times faster than for three.
    """
    if _rgb8(image):
        out = cv2.remap(
            cv2.cvtColor(image, cv2.COLOR_RGB2RGBA), xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB)
    return cv2.remap(image, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def blur(
    image: np.ndarray,
    velocity: np.ndarray,
    exposure_s: float,
    samples: int,
    rolling_shutter_s: float = 0.0,
    rows: np.ndarray | None = None,
    maps: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """``image`` (the scene at the end of the exposure) integrated over the exposure along ``velocity``.

    Args:
        image: (H, W, C) uint8 rendered at the readout of the frame (the last row's, with a
            rolling shutter).
        velocity: (H, W, 2) image velocity [px/s] (:meth:`MotionField.velocity`, or a renderer's
            velocity buffer).
        exposure_s: Exposure [s].
        samples: Most samples along a path; fewer when the longest path is shorter (at most a
            pixel apart along it, interpolated bilinearly).
        rolling_shutter_s: Readout time from the first row to the last [s]: a pixel on the
            sensor's row fraction ``y`` (0: first row, 1: last) ends its exposure
            ``rolling_shutter_s * (1 - y)`` before the last.
        rows: float32 each output pixel's sensor row fraction ((H, W), or (H', W') with
            ``maps``), where the output is not the sensor's own grid (a fisheye's cube faces);
            None: the output's rows.
        maps: (x, y) float32 (H', W') each output pixel's position in ``image`` [px] (a lens's
            remap, :meth:`cv2.remap`'s maps): the output is the sensor's grid, each pixel's path
            sampled in ``image`` about its position there, in one resampling. None: the output
            is ``image``'s grid.

    Returns:
        (H, W, C) uint8, or (H', W', C) with ``maps``.
    """
    if maps is not None:
        xs, ys = maps
        velocity = cv2.remap(velocity, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        h, w = xs.shape
    else:
        h, w = image.shape[:2]
        xs, ys = _grid(w, h)
    vx, vy = np.ascontiguousarray(velocity[..., 0]), np.ascontiguousarray(velocity[..., 1])
    span = float(max(-vx.min(), vx.max(), -vy.min(), vy.max())) if velocity.size else 0.0
    longest = span * (exposure_s + rolling_shutter_s)
    if longest < 0.25:
        return image if maps is None else remap_image(image, xs, ys)
    # samples at most a pixel apart along the longest path (bilinear between them)
    n = int(min(samples, max(2, math.ceil(longest) + 1)))
    rgb = _rgb8(image)
    if rgb:  # through four channels (see remap_image)
        image = cv2.cvtColor(image, cv2.COLOR_RGB2RGBA)
    acc = np.zeros((h, w, image.shape[2]), np.float32)
    if rolling_shutter_s > 0:
        frac = _grid(w, h)[1] / max(h - 1, 1) if rows is None else rows
        lag = np.float32(rolling_shutter_s) * (1.0 - frac)
    for k in range(n):
        # a pixel saw, s seconds before its readout, what is now (at the last readout) at x + v s
        s = float(exposure_s * (k + 0.5) / n)  # the midpoints of n equal parts
        if rolling_shutter_s > 0:
            t = lag + np.float32(s)
            mx, my = xs + vx * t, ys + vy * t
        else:
            mx, my = cv2.scaleAdd(vx, s, xs), cv2.scaleAdd(vy, s, ys)
        cv2.accumulate(cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE), acc)
    out = cv2.convertScaleAbs(acc, alpha=1.0 / n)
    return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB) if rgb else out

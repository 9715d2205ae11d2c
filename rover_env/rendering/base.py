"""What every renderer gives: the :class:`Renderer` interface, lighting, and rendered views.

Two implementations draw the same scene, sun, sky light and shadows:
:class:`rover_env.rendering.tiny.TinyRenderer` (PyBullet's TinyRenderer, on the CPU, with cast
shadows computed from the rover's convex shapes) and :class:`rover_env.rendering.gl.GLRenderer`
(OpenGL on headless EGL: 10-20x faster on a CPU, and runs on a GPU). Frames: a view's pose is
that of its optical frame (x right, y down, z forward) in the world [m].
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from perception.models.cameras import PinholeCamera
from rover_env.config.scenario import cloud_shade


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose (4x4, world) of a camera optical frame at ``eye`` looking at ``target`` [m]."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: the viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def view_planes(K: np.ndarray, size: tuple[int, int], T_world_cam: np.ndarray, near: float) -> np.ndarray:
    """(5, 4) half-spaces n . x + d >= 0 (world frame) that bound a pinhole view.

    The four sides through the image's edges and the near plane; ``K`` [px] and ``size`` = (W, H)
    [px] as in :func:`render_K` (the principal point may lie outside the image: a crop), ``near`` [m].
    """
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x0, x1 = -cx / fx, (w - cx) / fx  # normalised image coordinates of the edges
    y0, y1 = -cy / fy, (h - cy) / fy
    # inward normals in the camera frame: x - x0 >= 0, x1 - x >= 0, y - y0 >= 0, y1 - y >= 0 on
    # the ray (x, y, 1) scaled by its depth; then the near plane z >= near
    n_cam = np.array([[1.0, 0.0, -x0], [-1.0, 0.0, x1], [0.0, 1.0, -y0], [0.0, -1.0, y1], [0.0, 0.0, 1.0]])
    R, o = T_world_cam[:3, :3], T_world_cam[:3, 3]
    planes = np.empty((5, 4))
    planes[:, :3] = n_cam @ R.T
    planes[:, 3] = -(planes[:, :3] @ o)
    planes[4, 3] -= near
    return planes


@dataclass(frozen=True)
class Lighting:
    """Sun lighting of a rendered view.

    Attributes:
        sun_direction: Unit vector toward the sun, world frame.
        ambient: Share of the albedo seen in full shadow (sky light).
        diffuse: Sunlit share at normal incidence; lit/shadow = (ambient + diffuse cos i) / ambient.
        shadows: Compute cast shadows.
        clouds: Cloud shadows over the ground now (:meth:`rover_env.config.scenario.SunConfig.cloud_bands`).
    """

    sun_direction: tuple[float, float, float]
    ambient: float = 0.25
    diffuse: float = 1.0
    shadows: bool = True
    clouds: tuple[tuple[float, ...], ...] = ()

    def cloud_shade(self, points) -> np.ndarray:
        """Factor (N,) on the direct light at world ``points`` (N, 3) [m] from :attr:`clouds`."""
        return cloud_shade(self.clouds, self.sun_direction, points)


@dataclass
class RenderedView:
    """One rendered pinhole view.

    Attributes:
        rgb: (H, W, 3) uint8.
        depth: (H, W) float32 distance along the optical axis [m] (far plane where nothing was hit);
            None from the GL renderer when no segmentation was asked for.
        segmentation: (H, W) int: PyBullet's body id + ((link + 1) << 24), -1 for background;
            None if it was not asked for (rendering is then about 15 % faster).
        shadow: (H, W) bool, True where the sun is blocked (all False without shadows).
        K: Intrinsics of the view.
        T_world_cam: Pose of the view's optical frame in the world [m].
    """

    rgb: np.ndarray
    depth: np.ndarray | None
    segmentation: np.ndarray | None
    shadow: np.ndarray
    K: np.ndarray
    T_world_cam: np.ndarray
    _points: np.ndarray | None = field(default=None, repr=False)
    #: (H, W, 2) float32 each pixel's image velocity [px/s] in this view (:class:`MotionSpec`), 0
    #: where nothing was drawn; None unless asked for.
    motion: np.ndarray | None = None

    @property
    def points_world(self) -> np.ndarray:
        """(H, W, 3) float32 world position of each pixel's surface point [m] (computed on first use)."""
        if self._points is None:
            if self.depth is None:
                raise ValueError("points_world needs the view's depth; render it with depth")
            h, w = self.depth.shape
            K, T = self.K, self.T_world_cam
            R = T[:3, :3].astype(np.float32)
            xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
            ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
            # world direction of each pixel's ray, scaled to unit optical-axis depth
            rays = xs[None, :, None] * R[:, 0] + (ys[:, None, None] * R[:, 1] + R[:, 2])
            self._points = rays * self.depth[:, :, None] + T[:3, 3].astype(np.float32)
        return self._points


@dataclass
class FisheyeView:
    """One rendered fisheye frame with per-pixel ground truth.

    Attributes:
        rgb: (H, W, 3) uint8, black outside the field of view.
        segmentation: (H, W) int: body id + ((link + 1) << 24), -1 for background or outside.
        shadow: (H, W) bool, True where the sun is blocked.
        points_world: (H, W, 3) float32 world position of each pixel's surface point [m] (NaN
            outside the field of view).

    The last three are None unless rendered with ``labels=True``.
    """

    rgb: np.ndarray
    segmentation: np.ndarray | None = None
    shadow: np.ndarray | None = None
    points_world: np.ndarray | None = None


@dataclass(frozen=True)
class MotionSpec:
    """What a renderer needs to draw a velocity buffer: how the scene moves relative to a camera.

    A surface point ``p`` of body ``body``'s link ``k`` moves at ``v + w x (p - c)`` with
    ``(c, v, w) = links[k]`` (world frame; ``k = -1``: the base); every other body is still. The
    camera's optical centre moves at ``v_cam`` and turns at ``w_cam`` (world frame). The buffer
    holds, per pixel of each pinhole view drawn (a pinhole camera's view; a fisheye's cube
    faces), the image velocity [px/s] of its surface point relative to the camera, exact in the
    colour pass: the point and its relative velocity are affine over a rigid triangle.

    ``expose(image, velocity, origin) -> image``: applied to each drawn view's (H, W, 3) uint8
    colour with its (H, W, 2) buffer before any resampling (a fisheye's faces, window by
    window, before their remap), as a sensor integrates its exposure; ``origin`` (x, y) [px]
    is the image's corner in the renderer's grid (a fisheye's face atlas; (0, 0) for a pinhole
    view). None: the views are returned as drawn.
    """

    body: int
    links: dict
    v_cam: np.ndarray
    w_cam: np.ndarray
    expose: Callable[[np.ndarray, np.ndarray, tuple[int, int]], np.ndarray] | None = None


#: Half the edge of the square about the renderer's focus in which ruts are drawn [m] (the
#: cameras' near ground: the downward camera's view and the fisheye's wheels).
RUT_VIEW_HALF = 2.5


def rut_shade(ruts, points: np.ndarray, normals: np.ndarray, lighting: Lighting) -> np.ndarray:
    """Factor (k,) on the sunlit brightness of ground points for the slope of the ruts there.

    The rut surface lies ``depth(x, y)`` below the ground (:meth:`RutMap.surface_at`); its
    normal is the ground's ``normals`` (k, 3) tilted by the depth's central difference over one
    cell, and the factor is ``(ambient + diffuse cos i') / (ambient + diffuse cos i)`` with the
    incidence on the tilted and on the ground's own normal (1 where neither is lit). ``points``
    (k, 3) world [m]. The depth moves no point (its parallax is not drawn).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    c = ruts.cell
    xy = pts[:, :2]
    gx = ruts.surface_at(xy + [c, 0.0]) - ruts.surface_at(xy - [c, 0.0])
    gy = ruts.surface_at(xy + [0.0, c]) - ruts.surface_at(xy - [0.0, c])
    tilted = n / n[:, 2:3] + np.stack([gx, gy, np.zeros(len(xy))], axis=1) / (2.0 * c)
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    sun = np.asarray(lighting.sun_direction, dtype=np.float64)
    sun = sun / np.linalg.norm(sun)
    a, d = float(lighting.ambient), float(lighting.diffuse)
    before = a + d * np.maximum(n @ sun, 0.0)
    after = a + d * np.maximum(tilted @ sun, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(before > 0.0, after / before, 1.0)


class Renderer(ABC):
    """Draws one PyBullet client's scene: pinhole views and fisheye images with sun shadows.

    A renderer reads the scene (bodies, poses, textures) and never changes the physics: the
    ground detail it may add to the client is visual only, and :meth:`before_restore` removes it
    before a saved state is restored.
    """

    #: ``"gl"`` or ``"tiny"``.
    name: ClassVar[str]
    #: Whether :meth:`render_K` and :meth:`render_fisheye` take ``motion=`` (:class:`MotionSpec`)
    #: and draw a velocity buffer in the colour pass.
    draws_motion: ClassVar[bool] = False

    @abstractmethod
    def focus(self, x: float, y: float, ground_range: float | None = None) -> None:
        """Draw the ground for views taken from near world (x, y) [m]; call before rendering them.

        ``ground_range`` [m]: the views see no ground farther than this from (x, y) (only the
        ground within it need be drawn); None: they may see the horizon.
        """

    @abstractmethod
    def render_K(
        self,
        K: np.ndarray,
        size: tuple[int, int],
        T_world_cam: np.ndarray,
        lighting: Lighting,
        near: float = 0.05,
        far: float = 20.0,
        segmentation: bool = True,
    ) -> RenderedView:
        """Render the pinhole view with intrinsics ``K`` [px] and ``size`` = (W, H) [px], with sun shadows.

        The principal point may lie outside the image (the view is a crop of a larger one).
        ``T_world_cam``: the optical frame's pose in the world [m]; ``near``, ``far``: clip
        distances [m]; ``segmentation``: also return the segmentation labels and the depth.
        """

    def render_pinhole(
        self, camera: PinholeCamera, T_world_cam: np.ndarray, lighting: Lighting, **options
    ) -> RenderedView:
        """Render an ideal pinhole view (distortion is not rendered) with sun shadows.

        ``camera`` gives the intrinsics and image size (its distortion must be zero); the other
        arguments and ``options`` are those of :meth:`render_K`.
        """
        if np.any(camera.distortion):
            raise ValueError("render_pinhole renders ideal pinhole images; use a camera with zero distortion")
        return self.render_K(camera.K, camera.image_size, T_world_cam, lighting, **options)

    @abstractmethod
    def render_fisheye(
        self,
        remapper,
        T_world_cam: np.ndarray,
        lighting: Lighting,
        labels: bool = False,
        near: float = 0.01,
        far: float = 20.0,
        windows=None,
    ) -> FisheyeView:
        """Render the fisheye image of the camera at ``T_world_cam`` (optical frame, world) [m].

        Args:
            remapper: Face layout and remap of the fisheye model
                (:class:`rover_env.rendering.cubemap.CubemapRemap`).
            T_world_cam: Pose of the fisheye optical frame in the world.
            lighting: Sun and shadow settings.
            labels: Also remap segmentation, shadow and 3-D points (for tests and evaluation).
            near: Near clipping distance [m].
            far: Far clipping distance [m].
            windows: Render only these rectangles of the faces (``CubemapRemap.windows``); the
                rest of the image is black (no labels, no points). None: whole faces.
        """

    @property
    @abstractmethod
    def ground_ids(self) -> tuple[int, ...]:
        """Body ids that label ground pixels in the segmentation."""

    def before_restore(self) -> None:  # noqa: B027 - optional hook
        """Remove what this renderer added to the client (before a saved state is restored)."""

    def release(self) -> None:  # noqa: B027 - optional hook
        """Free this renderer's resources; safe to call more than once."""

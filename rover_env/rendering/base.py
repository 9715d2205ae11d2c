"""Pinhole rendering: exact views and sun shadows with real contrast, on TinyRenderer or OpenGL.

:func:`render_K` draws with PyBullet's TinyRenderer, or hands the view to a
:class:`rover_env.rendering.gl.GLRenderer` (which draws the same lighting and shadows on the GPU side).

TinyRenderer's built-in shadow only scales the diffuse term by 0.8 and its shadow map is aimed at
the world origin, so a rover 10 m away casts no shadow and a shadowed patch is at most 1.25x
darker. Real sunlight gives 2.5x and more. So shadows are computed here: every camera pixel's 3-D
point (from the depth buffer) is tested against the rover's convex shapes along the sun direction
(:class:`rover_env.rendering.shadows.ShadowCaster`), and shadowed pixels keep only the ambient share of their
lit brightness.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import pybullet as pb

from perception.cameras import PinholeCamera
from rover_env.rendering.shadows import ShadowCaster, ShadowMap

# camera optical frame (x right, y down, z forward) -> OpenGL eye frame (x right, y up, z back)
_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


def gl_view_matrix(T_world_cam: np.ndarray) -> list[float]:
    """PyBullet (column-major) view matrix of a camera whose optical frame pose is ``T_world_cam``."""
    view = np.linalg.inv(T_world_cam @ _OPTICAL_TO_GL)
    return view.T.reshape(-1).tolist()


def gl_projection_from_K(K: np.ndarray, size: tuple[int, int], near: float, far: float) -> list[float]:
    """Column-major frustum with which TinyRenderer renders exactly the pinhole ``K`` at ``size`` = (W, H).

    Pixel centres are at integer coordinates. TinyRenderer samples pixel (i, j) at viewport point
    (i, H - j) (measured with boxes at known points), so the frustum spans [0, W] across and
    [-1, H - 1] down. (The GL renderer's matrix is :func:`rover_env.rendering.gl.projection_from_K`.)
    """
    w, h = size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # image coordinates of the frustum's left and top edges
    x0, y0 = 0.0, -1.0
    left = (x0 - cx) * near / fx
    right = (x0 + w - cx) * near / fx
    top = (cy - y0) * near / fy
    bottom = -(y0 + h - cy) * near / fy
    P = np.zeros((4, 4))
    P[0, 0] = 2 * near / (right - left)
    P[0, 2] = (right + left) / (right - left)
    P[1, 1] = 2 * near / (top - bottom)
    P[1, 2] = (top + bottom) / (top - bottom)
    P[2, 2] = -(far + near) / (far - near)
    P[2, 3] = -2 * far * near / (far - near)
    P[3, 2] = -1.0
    return P.T.reshape(-1).tolist()


@dataclass(frozen=True)
class Lighting:
    """Sun lighting of a rendered view.

    Attributes:
        sun_direction: Unit vector toward the sun, world frame.
        ambient: Share of the albedo seen in full shadow (sky light).
        diffuse: Sunlit share at normal incidence; lit/shadow = (ambient + diffuse cos i) / ambient.
        shadows: Compute cast shadows.
    """

    sun_direction: tuple[float, float, float]
    ambient: float = 0.25
    diffuse: float = 1.0
    shadows: bool = True


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

    @property
    def points_world(self) -> np.ndarray:
        """(H, W, 3) float32 world position of each pixel's surface point [m] (computed on first use)."""
        if self._points is None:
            h, w = self.depth.shape
            K, T = self.K, self.T_world_cam
            R = T[:3, :3].astype(np.float32)
            xs = ((np.arange(w) - K[0, 2]) / K[0, 0]).astype(np.float32)
            ys = ((np.arange(h) - K[1, 2]) / K[1, 1]).astype(np.float32)
            # world direction of each pixel's ray, scaled to unit optical-axis depth
            rays = xs[None, :, None] * R[:, 0] + (ys[:, None, None] * R[:, 1] + R[:, 2])
            self._points = rays * self.depth[:, :, None] + T[:3, 3].astype(np.float32)
        return self._points


#: Renderer names: ``"gl"`` (OpenGL on headless EGL, :mod:`rover_env.rendering.gl`) and ``"tiny"``
#: (PyBullet's TinyRenderer, on the CPU).
RENDERERS: tuple[str, ...] = ("gl", "tiny")


def check_renderer(name) -> str:
    """``name`` if it is a renderer choice (``"auto"`` included).

    Raises:
        ValueError: Unknown name; the message lists the choices.
    """
    if name not in ("auto",) + RENDERERS:
        raise ValueError(
            f"renderer={name!r}: use 'gl' (OpenGL on headless EGL), 'tiny' (PyBullet's TinyRenderer) "
            "or 'auto' (gl where an EGL context can be created, else tiny)"
        )
    return name


def _camera_image(client, size, view, proj, lighting: Lighting, segmentation=True):
    w, h = size
    img = client.getCameraImage(
        w,
        h,
        view,
        proj,
        shadow=0,
        lightDirection=list(lighting.sun_direction),
        lightAmbientCoeff=lighting.ambient,
        lightDiffuseCoeff=lighting.diffuse,
        lightSpecularCoeff=0.0,
        renderer=pb.ER_TINY_RENDERER,
        flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX if segmentation else pb.ER_NO_SEGMENTATION_MASK,
    )
    rgba = np.reshape(np.asarray(img[2], dtype=np.uint8), (h, w, 4))
    rgb = cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB)
    depth = np.reshape(np.asarray(img[3], dtype=np.float32), (h, w))
    seg = np.reshape(np.asarray(img[4], dtype=np.int32), (h, w)) if segmentation else None
    return rgb, depth, seg


def render_pinhole(
    client, camera: PinholeCamera, T_world_cam: np.ndarray, lighting: Lighting, **options
) -> RenderedView:
    """Render an ideal pinhole view (distortion is not rendered) with sun shadows.

    ``camera`` gives the intrinsics and image size (its distortion must be zero); the other
    arguments and ``options`` are those of :func:`render_K`.
    """
    if np.any(camera.distortion):
        raise ValueError("render_pinhole renders ideal pinhole images; use a camera with zero distortion")
    return render_K(client, camera.K, camera.image_size, T_world_cam, lighting, **options)


def render_K(
    client,
    K: np.ndarray,
    size: tuple[int, int],
    T_world_cam: np.ndarray,
    lighting: Lighting,
    near: float = 0.05,
    far: float = 20.0,
    caster: ShadowCaster | None = None,
    shadow_map: ShadowMap | None = None,
    renderer="tiny",
    segmentation: bool = True,
    cull=None,
) -> RenderedView:
    """Render the pinhole view with intrinsics ``K`` [px] and ``size`` = (W, H) [px], with sun shadows.

    The principal point may lie outside the image (the view is a crop of a larger one).

    Args:
        client: The environment's BulletClient.
        K: Intrinsics [px].
        size: Image (width, height) [px].
        T_world_cam: Pose of the camera optical frame in the world [m].
        lighting: Sun and shadow settings.
        near: Near clipping distance [m].
        far: Far clipping distance [m].
        caster: The shadow-casting body; with ``lighting.shadows`` on, this or ``shadow_map``.
        shadow_map: A shadow map already built for this instant (several views of one frame).
        renderer: ``"tiny"`` (TinyRenderer) or a :class:`rover_env.rendering.gl.GLRenderer` of
            ``client`` (which draws its own shadow map: ``caster``, ``shadow_map`` and ``cull``
            are not used, and ``depth`` is None without ``segmentation``).
        segmentation: Also return the segmentation labels (and, with GL, the depth).
        cull: Called with the view's :func:`view_planes` before it is rendered (for example
            :meth:`rover_env.sim.terrain.Terrain.cull`, which leaves out ground the view cannot see).
    """
    if not isinstance(renderer, str):
        return renderer.render_K(K, size, T_world_cam, lighting, near, far, segmentation)
    if renderer != "tiny":
        raise ValueError(f"renderer={renderer!r}: pass 'tiny' or a GLRenderer (RoverSim.backend gives it)")
    if cull is not None:
        cull(view_planes(K, size, T_world_cam, near))
    view, proj = gl_view_matrix(T_world_cam), gl_projection_from_K(K, size, near, far)
    rgb, zbuf, seg = _camera_image(client, size, view, proj, lighting, segmentation)
    depth = np.float32(far * near) / (np.float32(far) - np.float32(far - near) * zbuf)
    w, h = size
    view = RenderedView(rgb, depth, seg, np.zeros((h, w), dtype=bool), K, np.asarray(T_world_cam))
    if lighting.shadows:
        hit = seg >= 0 if seg is not None else zbuf < 1.0  # nothing hit: the far plane, 1
        if shadow_map is None and hit.any():
            if caster is None:
                raise ValueError("lighting.shadows is on: pass the rover's ShadowCaster or a ShadowMap")
            texel = float(np.median(depth[hit])) / K[0, 0]  # ground size of a pixel [m]
            shadow_map = caster.shadow_map(lighting.sun_direction, texel)
        if shadow_map is not None:
            view.shadow = shadow_map.lookup_view(depth, K, view.T_world_cam) & hit
        if view.shadow.any():
            _darken(rgb, view.shadow, depth, K, view.T_world_cam[:3, :3], lighting)
    return view


def _darken(
    rgb: np.ndarray,
    shadow: np.ndarray,
    depth: np.ndarray,
    K: np.ndarray,
    R_world_cam: np.ndarray,
    lighting: Lighting,
) -> None:
    """Scale shadowed pixels of ``rgb`` (in place) from ambient + diffuse cos(i) to ambient only.

    The incidence cosine comes from surface normals estimated from the depth image's central
    differences (one-sided at the image border) of the view with intrinsics ``K`` [px] and
    orientation ``R_world_cam``. Only the bounding box of the shadow is computed.
    """
    rows = np.flatnonzero(shadow.any(axis=1))
    cols = np.flatnonzero(shadow.any(axis=0))
    r0, r1 = int(rows[0]), int(rows[-1]) + 1
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    h, w = shadow.shape
    # the box and a one-pixel border (edge-replicated at the image border)
    z = depth[max(r0 - 1, 0) : min(r1 + 1, h), max(c0 - 1, 0) : min(c1 + 1, w)]
    pad = ((int(r0 == 0), int(r1 == h)), (int(c0 == 0), int(c1 == w)))
    if any(any(v) for v in pad):
        z = cv2.copyMakeBorder(z, *pad[0], *pad[1], cv2.BORDER_REPLICATE)
    # dZ/dx and dZ/dy [m/px]: central differences, one-sided where the border was replicated
    kx = np.full(c1 - c0, 0.5, np.float32)
    ky = np.full((r1 - r0, 1), 0.5, np.float32)
    kx[[0, -1]] += 0.5 * np.array(pad[1], np.float32)
    ky[[0, -1], 0] += 0.5 * np.array(pad[0], np.float32)
    zx = (z[1:-1, 2:] - z[1:-1, :-2]) * kx
    zy = (z[2:, 1:-1] - z[:-2, 1:-1]) * ky
    z = z[1:-1, 1:-1]
    x = ((np.arange(c0, c1) - K[0, 2]) / K[0, 0]).astype(np.float32)  # normalised image coordinates
    y = ((np.arange(r0, r1) - K[1, 2]) / K[1, 1]).astype(np.float32)[:, None]
    # the surface P = Z (x, y, 1) has the normal dP/dx x dP/dy ~ (-a, -b, nz) below, which points
    # away from the camera; its negative is lit
    a, b = np.float32(K[0, 0]) * zx, np.float32(K[1, 1]) * zy
    nz = a * x + b * y + z
    sx, sy, sz = (np.float32(v) for v in R_world_cam.T @ lighting.sun_direction)  # optical frame
    norm = np.sqrt(a * a + b * b + nz * nz)
    cos_i = np.clip((sx * a + sy * b - sz * nz) / np.maximum(norm, np.float32(1e-30)), 0.0, 1.0)
    a, d = np.float32(lighting.ambient), np.float32(lighting.diffuse)
    box = shadow[r0:r1, c0:c1]
    factor = np.where(box, a / (a + d * cos_i), np.float32(1.0))
    rgb[r0:r1, c0:c1] = cv2.convertScaleAbs(rgb[r0:r1, c0:c1] * factor[:, :, None])  # rounded

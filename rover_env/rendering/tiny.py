"""TinyRenderer: PyBullet's CPU rasteriser, with real sun shadows computed here.

TinyRenderer's built-in shadow only scales the diffuse term by 0.8 and its shadow map is aimed at
the world origin, so a rover 10 m away casts no shadow and a shadowed patch is at most 1.25x
darker. Real sunlight gives 2.5x and more. So shadows are computed here: every camera pixel's 3-D
point (from the depth buffer) is tested against the rover's convex shapes along the sun direction
(:class:`rover_env.rendering.shadows.ShadowCaster`), and shadowed pixels keep only the ambient
share of their lit brightness. The ground near the rover is drawn at full detail
(:class:`rover_env.rendering.ground_detail.GroundDetail`).
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np
import pybullet as pb

from rover_env.rendering.base import (
    RUT_VIEW_HALF,
    FisheyeView,
    Lighting,
    RenderedView,
    Renderer,
    rut_shade,
    view_planes,
)
from rover_env.rendering.cubemap import SHADOW_DETAIL_RANGE, CubemapRemap
from rover_env.rendering.ground_detail import GroundDetail
from rover_env.rendering.shadows import ShadowCaster, ShadowMap
from rover_env.sim.terrain import Terrain

# camera optical frame (x right, y down, z forward) -> OpenGL eye frame (x right, y up, z back)
_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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


class TinyRenderer(Renderer):
    """PyBullet's TinyRenderer drawing ``client``'s scene, with sun shadows cast by one body.

    Args:
        client: The BulletClient whose scene is drawn.
        terrain: The ground, drawn at full detail near the focus (None: the client's bodies as
            they are).
        shadow_body: The body whose sun shadow is computed (the rover); None: views with
            ``lighting.shadows`` on cannot be rendered.
        ruts: The wheels' ruts in deformable soil (:class:`rover_env.sim.ruts.RutMap`), if any:
            sunlit ground within :data:`~rover_env.rendering.base.RUT_VIEW_HALF` of the focus
            is shaded with the slope of their surface (:func:`~rover_env.rendering.base.rut_shade`,
            as the GL renderer does), after the image is drawn.
    """

    name = "tiny"

    def __init__(
        self, client, terrain: Terrain | None = None, shadow_body: int | None = None, ruts=None
    ) -> None:
        self.client = client
        self.terrain = terrain
        self.detail = GroundDetail(client, terrain) if terrain is not None else None
        self._shadow_body = shadow_body
        self.ruts = ruts
        self._focus: tuple[float, float] | None = None

    @functools.cached_property
    def shadow_caster(self) -> ShadowCaster:
        """The shadow body's sun-shadow caster (built on first use)."""
        if self._shadow_body is None:
            raise ValueError("lighting.shadows is on, but this renderer has no shadow_body (the rover)")
        return ShadowCaster(self.client, self._shadow_body)

    @property
    def ground_ids(self) -> tuple[int, ...]:
        """The terrain's body and its near-ground chunks (empty without a terrain)."""
        return self.detail.ground_ids if self.detail is not None else ()

    def focus(self, x: float, y: float, ground_range: float | None = None) -> None:
        """See :meth:`Renderer.focus`: the exact ground near (x, y) [m] (:class:`GroundDetail`)."""
        self._focus = (float(x), float(y))
        if self.detail is not None:
            self.detail.focus(x, y, ground_range)

    def before_restore(self) -> None:
        """Remove the near-ground chunks (a saved state has none)."""
        if self.detail is not None:
            self.detail.drop_detail()

    def render_K(
        self,
        K: np.ndarray,
        size: tuple[int, int],
        T_world_cam: np.ndarray,
        lighting: Lighting,
        near: float = 0.05,
        far: float = 20.0,
        segmentation: bool = True,
        shadow_map: ShadowMap | None = None,
        cull: bool = True,
    ) -> RenderedView:
        """See :meth:`Renderer.render_K`.

        ``shadow_map``: a shadow map already built for this instant (several views of one frame);
        None: built for this view by the shadow body's caster. ``cull``: draw only the
        near-ground chunks that may be inside the view (:meth:`GroundDetail.cull`: the same
        image, at less cost).
        """
        if lighting.clouds:  # no per-pixel light here: the cloud shadows' shade at the camera
            shade = float(lighting.cloud_shade(np.asarray(T_world_cam)[:3, 3])[0])
            lighting = dataclasses.replace(lighting, diffuse=lighting.diffuse * shade, clouds=())
        if cull and self.detail is not None and self.detail.view_cull is not None:
            self.detail.view_cull(view_planes(K, size, T_world_cam, near))
        view, proj = gl_view_matrix(T_world_cam), gl_projection_from_K(K, size, near, far)
        rgb, zbuf, seg = _camera_image(self.client, size, view, proj, lighting, segmentation)
        depth = np.float32(far * near) / (np.float32(far) - np.float32(far - near) * zbuf)
        w, h = size
        out = RenderedView(rgb, depth, seg, np.zeros((h, w), dtype=bool), K, np.asarray(T_world_cam))
        if lighting.shadows:
            hit = seg >= 0 if seg is not None else zbuf < 1.0  # nothing hit: the far plane, 1
            if shadow_map is None and hit.any():
                texel = float(np.median(depth[hit])) / K[0, 0]  # ground size of a pixel [m]
                shadow_map = self.shadow_caster.shadow_map(lighting.sun_direction, texel)
            if shadow_map is not None:
                out.shadow = shadow_map.lookup_view(depth, K, out.T_world_cam) & hit
            if out.shadow.any():
                _darken(rgb, out.shadow, depth, K, out.T_world_cam[:3, :3], lighting)
        if self.ruts is not None and self.ruts.pressed and self.terrain is not None:
            self._shade_ruts(out, seg, lighting)
        return out

    def _shade_ruts(self, view: RenderedView, seg: np.ndarray | None, lighting: Lighting) -> None:
        """Shade the view's sunlit ground near the focus for the ruts' slope (in place)."""
        assert self.ruts is not None and self.terrain is not None
        ruts = self.ruts
        cx, cy = self._focus if self._focus is not None else tuple(ruts.origin + 0.5 * ruts.size)
        pts = view.points_world
        near = (np.abs(pts[..., 0] - cx) < RUT_VIEW_HALF) & (np.abs(pts[..., 1] - cy) < RUT_VIEW_HALF)
        near &= ~view.shadow
        if seg is not None:
            near &= np.isin(seg, self.ground_ids)
        if not near.any():
            return
        p = pts[near].astype(np.float64)
        ground = self.terrain.height_at(p[:, 0], p[:, 1])
        on = np.abs(p[:, 2] - ground) < 0.005  # the ground itself (without labels: by its height)
        idx = np.flatnonzero(near)[on]
        if not len(idx):
            return
        p = p[on]
        factor = rut_shade(ruts, p, self.terrain.normal_at(p[:, 0], p[:, 1]), lighting)
        changed = factor != 1.0
        if changed.any():
            flat = view.rgb.reshape(-1, 3)
            k = idx[changed]
            flat[k] = np.clip(np.rint(flat[k] * factor[changed, None]), 0, 255).astype(np.uint8)

    def render_fisheye(
        self,
        remapper: CubemapRemap,
        T_world_cam: np.ndarray,
        lighting: Lighting,
        labels: bool = False,
        near: float = 0.01,
        far: float = 20.0,
        windows=None,
    ) -> FisheyeView:
        """See :meth:`Renderer.render_fisheye`: each face a pinhole view, one shadow map for all."""
        shadow_map = None
        if lighting.shadows:
            # one map for all faces, resolved like the image at the distance of the wheels
            shadow_map = self.shadow_caster.shadow_map(
                lighting.sun_direction, SHADOW_DETAIL_RANGE / remapper.focal
            )
        views: list[RenderedView | None] = []
        for k, fc in enumerate(remapper.faces):
            face = fc.view(T_world_cam, None if windows is None else windows[k])
            if face is None:
                views.append(None)
                continue
            K, size, T_face, _ = face
            views.append(self.render_K(K, size, T_face, lighting, near, far, labels, shadow_map=shadow_map))
        w, h = remapper.model.image_size
        if all(v is None for v in views):  # every window empty: a black frame
            if not labels:
                return FisheyeView(rgb=np.zeros((h, w, 3), np.uint8))
            return FisheyeView(
                np.zeros((h, w, 3), np.uint8), np.full((h, w), -1, np.int32), np.zeros((h, w), bool),
                np.full((h, w, 3), np.nan, np.float32),
            )  # fmt: skip

        def atlas(name, fill):
            return remapper.atlas([None if v is None else getattr(v, name) for v in views], fill, windows)

        rgb = remapper.remap(atlas("rgb", 0))
        if not labels:
            return FisheyeView(rgb=rgb)
        seg = remapper.lookup(atlas("segmentation", -1), outside=-1)
        shadow = remapper.lookup(atlas("shadow", False), outside=False)
        pts = remapper.lookup(atlas("points_world", np.nan), outside=np.nan)
        return FisheyeView(rgb=rgb, segmentation=seg, shadow=shadow, points_world=pts)


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

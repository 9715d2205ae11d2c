"""A fisheye image from cubemap faces rendered as pinhole views, and one remap.

Renderers draw pinhole views, so a >180 deg fisheye is assembled from cube faces: the face
along the optical axis and the four side faces, each rendered only over the part of it that the
fisheye image uses (plus a 2-pixel margin, so that bilinear sampling never reads across a face
edge; that is what keeps the image free of seams). The faces are packed into one atlas image and
every fisheye pixel is looked up through one precomputed fixed-point ``cv2.remap``, using the
exact :class:`perception.OmniCamera` model that the estimators receive.

A region of interest renders less (a mask of the fisheye pixels to draw, such as
:func:`perception.models.rover_parts.kinematics_roi`), like a sensor's ROI readout; the rest of the
image is black. Rendering time is proportional to the rendered pixels.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from perception.models.cameras import OmniCamera

SHADOW_DETAIL_RANGE = 0.5  # [m] about the distance of wheels and markers from the fisheye
MAX_VIEW_HALF_ANGLE = math.radians(55.0)  # widest ray of a ROI view from its axis


# cube faces in the camera optical frame: (name, face optical axis, face image "down" direction)
_FACES = (
    ("axis", (0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    ("+x", (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("-x", (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ("+y", (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ("-y", (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
)


@dataclass(frozen=True)
class CubeFace:
    """One rendered pinhole view: a cube face, or a view aimed at one part of a ROI.

    Attributes:
        name: ``axis``, ``+x``, ``-x``, ``+y`` or ``-y`` (direction in the fisheye optical frame),
            or ``roi<k>`` for the k-th part of a ROI.
        R_cam_face: Rotation from the face's optical frame to the fisheye's optical frame.
        K: The view's pinhole intrinsics [px], cropped to the region the fisheye uses (the
            principal point may lie outside the view).
        size: The view's (width, height) [px].
        atlas_row: First row of this view in the atlas [px].
    """

    name: str
    R_cam_face: np.ndarray
    K: np.ndarray
    size: tuple[int, int]
    atlas_row: int

    def view(self, T_world_cam: np.ndarray, window=None):
        """The view to render of this face: (K, (w, h), T_world_face, (u0, v0, u1, v1)), or None.

        ``window`` (u0, v0, u1, v1) [face px] crops the face (its K shifted by the window's
        corner); None: the whole face. An empty window gives None.
        """
        u0, v0, u1, v1 = (0, 0, *self.size) if window is None else window
        if u1 <= u0 or v1 <= v0:
            return None
        K = self.K.copy()
        K[0, 2] -= u0  # the window is a crop of the face
        K[1, 2] -= v0
        T_face = T_world_cam.copy()
        T_face[:3, :3] = T_world_cam[:3, :3] @ self.R_cam_face
        return K, (u1 - u0, v1 - v0), T_face, (u0, v0, u1, v1)


class CubemapRemap:
    """Face layout and the fixed-point remap from a cube-face atlas to an :class:`OmniCamera` image.

    Args:
        model: The fisheye model; the output image has its size.
        margin: Extra face pixels around the used region [px] (>= 2 for seamless bilinear sampling).
        oversample: Face focal length relative to the fisheye's finest angular resolution.
        cube_roll: Rotation of the cube about the optical axis [rad] (moves the face edges; the
            image must not change, which is how the seam test works).
        roi: (H, W) bool mask of the fisheye pixels to render (None: all); each connected part
            of it is rendered as one pinhole view aimed at it, the other pixels stay black. A
            sequence of masks is a region of interest in parts: each mask's connected parts are
            views of their own even where they touch another mask's (a pixel in several is the
            first one's), so that a readout window can take each separately.
        region_oversample: With ``roi`` masks, each region's views' focal length relative to
            ``oversample``'s (None: all 1). A cube face is finest at its centre, where its
            resolution matches the fisheye's, and oversamples the fisheye twice at its edges; a
            region whose detail matters less (the ground the one-camera rig's odometry tracks)
            can be rendered coarser, at that factor squared of the pixels.
    """

    def __init__(
        self,
        model: OmniCamera,
        margin: int = 2,
        oversample: float = 1.0,
        cube_roll: float = 0.0,
        roi: np.ndarray | Sequence[np.ndarray] | None = None,
        region_oversample: Sequence[float] | None = None,
    ) -> None:
        if margin < 1:
            raise ValueError(f"margin: {margin} px; use >= 1 (2 recommended) so faces can be interpolated")
        if not oversample > 0:
            raise ValueError(f"oversample: {oversample!r} must be > 0")
        self.model = model
        w, h = model.image_size
        regions: list[np.ndarray] = []
        if roi is not None:
            masks = [roi] if isinstance(roi, np.ndarray) else list(roi)
            for m in masks:
                m = np.asarray(m)
                if m.shape != (h, w):
                    raise ValueError(f"roi: shape {m.shape}, expected the image's ({h}, {w})")
                regions.append(m.astype(bool))
            if not regions:
                raise ValueError("roi: an empty sequence of masks; give a mask, masks, or None")
            roi = np.logical_or.reduce(regions)
        factors = (
            [1.0] * max(len(regions), 1)
            if region_oversample is None
            else [float(v) for v in region_oversample]
        )
        if len(factors) != max(len(regions), 1) or not all(math.isfinite(v) and v > 0 for v in factors):
            raise ValueError(
                f"region_oversample: {region_oversample!r}; give one factor > 0 per roi mask "
                f"({max(len(regions), 1)})"
            )
        xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays = model.cam2world(np.stack([xs, ys], -1)).reshape(-1, 3)
        valid = np.isfinite(rays[:, 0])
        self.valid = valid.reshape(h, w)  # inside the field of view
        #: Pixels that are rendered: the field of view, within the ROI if there is one.
        self.rendered = self.valid & roi if roi is not None else self.valid.copy()
        # focal length of the faces: the fisheye's finest angular resolution [px/rad]
        alpha = np.arccos(np.clip(rays[valid, 2], -1.0, 1.0))
        pix = np.stack([xs.reshape(-1)[valid], ys.reshape(-1)[valid]], 1)
        dist = np.hypot(pix[:, 0] - model.center[0], pix[:, 1] - model.center[1])
        ring = alpha > 0.05
        k = float(np.max(dist[ring] / alpha[ring])) if ring.any() else float(max(w, h))
        f = math.ceil(k * oversample)
        #: The faces' focal length [px] before ``region_oversample`` (what the shadow map's detail follows).
        self.focal = f

        cr, sr = math.cos(cube_roll), math.sin(cube_roll)
        R_cam_cube = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
        # each ray belongs to the face whose axis it is closest to
        axes = np.array([axis for _, axis, _ in _FACES])
        owner = np.where(valid, np.argmax(np.nan_to_num(rays @ R_cam_cube) @ axes.T, axis=1), -1)
        face_R = [R_cam_cube @ np.stack([np.cross(down, axis), down, axis], 1) for _, axis, down in _FACES]
        views: list[tuple[str, np.ndarray, np.ndarray]] = []  # (name, R_cam_view, pixel indices)
        region_of: dict[int, int] = {}  # ROI part -> its region
        view_region: list[int] = []  # the region of each view
        if roi is None:
            for i, (name, _, _) in enumerate(_FACES):
                views.append((name, face_R[i], np.flatnonzero(owner == i)))
        else:
            # one view per connected part of the ROI, aimed at its middle; a part wider than
            # +-MAX_VIEW_HALF_ANGLE is split along the cube faces instead
            labels = np.zeros((h, w), np.int32)
            part_region = [0]  # the region of each part
            taken = ~self.valid
            for r, region in enumerate(regions):
                n, lab = cv2.connectedComponents((region & ~taken).astype(np.uint8), connectivity=8)
                top = int(labels.max())
                labels = np.where(lab > 0, lab + top, labels)
                part_region += [r] * (n - 1)
                taken = taken | region
            parts = labels.reshape(-1)
            for k in range(1, int(parts.max()) + 1):
                sel = np.flatnonzero(parts == k)
                region_of[k] = part_region[k]
                z = rays[sel].mean(axis=0)
                z /= np.linalg.norm(z)
                if np.min(rays[sel] @ z) >= math.cos(MAX_VIEW_HALF_ANGLE):
                    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
                    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([0.0, 1.0, 0.0])
                    views.append((f"roi{k}", np.stack([x, np.cross(z, x), z], 1), sel))
                    view_region.append(region_of[k])
                    continue
                for i, (name, _, _) in enumerate(_FACES):
                    if np.any(owner[sel] == i):
                        views.append((name, face_R[i], sel[owner[sel] == i]))
                        view_region.append(region_of[k])
        faces: list[CubeFace] = []
        face_of = np.full(w * h, -1)
        map_x = np.full(w * h, -10.0, dtype=np.float32)
        map_y = np.full(w * h, -10.0, dtype=np.float32)
        row = 0
        width = 0
        regions_kept: list[int] = []
        for j, (name, R, sel) in enumerate(views):
            if len(sel) == 0:
                continue
            regions_kept.append(view_region[j] if view_region else 0)
            fv = max(1, round(f * factors[regions_kept[-1]]))  # this view's focal length [px]
            local = rays[sel] @ R  # view optical-frame rays
            u = fv * local[:, 0] / local[:, 2]
            v = fv * local[:, 1] / local[:, 2]
            u0 = int(math.floor(u.min())) - margin
            v0 = int(math.floor(v.min())) - margin
            u1 = int(math.ceil(u.max())) + margin
            v1 = int(math.ceil(v.max())) + margin
            K = np.array([[fv, 0.0, -u0], [0.0, fv, -v0], [0.0, 0.0, 1.0]], dtype=np.float64)
            size = (u1 - u0 + 1, v1 - v0 + 1)
            face_of[sel] = len(faces)
            faces.append(CubeFace(name, R, K, size, row))
            map_x[sel] = u - u0
            map_y[sel] = v - v0 + row
            row += size[1]
            width = max(width, size[0])
        self.faces: tuple[CubeFace, ...] = tuple(faces)
        #: The ROI region (index into a sequence of masks; 0 for one mask or none) of each face.
        self.face_region: tuple[int, ...] = tuple(regions_kept)
        self.face_index = face_of.reshape(h, w)  # index into faces of each pixel, -1 outside
        self.atlas_size = (width, row)
        #: Float atlas coordinates [atlas px] of every fisheye pixel, (H, W) each; -10 where
        #: nothing is rendered (outside the field of view or the region of interest).
        self.maps = (map_x.reshape(h, w), map_y.reshape(h, w))
        self._map1, self._map2 = cv2.convertMaps(
            map_x.reshape(h, w), map_y.reshape(h, w), cv2.CV_16SC2, nninterpolation=False
        )
        # nearest atlas pixel of every output pixel (labels and points), -1 where nothing is rendered
        near_x = np.clip(np.rint(map_x).astype(np.int64), 0, width - 1)
        near_y = np.clip(np.rint(map_y).astype(np.int64), 0, row - 1)
        self._nearest = np.where(face_of >= 0, near_y * width + near_x, -1).reshape(h, w)

    @functools.cached_property
    def atlas_rows(self) -> np.ndarray:
        """(H, W) float32 the fisheye image row [px] of each atlas pixel's ray.

        What a rolling shutter needs to expose the atlas (:func:`rover_env.sensors.motion_blur.blur`).
        A ray outside the fisheye's field of view (a face's margin) and a pixel of no face take
        the nearest one's row.
        """
        aw, ah = self.atlas_size
        out = np.full((ah, aw), np.nan, np.float32)
        for fc in self.faces:
            fw, fh = fc.size
            u, v = np.meshgrid(np.arange(fw, dtype=np.float64), np.arange(fh, dtype=np.float64))
            x, y = (u - fc.K[0, 2]) / fc.K[0, 0], (v - fc.K[1, 2]) / fc.K[1, 1]
            rays = np.stack([x, y, np.ones_like(u)], -1)
            px = self.model.world2cam((rays @ fc.R_cam_face.T).reshape(-1, 3)).reshape(fh, fw, 2)
            out[fc.atlas_row : fc.atlas_row + fh, :fw] = px[..., 1]
        none = ~np.isfinite(out)
        if none.all():
            out[:] = 0.0
        elif none.any():
            _, (iy, ix) = ndimage.distance_transform_edt(none, return_indices=True)
            out = out[iy, ix]
        out.flags.writeable = False
        return out

    @property
    def face_pixels(self) -> int:
        """Total number of rendered face pixels per fisheye frame (ROI views included)."""
        return sum(fc.size[0] * fc.size[1] for fc in self.faces)

    def atlas(self, face_images, fill=0, windows=None) -> np.ndarray:
        """Pack face images (in ``faces`` order) into one atlas image.

        With ``windows`` (:meth:`windows`), image k covers window k of face k (None for an empty
        window) and the rest of the atlas is ``fill``.
        """
        first = next(np.asarray(img) for img in face_images if img is not None)
        W, H = self.atlas_size
        out = np.full((H, W) + first.shape[2:], fill, dtype=first.dtype)
        if windows is None:
            windows = [(0, 0) + fc.size for fc in self.faces]
        for fc, img, (u0, v0, u1, v1) in zip(self.faces, face_images, windows, strict=True):
            if u1 <= u0 or v1 <= v0:
                continue
            if img.shape[:2] != (v1 - v0, u1 - u0):
                raise ValueError(
                    f"face {fc.name}: image is {img.shape[1]}x{img.shape[0]}, expected {u1 - u0}x{v1 - v0}"
                )
            out[fc.atlas_row + v0 : fc.atlas_row + v1, u0:u1] = img
        return out

    def windows(self, points_cam: np.ndarray, margin: int) -> list[tuple[int, int, int, int]]:
        """Per face, the rectangle of its image that holds the images of ``points_cam``.

        Args:
            points_cam: (N, 3) points in the fisheye's optical frame [m].
            margin: Growth of each rectangle [face px] (>= 2 keeps the fisheye's bilinear samples
                of the points' images inside it).

        Returns:
            (u0, v0, u1, v1) per face [face px, end exclusive], clipped to the face; (0, 0, 0, 0)
            for a face that none of the points reach.
        """
        pts = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
        R, K, size = self._face_arrays
        p = np.matmul(pts[None], R)  # every face's optical frame, (faces, N, 3)
        z = p[..., 2]
        front = z > 1e-6
        z = np.where(front, z, 1.0)
        u = K[:, 0, None] * p[..., 0] / z + K[:, 1, None]
        v = K[:, 2, None] * p[..., 1] / z + K[:, 3, None]
        W, H = size[:, 0, None], size[:, 1, None]
        ins = front & (u > -margin) & (u < W - 1 + margin) & (v > -margin) & (v < H - 1 + margin)
        lo_u, hi_u = np.where(ins, u, np.inf).min(axis=1), np.where(ins, u, -np.inf).max(axis=1)
        lo_v, hi_v = np.where(ins, v, np.inf).min(axis=1), np.where(ins, v, -np.inf).max(axis=1)
        out = []
        for k, (w, h) in enumerate(size.tolist()):
            if not ins[k].any():
                out.append((0, 0, 0, 0))
                continue
            out.append(
                (
                    max(0, math.floor(lo_u[k]) - margin),
                    max(0, math.floor(lo_v[k]) - margin),
                    min(w, math.ceil(hi_u[k]) + margin + 1),
                    min(h, math.ceil(hi_v[k]) + margin + 1),
                )
            )
        return out

    @functools.cached_property
    def _face_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The faces' rotations (F, 3, 3), (fx, cx, fy, cy) (F, 4) and sizes (F, 2), stacked."""
        R = np.stack([fc.R_cam_face for fc in self.faces])
        K = np.array([[fc.K[0, 0], fc.K[0, 2], fc.K[1, 1], fc.K[1, 2]] for fc in self.faces])
        return R, K, np.array([fc.size for fc in self.faces])

    def remap(self, atlas: np.ndarray) -> np.ndarray:
        """The fisheye image from an atlas image, bilinear; 0 outside the field of view."""
        return cv2.remap(atlas, self._map1, self._map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def lookup(self, atlas: np.ndarray, outside) -> np.ndarray:
        """Labels or points in the fisheye image (nearest atlas pixel; ``outside`` beyond the view)."""
        flat = atlas.reshape((-1,) + atlas.shape[2:])
        out = flat[np.maximum(self._nearest, 0)]
        out[self._nearest < 0] = outside
        return out

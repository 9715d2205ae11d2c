"""Sun shadows cast by the rover, computed exactly from its convex visual shapes.

Every visual shape of the rover is convex (boxes, the wheel cylinder), so it is an intersection of
half-spaces n . x <= d. Along a sun ray x = o + u x_s + v y_s + w s (s toward the sun), each
half-space bounds w from above (faces toward the sun) or from below (faces away), and the shape's
sun-facing surface is w_front(u, v) = min over sun-facing planes. A shadow map of w_front over the
rover's sun-view footprint is therefore a handful of vectorised plane evaluations per shape, with
no rasterisation and no depth quantisation. A point is in shadow when a shape's sun-facing surface
lies above it along its sun ray.

TinyRenderer's own shadow pass cannot be used: it only scales the diffuse term by 0.8, its light
map is aimed at the world origin, and a sun-view depth render costs 60-150 ms per frame.

Only the rover casts shadows; terrain self-shadowing is not modelled (slopes facing away from the
sun are still darkened by the renderer's diffuse term).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pybullet as pb
from scipy.spatial import ConvexHull

_MIN_THICKNESS = 0.005  # [m] thinner shapes (surface markers) cast no shadow of their own


@dataclass(frozen=True)
class ConvexShape:
    """A convex shadow caster fixed to one link.

    Attributes:
        link: PyBullet link index (-1 for the base).
        normals: (P, 3) outward plane normals in the link frame.
        offsets: (P,) plane offsets: inside is normals @ x <= offsets [m].
        vertices: (V, 3) hull vertices in the link frame [m].
    """

    link: int
    normals: np.ndarray
    offsets: np.ndarray
    vertices: np.ndarray


def _obj_vertices(path: Path) -> np.ndarray:
    verts = []
    with open(path) as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(t) for t in line.split()[1:4]])
    if not verts:
        raise ValueError(f"{path}: no vertices in this OBJ mesh; shadows need a convex mesh")
    return np.asarray(verts)


def convex_shape(link: int, vertices: np.ndarray) -> ConvexShape:
    """Half-space form of the convex hull of ``vertices`` (link frame) [m]."""
    hull = ConvexHull(vertices)
    eq = hull.equations  # n . x + c <= 0 inside
    # Qhull triangulates facets: merge coplanar duplicates
    key = np.round(eq, 6)
    _, keep = np.unique(key, axis=0, return_index=True)
    eq = eq[np.sort(keep)]
    return ConvexShape(link, eq[:, :3].copy(), -eq[:, 3].copy(), vertices[hull.vertices].copy())


def body_shapes(client, body_id: int) -> list[ConvexShape]:
    """Convex casters of every visual shape of ``body_id`` (boxes, spheres, cylinders, meshes).

    Meshes are replaced by their convex hull. Shapes thinner than 5 mm (surface markers) are
    skipped: they lie on other shapes and add nothing to the shadow.
    """
    shapes = []
    for vs in client.getVisualShapeData(body_id):
        link, gtype, dims, fname, lpos, lorn = vs[1], vs[2], vs[3], vs[4], vs[5], vs[6]
        if gtype == pb.GEOM_BOX:
            h = np.asarray(dims) / 2
            corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
            verts = corners
        elif gtype == pb.GEOM_SPHERE:
            tt, pp = np.meshgrid(np.linspace(0, math.pi, 9), np.linspace(0, 2 * math.pi, 16, endpoint=False))
            verts = dims[0] * np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
            verts = np.unique(np.round(verts.reshape(-1, 3), 12), axis=0)
        elif gtype in (pb.GEOM_CYLINDER, pb.GEOM_CAPSULE):
            length, r = dims[0], dims[1]
            phi = np.linspace(0, 2 * math.pi, 32, endpoint=False)
            circle = np.stack([r * np.cos(phi), r * np.sin(phi)], 1)
            half = length / 2 + (r if gtype == pb.GEOM_CAPSULE else 0.0)
            verts = np.concatenate([np.c_[circle, np.full(32, z)] for z in (-half, half)])
        elif gtype == pb.GEOM_MESH:
            verts = _obj_vertices(Path(fname.decode() if isinstance(fname, bytes) else fname))
            verts = verts * np.asarray(dims)
        else:
            continue
        extent = verts.max(axis=0) - verts.min(axis=0)
        if extent.min() < _MIN_THICKNESS:
            continue
        R = np.array(pb.getMatrixFromQuaternion(lorn)).reshape(3, 3)
        shapes.append(convex_shape(link, verts @ R.T + np.asarray(lpos)))
    return shapes


def sun_frame(sun_direction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal (x_s, y_s, s): s toward the sun, x_s horizontal (read-only arrays)."""
    return _sun_frame(tuple(float(v) for v in np.ravel(sun_direction)))


@functools.lru_cache(maxsize=16)
def _sun_frame(sun_direction: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s = np.asarray(sun_direction, dtype=np.float64)
    s = s / np.linalg.norm(s)
    up = np.array([0.0, 0.0, 1.0]) if abs(s[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, s)
    x /= np.linalg.norm(x)
    out = (x, np.cross(s, x), s)
    for v in out:
        v.setflags(write=False)
    return out


@dataclass(frozen=True)
class _StackedShapes:
    """The planes and vertices of all shapes in flat arrays (link frames), for batched transforms."""

    links: tuple[int, ...]  # each shape's link
    normals: np.ndarray  # (planes, 3)
    offsets: np.ndarray  # (planes,)
    plane_shape: np.ndarray  # (planes,) index of the plane's shape
    vertices: np.ndarray  # (vertices, 3)
    vertex_shape: np.ndarray  # (vertices,)
    vertex_start: np.ndarray  # (shapes,) first vertex of each shape

    @classmethod
    def of(cls, shapes: list[ConvexShape]) -> _StackedShapes:
        if not shapes:
            raise ValueError("the body has no visual shape to cast a shadow")
        k = np.arange(len(shapes))
        counts = [len(sh.vertices) for sh in shapes]
        return cls(
            tuple(sh.link for sh in shapes),
            np.concatenate([sh.normals for sh in shapes]),
            np.concatenate([sh.offsets for sh in shapes]),
            np.repeat(k, [len(sh.normals) for sh in shapes]),
            np.concatenate([sh.vertices for sh in shapes]),
            np.repeat(k, counts),
            np.cumsum([0, *counts[:-1]]),
        )


class ShadowCaster:
    """Shadows of one multibody (the rover) on any surface, from its convex visual shapes.

    Args:
        client: The BulletClient holding the body.
        body_id: The casting body.
    """

    def __init__(self, client, body_id: int) -> None:
        self.client = client
        self.body_id = body_id
        self.shapes = body_shapes(client, body_id)
        self._links = sorted({s.link for s in self.shapes if s.link >= 0})
        self._stacked = _StackedShapes.of(self.shapes)
        self._last: tuple[tuple, tuple, float, ShadowMap] | None = None  # (poses, sun, texel, map)

    def _link_poses(self) -> tuple[tuple, dict[int, tuple[np.ndarray, np.ndarray]]]:
        """(PyBullet's raw poses, link -> (rotation, position) in the world) of every casting link."""
        c = self.client
        base = c.getBasePositionAndOrientation(self.body_id)
        states = c.getLinkStates(self.body_id, self._links) if self._links else []
        raw = (base, *((st[4], st[5]) for st in states))
        out = {}
        for link, (pos, quat) in zip((-1, *self._links), raw, strict=True):
            out[link] = (np.array(c.getMatrixFromQuaternion(quat)).reshape(3, 3), np.asarray(pos))
        return raw, out

    def mask(self, points_world: np.ndarray, sun_direction, texel: float) -> np.ndarray:
        """Whether the body blocks the sun at each world point (builds a map, then looks up).

        Args:
            points_world: (..., 3) surface points, world frame [m].
            sun_direction: Vector toward the sun, world frame.
            texel: Shadow-map cell size across the sun direction [m]; about the ground size of a
                camera pixel.

        Returns:
            (...) bool, True in shadow.
        """
        return self.shadow_map(sun_direction, texel).lookup(points_world)

    def shadow_map(self, sun_direction, texel: float) -> ShadowMap:
        """The body's sun-facing surface over its cross-section seen along the sun, now.

        Args:
            sun_direction: Vector toward the sun, world frame.
            texel: Cell size across the sun direction [m].
        """
        if not texel > 0:
            raise ValueError(f"texel: {texel!r} m must be > 0")
        key, poses = self._link_poses()
        # the cameras of one instant share a map: reuse the last one if nothing moved and its
        # cells are at least as fine
        sun = tuple(float(v) for v in sun_direction)
        last = self._last
        if last is not None and last[2] <= texel and last[0] == key and last[1] == sun:
            return last[3]
        xs, ys, s = sun_frame(sun)
        o = poses[-1][1]
        st = self._stacked
        R = np.stack([poses[link][0] for link in st.links])  # (shapes, 3, 3)
        t = np.stack([poses[link][1] for link in st.links]) - o
        # every plane and vertex in the world, about o: sun frame coordinates
        n = np.einsum("kij,kj->ki", R[st.plane_shape], st.normals)
        d = st.offsets + np.einsum("ki,ki->k", n, t[st.plane_shape])
        abc = n @ np.stack([xs, ys, s], 1)  # plane k: a u + b v + c w <= d
        uv = (np.einsum("kij,kj->ki", R[st.vertex_shape], st.vertices) + t[st.vertex_shape]) @ np.stack(
            [xs, ys], 1
        )
        # the map covers the body's cross-section seen along the sun: bounded by its size
        u0, v0 = uv.min(axis=0) - texel
        u1, v1 = uv.max(axis=0) + texel
        nu = int(math.ceil((u1 - u0) / texel))
        nv = int(math.ceil((v1 - v0) / texel))
        if nu * nv > 16_000_000:
            raise ValueError(f"texel: {texel:g} m makes a {nu}x{nv} shadow map; use a coarser texel")
        lo = np.minimum.reduceat(uv, st.vertex_start)
        hi = np.maximum.reduceat(uv, st.vertex_start)
        i0 = np.maximum(0, np.floor((lo[:, 0] - u0) / texel)).astype(int).tolist()
        i1 = np.minimum(nu, np.ceil((hi[:, 0] - u0) / texel) + 1).astype(int).tolist()
        j0 = np.maximum(0, np.floor((lo[:, 1] - v0) / texel)).astype(int).tolist()
        j1 = np.minimum(nv, np.ceil((hi[:, 1] - v0) / texel) + 1).astype(int).tolist()
        U = (u0 + (np.arange(nu) + 0.5) * texel).astype(np.float32)  # cell centres
        V = (v0 + (np.arange(nv) + 0.5) * texel).astype(np.float32)[:, None]
        # planes facing the sun bound w from above (w <= p - q u - r v), those facing away from
        # below; planes along the sun bound (u, v) (d - a u - b v >= 0). The shape's sun-facing
        # surface is the lowest upper bound, where it lies above every lower bound.
        a, b, c = abc.T
        kind = np.where(c > 1e-9, 0, np.where(c < -1e-9, 1, 2))
        order = np.lexsort((kind, st.plane_shape))
        a, b, c, d, kind = a[order], b[order], c[order], d[order], kind[order]
        along = kind == 2
        c = np.where(along, 1.0, c)
        p, q, r = (x.astype(np.float32)[:, None, None] for x in (d / c, a / c, b / c))
        bounds = np.searchsorted(st.plane_shape[order] * 3 + kind, np.arange(3 * len(st.links) + 1)).tolist()
        front = np.full((nv, nu), -np.inf, dtype=np.float32)
        for k in range(len(st.links)):
            if i1[k] <= i0[k] or j1[k] <= j0[k]:
                continue
            Uk, Vk = U[i0[k] : i1[k]], V[j0[k] : j1[k]]
            up, down, side = (slice(bounds[3 * k + m], bounds[3 * k + m + 1]) for m in range(3))
            w_hi = (p[up] - r[up] * Vk - q[up] * Uk).min(axis=0)
            inside = np.ones(w_hi.shape, dtype=bool)
            if down.stop > down.start:
                inside &= (p[down] - r[down] * Vk - q[down] * Uk).max(axis=0) <= w_hi
            if side.stop > side.start:
                inside &= (p[side] - r[side] * Vk - q[side] * Uk).min(axis=0) >= 0
            crop = front[j0[k] : j1[k], i0[k] : i1[k]]
            np.maximum(crop, np.where(inside, w_hi, -np.inf), out=crop)
        # world point -> (map column, map row, height toward the sun); cell centres at integers
        M = np.zeros((3, 4))
        M[0, :3], M[1, :3], M[2, :3] = xs / texel, ys / texel, s
        M[:, 3] = -(M[:, :3] @ o)
        M[0, 3] -= u0 / texel + 0.5
        M[1, 3] -= v0 / texel + 0.5
        # bias: the map is sampled at cell centres, so a receiver on a sloped sun-facing surface
        # may sit up to half a cell's slope below its own cell value
        cos_elev = math.sqrt(max(0.0, 1.0 - s[2] ** 2))
        bias = 0.002 + texel * cos_elev / max(1e-3, abs(s[2]))
        out = ShadowMap(front=front, M=M, bias=bias)
        self._last = (key, sun, texel, out)
        return out


@dataclass(frozen=True)
class ShadowMap:
    """A body's sun-facing surface sampled across the sun direction.

    Attributes:
        front: (rows, cols) float32 height toward the sun of the body's sun-facing surface
            (-inf where the body is absent) [m].
        M: (3, 4) world point -> (column, row, height toward the sun).
        bias: Height margin of the shadow test [m].
    """

    front: np.ndarray
    M: np.ndarray
    bias: float

    def lookup_view(self, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
        """:meth:`lookup` of the surface points of a pinhole view, from its depth image.

        Args:
            depth: (H, W) float32 distance along the optical axis [m].
            K: The view's intrinsics [px].
            T_world_cam: Pose of the view's optical frame in the world [m].

        Returns:
            (H, W) bool, True where the body lies sunward of the pixel's surface point.
        """
        h, w = depth.shape
        # a pixel's point is t + depth R K^-1 (x, y, 1): its map coordinates are affine in it
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        K_inv = np.array([[1 / fx, 0.0, -cx / fx], [0.0, 1 / fy, -cy / fy], [0.0, 0.0, 1.0]])
        A = self.M[:, :3] @ T_world_cam[:3, :3] @ K_inv
        b = self.M[:, :3] @ T_world_cam[:3, 3] + self.M[:, 3]
        b[2] += self.bias
        xs, ys = np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32)[:, None]
        uvw = [
            (np.float32(a[0]) * xs + (np.float32(a[1]) * ys + np.float32(a[2]))) * depth + np.float32(c)
            for a, c in zip(A, b, strict=True)
        ]
        caster_w = cv2.remap(self.front, uvw[0], uvw[1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=-np.inf)  # fmt: skip
        return caster_w > uvw[2]

    def lookup(self, points_world: np.ndarray) -> np.ndarray:
        """(...) bool: True where the body lies sunward of the points (..., 3) [m]."""
        pts = np.asarray(points_world, dtype=np.float32)
        if pts.shape[-1] != 3:
            raise ValueError(f"points_world: shape {pts.shape}; expected (..., 3)")
        out_shape = pts.shape[:-1]
        if pts.size == 0:
            return np.zeros(out_shape, dtype=bool)
        if pts.ndim == 3 and pts.shape[0] < 32767 and pts.shape[1] < 32767:
            grid = pts
        else:  # cv2.remap takes images under 32767 rows: lay the points out in rows
            flat = pts.reshape(-1, 3)
            cols = 1024
            grid = np.concatenate([flat, np.zeros((-len(flat) % cols, 3), np.float32)]).reshape(-1, cols, 3)
        uv = cv2.transform(grid, self.M[:2])
        # cv2's stubs do not allow map2=None (one two-channel map), which remap takes
        caster_w = cv2.remap(  # type: ignore[call-overload]
            self.front, uv, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=-np.inf
        )
        M = self.M[2].astype(np.float32)
        hit = caster_w > grid @ M[:3] + np.float32(M[3] + self.bias)
        return hit.reshape(-1)[: math.prod(out_shape)].reshape(out_shape)

"""Terrain: ground shape (plane or heightfield), its textured visual mesh, and the friction map.

World frame: z up, the terrain centred on the origin. Heights are exact: for the plane the
analytic plane, for the heightfield the same triangles Bullet collides with.

Rough terrain is drawn at two levels of detail, because TinyRenderer transforms every triangle of
the scene for every view it renders (a 30 m x 30 m heightfield at 0.1 m is 180,000 triangles,
about 30 ms per view whatever the view's size). Near the rover (:meth:`Terrain.focus`) the ground
is drawn with the collision triangles themselves, in 1 m chunks that are added and removed as the
rover moves; everywhere else a 1 m mesh lies just below them, so that it never shows through
the exact ground.
"""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rover_env.config.cameras import FINE_RADIUS
from rover_env.config.scenario import TEXTURE_PRESETS, FrictionMapConfig, TerrainConfig
from rover_env.sim.textures import cache_dir, periodic_noise, read_texture, texture_file

if TYPE_CHECKING:
    from pybullet_utils.bullet_client import BulletClient

log = logging.getLogger(__name__)

FINE_CHUNK = 1.0  # [m] edge of a near-ground chunk
COARSE_CELL = 1.0  # [m] grid of the far ground


class FrictionMap:
    """Friction coefficient over the world x-y plane: a default and overriding patches.

    Patch edges are sharp; where patches overlap the later one wins.
    """

    def __init__(self, cfg: FrictionMapConfig) -> None:
        self.cfg = cfg
        self._patches = []
        for p in cfg.patches:
            yaw = math.radians(p.yaw_deg)
            self._patches.append(
                (
                    p.shape == "circle",
                    p.center[0],
                    p.center[1],
                    math.cos(yaw),
                    math.sin(yaw),
                    p.size[0] / 2,
                    p.size[1] / 2,
                    p.radius * p.radius,
                    p.mu,
                    p.slip_loss,
                )
            )
        #: Whether any patch is loose soil (grip lost to slip, :class:`FrictionMapConfig`).
        self.loose = any(p.slip_loss > 0 for p in cfg.patches)

    def mu_at(self, x: float, y: float) -> float:
        """Friction coefficient at world point (x, y) [m] (scalar fast path)."""
        return self.mu_loss_at(x, y)[0]

    def mu_loss_at(self, x: float, y: float) -> tuple[float, float]:
        """(friction coefficient, loose soil's ``slip_loss``) at world point (x, y) [m]."""
        mu, loss = self.cfg.default_mu, 0.0
        for circle, cx, cy, c, s, hx, hy, r2, pmu, ploss in self._patches:
            dx, dy = x - cx, y - cy
            if circle:
                if dx * dx + dy * dy <= r2:
                    mu, loss = pmu, ploss
            elif abs(c * dx + s * dy) <= hx and abs(-s * dx + c * dy) <= hy:
                mu, loss = pmu, ploss
        return mu, loss

    def dig(self, slip_ratio: np.ndarray, slip_speed: np.ndarray) -> np.ndarray:
        """How far each wheel has dug in (0-1) at slip ratios and slip speeds [m/s] (see the config)."""
        c = self.cfg
        by_slip = np.clip((np.abs(slip_ratio) - c.critical_slip) / (1.0 - c.critical_slip), 0.0, 1.0)
        return by_slip * np.clip(np.abs(slip_speed) / c.dig_speed, 0.0, 1.0)

    def mu_grid(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`mu_at` over arrays of equal shape [m]."""
        mu = np.full(np.broadcast(x, y).shape, self.cfg.default_mu, dtype=np.float64)
        for circle, cx, cy, c, s, hx, hy, r2, pmu, _ in self._patches:
            dx, dy = x - cx, y - cy
            if circle:
                inside = dx * dx + dy * dy <= r2
            else:
                inside = (np.abs(c * dx + s * dy) <= hx) & (np.abs(-s * dx + c * dy) <= hy)
            mu[inside] = pmu
        return mu


def make_heights(cfg: TerrainConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid coordinates and heights of the terrain.

    Returns:
        ``(xs, ys, heights)`` with xs (nx,), ys (ny,) [m] and heights (ny, nx) [m]
        (row j is y = ys[j]). Includes the slope plane; the random relief has RMS
        ``cfg.roughness`` and periods between ``wavelength / 2`` and ``4 * wavelength``.
    """
    nx = int(round(cfg.size[0] / cfg.cell)) + 1
    ny = int(round(cfg.size[1] / cfg.cell)) + 1
    xs = (np.arange(nx) - (nx - 1) / 2) * cfg.cell
    ys = (np.arange(ny) - (ny - 1) / 2) * cfg.cell
    gx, gy = np.meshgrid(xs, ys)
    h = _slope_height(cfg, gx, gy)
    if cfg.roughness > 0:
        n = int(2 ** math.ceil(math.log2(max(nx, ny))))
        rng = np.random.default_rng(cfg.seed)
        noise = periodic_noise(
            n,
            rng,
            beta=2.0,
            min_period_px=cfg.wavelength / 2 / cfg.cell,
            max_period_px=4 * cfg.wavelength / cfg.cell,
        )[:ny, :nx]
        noise = (noise - noise.mean()) / noise.std()
        h = h + cfg.roughness * noise
    return xs, ys, h


def _slope_height(cfg: TerrainConfig, x, y):
    t = math.tan(cfg.slope)
    return t * (math.cos(cfg.slope_azimuth) * x + math.sin(cfg.slope_azimuth) * y)


class Terrain:
    """The ground body in one PyBullet client: collision shape, textured visual, friction map.

    Args:
        client: The environment's own BulletClient.
        cfg: Terrain shape and texture.
        friction: Friction map configuration.
    """

    def __init__(self, client: BulletClient, cfg: TerrainConfig, friction: FrictionMapConfig):
        import pybullet as pb

        self.cfg = cfg
        self.friction = FrictionMap(friction)
        self._client = client
        self._chunks: dict[tuple[int, int], int] = {}  # chunk (i, j) -> its visual body
        self._chunk_shapes: dict[tuple[int, int], int] = {}  # chunk (i, j) -> its visual shape
        self._shown: dict[int, bool] = {}  # body -> drawn (alpha 1) or hidden (alpha 0)
        # bodies of the rough-ground chunks that the last focus() draws, and their (n, 8, 3) world
        # bounding-box corners
        self._focused: tuple[list[int], np.ndarray] = ([], np.zeros((0, 8, 3)))
        self._focus_key: tuple | None = None  # (x, y, near) of the last focus()
        self._boxes: dict[tuple[int, int], np.ndarray] = {}  # chunk -> (8, 3) world bounding-box corners
        if cfg.kind == "rough":
            self.xs, self.ys, self.heights = make_heights(cfg)
            gz = np.gradient(self.heights, self.ys, self.xs)
            nrm = np.stack([-gz[1], -gz[0], np.ones_like(self.heights)], axis=-1)
            self._normals = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
            nx, ny = len(self.xs), len(self.ys)
            hmin, hmax = float(self.heights.min()), float(self.heights.max())
            shape = client.createCollisionShape(
                pb.GEOM_HEIGHTFIELD,
                meshScale=[cfg.cell, cfg.cell, 1.0],
                heightfieldData=self.heights.ravel().tolist(),
                numHeightfieldRows=nx,
                numHeightfieldColumns=ny,
            )
            # Bullet centres a heightfield on its mid-height; shift it back to true heights.
            base_z = 0.5 * (hmin + hmax)
        else:
            self.xs = self.ys = self.heights = None
            t = math.tan(cfg.slope)
            n = np.array([-t * math.cos(cfg.slope_azimuth), -t * math.sin(cfg.slope_azimuth), 1.0])
            n /= np.linalg.norm(n)
            self._plane_normal = n
            shape = client.createCollisionShape(pb.GEOM_PLANE, planeNormal=n.tolist())
            base_z = 0.0
        if self.heights is None:
            visual = client.createVisualShape(pb.GEOM_MESH, fileName=str(self._visual_mesh()))
        else:
            visual = self._mesh_shape(*self._coarse_grid(), base_z)
        self.body_id = client.createMultiBody(0, shape, visual, basePosition=[0, 0, base_z])
        self._base_z = base_z
        client.changeDynamics(
            self.body_id, -1, lateralFriction=1.0, restitution=0.0, rollingFriction=0.0, spinningFriction=0.0
        )
        tex_path = (
            texture_file(cfg.texture, cfg.texture_px, cfg.seed)
            if cfg.texture in TEXTURE_PRESETS
            else Path(cfg.texture)
        )
        read_texture(tex_path)  # a clear error for a file that is not an image
        #: The ground texture's image file.
        self.texture_path = Path(tex_path)
        self.texture_id = client.loadTexture(str(tex_path))
        if self.texture_id < 0:
            raise ValueError(f"terrain.texture: PyBullet could not load image {tex_path}")
        client.changeVisualShape(
            self.body_id, -1, textureUniqueId=self.texture_id, rgbaColor=[1, 1, 1, 1], specularColor=[0, 0, 0]
        )

    # ------------------------------------------------------------------ level of detail
    @property
    def ground_ids(self) -> tuple[int, ...]:
        """Body ids that draw the ground (segmentation labels of ground pixels)."""
        return (self.body_id, *self._chunks.values())

    def focus(self, x: float, y: float, near: float | None = None) -> None:
        """Draw the ground for views taken from near world (x, y) [m]; call before rendering them.

        On rough terrain the exact triangles are drawn within ``FINE_RADIUS`` of (x, y) and a
        coarser mesh beyond. With ``near`` [m] (at most ``FINE_RADIUS``), only the exact chunks that
        reach within ``near`` of (x, y) are drawn (ground beyond ``near`` + a chunk's diagonal
        never is), for views that need no farther ground: TinyRenderer walks every triangle whose
        projection overlaps a view, so far ground costs time even where nearer surfaces hide it.
        ``None``: the views may see the horizon; all is drawn.
        """
        if near is not None and not 0.0 < near <= FINE_RADIUS:
            raise ValueError(f"near: {near!r} m; use 0 < near <= FINE_RADIUS ({FINE_RADIUS} m) or None")
        if (x, y, near) == self._focus_key:  # the same views' place: undo only their culling
            for body in self._focused[0]:
                self._show(body, True)
            return
        self._focus_key = (x, y, near)
        flat = self.heights is None
        if flat and near is None:  # the far body alone draws flat ground exactly
            self._show(self.body_id, True)
            for body in self._chunks.values():
                self._show(body, False)
            return
        x0, y0, cell, nx, ny, n = self._chunk_grid
        size = n * cell
        keep = FINE_RADIUS if not flat else near
        i_lo = max(0, int((x - keep - x0) // size))
        i_hi = min((nx - 1) // n, int((x + keep - x0) // size))
        j_lo = max(0, int((y - keep - y0) // size))
        j_hi = min((ny - 1) // n, int((y + keep - y0) // size))
        dist = {}
        for i in range(i_lo, i_hi + 1):
            for j in range(j_lo, j_hi + 1):
                d = self._chunk_distance((i, j), x, y)
                if d <= keep:
                    dist[(i, j)] = d
        c = self._client
        # flat chunks outside ``near`` stay (hidden) until they are beyond FINE_RADIUS
        gone = [
            k
            for k in self._chunks
            if k not in dist and (not flat or self._chunk_distance(k, x, y) > FINE_RADIUS)
        ]
        for key in gone:
            body = self._chunks.pop(key)
            self._shown.pop(body, None)
            c.removeBody(body)
        for key in sorted(dist.keys() - self._chunks.keys()):
            if key not in self._chunk_shapes:
                self._chunk_shapes[key] = self._chunk_shape(key)
            body = c.createMultiBody(0, -1, self._chunk_shapes[key], basePosition=[0, 0, self._base_z])
            c.changeVisualShape(
                body, -1, textureUniqueId=self.texture_id, rgbaColor=[1, 1, 1, 1], specularColor=[0, 0, 0]
            )
            self._shown[body] = True
            self._chunks[key] = body
        self._show(self.body_id, near is None)
        focused = [k for k in self._chunks if near is None or dist.get(k, math.inf) <= near]
        for key, body in self._chunks.items():
            self._show(body, key in focused)
        self._focused = ([], np.zeros((0, 8, 3)))
        if not flat and focused:
            for key in focused:
                if key not in self._boxes:
                    self._boxes[key] = self._chunk_box(key)
            self._focused = ([self._chunks[k] for k in focused], np.array([self._boxes[k] for k in focused]))

    @property
    def view_cull(self):
        """:meth:`cull` where it has work (rough ground), else None: flat chunks are two triangles each."""
        return self.cull if self.heights is not None else None

    def cull(self, planes: np.ndarray) -> None:
        """Of the chunks that :meth:`focus` draws, draw only those that may be inside a view.

        TinyRenderer transforms every drawn triangle for every view, so on rough ground each view
        draws only the chunks whose bounding box is not wholly outside one of its planes. Call it
        after :meth:`focus`, before each view (flat ground has two triangles a chunk: no-op).

        Args:
            planes: (k, 4) half-spaces n . x + d >= 0 (world frame [m]) whose intersection holds
                the view (:func:`rover_env.rendering.base.view_planes`).
        """
        bodies, boxes = self._focused
        if self.heights is None or not bodies:
            return
        inside = boxes @ planes[:, :3].T + planes[:, 3] >= 0.0  # (chunks, 8 corners, k planes)
        for body, on in zip(bodies, inside.any(axis=1).all(axis=1).tolist(), strict=True):
            self._show(body, on)

    def _chunk_slices(self, key: tuple[int, int]) -> tuple[slice, slice]:
        """Grid-point slices (along x, along y) of rough-ground chunk ``key``."""
        i, j = key
        _, _, _, nx, ny, n = self._chunk_grid
        return slice(i * n, min((i + 1) * n, nx) + 1), slice(j * n, min((j + 1) * n, ny) + 1)

    def _chunk_box(self, key: tuple[int, int]) -> np.ndarray:
        """(8, 3) corners of chunk ``key``'s axis-aligned bounding box in the world [m]."""
        sx, sy = self._chunk_slices(key)
        h = self.heights[sy, sx]
        xs, ys = self.xs[sx], self.ys[sy]
        return np.array(
            [[x, y, z] for x in (xs[0], xs[-1]) for y in (ys[0], ys[-1]) for z in (h.min(), h.max())]
        )

    @functools.cached_property
    def _chunk_grid(self) -> tuple[float, float, float, int, int, int]:
        """(x0, y0, cell, cells along x, cells along y, cells per chunk edge) of the chunks' grid."""
        if self.heights is not None:
            cell, nx, ny = self.cfg.cell, len(self.xs) - 1, len(self.ys) - 1
            x0, y0 = float(self.xs[0]), float(self.ys[0])
        else:
            cell = FINE_CHUNK  # flat ground: one quad per chunk
            nx, ny = (max(1, int(math.ceil(s / cell))) for s in self.cfg.size)
            x0, y0 = -nx * cell / 2, -ny * cell / 2
        return x0, y0, cell, nx, ny, max(1, int(round(FINE_CHUNK / cell)))

    def _chunk_distance(self, key: tuple[int, int], x: float, y: float) -> float:
        """Distance from world (x, y) to chunk ``key``'s rectangle [m] (0 inside it)."""
        x0, y0, cell, _, _, n = self._chunk_grid
        size = n * cell
        i, j = key
        dx = max(x0 + i * size - x, 0.0, x - x0 - (i + 1) * size)
        dy = max(y0 + j * size - y, 0.0, y - y0 - (j + 1) * size)
        return math.hypot(dx, dy)

    def _chunk_shape(self, key: tuple[int, int]) -> int:
        """The visual shape of chunk ``key``."""
        i, j = key
        x0, y0, cell, nx, ny, n = self._chunk_grid
        if self.heights is not None:
            sx, sy = self._chunk_slices(key)
            return self._mesh_shape(
                self.xs[sx], self.ys[sy], self.heights[sy, sx], self._normals[sy, sx], self._base_z
            )
        xs = x0 + cell * np.array([i, i + 1], dtype=np.float64)
        ys = y0 + cell * np.array([j, j + 1], dtype=np.float64)
        gx, gy = np.meshgrid(xs, ys)
        h = _slope_height(self.cfg, gx, gy)
        return self._mesh_shape(xs, ys, h, np.broadcast_to(self._plane_normal, h.shape + (3,)), self._base_z)

    def _show(self, body: int, on: bool) -> None:
        if self._shown.get(body, True) != on:
            self._client.changeVisualShape(body, -1, rgbaColor=[1, 1, 1, 1.0 if on else 0.0])
            self._shown[body] = on

    def drop_detail(self) -> None:
        """Remove the near-ground chunks (before restoring a state saved without them)."""
        for body in self._chunks.values():
            self._client.removeBody(body)
        self._chunks.clear()
        self._focused = ([], np.zeros((0, 8, 3)))
        self._focus_key = None
        self._shown = {b: v for b, v in self._shown.items() if b == self.body_id}
        self._show(self.body_id, True)

    def _coarse_grid(self):
        """The far-ground grid, about ``COARSE_CELL`` apart, as (xs, ys, heights, normals).

        The grid's triangles follow the exact ones' split, so their edges run along exact edges
        and the exact surface is lowest against them at exact vertices; each coarse cell is
        lowered by the most that its two triangles stand above those vertices (plus 2 mm), so
        the mesh stays below the exact ground everywhere (on the rough missions by 1-4 cm at the
        median: a low step at ``FINE_RADIUS`` that only distant views show).
        """
        h = self.heights
        step = max(1, int(round(COARSE_CELL / self.cfg.cell)))
        ix = np.unique(np.r_[np.arange(0, len(self.xs), step), len(self.xs) - 1])
        iy = np.unique(np.r_[np.arange(0, len(self.ys), step), len(self.ys) - 1])
        hc = h[np.ix_(iy, ix)]
        drop = np.zeros_like(hc)
        for cj in range(len(iy) - 1):
            for ci in range(len(ix) - 1):
                block = h[iy[cj] : iy[cj + 1] + 1, ix[ci] : ix[ci + 1] + 1]
                v = np.linspace(0.0, 1.0, block.shape[0])[:, None]
                u = np.linspace(0.0, 1.0, block.shape[1])[None, :]
                h00, h10, h01, h11 = hc[cj, ci], hc[cj, ci + 1], hc[cj + 1, ci], hc[cj + 1, ci + 1]
                low = h00 + u * (h10 - h00) + v * (h01 - h00)
                high = h11 + (1 - u) * (h01 - h11) + (1 - v) * (h10 - h11)
                above = float(np.max(np.where(u + v <= 1.0, low, high) - block))
                drop[cj : cj + 2, ci : ci + 2] = np.maximum(drop[cj : cj + 2, ci : ci + 2], above)
        return self.xs[ix], self.ys[iy], hc - drop - 0.002, self._normals[np.ix_(iy, ix)]

    def _mesh_shape(self, xs, ys, h, normals, base_z: float) -> int:
        """A visual shape of the height grid ``h`` (rows along y) in the body frame at ``base_z``."""
        import pybullet as pb

        gx, gy = np.meshgrid(xs, ys)
        verts = np.stack([gx.ravel(), gy.ravel(), h.ravel() - base_z], 1)
        tile = self.cfg.texture_tile
        uvs = np.stack([gx.ravel() / tile, gy.ravel() / tile], 1)
        ny, nx = h.shape
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # Bullet's heightfield split, as in write_grid_obj
        faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
        return self._client.createVisualShape(
            pb.GEOM_MESH,
            vertices=verts.tolist(),
            indices=faces.ravel().tolist(),
            uvs=uvs.tolist(),
            normals=normals.reshape(-1, 3).tolist(),
        )

    def render_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The ground's exact visual surface as a height grid: (xs, ys, heights, normals).

        xs (nx,) and ys (ny,) [m], heights (ny, nx) [m] world z, normals (ny, nx, 3) unit; split
        into triangles as Bullet splits its heightfield. Rough ground: the collision grid itself;
        planar ground: a 2 m grid over the terrain (exact, since the plane is flat).
        """
        if self.heights is not None:
            return self.xs, self.ys, self.heights, self._normals
        nx = max(1, int(math.ceil(self.cfg.size[0] / (2 * FINE_CHUNK)))) + 1
        ny = max(1, int(math.ceil(self.cfg.size[1] / (2 * FINE_CHUNK)))) + 1
        xs = np.linspace(-self.cfg.size[0] / 2, self.cfg.size[0] / 2, nx)
        ys = np.linspace(-self.cfg.size[1] / 2, self.cfg.size[1] / 2, ny)
        gx, gy = np.meshgrid(xs, ys)
        h = _slope_height(self.cfg, gx, gy)
        return xs, ys, h, np.broadcast_to(self._plane_normal, h.shape + (3,)).copy()

    # ------------------------------------------------------------------ geometry queries
    def height_at(self, x: float | np.ndarray, y: float | np.ndarray) -> np.ndarray:
        """Ground height z at world (x, y) [m], exact on Bullet's triangles."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.heights is None:
            return _slope_height(self.cfg, x, y)
        cell = self.cfg.cell
        fx = np.clip((x - self.xs[0]) / cell, 0, len(self.xs) - 1 - 1e-9)
        fy = np.clip((y - self.ys[0]) / cell, 0, len(self.ys) - 1 - 1e-9)
        i, j = np.floor(fx).astype(int), np.floor(fy).astype(int)
        u, v = fx - i, fy - j
        h = self.heights
        h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
        # Bullet splits each cell along the (i+1, j)-(i, j+1) diagonal.
        z_low = h00 + u * (h10 - h00) + v * (h01 - h00)
        z_high = h11 + (1 - u) * (h01 - h11) + (1 - v) * (h10 - h11)
        return np.where(u + v <= 1.0, z_low, z_high)

    def contains(self, x: float, y: float, margin: float = 0.5) -> bool:
        """True if (x, y) lies on the terrain at least ``margin`` m from its edge."""
        return abs(x) <= self.cfg.size[0] / 2 - margin and abs(y) <= self.cfg.size[1] / 2 - margin

    # ------------------------------------------------------------------ visual mesh
    def _visual_mesh(self) -> Path:
        """Write (once, cached) the textured OBJ mesh of the flat ground and return its path."""
        cfg = self.cfg
        key = f"terrain-v2:{cfg!r}"
        import hashlib

        path = cache_dir() / f"terrain_{hashlib.sha1(key.encode()).hexdigest()[:16]}.obj"
        if path.is_file():
            return path
        step = min(cfg.texture_tile, 2.0)
        nx = int(math.ceil(cfg.size[0] / step)) + 1
        ny = int(math.ceil(cfg.size[1] / step)) + 1
        xs = np.linspace(-cfg.size[0] / 2, cfg.size[0] / 2, nx)
        ys = np.linspace(-cfg.size[1] / 2, cfg.size[1] / 2, ny)
        gx, gy = np.meshgrid(xs, ys)
        h = _slope_height(cfg, gx, gy)
        write_grid_obj(path, xs, ys, h, cfg.texture_tile)
        log.debug("wrote terrain mesh %s (%d x %d vertices)", path, len(xs), len(ys))
        return path


def write_grid_obj(path: Path, xs: np.ndarray, ys: np.ndarray, h: np.ndarray, tile: float) -> None:
    """Write a height grid as an OBJ triangle mesh with normals and tiling UVs (u = x / tile).

    Triangles follow Bullet's heightfield split, so the visual matches the collision surface.
    """
    import os
    import tempfile

    gx, gy = np.meshgrid(xs, ys)
    gz = np.gradient(h, ys, xs)
    nrm = np.stack([-gz[1], -gz[0], np.ones_like(h)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    ny, nx = h.shape
    idx = np.arange(nx * ny).reshape(ny, nx) + 1
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    lines = ["# rover_env terrain mesh"]
    v = np.stack([gx.ravel(), gy.ravel(), h.ravel()], 1)
    lines += [f"v {p[0]:.4f} {p[1]:.4f} {p[2]:.5f}" for p in v]
    lines += [f"vt {p[0] / tile:.5f} {p[1] / tile:.5f}" for p in v]
    lines += [f"vn {n[0]:.4f} {n[1]:.4f} {n[2]:.4f}" for n in nrm.reshape(-1, 3)]
    lines += [f"f {i}/{i}/{i} {j}/{j}/{j} {k}/{k}/{k}" for i, j, k in faces]
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".obj")
    with os.fdopen(fd, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    os.replace(tmp, path)

"""Terrain: ground shape (plane or heightfield), its textured visual mesh, and the friction map.

World frame: z up, the terrain centred on the origin. Heights are exact: for the plane the
analytic plane, for the heightfield the same triangles Bullet collides with.

The rough ground's body is drawn with a 1 m mesh lying just below the collision triangles
(:meth:`Terrain.coarse_grid`), so that it never shows through the exact ground that a renderer
draws near the rover (:mod:`rover_env.rendering.ground_detail`, :mod:`rover_env.rendering.gl`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

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
        self.loose = any(p.slip_loss > 0 and p.soil is None for p in cfg.patches)
        #: The deformable soils of the patches (:mod:`rover_env.sim.terramechanics`), each once.
        self.soils: list = []
        self._soil_of: list[int] = []
        for p in cfg.patches:
            if p.soil is None:
                self._soil_of.append(-1)
                continue
            if p.soil not in self.soils:
                self.soils.append(p.soil)
            self._soil_of.append(self.soils.index(p.soil))
        #: Factor on every friction coefficient of the map (domain randomisation; 1: as configured).
        self.scale = 1.0

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
        return mu * self.scale, loss

    def soil_at(self, x: float, y: float, grow: float = 0.0) -> int:
        """Index into :attr:`soils` of the deformable soil at world (x, y) [m]; -1: rigid ground.

        ``grow`` [m] widens every patch (a wheel already on soil leaves it only that far out).
        """
        soil = -1
        for k, (circle, cx, cy, c, s, hx, hy, r2, _, _) in enumerate(self._patches):
            dx, dy = x - cx, y - cy
            if circle:
                r = math.sqrt(r2) + grow
                if dx * dx + dy * dy <= r * r:
                    soil = self._soil_of[k]
            elif abs(c * dx + s * dy) <= hx + grow and abs(-s * dx + c * dy) <= hy + grow:
                soil = self._soil_of[k]
        return soil

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
        return mu * self.scale


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
    h = slope_height(cfg, gx, gy)
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


def slope_height(cfg: TerrainConfig, x, y):
    """Height of the terrain's slope plane at world (x, y) [m] (no relief)."""
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
        self._normals: dict[tuple, np.ndarray] = {}  # a plane's normal, by query shape
        self._client = client
        # the height grid (rough ground only): x and y samples [m], heights (rows along y) [m]
        self.xs: np.ndarray | None
        self.ys: np.ndarray | None
        self.heights: np.ndarray | None
        if cfg.kind == "rough":
            self.xs, self.ys, self.heights = make_heights(cfg)
            gz = np.gradient(self.heights, self.ys, self.xs)
            nrm = np.stack([-gz[1], -gz[0], np.ones_like(self.heights)], axis=-1)
            self.normals = nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)
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
            self.plane_normal = n
            shape = client.createCollisionShape(pb.GEOM_PLANE, planeNormal=n.tolist())
            base_z = 0.0
        if self.heights is None:
            visual = client.createVisualShape(pb.GEOM_MESH, fileName=str(self._visual_mesh()))
        else:
            visual = self.mesh_shape(*self.coarse_grid(), base_z)
        self.body_id = client.createMultiBody(0, shape, visual, basePosition=[0, 0, base_z])
        self.base_z = base_z
        client.changeDynamics(
            self.body_id, -1, lateralFriction=1.0, restitution=0.0, rollingFriction=0.0, spinningFriction=0.0
        )
        tex_path = (
            texture_file(cfg.texture, cfg.texture_px, cfg.seed)
            if cfg.texture in TEXTURE_PRESETS
            else Path(cfg.texture)
        )
        read_texture(tex_path)  # a clear error for a file that is not an image
        self._client = client
        self._texture_ids: dict[str, int] = {}
        #: The scenario's own ground texture (image file).
        self.base_texture = Path(tex_path)
        #: The ground's look now (:meth:`set_look`): texture file, albedo and contrast factors.
        self.texture_path = self.base_texture
        self.albedo = 1.0
        self.contrast = 1.0
        self.texture_id = self._load(self.texture_path)
        client.changeVisualShape(
            self.body_id, -1, textureUniqueId=self.texture_id, rgbaColor=[1, 1, 1, 1], specularColor=[0, 0, 0]
        )

    def _load(self, path: Path) -> int:
        """PyBullet's texture id of an image file (loaded once per client: PyBullet never frees one)."""
        key = str(path)
        if key not in self._texture_ids:
            tid = self._client.loadTexture(key)
            if tid < 0:
                raise ValueError(f"terrain.texture: PyBullet could not load image {path}")
            self._texture_ids[key] = tid
        return self._texture_ids[key]

    def set_look(self, texture: str | None = None, albedo: float = 1.0, contrast: float = 1.0) -> None:
        """Give the ground another look (domain randomisation); its shape and friction stay.

        Args:
            texture: A texture preset (:data:`TEXTURE_PRESETS`, made with this terrain's seed
                and size) or None: the scenario's own.
            albedo: Factor on the ground's reflectance [-].
            contrast: Factor on the texture's deviations from its mean colour [-] (1: as made).
                The GL renderer draws it; TinyRenderer draws the albedo (up to 1) and not this.
        """
        cfg = self.cfg
        if texture is None:
            path = self.base_texture
        elif texture in TEXTURE_PRESETS:
            path = texture_file(texture, cfg.texture_px, cfg.seed)
        else:
            raise ValueError(f"texture: {texture!r}; use one of {TEXTURE_PRESETS} or None")
        if (Path(path), float(albedo), float(contrast)) == (self.texture_path, self.albedo, self.contrast):
            return  # as it is (every reset without randomisation asks for the scenario's own)
        self.texture_path = Path(path)
        self.albedo, self.contrast = float(albedo), float(contrast)
        self.texture_id = self._load(self.texture_path)
        a = min(self.albedo, 1.0)
        self._client.changeVisualShape(
            self.body_id, -1, textureUniqueId=self.texture_id, rgbaColor=[a, a, a, 1], specularColor=[0, 0, 0]
        )

    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rough ground's collision grid: xs (nx,), ys (ny,) [m] and heights (ny, nx) [m] world z.

        Raises:
            ValueError: on planar ground, which has no height grid.
        """
        if self.xs is None or self.ys is None or self.heights is None:
            raise ValueError(f"{self.cfg.kind!r} ground has no height grid (only 'rough' ground has one)")
        return self.xs, self.ys, self.heights

    def coarse_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The far-ground grid, about ``COARSE_CELL`` apart, as (xs, ys, heights, normals).

        The grid's triangles follow the exact ones' split, so their edges run along exact edges
        and the exact surface is lowest against them at exact vertices; each coarse cell is
        lowered by the most that its two triangles stand above those vertices (plus 2 mm), so
        the mesh stays below the exact ground everywhere (on the rough missions by 1-4 cm at the
        median: a low step at ``FINE_RADIUS`` that only distant views show).
        """
        xs, ys, h = self.grid()
        step = max(1, int(round(COARSE_CELL / self.cfg.cell)))
        ix = np.unique(np.r_[np.arange(0, len(xs), step), len(xs) - 1])
        iy = np.unique(np.r_[np.arange(0, len(ys), step), len(ys) - 1])
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
        return xs[ix], ys[iy], hc - drop - 0.002, self.normals[np.ix_(iy, ix)]

    def mesh_shape(self, xs, ys, h, normals, base_z: float) -> int:
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
            return *self.grid(), self.normals
        nx = max(1, int(math.ceil(self.cfg.size[0] / (2 * FINE_CHUNK)))) + 1
        ny = max(1, int(math.ceil(self.cfg.size[1] / (2 * FINE_CHUNK)))) + 1
        xs = np.linspace(-self.cfg.size[0] / 2, self.cfg.size[0] / 2, nx)
        ys = np.linspace(-self.cfg.size[1] / 2, self.cfg.size[1] / 2, ny)
        gx, gy = np.meshgrid(xs, ys)
        h = slope_height(self.cfg, gx, gy)
        return xs, ys, h, np.broadcast_to(self.plane_normal, h.shape + (3,)).copy()

    # ------------------------------------------------------------------ geometry queries
    def height_at(self, x: float | np.ndarray, y: float | np.ndarray) -> np.ndarray:
        """Ground height z at world (x, y) [m], exact on Bullet's triangles."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.heights is None:
            return slope_height(self.cfg, x, y)
        cell = self.cfg.cell
        xs, ys, h = self.grid()
        fx = np.clip((x - xs[0]) / cell, 0, len(xs) - 1 - 1e-9)
        fy = np.clip((y - ys[0]) / cell, 0, len(ys) - 1 - 1e-9)
        i, j = np.floor(fx).astype(int), np.floor(fy).astype(int)
        u, v = fx - i, fy - j
        h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
        # Bullet splits each cell along the (i+1, j)-(i, j+1) diagonal.
        z_low = h00 + u * (h10 - h00) + v * (h01 - h00)
        z_high = h11 + (1 - u) * (h01 - h11) + (1 - v) * (h10 - h11)
        return np.where(u + v <= 1.0, z_low, z_high)

    def normal_at(self, x: float | np.ndarray, y: float | np.ndarray, step: float = 0.01) -> np.ndarray:
        """Unit normal of the ground at world (x, y) [m] (central differences over ``step`` m), (..., 3)."""
        if self.heights is None:
            shape = np.broadcast(x, y).shape
            cached = self._normals.get(shape)
            if cached is None:
                cached = self._normals[shape] = np.tile(self.plane_normal, (int(np.prod(shape)), 1)).reshape(
                    shape + (3,)
                )
                cached.flags.writeable = False
            return cached
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        gx = (self.height_at(x + step, y) - self.height_at(x - step, y)) / (2 * step)
        gy = (self.height_at(x, y + step) - self.height_at(x, y - step)) / (2 * step)
        n = np.stack([-gx, -gy, np.ones_like(gx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

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
        h = slope_height(cfg, gx, gy)
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

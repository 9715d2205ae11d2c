"""The exact ground near the rover, for TinyRenderer: chunks of the collision triangles.

TinyRenderer transforms every triangle of the scene for every view it renders (a 30 m x 30 m
heightfield at 0.1 m is 180,000 triangles, about 30 ms per view whatever the view's size). So the
terrain's own body draws rough ground with a 1 m mesh lying just below the exact surface
(:meth:`rover_env.sim.terrain.Terrain.coarse_grid`), and near the rover (:meth:`GroundDetail.focus`)
the ground is drawn with the collision triangles themselves, in 1 m chunks that are added and
removed as the rover moves. The chunks are visual bodies only (no collision shape): they never
touch the physics, and :meth:`GroundDetail.drop_detail` removes them before a saved state is
restored.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from rover_env.config.cameras import FINE_RADIUS
from rover_env.sim.terrain import FINE_CHUNK, Terrain, slope_height


class GroundDetail:
    """The near-ground chunks of one terrain in one client.

    Args:
        client: The BulletClient the terrain is in.
        terrain: The ground.
    """

    def __init__(self, client, terrain: Terrain) -> None:
        self.client = client
        self.terrain = terrain
        self._chunks: dict[tuple[int, int], int] = {}  # chunk (i, j) -> its visual body
        self._chunk_shapes: dict[tuple[int, int], int] = {}  # chunk (i, j) -> its visual shape
        self._shown: dict[int, bool] = {}  # body -> drawn (alpha 1) or hidden (alpha 0)
        # bodies of the rough-ground chunks that the last focus() draws, and their (n, 8, 3) world
        # bounding-box corners
        self._focused: tuple[list[int], np.ndarray] = ([], np.zeros((0, 8, 3)))
        self._focus_key: tuple | None = None  # (x, y, near) of the last focus()
        self._boxes: dict[tuple[int, int], np.ndarray] = {}  # chunk -> (8, 3) world bounding-box corners

    @property
    def ground_ids(self) -> tuple[int, ...]:
        """Body ids that draw the ground (segmentation labels of ground pixels)."""
        t = self.terrain
        return (t.body_id, *self._chunks.values())

    def focus(self, x: float, y: float, near: float | None = None) -> None:
        """Draw the ground for views taken from near world (x, y) [m]; call before rendering them.

        On rough terrain the exact triangles are drawn within ``FINE_RADIUS`` of (x, y) and a
        coarser mesh beyond. With ``near`` [m] (at most ``FINE_RADIUS``), only the exact chunks that
        reach within ``near`` of (x, y) are drawn (ground beyond ``near`` + a chunk's diagonal
        never is), for views that need no farther ground: TinyRenderer walks every triangle whose
        projection overlaps a view, so far ground costs time even where nearer surfaces hide it.
        ``None``: the views may see the horizon; all is drawn.
        """
        t = self.terrain
        if near is not None and not 0.0 < near <= FINE_RADIUS:
            raise ValueError(f"near: {near!r} m; use 0 < near <= FINE_RADIUS ({FINE_RADIUS} m) or None")
        if (x, y, near) == self._focus_key:  # the same views' place: undo only their culling
            for body in self._focused[0]:
                self._show(body, True)
            return
        self._focus_key = (x, y, near)
        flat = t.heights is None
        if flat and near is None:  # the far body alone draws flat ground exactly
            self._show(t.body_id, True)
            for body in self._chunks.values():
                self._show(body, False)
            return
        x0, y0, cell, nx, ny, n = self._chunk_grid
        size = n * cell
        keep = FINE_RADIUS if not flat or near is None else near
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
        c = self.client
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
            body = c.createMultiBody(0, -1, self._chunk_shapes[key], basePosition=[0, 0, t.base_z])
            c.changeVisualShape(
                body, -1, textureUniqueId=t.texture_id, rgbaColor=self._tint(1.0), specularColor=[0, 0, 0]
            )
            self._shown[body] = True
            self._chunks[key] = body
        self._show(t.body_id, near is None)
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
        t = self.terrain
        return self.cull if t.heights is not None else None

    def cull(self, planes: np.ndarray) -> None:
        """Of the chunks that :meth:`focus` draws, draw only those that may be inside a view.

        TinyRenderer transforms every drawn triangle for every view, so on rough ground each view
        draws only the chunks whose bounding box is not wholly outside one of its planes. Call it
        after :meth:`focus`, before each view (flat ground has two triangles a chunk: no-op).

        Args:
            planes: (k, 4) half-spaces n . x + d >= 0 (world frame [m]) whose intersection holds
                the view (:func:`rover_env.rendering.base.view_planes`).
        """
        t = self.terrain
        bodies, boxes = self._focused
        if t.heights is None or not bodies:
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
        t = self.terrain
        sx, sy = self._chunk_slices(key)
        gx, gy, gh = t.grid()
        h = gh[sy, sx]
        xs, ys = gx[sx], gy[sy]
        return np.array(
            [[x, y, z] for x in (xs[0], xs[-1]) for y in (ys[0], ys[-1]) for z in (h.min(), h.max())]
        )

    @functools.cached_property
    def _chunk_grid(self) -> tuple[float, float, float, int, int, int]:
        """(x0, y0, cell, cells along x, cells along y, cells per chunk edge) of the chunks' grid."""
        t = self.terrain
        if t.heights is not None:
            xs, ys, _ = t.grid()
            cell, nx, ny = t.cfg.cell, len(xs) - 1, len(ys) - 1
            x0, y0 = float(xs[0]), float(ys[0])
        else:
            cell = FINE_CHUNK  # flat ground: one quad per chunk
            nx, ny = (max(1, int(math.ceil(s / cell))) for s in t.cfg.size)
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
        t = self.terrain
        i, j = key
        x0, y0, cell, nx, ny, n = self._chunk_grid
        if t.heights is not None:
            sx, sy = self._chunk_slices(key)
            gx, gy, gh = t.grid()
            return t.mesh_shape(gx[sx], gy[sy], gh[sy, sx], t.normals[sy, sx], t.base_z)
        xs = x0 + cell * np.array([i, i + 1], dtype=np.float64)
        ys = y0 + cell * np.array([j, j + 1], dtype=np.float64)
        gx, gy = np.meshgrid(xs, ys)
        h = slope_height(t.cfg, gx, gy)
        return t.mesh_shape(xs, ys, h, np.broadcast_to(t.plane_normal, h.shape + (3,)), t.base_z)

    def _tint(self, alpha: float) -> list[float]:
        """The ground's colour factor: its albedo (TinyRenderer caps it at 1) and ``alpha``."""
        a = min(float(getattr(self.terrain, "albedo", 1.0)), 1.0)
        return [a, a, a, alpha]

    def _show(self, body: int, on: bool) -> None:
        if self._shown.get(body, True) != on:
            self.client.changeVisualShape(body, -1, rgbaColor=self._tint(1.0 if on else 0.0))
            self._shown[body] = on

    def drop_detail(self) -> None:
        """Remove the near-ground chunks (before restoring a state saved without them)."""
        t = self.terrain
        for body in self._chunks.values():
            self.client.removeBody(body)
        self._chunks.clear()
        self._focused = ([], np.zeros((0, 8, 3)))
        self._focus_key = None
        self._shown = {b: v for b, v in self._shown.items() if b == t.body_id}
        self._show(t.body_id, True)

"""Ruts: what the wheels leave in the soil, kept in a window that travels with the rover.

A wheel that sinks ``z`` into the soil leaves, behind it, soil pressed to ``z`` (the rut's
surface rebounds above that, :func:`rover_env.sim.terramechanics.rut_surface`) and sheared by
the shear displacement at its exit. A later wheel on the same track meets both
(:func:`rover_env.sim.terramechanics.contact_forces`' ``prior`` and ``prior_shear``).

The map is a square grid of ``size`` metres at ``cell`` metres around the rover, four layers
(the largest sinkage [m], the shear's world x and y components [m], and the depth of the rut's
surface [m], shallower than the sinkage by the soil's rebound: what the cameras see). When the
rover comes within ``margin`` of its edge the window moves to centre on it, keeping what
overlaps: ruts further than about half the window behind are forgotten. Memory is fixed:
4 x (size/cell)^2 float32 (23 MB at the default 12 m and 1 cm).
"""

from __future__ import annotations

import math

import numpy as np

from rover_env.config.io import check_range
from rover_env.sim.terramechanics import _compiled

__all__ = ["RutMap"]


@_compiled
def _sample(grid, x0, y0, cell, px, py, out):  # pragma: no cover (compiled)
    n = grid.shape[1]
    for k in range(px.shape[0]):
        i = int(math.floor((px[k] - x0) / cell))
        j = int(math.floor((py[k] - y0) / cell))
        if 0 <= i < n and 0 <= j < n:
            out[k, 0], out[k, 1], out[k, 2] = grid[0, j, i], grid[1, j, i], grid[2, j, i]
        else:
            out[k, 0], out[k, 1], out[k, 2] = 0.0, 0.0, 0.0


@_compiled
def _press(grid, x0, y0, cell, cx, cy, hx, hy, half, depth, shear, on, rows, index):  # pragma: no cover
    n = grid.shape[1]
    steps = int(math.ceil(2.0 * half / (0.5 * cell)))
    for k in range(cx.shape[0]):
        if not on[k] or depth[k] <= 0.0:
            continue
        # the rut's surface: the sinkage less the rebound p / k_u (terramechanics.rut_surface),
        # from the wheel's soil's row of terramechanics._params (kb 4, n 5, k0 16, A_u 17)
        surf = 0.0
        if index[k] >= 0:
            q = rows[index[k]]
            ku = q[16] + q[17] * depth[k]
            surf = max(depth[k] - q[4] * depth[k] ** q[5] / ku, 0.0) if ku > 0.0 else depth[k]
        # across the wheel: the heading turned by 90 degrees to the left
        norm = math.hypot(hx[k], hy[k])
        if norm <= 0.0:
            continue
        ux, uy = hx[k] / norm, hy[k] / norm
        lx, ly = -uy, ux
        for m in range(steps + 1):
            u = -half + 2.0 * half * m / steps
            i = int(math.floor((cx[k] + u * lx - x0) / cell))
            j = int(math.floor((cy[k] + u * ly - y0) / cell))
            if 0 <= i < n and 0 <= j < n:
                if depth[k] > grid[0, j, i]:
                    grid[0, j, i] = depth[k]
                    grid[3, j, i] = surf
                grid[1, j, i] = shear[k] * ux
                grid[2, j, i] = shear[k] * uy


@_compiled
def _meet(grid, x0, y0, cell, wheels, frames, out, rolled, rs, prior, prior_shear, leave):  # pragma: no cover
    """Per wheel: the rut where it meets the soil, and where it leaves the soil.

    ``prior``: the largest earlier sinkage there; ``prior_shear``: the shear left there along
    the wheel's heading; ``leave`` (n, 2): the exit point, from its last contact angles.
    """
    n = grid.shape[1]
    for k in range(wheels.shape[0]):
        hx, hy = frames[k, 0, 0], frames[k, 0, 1]
        norm = math.hypot(hx, hy)
        if norm > 0.0:  # the heading's direction on the map (shortened by the slope in 3-D)
            hx, hy = hx / norm, hy / norm
        # the way it rolls (forward from rest, and until it has rolled half a contact back;
        # the force law mirrors from the first backward roll, with that roll's small weight)
        go = -1.0 if rolled[k] < -0.5 else 1.0
        front = 0.9 * rs * math.sin(out[k, 5])
        back = rs * math.sin(abs(out[k, 6]))
        px, py = wheels[k, 0] + go * hx * front, wheels[k, 1] + go * hy * front
        leave[k, 0], leave[k, 1] = wheels[k, 0] - go * hx * back, wheels[k, 1] - go * hy * back
        i = int(math.floor((px - x0) / cell))
        j = int(math.floor((py - y0) / cell))
        if 0 <= i < n and 0 <= j < n:
            prior[k] = grid[0, j, i]
            prior_shear[k] = grid[1, j, i] * hx + grid[2, j, i] * hy
        else:
            prior[k] = 0.0
            prior_shear[k] = 0.0


class RutMap:
    """The soil's memory of the wheels that passed: pressed depth and shear, world frame.

    Args:
        size: Edge of the square window [m].
        cell: Grid cell [m].
        margin: Distance from the window's edge at which it moves to centre on the rover [m].
    """

    def __init__(self, size: float = 12.0, cell: float = 0.01, margin: float = 2.0) -> None:
        check_range("ruts.cell", cell, 0.001, 0.5)
        check_range("ruts.size", size, 20 * cell, 200.0)
        check_range("ruts.margin", margin, 0.0, size / 2, hi_open=True)
        self.cell = float(cell)
        self.n = int(round(size / cell))
        self.size = self.n * self.cell
        self.margin = float(margin)
        points = 4 * self.n * self.n
        if points * 4 > 2 * 1024**3:
            raise ValueError(
                f"ruts: a {size} m window at {cell} m needs {points * 4 / 1e9:.1f} GB; enlarge the cell"
            )
        self.grid = np.zeros((4, self.n, self.n), dtype=np.float32)
        #: Counts the changes of the map (a renderer uploads it again when this moves).
        self.version = 0
        #: Whether any wheel has pressed the soil since the last reset.
        self.pressed = False
        self.origin = np.array([-self.size / 2, -self.size / 2])
        self._buf = np.zeros((0, 3))
        self._meet_buf: tuple[np.ndarray, np.ndarray, np.ndarray] = (
            np.zeros(0),
            np.zeros(0),
            np.zeros((0, 2)),
        )

    def reset(self, x: float = 0.0, y: float = 0.0) -> None:
        """Fresh soil everywhere; the window centred on (x, y) [m]."""
        self.grid[:] = 0.0
        self.origin = np.array([x - self.size / 2, y - self.size / 2])
        self.version += 1
        self.pressed = False

    def follow(self, x: float, y: float) -> None:
        """Move the window to centre on (x, y) [m] if that is within ``margin`` of its edge."""
        lo = self.origin + self.margin
        hi = self.origin + self.size - self.margin
        if lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1]:
            return
        new = np.array([x - self.size / 2, y - self.size / 2])
        shift = np.round((new - self.origin) / self.cell).astype(int)
        new = self.origin + shift * self.cell
        moved = np.zeros_like(self.grid)
        di, dj = int(shift[0]), int(shift[1])
        n = self.n
        if abs(di) < n and abs(dj) < n:
            src_i = slice(max(di, 0), n + min(di, 0))
            dst_i = slice(max(-di, 0), n - max(di, 0))
            src_j = slice(max(dj, 0), n + min(dj, 0))
            dst_j = slice(max(-dj, 0), n - max(dj, 0))
            moved[:, dst_j, dst_i] = self.grid[:, src_j, src_i]
        self.grid = moved
        self.origin = new
        self.version += 1

    def sample(self, xy) -> np.ndarray:
        """(k, 3) at world points ``xy`` (k, 2) [m]: largest sinkage [m], shear x and y [m]."""
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        if self._buf.shape[0] != len(xy):
            self._buf = np.zeros((len(xy), 3))
        _sample(self.grid, self.origin[0], self.origin[1], self.cell, xy[:, 0], xy[:, 1], self._buf)
        return self._buf

    def press(self, xy, heading, width: float, depth, shear, on, soils, index) -> None:
        """Record wheels passing: a strip ``width`` [m] across each ``heading`` (k, 2) at ``xy``.

        Args:
            xy: (k, 2) where each wheel leaves the soil [m].
            heading: (k, 2) unit travel directions in the ground's plane (x, y).
            width: Wheel width [m].
            depth: (k,) each wheel's sinkage there [m] (the map keeps the largest).
            shear: (k,) the shear displacement each leaves, along its heading [m].
            on: (k,) bool, the wheels on soil.
            soils: (m, N_PARAMS) the soils' rows of ``terramechanics._params`` (the rut's
                surface rebounds by each wheel's own soil).
            index: (k,) each wheel's soil, a row of ``soils`` (-1: none).
        """
        xy = np.ascontiguousarray(xy, dtype=np.float64)
        hd = np.ascontiguousarray(heading, dtype=np.float64)
        on = on if isinstance(on, np.ndarray) and on.dtype == np.bool_ else np.asarray(on, dtype=np.bool_)
        if on.any():
            self.version += 1
            self.pressed = True
        _press(
            self.grid,
            self.origin[0],
            self.origin[1],
            self.cell,
            xy[:, 0],
            xy[:, 1],
            hd[:, 0],
            hd[:, 1],
            0.5 * width,
            np.ascontiguousarray(depth, dtype=np.float64),
            np.ascontiguousarray(shear, dtype=np.float64),
            on,
            np.ascontiguousarray(soils, dtype=np.float64),
            np.ascontiguousarray(index, dtype=np.int64),
        )

    def surface_at(self, xy) -> np.ndarray:
        """The ruts' surface depth [m] at world points ``xy`` (k, 2) [m].

        Bilinear between cell centres (as a filtered texture of :meth:`surface` samples it), 0
        beyond the map.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        u = (xy[:, 0] - self.origin[0]) / self.cell - 0.5
        v = (xy[:, 1] - self.origin[1]) / self.cell - 0.5
        i, j = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        fu, fv = u - i, v - j
        layer = self.grid[3]
        out = np.zeros(len(xy))
        for di, dj, wgt in (
            (0, 0, (1 - fu) * (1 - fv)),
            (1, 0, fu * (1 - fv)),
            (0, 1, (1 - fu) * fv),
            (1, 1, fu * fv),
        ):
            ii, jj = i + di, j + dj
            ok = (ii >= 0) & (ii < self.n) & (jj >= 0) & (jj < self.n)
            out[ok] += wgt[ok] * layer[jj[ok], ii[ok]]
        return out

    def surface(self, x: float, y: float, half: float) -> tuple[float, float, np.ndarray]:
        """The ruts' surface depth [m] in the square of ``2 half`` metres about world (x, y).

        Returns:
            ``(x0, y0, depth)``: the world position of cell (0, 0)'s corner [m] and a
            (m, m) float32 copy of the depth below the original surface (rows along y, 0
            beyond the map), m = round(2 half / cell).
        """
        m = int(round(2.0 * half / self.cell))
        i0 = int(math.floor((x - half - self.origin[0]) / self.cell))
        j0 = int(math.floor((y - half - self.origin[1]) / self.cell))
        out = np.zeros((m, m), dtype=np.float32)
        a0, a1 = max(i0, 0), min(i0 + m, self.n)
        b0, b1 = max(j0, 0), min(j0 + m, self.n)
        if a0 < a1 and b0 < b1:
            out[b0 - j0 : b1 - j0, a0 - i0 : a1 - i0] = self.grid[3, b0:b1, a0:a1]
        return (
            float(self.origin[0] + i0 * self.cell),
            float(self.origin[1] + j0 * self.cell),
            out,
        )

    def meet(self, wheels, frames, out, rolled, shear_radius: float):
        """The ruts the wheels are about to meet, and where they leave the soil.

        Args:
            wheels: (n, >=2) wheel centres' world x, y first [m].
            frames: (n, 3, 3) each wheel's heading, left and axle (world).
            out: (n, 9) the contact's last output (its angles, columns 5 and 6).
            rolled: (n,) the contact's rolling state (its sign: the direction).
            shear_radius: The wheels' shear radius [m].

        Returns:
            ``(prior, prior_shear, leave)``: (n,) largest earlier sinkage ahead [m], (n,) the
            shear left there along each heading [m], (n, 2) the points each leaves the soil.
            Reused by the next call.
        """
        n = len(wheels)
        if self._meet_buf[0].shape[0] != n:
            self._meet_buf = (np.zeros(n), np.zeros(n), np.zeros((n, 2)))
        prior, shear, leave = self._meet_buf
        _meet(self.grid, self.origin[0], self.origin[1], self.cell, wheels, frames, out, rolled,
              shear_radius, prior, shear, leave)  # fmt: skip
        return prior, shear, leave

    @property
    def nbytes(self) -> int:
        """Memory held by the grid [bytes]."""
        return int(self.grid.nbytes)

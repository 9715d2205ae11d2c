"""Each wheel's sinkage from the downward fisheye: where its inner face disappears into the soil.

The fisheye under the body sees the inner face of every wheel. The soil's surface cuts that
face along a chord at the sinkage z above the rim's lowest point: below the chord the camera
sees the soil in front of the face, above it the face. For each wheel, through the exact
camera model and the wheel's pose from the kinematics (axle roll, depth, steering), the
image is sampled along vertical lines of the face near its centre (columns at abscissae
``columns_mm`` from the centre, heights zeta from the rim up to ``max_sinkage``), and the
sinkage is the one break height shared by all columns that best splits each column's samples
into two constant colours (least squares over all breaks; Brooks, Iagnemma and Dubowsky's
visual sinkage measurement, 2006, finds the same wheel-terrain boundary along the rim).

Samples hidden behind the rover's parts (a steering arm, a magenta marker) or outside the
image are left out. The quality is the colour step's size over the samples' spread about the
two levels, scaled to [0, 1] (``min_contrast`` gives 0, ``full_contrast`` 1), times the share
of the columns seen: a face in the rover's own shadow against soil in that shadow, or a contact
out of view, falls toward 0. No pybullet here: camera, rover model and image only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from perception.models.cameras import OmniCamera
from perception.models.drive_geometry import WHEELS
from perception.models.rover import RoverKinematicModel


@dataclass(frozen=True)
class SinkageConfig:
    """Parameters of :class:`SinkageEstimator`.

    Attributes:
        max_sinkage: Deepest sinkage searched [m].
        step: Spacing of the samples up the face [m].
        columns_mm: Abscissae of the sampled columns from the face's centre along the wheel's
            heading [mm]; near the centre the rim is within 3 mm of its lowest point.
        min_samples: Fewest samples on either side of a break [-].
        min_step: Smallest colour step between soil and face that is a boundary [grey levels].
        std_scale: The break's standard deviation at which the quality is one half [m].
        min_columns: Fewest columns seen for any estimate [-].
    """

    max_sinkage: float = 0.07
    step: float = 0.001
    columns_mm: tuple[float, ...] = tuple(float(x) for x in range(-90, 91, 5))
    min_samples: int = 4
    min_step: float = 6.0
    std_scale: float = 0.003
    min_columns: int = 4


@dataclass
class SinkageEstimate:
    """Per wheel (FL, FR, RL, RR): the sinkage [m] (NaN: none) and its quality [0, 1]."""

    sinkage: np.ndarray
    quality: np.ndarray


class SinkageEstimator:
    """Sinkage of the four wheels in one fisheye frame (see the module docstring).

    Args:
        camera: The fisheye's calibration.
        model: The rover's kinematic model (wheel radius and width, parts, the fisheye's mount).
        config: Parameters.
    """

    def __init__(self, camera: OmniCamera, model: RoverKinematicModel, config: SinkageConfig | None = None):
        self.camera = camera
        self.model = model
        self.config = config or SinkageConfig()
        c = self.config
        r = model.wheel_radius
        x = np.asarray(c.columns_mm, dtype=np.float64) / 1000.0
        if np.any(np.abs(x) >= r):
            raise ValueError(f"columns_mm {c.columns_mm}: every column lies within the wheel's radius {r} m")
        #: Heights above the rim's lowest point that are searched [m].
        self.zeta = np.arange(0.0, c.max_sinkage + 1e-12, c.step)
        X, Z = np.meshgrid(x, self.zeta, indexing="ij")
        on_face = Z >= r - np.sqrt(r * r - X**2)  # within the rim
        self._row = np.broadcast_to(np.arange(len(self.zeta)), X.shape)[on_face]  # each point's height
        self._col = np.broadcast_to(np.arange(len(x))[:, None], X.shape)[on_face]
        self._ncol = len(x)
        # the face's points in each wheel's knuckle frame (the inner face: toward the body)
        self._local = []
        for wheel in WHEELS:
            side = -1.0 if wheel[1] == "L" else 1.0
            pts = np.stack(
                [X[on_face], np.full(on_face.sum(), side * 0.5 * model.wheel_width), Z[on_face] - r], -1
            )
            self._local.append(pts)

    def face_points(self, wheel: int, R: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(n, 3) body-frame points sampled on wheel ``wheel``'s inner face (``self.zeta`` heights)."""
        return self._local[wheel] @ np.asarray(R).T + c

    def measure(self, image: np.ndarray, psi, depth, delta) -> SinkageEstimate:
        """The four wheels' sinkage in ``image`` (H, W, 3) at the joint state (psi, depth, delta).

        Args:
            image: The fisheye frame (uint8 or float, RGB).
            psi: (2,) axle roll [rad].
            depth: (2,) axle depth [m].
            delta: (4,) wheel steering [rad].
        """
        cam = self.camera
        T = self.model.T_body_cam
        frames = self.model.wheel_frames(np.asarray(psi), np.asarray(depth), np.asarray(delta))
        img = np.asarray(image)
        if img.dtype not in (np.uint8, np.float32):
            img = img.astype(np.float32)
        h, w = img.shape[:2]
        P = np.stack([self.face_points(k, R, c) for k, (R, c) in enumerate(frames)]) - T[:3, 3]
        pc = P @ T[:3, :3]  # camera frame
        u, v = cam.project_xyz(pc[..., 0], pc[..., 1], pc[..., 2])
        seen = np.isfinite(u) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        # the magenta markers (on the axle plates and tie rods) and each wheel's steering arm
        markers = np.array(list(self.model.marker_positions(psi, depth, delta).values()))
        beams, beam_r = self.model.beam_parts(psi, depth)  # a beam may hide a rear contact
        markers = np.vstack([markers, beams])
        marker_r = np.r_[np.full(8, 0.75 * self.model.marker_size), beam_r]
        for k, (R, c) in enumerate(frames):
            occ_p, occ_r = self.model.occluders(WHEELS[k], R, c)
            parts = np.vstack([occ_p, markers]) - T[:3, 3]
            seen[k] &= ~_behind_parts(P[k], parts, np.r_[occ_r, marker_r])
        samples = cv2.remap(
            img,
            np.where(seen, u, -1).astype(np.float32).reshape(1, -1),
            np.where(seen, v, -1).astype(np.float32).reshape(1, -1),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        samples = samples.reshape(*seen.shape, -1).astype(np.float64)
        seen &= samples.max(axis=-1) > 0  # a black pixel is no image (a window not read out)
        sink = np.full(4, math.nan)
        qual = np.zeros(4)
        for k in range(4):
            sink[k], qual[k] = self._break(samples[k], seen[k])
        return SinkageEstimate(sink, qual)

    def _break(self, samples: np.ndarray, seen: np.ndarray) -> tuple[float, float]:
        """The height below which one face's samples are the soil's colour and above it the face's.

        Two colours, the soil's and the face's, shared by every column: a column near the rim's
        end holds face samples only down to the rim, so the soil's reach along the rim (its
        entry and exit) counts as well as its height at the centre. Returns (z [m] or NaN,
        quality).
        """
        cfg = self.config
        if np.count_nonzero(np.bincount(self._col[seen], minlength=self._ncol)) < cfg.min_columns:
            return math.nan, 0.0
        rows, nz = self._row[seen], len(self.zeta)
        x = samples[seen]
        # per height, over the columns: count, colour sums, sum of squares; then prefix sums
        cnt = np.bincount(rows, minlength=nz).astype(np.float64)
        s = np.stack([np.bincount(rows, x[:, j], nz) for j in range(x.shape[1])], -1)
        q = np.bincount(rows, (x * x).sum(axis=1), nz)
        n1, s1, q1 = np.cumsum(cnt), np.cumsum(s, axis=0), np.cumsum(q)
        n, st, qt = n1[-1], s1[-1], q1[-1]
        n2, s2, q2 = n - n1, st - s1, qt - q1
        least = cfg.min_samples * cfg.min_columns
        enough = (n1 >= least) & (n2 >= least)
        if not enough.any():
            return math.nan, 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            sse = (q1 - (s1 * s1).sum(-1) / n1) + (q2 - (s2 * s2).sum(-1) / n2)
        sse = np.where(enough, sse, np.inf)
        k = int(np.argmin(sse))
        z = 0.5 * (self.zeta[k] + self.zeta[min(k + 1, nz - 1)])  # between samples k and k + 1
        step = float(np.linalg.norm(s2[k] / n2[k] - s1[k] / n1[k]))
        if step < cfg.min_step:  # face and soil alike (deep shadow, a black frame): no boundary
            return math.nan, 0.0
        # the break's spread: each height's likelihood exp(-SSE / 2 var), var the samples' own
        # spread about their two colours at the best break (at least a grey level)
        var = max(float(sse[k]) / (float(n) * x.shape[1]), 1.0)
        like = np.exp(-(sse - sse[k]) / (2.0 * var))
        like /= like.sum()
        std = math.sqrt(float(like @ (self.zeta - self.zeta[k]) ** 2) + cfg.step**2 / 12.0)
        above = np.count_nonzero(np.bincount(self._col[seen & (self._row > k)], minlength=self._ncol))
        quality = 1.0 / (1.0 + (std / cfg.std_scale) ** 2) * min(1.0, 2.0 * above / self._ncol)
        return z, float(quality)


def _behind_parts(P: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Which points (..., 3) (from the camera) lie behind one of the spheres (centres, radii) from it."""
    flat = P.reshape(-1, 3)
    d = np.linalg.norm(flat, axis=1)
    ray = flat / d[:, None]
    along = ray @ centres.T  # (n, parts)
    perp2 = np.einsum("pk,pk->p", centres, centres)[None, :] - along**2
    hidden = (perp2 < radii[None, :] ** 2) & (along > 0) & (along < d[:, None] - radii[None, :])
    return hidden.any(axis=1).reshape(P.shape[:-1])

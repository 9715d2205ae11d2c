"""Each wheel's sinkage from the downward fisheye: where its inner face disappears into the soil.

The fisheye under the body sees the inner face of every wheel. The soil's surface cuts that
face along a chord at the sinkage z above the rim's lowest point: below the chord the camera
sees the soil in front of the face, above it the face. For each wheel, through the exact
camera model and the wheel's pose from the kinematics (axle roll, depth, steering), the image
is sampled on the face's lowest ``max_sinkage`` (columns at ``columns_mm`` along the wheel's
heading, heights zeta above the rim's lowest point, within the rim) and on the ground beside
the face. Colours are compared as chromaticity, which a shadow keeps, and damped log intensity
(:func:`_features`). The sinkage is the height of the split of the face's samples into two
colours (below it, above it) of least squared error, refined between the sampled heights by a
parabola; where what lies below that split looks more like the face (the median of its
samples in the top ``face_band`` of the heights searched) than like the ground beside it, the
face reaches the rim: rigid ground, sinkage 0. Columns near the rim's ends hold face samples
only down to the rim, so the soil's reach along the rim (where it meets the wheel in front and
behind) counts as well as its height at the centre, which the camera sees foreshortened. (Brooks, Iagnemma and
Dubowsky's visual sinkage measurement, 2006, finds the same wheel-terrain boundary along the
rim, from a camera on the wheel's side.)

Samples hidden behind the rover's parts (a steering arm, a magenta marker, an axle beam),
outside the image or black (not read out) are left out. The quality is one over one plus the
split's spread over ``std_scale``, squared, times the share of the columns seen above it and
how clearly the colour below it is the soil's (or, on rigid ground, the face's); soil and face
of like colour (the face in the rover's shadow against soil in that shadow, a black frame), a
face as mottled as the soil, or a contact out of view give no sinkage (NaN, quality 0). No
simulator here: camera, rover model and image only.

A frame's reading can flip (the soil in the wheel's shade taken for the face, reading 0), while
a wheel's sinkage changes over decimetres of its travel: :class:`SinkageTrack` reports the
quality-weighted median of the last 0.8 s of measurements where they weigh enough.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from perception.models._jit import compiled
from perception.models.cameras import OmniCamera
from perception.models.drive_geometry import WHEELS
from perception.models.rover import PLATE, ROD, RoverKinematicModel


@dataclass(frozen=True)
class SinkageConfig:
    """Parameters of :class:`SinkageEstimator`.

    Attributes:
        max_sinkage: Deepest sinkage searched [m].
        step: Spacing of the samples up the face [m].
        columns_mm: Abscissae of the sampled columns from the face's centre along the wheel's
            heading [mm].
        min_columns: Fewest columns seen for any estimate [-].
        min_step: Smallest difference of the colour features (:func:`_features`) between soil
            and face that is a boundary [-].
        intensity_weight: The weight of log intensity in the colour features against that of
            the chromaticity (100): low, because the soil next to a wheel is often in its shade.
        min_margin: The soil under the break must look this much more like the soil beside
            the face than like the face (in units of their difference) for a quality of 1 [-].
        max_mottle: The face's samples' median distance from its colour, over the soil's and
            the face's difference, beyond which no sinkage is read (a face as textured as soil).
        face_band: The face's colour is read from its samples this far below ``max_sinkage`` [m].
        ground_height: The soil's colour is read from the ground beside the face at this height
            above the rim's lowest point [m] (a typical sinkage).
        std_scale: The break's standard deviation at which the quality is one half [m].
        soil_break: A break at least this high [m] is soil where most of the samples under it
            are unlike the face, whatever their mean colour: soil half in the wheel's shade,
            darker and brighter than the face, averages to the face's grey. Lower, where a
            pose error of a pixel or two shows the ground under a rim on rigid ground, the
            mean decides.
        face_tolerance: A sample is like the face within this share of the soil's and the
            face's difference (or three times the face's mottle, if more) [-].
    """

    max_sinkage: float = 0.07
    step: float = 0.003
    columns_mm: tuple[float, ...] = tuple(float(x) for x in range(-90, 91, 5))
    min_columns: int = 4
    min_step: float = 3.0
    min_margin: float = 0.5
    max_mottle: float = 0.35
    intensity_weight: float = 50.0
    face_band: float = 0.012
    ground_height: float = 0.02
    std_scale: float = 0.003
    soil_break: float = 0.015
    face_tolerance: float = 0.3


#: A wheel's sinkage is reported where its measurement has at least this quality.
MIN_QUALITY = 0.4


@dataclass
class SinkageEstimate:
    """Per wheel (FL, FR, RL, RR): the sinkage [m] (NaN: none) and its quality [0, 1]."""

    sinkage: np.ndarray
    quality: np.ndarray

    @classmethod
    def none(cls) -> SinkageEstimate:
        """No wheel measured: NaN sinkages, quality 0."""
        return cls(np.full(4, math.nan), np.zeros(4))

    def reported(self) -> tuple[np.ndarray, float]:
        """The reported sinkages and their quality.

        Returns:
            The sinkages [m] of quality at least :data:`MIN_QUALITY` (NaN: the others), and
            their mean quality over the four wheels (the others count 0).
        """
        ok = self.quality >= MIN_QUALITY
        return np.where(ok, self.sinkage, np.nan), float(np.mean(np.where(ok, self.quality, 0.0)))


class SinkageTrack:
    """Each wheel's sinkage over the last ``window`` seconds of measurements.

    A wheel's sinkage changes over its travel, a frame's reading can flip (the soil in the
    wheel's shade taken for the face, reading 0; a streak of texture taken for the soil line):
    the track reports the quality-weighted median of the measurements of quality at least
    :data:`MIN_QUALITY` within the window, where their qualities sum to ``min_weight``, with a
    quality of their sum over twice that (at most 1; at least 0.5 where reported). A
    measurement older than the window is forgotten; time running back starts afresh.

    Args:
        window: How far back measurements count [s].
        min_weight: The sum of qualities needed for a sinkage [-].
    """

    def __init__(self, window: float = 0.8, min_weight: float = 1.5):
        if not (math.isfinite(window) and window > 0.0):
            raise ValueError(f"window {window!r} s: give a positive duration")
        if not (math.isfinite(min_weight) and min_weight > 0.0):
            raise ValueError(f"min_weight {min_weight!r}: give a positive sum of qualities")
        self.window = float(window)
        self.min_weight = float(min_weight)
        self._t: list[float] = []
        self._z: list[np.ndarray] = []
        self._q: list[np.ndarray] = []

    def reset(self) -> None:
        """Forget every measurement."""
        self._t.clear()
        self._z.clear()
        self._q.clear()

    def update(self, t: float, measured: SinkageEstimate | None) -> SinkageEstimate:
        """Add a frame's measurement (None: none at ``t``) and return the sinkages at ``t`` [s]."""
        if self._t and t < self._t[-1]:
            self.reset()
        if measured is not None:
            good = (measured.quality >= MIN_QUALITY) & np.isfinite(measured.sinkage)
            self._t.append(float(t))
            self._z.append(np.where(good, measured.sinkage, 0.0))
            self._q.append(np.where(good, measured.quality, 0.0))
        old = next((i for i, ti in enumerate(self._t) if ti >= t - self.window - 1e-9), len(self._t))
        del self._t[:old], self._z[:old], self._q[:old]
        out = SinkageEstimate.none()
        if not self._t:
            return out
        Z, Q = np.array(self._z), np.array(self._q)  # (measurements, wheels)
        total = Q.sum(axis=0)
        for k in np.flatnonzero(total >= self.min_weight):
            order = np.argsort(Z[:, k], kind="stable")
            cum = np.cumsum(Q[order, k])
            out.sinkage[k] = Z[order[np.searchsorted(cum, 0.5 * cum[-1])], k]
            out.quality[k] = min(1.0, total[k] / (2.0 * self.min_weight))
        return out


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
        self.config = c = config or SinkageConfig()
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
        self._n_face = len(self._row)
        self._top = self.zeta[self._row] >= c.max_sinkage - c.face_band  # the face's band
        #: The breaks searched: below the lowest height, between the heights, above the highest [m].
        self._breaks_at = np.r_[0.0, self.zeta[1:] - 0.5 * c.step, self.zeta[-1] + 0.5 * c.step]
        # per wheel, knuckle frame: the inner face's points (toward the body), then the ground
        # beside it, 15-45 mm inward, at a typical sinkage's height
        gx, gy = np.meshgrid(np.linspace(-0.06, 0.06, 9), np.linspace(0.015, 0.045, 4), indexing="ij")
        self._local = []
        for wheel in WHEELS:
            side = -1.0 if wheel[1] == "L" else 1.0
            y = side * 0.5 * model.wheel_width
            face = np.stack([X[on_face], np.full(self._n_face, y), Z[on_face] - r], -1)
            ground = np.stack([gx.ravel(), y + side * gy.ravel(), np.full(gx.size, c.ground_height - r)], -1)
            self._local.append(np.vstack([face, ground]))

    def sample_points(self, wheel: int, R: np.ndarray, c: np.ndarray) -> np.ndarray:
        """(n, 3) body-frame points sampled for wheel ``wheel``: on its inner face, then beside it."""
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
        P = np.stack([self.sample_points(k, R, c) for k, (R, c) in enumerate(frames)]) - T[:3, 3]
        pc = P @ T[:3, :3]  # camera frame
        u, v = cam.project_xyz(pc[..., 0], pc[..., 1], pc[..., 2])
        seen = np.isfinite(u) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        # its axle's magenta markers and beam (which may hide a rear contact), its steering arm
        markers = self.model.marker_positions(psi, depth, delta)
        beams, beam_r = self.model.beam_parts(psi, depth)
        per_axle = len(beams) // 2
        parts, radii = [], []
        for k, (R, c) in enumerate(frames):
            axle = WHEELS[k][0]
            mine = [markers[m] for m in (*PLATE[axle], *ROD[axle])]
            i = "FR".index(axle)
            beam = slice(i * per_axle, (i + 1) * per_axle)
            arm, arm_r = self.model.occluders(WHEELS[k], R, c)
            parts.append(np.vstack([arm, *mine, beams[beam]]))
            radii.append(np.r_[arm_r, np.full(len(mine), 0.75 * self.model.marker_size), beam_r[beam]])
        seen &= ~_behind_parts(P, np.stack(parts) - T[:3, 3], np.stack(radii))
        samples = cv2.remap(
            img,
            np.where(seen, u, -1).astype(np.float32).reshape(1, -1),
            np.where(seen, v, -1).astype(np.float32).reshape(1, -1),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        samples = samples.reshape(*seen.shape, -1)
        seen &= samples.max(axis=-1) > 0  # a black pixel is no image (a window not read out)
        samples = _features(samples.astype(np.float64), self.config.intensity_weight)
        nf = self._n_face
        return self._breaks(samples[:, :nf], seen[:, :nf], samples[:, nf:], seen[:, nf:])

    def _breaks(
        self, samples: np.ndarray, seen: np.ndarray, ground: np.ndarray, ground_seen: np.ndarray
    ) -> SinkageEstimate:
        """The wheels' sinkages [m] (or NaN) and their quality from their faces' and grounds' samples.

        Args:
            samples: (4, n, f) the faces' samples' colour features.
            seen: (4, n) which of them are seen.
            ground: (4, m, f) the colour features of the ground beside each face.
            ground_seen: (4, m) which of them are seen.
        """
        c = self.config
        out = SinkageEstimate.none()
        for k in range(len(samples)):
            out.sinkage[k], out.quality[k] = _split(
                samples[k], seen[k], self._row, self._col, self._top, ground[k], ground_seen[k],
                self._breaks_at, self._ncol, c.step, c.min_columns, c.min_step, c.max_mottle,
                c.min_margin, c.std_scale, c.soil_break, c.face_tolerance,
            )  # fmt: skip
        return out


def _features(rgb: np.ndarray, intensity_weight: float) -> np.ndarray:
    """(..., 3) colour features of RGB samples [-].

    100 log(R/G) and 100 log(B/G), the chromaticity (which a shadow keeps), and
    ``intensity_weight`` log(R + G + B) (which a shadow changes).
    """
    c = np.maximum(rgb, 1.0)
    if c.shape[-1] < 3:  # grey images: intensity only
        return intensity_weight * np.log(c)
    g = np.log(c[..., 1])
    return np.stack(
        [
            100.0 * (np.log(c[..., 0]) - g),
            100.0 * (np.log(c[..., 2]) - g),
            intensity_weight * np.log(c.sum(-1)),
        ],
        -1,
    )


@compiled
def _behind_parts(P, centres, radii):  # pragma: no cover (compiled)
    """Which points (b, n, 3) (from the camera) lie behind one of the spheres (b, m, 3) of radii (b, m).

    Each batch b of points is tested against its own spheres (a radius of 0: none). The spheres
    outside the cone of a batch's rays (with their own angular radius) are left out first: a
    wheel's points lie in a narrow cone, and most parts are elsewhere.
    """
    b, n, m = P.shape[0], P.shape[1], centres.shape[1]
    hidden = np.zeros((b, n), dtype=np.bool_)
    ray = np.empty((n, 3))
    d = np.empty(n)
    near = np.empty(m, dtype=np.int64)
    for w in range(b):
        axis = np.zeros(3)
        for i in range(n):
            d[i] = math.sqrt(P[w, i, 0] ** 2 + P[w, i, 1] ** 2 + P[w, i, 2] ** 2)
            ray[i] = P[w, i] / max(d[i], 1e-12)
            axis += ray[i]
        axis /= max(math.sqrt(np.sum(axis**2)), 1e-12)
        cos_spread = 1.0
        for i in range(n):
            cos_spread = min(cos_spread, np.sum(ray[i] * axis))
        spread = math.acos(max(-1.0, min(1.0, cos_spread)))
        k = 0
        for j in range(m):
            dist = math.sqrt(np.sum(centres[w, j] ** 2))
            if radii[w, j] <= 0.0 or dist <= 0.0:
                continue
            off = math.acos(max(-1.0, min(1.0, np.sum(centres[w, j] * axis) / dist)))
            if off <= spread + math.asin(min(1.0, radii[w, j] / dist)) + 1e-9:
                near[k] = j
                k += 1
        for i in range(n):
            for a in range(k):
                j = near[a]
                r = radii[w, j]
                along = (
                    ray[i, 0] * centres[w, j, 0] + ray[i, 1] * centres[w, j, 1] + ray[i, 2] * centres[w, j, 2]
                )
                if along <= 0.0 or along >= d[i] - r:
                    continue
                if (
                    centres[w, j, 0] ** 2 + centres[w, j, 1] ** 2 + centres[w, j, 2] ** 2 - along * along
                    < r * r
                ):
                    hidden[w, i] = True
                    break
    return hidden


@compiled
def _split(
    x,
    seen,
    row,
    col,
    top,
    ground,
    ground_seen,
    breaks,
    ncol,
    step,
    min_columns,
    min_step,
    max_mottle,
    min_margin,
    std_scale,
    soil_break,
    face_tolerance,
):  # pragma: no cover (compiled)
    """One wheel's sinkage [m] (NaN: none) and its quality from its face's and ground's samples.

    ``x`` (n, f) the face's samples' colour features, ``seen`` (n,), ``row`` and ``col`` (n,)
    each sample's height and column, ``top`` (n,) the face's band; ``ground`` (m, f) and
    ``ground_seen`` (m,) the ground beside the face; ``breaks`` (heights + 1,) the breaks [m].
    The rest: :class:`SinkageConfig`.
    """
    n, f = x.shape
    nz = breaks.shape[0] - 1
    cols = np.zeros(ncol, dtype=np.bool_)
    n_top = 0
    for i in range(n):
        if seen[i]:
            cols[col[i]] = True
            if top[i]:
                n_top += 1
    n_ground = 0
    for i in range(ground.shape[0]):
        if ground_seen[i]:
            n_ground += 1
    if cols.sum() < min_columns or n_ground < 8 or n_top < 8:
        return math.nan, 0.0  # too little of the face in view, or no soil or no face to compare
    soil = np.empty(f)
    face = np.empty(f)
    g = np.empty(n_ground)
    t = np.empty(n_top)
    for j in range(f):
        a = 0
        for i in range(ground.shape[0]):
            if ground_seen[i]:
                g[a] = ground[i, j]
                a += 1
        soil[j] = np.median(g)
        a = 0
        for i in range(n):
            if seen[i] and top[i]:
                t[a] = x[i, j]
                a += 1
        face[j] = np.median(t)
    contrast = math.sqrt(np.sum((face - soil) ** 2))
    if contrast < min_step:  # face and soil alike (deep shadow, a black frame)
        return math.nan, 0.0
    # a face as mottled as the soil (a textured face; TinyRenderer draws the tread's texture
    # on it) cannot be told from the soil by its colour
    a = 0
    for i in range(n):
        if seen[i] and top[i]:
            t[a] = math.sqrt(np.sum((x[i] - face) ** 2))
            a += 1
    mottle = np.median(t)
    if mottle > max_mottle * contrast:
        return math.nan, 0.0
    # the split into two colours of least squared error: below each break the soil, above it
    # the face (prefix sums over the heights)
    n1 = np.zeros(nz + 1)
    s1 = np.zeros((nz + 1, f))
    q1 = np.zeros(nz + 1)
    for i in range(n):
        if seen[i]:
            r = row[i] + 1
            n1[r] += 1.0
            for j in range(f):
                s1[r, j] += x[i, j]
                q1[r] += x[i, j] * x[i, j]
    for r in range(1, nz + 1):
        n1[r] += n1[r - 1]
        s1[r] += s1[r - 1]
        q1[r] += q1[r - 1]
    least = 2 * min_columns
    sse = np.full(nz + 1, np.inf)
    for r in range(nz + 1):
        na, nb = n1[r], n1[nz] - n1[r]
        if na >= least and nb >= least:
            e = q1[r] - np.sum(s1[r] ** 2) / na + (q1[nz] - q1[r]) - np.sum((s1[nz] - s1[r]) ** 2) / nb
            sse[r] = e
    if not np.isfinite(sse).any():
        return math.nan, 0.0
    k = int(np.argmin(sse))
    below = s1[k] / n1[k]
    # how much more the colour under the break is the soil's than the face's, in units of their
    # difference: 1 the soil's exactly, 0 halfway, below 0 nearer the face's
    margin = (math.sqrt(np.sum((below - face) ** 2)) - math.sqrt(np.sum((below - soil) ** 2))) / contrast
    if margin <= 0.0 and breaks[k] >= soil_break:
        # a high break whose samples below are mostly unlike the face: soil, half in the
        # wheel's shade, whose mean passes for the face's grey; as sure as few are face-like
        tol = max(3.0 * mottle, face_tolerance * contrast)
        n_low = 0
        n_like = 0
        for i in range(n):
            if seen[i] and row[i] < k:
                n_low += 1
                if math.sqrt(np.sum((x[i] - face) ** 2)) <= tol:
                    n_like += 1
        if n_low and n_like < 0.5 * n_low:
            margin = 1.0 - 2.0 * n_like / n_low
    if margin <= 0.0:
        # what lies under the break looks like the face, not the soil beside it: the face
        # reaches the rim (rigid ground, or a sinkage under the first rows), as surely as the
        # colour under the break is nearer the face's
        k, z, std, margin = 0, 0.0, step, -margin
    else:
        z = breaks[k]
        if 0 < k < nz and np.isfinite(sse[k - 1]) and np.isfinite(sse[k + 1]):
            # between the breaks: the vertex of the parabola through the three least SSEs
            curv = sse[k - 1] - 2.0 * sse[k] + sse[k + 1]
            if curv > 0:
                z += 0.5 * step * min(1.0, max(-1.0, (sse[k - 1] - sse[k + 1]) / curv))
        # the break's spread: each break's likelihood exp(-SSE / 2 var), var the samples'
        # spread about the two colours at the best break (floored)
        var = max(sse[k] / (n1[nz] * f), 0.01)
        wsum = 0.0
        m2 = 0.0
        for r in range(nz + 1):
            if np.isfinite(sse[r]):
                lk = math.exp(-(sse[r] - sse[k]) / (2.0 * var))
                wsum += lk
                m2 += lk * (breaks[r] - z) ** 2
        std = math.sqrt(m2 / wsum + step * step / 12.0)
    cols[:] = False
    for i in range(n):
        if seen[i] and row[i] >= k:
            cols[col[i]] = True
    quality = 1.0 / (1.0 + (std / std_scale) ** 2) * min(1.0, 2.0 * cols.sum() / ncol)
    # soil that looks barely more like the soil beside it than like the face: unsure
    return z, quality * min(1.0, margin / min_margin)

"""Fiducial markers in the fisheye image, and the axle roll, height and steering they give.

Kinematics paper, sections IV-B and V-A/B:

- Magenta markers are segmented in HSV, cleaned by an opening (erosion then dilation) and
  reduced to blob centroids. Each of A1 ... D2 takes the nearest blob to its predicted pixel (the
  previous state through the kinematic model and the camera), within a gate.
- Every centre is unprojected to a unit ray (:meth:`OmniCamera.cam2world`) from the camera
  centre, in the body frame.
- Axle roll and height (eq. 2): the plate markers lie in the plane x = +-(axle_x - plate_offset);
  the ray-plane intersections give the marker vector, whose direction in the y-z plane is the
  roll psi and whose midpoint is the roll centre at depth d.
- Steering (eqs. 3-4): the tie-rod ends lie in the axle's roll-corrected plane (normal R_x(psi) z,
  here moved to the tie-rod height); each ray-plane intersection, seen from its kingpin, gives
  the wheel's steering angle, and the inverse Ackermann map gives lambda. The paper's distance
  ratio (eq. 5) is available as :func:`steering_ratio` with a calibrated map (see
  :class:`SteeringCalibration`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from perception.models.calib_io import CalibrationError, as_array, read_mapping, write_mapping
from perception.models.cameras import OmniCamera
from perception.models.rover import AXLES, MARKERS, PLATE, ROD, WHEELS, RoverKinematicModel


@dataclass(frozen=True)
class MarkerConfig:
    """Marker segmentation.

    Attributes:
        hue_range: Magenta hue band in OpenCV units (0-180).
        min_saturation: Minimum HSV saturation (0-255).
        min_value: Minimum HSV value (0-255); low, so markers in the rover's shadow still count.
        min_area_frac: Smallest blob area as a share of the image area.
        gate_frac: Largest distance from a predicted marker pixel, as a share of the image width.
    """

    hue_range: tuple[int, int] = (135, 165)
    min_saturation: int = 110
    min_value: int = 20
    min_area_frac: float = 3e-5
    gate_frac: float = 0.05


def segment_magenta(
    rgb: np.ndarray, cfg: MarkerConfig, rois: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Magenta blobs: (centroids (n, 2) [px], areas (n,) [px], cleaned mask).

    Blobs are found in HSV (hue band, saturation and value floors) after an opening. Each blob's
    centre is then weighted by its saturation relative to the blob's core, over the blob grown
    by two pixels: saturation does not depend on brightness, so a marker half in shadow keeps
    its centre, and partly covered edge pixels count by about their share (sub-pixel centres).

    Args:
        rgb: (H, W, 3) uint8 RGB image.
        cfg: Thresholds.
        rois: Optional (n, 4) boxes (x0, y0, x1, y1) [px]: look only inside them (each marker's
            region of interest, predicted from the last state). Blobs within 3 px of a box's
            edge inside the image are left out, as they may be cut; the mask is then only
            filled in the boxes.
    """
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image: {img.dtype} {img.shape}; expected (H, W, 3) uint8 RGB")
    H, W = img.shape[:2]
    min_area = max(4.0, cfg.min_area_frac * H * W)
    if rois is None:
        boxes = [(0, 0, W, H)]
    else:
        boxes = []
        for x0, y0, x1, y1 in merge_boxes(np.asarray(rois, dtype=int).reshape(-1, 4)):
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W), min(y1, H)
            if x1 - x0 >= 3 and y1 - y0 >= 3:
                boxes.append((x0, y0, x1, y1))
    full = np.zeros((H, W), bool)
    if not boxes:
        return np.zeros((0, 2)), np.zeros(0), full
    # the boxes side by side in one image, 4 black columns apart (black is not magenta, and the
    # opening and 8-connectivity do not bridge 4 columns): every step runs once for all of them
    gap = 4
    starts = np.cumsum([0] + [x1 - x0 + gap for x0, _, x1, _ in boxes])[:-1]
    if len(boxes) == 1:
        x0, y0, x1, y1 = boxes[0]
        mosaic = img[y0:y1, x0:x1]
    else:
        mosaic = np.zeros(
            (max(y1 - y0 for _, y0, _, y1 in boxes), starts[-1] + boxes[-1][2] - boxes[-1][0], 3), np.uint8
        )
        for u, (x0, y0, x1, y1) in zip(starts, boxes, strict=True):
            mosaic[: y1 - y0, u : u + x1 - x0] = img[y0:y1, x0:x1]
    cent, area, mask = _blobs(mosaic, cfg, min_area, boxes, starts, (W, H))
    for u, (x0, y0, x1, y1) in zip(starts, boxes, strict=True):
        full[y0:y1, x0:x1] = mask[: y1 - y0, u : u + x1 - x0]
    return cent, area, full


def merge_boxes(boxes: np.ndarray) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1) with every overlapping group replaced by its bounding box."""
    out = [tuple(b) for b in np.asarray(boxes, dtype=int).tolist()]
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]:
                    out[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out


def _blobs(mosaic, cfg: MarkerConfig, min_area: float, boxes, starts, size):
    """Blobs of the boxes laid side by side in ``mosaic`` (box i from column starts[i]).

    Returns image centroids (n, 2), areas (n,) and the mosaic's cleaned mask. A blob within
    3 px of its box's edge is left out where that edge is inside the image (W, H) ``size``: the
    box may cut it.
    """
    hsv = cv2.cvtColor(mosaic, cv2.COLOR_RGB2HSV)
    lo, hi = cfg.hue_range
    mask = cv2.inRange(hsv, (lo, cfg.min_saturation, cfg.min_value), (hi, 255, 255))
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(mask, 8, cv2.CV_32S, cv2.CCL_GRANA)
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= min_area) + 1
    bx, by, bw, bh = (stats[keep, i] for i in range(4))
    box = np.searchsorted(starts, bx, side="right") - 1
    x0, y0, x1, y1 = np.array(boxes).T[:, box]
    u = np.asarray(starts)[box]
    m = 3  # the centre's weights reach this far beyond the blob
    cut = (
        ((x0 > 0) & (bx - u < m))
        | ((y0 > 0) & (by < m))
        | ((x1 < size[0]) & (bx + bw > u + x1 - x0 - m))
        | ((y1 < size[1]) & (by + bh > y1 - y0 - m))
    )
    keep, box, u = keep[~cut], box[~cut], u[~cut]
    if len(keep) == 0:
        return np.zeros((0, 2)), np.zeros(0), mask > 0
    cx, cy = _weighted_centres(hsv, labels, stats, keep, cfg)
    corner = np.array(boxes)[box]
    cent = np.stack([cx + corner[:, 0] - u, cy + corner[:, 1]], axis=1)
    return cent, stats[keep, cv2.CC_STAT_AREA].astype(np.float64), mask > 0


def _weighted_centres(hsv, labels, stats, keep, cfg: MarkerConfig) -> tuple[np.ndarray, np.ndarray]:
    """Centres of the blobs ``keep``, each weighted by saturation relative to its core's median.

    Each blob's weights cover the blob grown by two pixels, in the hue band (with a margin), at
    min(saturation / the median saturation of the blob, 1).
    """
    lo, hi = cfg.hue_range
    k = len(keep)
    x, y, w, h = (stats[keep, i] for i in range(4))
    # blobs whose grown areas may meet are done one by one; the others all at once
    ax0, ay0, ax1, ay1 = x - 2, y - 2, x + w + 2, y + h + 2
    meet = (ax0[:, None] < ax1[None]) & (ax0[None] < ax1[:, None]) & (ay0[:, None] < ay1[None])
    meet &= ay0[None] < ay1[:, None]
    np.fill_diagonal(meet, False)
    if meet.any():
        return _centres_one_by_one(hsv, labels, stats, keep, cfg)
    ids = np.zeros(labels.max() + 1, np.uint16)
    ids[keep] = np.arange(1, k + 1)
    core = np.take(ids, labels)
    grown = cv2.dilate(core, np.ones((5, 5), np.uint8))  # the blob's id over its grown area
    sat = hsv[..., 1]
    # each blob's median saturation over its core, by one sort
    on = core > 0
    lab, val = core[on], sat[on]
    order = np.lexsort((val, lab))
    val = val[order].astype(np.float64)
    cnt = np.bincount(lab, minlength=k + 1)[1:]
    first = np.cumsum(cnt) - cnt
    med = 0.5 * (val[first + (cnt - 1) // 2] + val[first + cnt // 2])
    idx = np.flatnonzero(grown)
    hue = hsv[..., 0].ravel()[idx].astype(np.int16)
    idx = idx[np.abs(2 * hue - (lo + hi)) <= 2 * (hi - lo)]  # in the hue band, with a margin
    g = grown.ravel()[idx]
    wgt = np.minimum(sat.ravel()[idx] / med[g - 1], 1.0)
    yy, xx = np.divmod(idx, hsv.shape[1])
    m00 = np.bincount(g, wgt, k + 1)[1:]
    return np.bincount(g, wgt * xx, k + 1)[1:] / m00, np.bincount(g, wgt * yy, k + 1)[1:] / m00


def _centres_one_by_one(hsv, labels, stats, keep, cfg: MarkerConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_weighted_centres`, blob by blob (for blobs whose grown areas may overlap)."""
    one = [_weighted_centres(hsv, labels, stats, keep[i : i + 1], cfg) for i in range(len(keep))]
    return np.concatenate([x for x, _ in one]), np.concatenate([y for _, y in one])


def assign_markers(predicted: dict[str, np.ndarray], centroids: np.ndarray, gate: float) -> dict[str, int]:
    """Greedy nearest assignment of blobs to markers, closest pairs first, each blob used once."""
    names = [m for m in predicted if np.all(np.isfinite(predicted[m]))]
    if not names or len(centroids) == 0:
        return {}
    P = np.array([predicted[m] for m in names])
    D = np.linalg.norm(P[:, None, :] - centroids[None, :, :], axis=2)
    nearest = D.argmin(axis=1)
    if len(set(nearest.tolist())) == len(names) and (D[np.arange(len(names)), nearest] <= gate).all():
        # every marker's nearest blob is its own: the greedy pass would give the same
        return {m: int(j) for m, j in zip(names, nearest, strict=True)}
    out: dict[str, int] = {}
    used = set()
    for flat in np.argsort(D, axis=None):
        i, j = np.unravel_index(flat, D.shape)
        if D[i, j] > gate:
            break
        if names[i] in out or j in used:
            continue
        out[names[i]] = int(j)
        used.add(int(j))
    return out


def body_rays(camera: OmniCamera, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), unit directions (n, 3)) of the rays through ``pixels``, body frame."""
    rays = camera.cam2world(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    T = camera.T_body_cam
    return T[:3, 3].copy(), rays @ T[:3, :3].T


def steering_ratio(a1: np.ndarray, a2: np.ndarray, b1: np.ndarray, b2: np.ndarray) -> float:
    """The paper's eq. (5): d(B1, A1) / d(B2, A2)."""
    return float(np.linalg.norm(b1 - a1) / np.linalg.norm(b2 - a2))


@dataclass(frozen=True)
class SteeringCalibration:
    """lambda as a function of the distance ratio x of eq. (5), per axle, from a steering sweep.

    The paper fits a 2nd-order polynomial. For this rover the ratio runs from 0.37 to 2.7 over
    +-30 deg and a quadratic misses by up to 5.8 deg, so the map is the swept table itself,
    interpolated in ln x (the ratio is 1/x for -lambda). Near full lock the inner tie-rod end
    passes closest to its plate marker and the ratio stops being monotonic: sweep only the
    range where it is (about +-24 deg here); the geometric steering of :func:`measure_axles`
    has no such limit.

    Attributes:
        ln_ratio: (axle, n) sorted ln x samples, axle order F, R.
        lam: (axle, n) lambda at those samples [rad].
    """

    ln_ratio: tuple[tuple[float, ...], tuple[float, ...]]
    lam: tuple[tuple[float, ...], tuple[float, ...]]

    @classmethod
    def fit(cls, ratios, lams) -> SteeringCalibration:
        """From swept (ratio, lambda) samples: ``ratios`` and ``lams`` are (2, n) arrays (F, R)."""
        x_out: list[tuple[float, ...]] = []
        l_out: list[tuple[float, ...]] = []
        for r, lam in zip(
            np.asarray(ratios, dtype=np.float64), np.asarray(lams, dtype=np.float64), strict=True
        ):
            lx = np.log(r)
            order = np.argsort(lx)
            lx, lam = lx[order], lam[order]
            if np.any(np.diff(lx) <= 0) or not (np.all(np.diff(lam) > 0) or np.all(np.diff(lam) < 0)):
                raise CalibrationError("steering sweep: the ratio is not monotonic in lambda; sweep finer")
            x_out.append(tuple(lx.tolist()))
            l_out.append(tuple(lam.tolist()))
        if len(x_out) != 2:
            raise CalibrationError(
                f"steering sweep: {len(x_out)} rows; give (2, n) arrays (front, rear axle)"
            )
        return cls((x_out[0], x_out[1]), (l_out[0], l_out[1]))

    def steering(self, axle: str, ratio: float) -> float:
        """Lambda [rad] of ``axle`` for distance ratio ``ratio`` (NaN outside the swept range)."""
        i = AXLES.index(axle)
        lx = math.log(ratio) if ratio > 0 else math.nan
        xs, ls = self.ln_ratio[i], self.lam[i]
        if not (xs[0] <= lx <= xs[-1]):
            return math.nan
        return float(np.interp(lx, xs, ls))

    def save(self, path: str | Path) -> Path:
        """Write ``ln_ratio_F, lam_F, ln_ratio_R, lam_R`` to YAML."""
        return write_mapping(
            path,
            {
                "ln_ratio_F": list(self.ln_ratio[0]),
                "lam_F": list(self.lam[0]),
                "ln_ratio_R": list(self.ln_ratio[1]),
                "lam_R": list(self.lam[1]),
            },
        )

    @classmethod
    def load(cls, path: str | Path) -> SteeringCalibration:
        """Read a file written by :meth:`save`; missing or unknown keys are errors that name them."""
        d = read_mapping(path, {"ln_ratio_F", "lam_F", "ln_ratio_R", "lam_R"}, set())
        try:
            arrs = {k: as_array(d[k], (-1,), k) for k in d}
            if any(
                len(arrs[f"ln_ratio_{a}"]) != len(arrs[f"lam_{a}"]) or len(arrs[f"lam_{a}"]) < 3
                for a in AXLES
            ):
                raise CalibrationError("ln_ratio_* and lam_* must have the same length, at least 3")
            return cls.fit(
                [np.exp(arrs["ln_ratio_F"]), np.exp(arrs["ln_ratio_R"])], [arrs["lam_F"], arrs["lam_R"]]
            )
        except CalibrationError as exc:
            raise CalibrationError(f"{path}: {exc}") from exc


@dataclass
class AxleMeasurement:
    """What the markers say about the axles in one frame.

    Attributes:
        pixels: Marker name -> measured centroid [px] (found markers only).
        points: Marker name -> body-frame position [m] (found markers only).
        psi: (psi_F, psi_R) [rad], NaN where the plate markers were not both found.
        depth: (d_F, d_R) [m], NaN likewise.
        delta: (4,) wheel steering angles [rad], NaN where a tie-rod marker is missing.
        lam: (lambda_F, lambda_R) [rad], NaN where neither tie-rod end of the axle was found.
    """

    pixels: dict[str, np.ndarray] = field(default_factory=dict)
    points: dict[str, np.ndarray] = field(default_factory=dict)
    psi: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    depth: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    delta: np.ndarray = field(default_factory=lambda: np.full(4, np.nan))
    lam: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))


def centroid_offsets(
    model: RoverKinematicModel, camera: OmniCamera, psi, depth, delta
) -> dict[str, np.ndarray]:
    """Image offset of each marker's blob centroid from the projection of its centre [px].

    A square seen obliquely through a fisheye does not have its centre at the centroid of its
    image. The image outline is the projected edge, sampled densely; its area centroid less the
    projected centre is the offset, for the given state.
    """
    return marker_projection(model, camera, psi, depth, delta)[1]


def marker_projection(
    model: RoverKinematicModel, camera: OmniCamera, psi, depth, delta
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(pixel of each marker's centre, :func:`centroid_offsets`) at a state [px]."""
    pos = model.marker_positions(psi, depth, delta)
    nrm = model.marker_normals(psi, delta)
    P = np.array([pos[m] for m in MARKERS])  # (8, 3)
    N = np.array([nrm[m] for m in MARKERS])
    T_cb = np.linalg.inv(model.T_body_cam)
    half = model.marker_size / 2
    s = np.linspace(-1.0, 1.0, 16, endpoint=False)
    one = np.ones(16)
    edge = np.concatenate([np.c_[s, -one], np.c_[one, s], np.c_[-s, one], np.c_[-one, -s]])  # (64, 2)
    U = np.stack([N[:, 1], -N[:, 0], np.zeros(len(N))], 1)  # N x z, in the face
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    V = np.cross(N, U)
    outline = P[:, None] + half * (edge[None, :, :1] * U[:, None] + edge[None, :, 1:] * V[:, None])
    pts = np.concatenate([outline, P[:, None]], axis=1)  # (8, 65, 3): outline, then the centre
    poly = camera.world2cam(pts @ T_cb[:3, :3].T + T_cb[:3, 3], refine=False)  # within 1e-5 px
    x, y = poly[:, :-1, 0], poly[:, :-1, 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * yn - xn * y
    area = cross.sum(axis=1) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.stack([((x + xn) * cross).sum(1), ((y + yn) * cross).sum(1)], 1) / (6 * area[:, None])
    off = c - poly[:, -1]
    off[~np.isfinite(off).all(axis=1)] = 0.0  # outside the field of view: no correction
    return {m: poly[i, -1] for i, m in enumerate(MARKERS)}, {m: off[i] for i, m in enumerate(MARKERS)}


def measure_axles(
    model: RoverKinematicModel,
    camera: OmniCamera,
    pixels: dict[str, np.ndarray],
    fallback_psi,
    fallback_depth,
    calibration: SteeringCalibration | None = None,
    refine: bool = True,
    offsets: dict[str, np.ndarray] | None = None,
) -> AxleMeasurement:
    """Axle roll, height and steering from marker pixels (eqs. 2-5).

    Args:
        model: Rover geometry.
        camera: The fisheye model (its ``T_body_cam`` is the mount).
        pixels: Found markers, name -> centroid [px].
        fallback_psi: Roll used for the tie-rod plane when an axle's plate markers are missing.
        fallback_depth: Likewise for the depth.
        calibration: Use the paper's distance ratio (eq. 5) through this map for lambda; by
            default lambda comes from the tie-rod ends' angles about their kingpins.
        refine: Measure once, then remove each blob's centroid offset (:func:`centroid_offsets`)
            predicted at that state and measure again.
        offsets: Centroid offsets [px] to remove instead, in one pass (e.g. those of the last
            state: they change by about 0.01 px per degree of roll or steering).
    """
    if offsets is not None:
        corrected = {m: np.asarray(p, dtype=np.float64) - offsets[m] for m, p in pixels.items()}
        out = _measure(model, camera, corrected, fallback_psi, fallback_depth, calibration)
        out.pixels = dict(pixels)
        return out
    first = _measure(model, camera, pixels, fallback_psi, fallback_depth, calibration)
    if not refine or not pixels:
        return first
    psi = np.where(np.isfinite(first.psi), first.psi, np.asarray(fallback_psi, dtype=np.float64))
    depth = np.where(np.isfinite(first.depth), first.depth, np.asarray(fallback_depth, dtype=np.float64))
    delta = np.where(np.isfinite(first.delta), first.delta, 0.0)
    off = centroid_offsets(model, camera, psi, depth, delta)
    corrected = {m: np.asarray(p, dtype=np.float64) - off[m] for m, p in pixels.items()}
    out = _measure(model, camera, corrected, psi, depth, calibration)
    out.pixels = dict(pixels)
    return out


def _hit(o, d, normal, point):
    """Ray o + t d (t > 0) with the plane normal . (r - point) = 0, on floats; None if it misses."""
    den = d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2]
    num = sum((point[i] - o[i]) * normal[i] for i in range(3))
    t = num / den if den != 0 else math.nan
    if not t > 0:
        return None
    return [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]]


def _measure(model, camera, pixels, fallback_psi, fallback_depth, calibration) -> AxleMeasurement:
    """Eqs. 2-5 for one set of marker pixels (see :func:`measure_axles`), on floats."""
    out = AxleMeasurement(pixels=dict(pixels))
    names = [m for m in MARKERS if m in pixels]
    if not names:
        return out
    origin, dirs = body_rays(camera, np.array([pixels[m] for m in names]))
    o = origin.tolist()
    ray = {m: d for m, d in zip(names, dirs.tolist(), strict=True) if all(math.isfinite(v) for v in d)}
    arms, ys = model.ackermann_arms()
    tip_z = float(model.arm_tip[2])
    for i, axle in enumerate(AXLES):
        p1, p2 = PLATE[axle]
        psi, depth = float(fallback_psi[i]), float(fallback_depth[i])
        x_plate = model.axle_sign(axle) * (model.axle_x - model.plate_offset)
        if p1 in ray and p2 in ray:
            m1 = _hit(o, ray[p1], (1.0, 0.0, 0.0), (x_plate, 0.0, 0.0))  # the plate plane
            m2 = _hit(o, ray[p2], (1.0, 0.0, 0.0), (x_plate, 0.0, 0.0))
            if m1 is not None and m2 is not None:
                out.points[p1], out.points[p2] = np.array(m1), np.array(m2)
                # eq. 2: index 1 is on the left (+y in the axle frame)
                psi = math.atan2(m1[2] - m2[2], m1[1] - m2[1])
                depth = -0.5 * (m1[2] + m2[2])
                out.psi[i], out.depth[i] = psi, depth
        # the roll-corrected tie-rod plane (eqs. 3-4): normal R_x(psi) z, at the tie-rod height
        c, s_ = math.cos(psi), math.sin(psi)
        normal = (0.0, -s_, c)
        centre = (model.axle_sign(axle) * model.axle_x, 0.0, -depth)
        point = (centre[0], centre[1] + tip_z * normal[1], centre[2] + tip_z * normal[2])
        for name, wheel in zip(ROD[axle], (axle + "L", axle + "R"), strict=True):
            if name not in ray:
                continue
            tip = _hit(o, ray[name], normal, point)
            if tip is None:
                continue
            out.points[name] = np.array(tip)
            k = WHEELS.index(wheel)
            # the tip's angle about the kingpin in the axle frame, less its angle at zero steering
            v = (tip[0] - centre[0], tip[1] - centre[1], tip[2] - centre[2])
            lx, ly = v[0], c * v[1] + s_ * v[2] - float(model.kingpin_local(wheel)[1])
            nominal = model.tip_knuckle(wheel)
            ang = math.atan2(ly, lx) - math.atan2(nominal[1], nominal[0])
            out.delta[k] = math.remainder(ang, 2 * math.pi)
        if calibration is not None:
            if all(m in out.points for m in (p1, p2, *ROD[axle])):
                r = steering_ratio(
                    out.points[p1], out.points[p2], out.points[ROD[axle][0]], out.points[ROD[axle][1]]
                )
                out.lam[i] = calibration.steering(axle, r)
            continue
        lams = []
        for k in (2 * i, 2 * i + 1):
            d = out.delta[k]
            if np.isfinite(d):
                lams.append(math.atan(arms[k] * math.tan(d) / (arms[k] + ys[k] * math.tan(d))))
        if lams:
            out.lam[i] = float(np.mean(lams))
    return out

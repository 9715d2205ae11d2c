"""Wheel rotation from the treads in the fisheye image (kinematics paper, section V-C).

Each wheel is a cylinder of the tread radius about its knuckle's y axis, placed by the axle roll,
height and steering. The paper follows tread features in an observation window around the tread
point facing the camera, intersects their rays with the cylinder and turns each feature's chord
into an arc angle (eq. 6). Here the window is the tread itself, unwrapped: a :class:`TreadStrip`
samples the image at cylinder points on a grid of (angle about the axle, position across the
tread), which is the ray-cylinder intersection done once for the whole window. In a strip a
wheel's rotation is a shift along the angle axis, whatever the roll, height and steering of
either frame, so that:

- the rotation between two frames is the shift that maximises the masked normalised
  cross-correlation of the two strips (:func:`align_strips`, all shifts at once by FFT), with a
  check that no other rotation fits nearly as well and that the strips overlap enough;
- the paper's features (Shi-Tomasi, pyramidal Lucas-Kanade forward and backward, eq. 6 per
  track, 1-D RANSAC) are tracked between the strips from that shift
  (:func:`track_strip_features`), where their motion is a translation, as Lucas-Kanade assumes.

The strips are band-passed on the tread surface so that shading and the levels of lit and
shadowed tread cancel, and the steps of shadow edges, which do not turn with the wheel, are
left out (the odometry paper's shadow-edge mask, applied to the treads).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from perception.cameras import OmniCamera
from perception.kinematics import RoverKinematicModel


@dataclass(frozen=True)
class TreadConfig:
    """Tread unwrapping and rotation measurement.

    Attributes:
        column_px: Strip column spacing: image pixels at the tread point facing the camera.
        rows: Strip rows across the tread.
        edge_margin: Tread edges left out [m].
        min_facing: Smallest cosine between the tread normal and the view direction of a cell
            (keeps away from the silhouette, where the tread is seen edge-on).
        fine: Band-pass: small Gaussian sigma on the tread [m] (removes pixel-scale flicker).
        coarse: Band-pass: large Gaussian sigma on the tread [m] (removes shading and light
            levels).
        min_step: Shadow-edge band: cells where the gradient of the log of the coarse image
            exceeds this [1/m]. The default catches the edges of the rover's shadow on its
            treads (light ratio about 3) and not the tread's own texture; without the band, a
            tenth of the frames of a drive with a low sun lose a wheel.
        min_level: Band-pass: the texture is divided by the local grey level, at least this.
        min_cells: Fewest overlapping valid cells for a shift to count.
        min_overlap: Fewest overlapping valid cells, as a share of the smaller strip's.
        min_ncc: Smallest correlation of the alignment for a valid rotation, when the tracked
            features confirm it ...
        strong_ncc: ... and when too few features are tracked to tell.
        min_override: Consistent features that outvote the alignment when they disagree with it.
        peak_separation: Rotations this far from the best one count as other candidates [rad].
        min_peak_margin: The best correlation must beat every other candidate's by this much.
        max_features: Shi-Tomasi features per strip.
        min_distance: Smallest feature spacing [cells].
        lk_window: Lucas-Kanade window [cells] (odd).
        fb_threshold: Largest forward-backward error [cells].
        ransac_tolerance: 1-D RANSAC inlier band [rad].
        min_inliers: Fewest consistent features for the features' rotation to count.
    """

    column_px: float = 0.7
    rows: int = 24
    edge_margin: float = 0.006
    min_facing: float = 0.3
    fine: float = 0.0025
    coarse: float = 0.011
    min_step: float = 45.0
    min_level: float = 8.0
    min_cells: int = 150
    min_overlap: float = 0.25
    min_ncc: float = 0.6
    strong_ncc: float = 0.75
    min_override: int = 10
    peak_separation: float = 0.1
    min_peak_margin: float = 0.08
    max_features: int = 25
    min_distance: float = 4.0
    lk_window: int = 7
    fb_threshold: float = 0.3
    ransac_tolerance: float = 0.01
    min_inliers: int = 4


def ray_cylinder(
    origin: np.ndarray, dirs: np.ndarray, R: np.ndarray, c: np.ndarray, radius: float, half_width: float
) -> tuple[np.ndarray, np.ndarray]:
    """First intersection of body-frame rays with a tread cylinder (axis: the frame's y).

    Args:
        origin: (3,) ray origin, body frame.
        dirs: (n, 3) unit directions, body frame.
        R: Rotation of the wheel's knuckle frame in the body frame.
        c: Wheel centre, body frame [m].
        radius: Tread radius [m].
        half_width: Half the tread width [m].

    Returns:
        (n, 3) hit points in the knuckle frame (NaN where the ray misses the tread) and (n,)
        bool hits.
    """
    o = R.T @ (origin - c)
    d = np.asarray(dirs, dtype=np.float64) @ R  # rows: R^T d
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[0] * d[:, 0] + o[2] * d[:, 2])
    cc = o[0] ** 2 + o[2] ** 2 - radius**2
    disc = b * b - 4 * a * cc
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)  # the near side: the tread surface facing the ray
    pts = o + t[:, None] * d
    hit = (disc > 0) & (t > 0) & (np.abs(pts[:, 1]) <= half_width)
    pts[~hit] = np.nan
    return pts, hit


def arc_angle(p1: np.ndarray, p2: np.ndarray, radius: float) -> np.ndarray:
    """Signed rotation about the wheel axis (+y) carrying tread points p1 to p2 (knuckle frame).

    |alpha| = acos((2 r^2 - |p1 - p2|^2) / (2 r^2)) (paper eq. 6, the chord measured in the wheel
    plane); the sign is that of (p1 x p2) . y.
    """
    q1 = p1[:, [0, 2]]
    q2 = p2[:, [0, 2]]
    chord2 = np.sum((q1 - q2) ** 2, axis=1)
    mag = np.arccos(np.clip((2 * radius**2 - chord2) / (2 * radius**2), -1.0, 1.0))
    # rotation about +y maps (x, z) -> (x cos + z sin, -x sin + z cos): (p1 x p2) . y = z1 x2 - x1 z2
    sign = np.sign(q1[:, 1] * q2[:, 0] - q1[:, 0] * q2[:, 1])
    return sign * mag


def ransac_1d(values: np.ndarray, tolerance: float) -> np.ndarray:
    """Largest set of values within ``tolerance`` of one of them (every value is tried: n <= ~50)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return np.zeros(0, dtype=bool)
    close = np.abs(v[:, None] - v[None, :]) <= tolerance
    return close[int(np.argmax(close.sum(axis=1)))]


def facing_angle(model: RoverKinematicModel, R: np.ndarray, c: np.ndarray) -> float:
    """Angle about the wheel axis (from the knuckle's +z, toward +x) of the tread point facing the camera."""
    cam = R.T @ (model.T_body_cam[:3, 3] - c)
    return math.atan2(cam[0], cam[2])


def tread_point(radius: float, phi, y) -> np.ndarray:
    """Knuckle-frame tread points (..., 3) at angles ``phi`` [rad] about the axle and ``y`` across [m]."""
    phi, y = np.broadcast_arrays(np.asarray(phi, dtype=np.float64), np.asarray(y, dtype=np.float64))
    return np.stack([radius * np.sin(phi), y, radius * np.cos(phi)], -1)


def strip_resolution(
    model: RoverKinematicModel, camera: OmniCamera, R: np.ndarray, c: np.ndarray, column_px: float
) -> float:
    """Angle step [rad] of strip columns that are ``column_px`` image pixels apart at the facing point."""
    phi = facing_angle(model, R, c)
    eps = 1e-3
    pts = tread_point(model.wheel_radius, np.array([phi - eps, phi + eps]), 0.0) @ R.T + c
    T_cb = np.linalg.inv(camera.T_body_cam)
    px = camera.world2cam(pts @ T_cb[:3, :3].T + T_cb[:3, 3])
    px_per_rad = float(np.linalg.norm(px[1] - px[0])) / (2 * eps)
    if not math.isfinite(px_per_rad) or px_per_rad <= 0:
        raise ValueError("the tread point facing the camera is outside the fisheye's field of view")
    return column_px / px_per_rad


@dataclass
class TreadStrip:
    """One wheel's tread in one frame, unwrapped onto (angle about the axle, position across).

    Column ``j`` is at angle ``(k0 + j) * dphi`` (from the knuckle's +z toward +x; a tread point
    at angle phi moves to phi + alpha when the wheel turns by alpha), row ``i`` at ``y[i]``.

    Attributes:
        k0: Index of the first column.
        dphi: Column step [rad].
        y: (rows,) positions across the tread, knuckle frame [m].
        pixels: (rows, cols, 2) float32 image pixel of every cell (-1 where none).
        visible: (rows, cols) cells on the tread, facing the camera, in the image, not behind the
            wheel's steering arm or tie-rod marker.
        valid: ``visible`` and not on a shadow-edge band: the cells the rotation uses.
        texture: (rows, cols) float32 band-passed grey level (0 where not valid).
    """

    k0: int
    dphi: float
    y: np.ndarray
    pixels: np.ndarray
    visible: np.ndarray
    valid: np.ndarray
    texture: np.ndarray

    @property
    def phi(self) -> np.ndarray:
        """(cols,) column angles [rad]."""
        return (self.k0 + np.arange(self.pixels.shape[1])) * self.dphi

    def sample(self, image: np.ndarray) -> np.ndarray:
        """The image (grey or colour) at every cell, bilinear (rows, cols[, channels])."""
        return cv2.remap(image, self.pixels[..., 0], self.pixels[..., 1], cv2.INTER_LINEAR)


def _masked_blur(img: np.ndarray, mask: np.ndarray, sigma: tuple[float, float]) -> np.ndarray:
    """Gaussian blur of ``img`` over the cells of ``mask`` only (normalised convolution)."""
    m = mask.astype(np.float32)
    num = cv2.GaussianBlur(img * m, (0, 0), sigmaX=sigma[0], sigmaY=sigma[1])
    den = cv2.GaussianBlur(m, (0, 0), sigmaX=sigma[0], sigmaY=sigma[1])
    return num / np.maximum(den, 1e-3)


def _band_pass(
    raw: np.ndarray, visible: np.ndarray, cell: tuple[float, float], cfg: TreadConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Tread texture without shading or pixel noise, and the band of strong steps to leave out.

    A difference of Gaussians on the tread surface (sigmas ``fine`` and ``coarse`` metres,
    over the visible cells only, so that the background beyond the silhouette does not bleed
    in), divided by the coarse level, keeps the speckle: the coarse blur removes smooth shading
    and the levels of lit and shadowed tread (light multiplies the albedo, so the ratio is the
    same in both), the fine one the pixel-scale flicker of a renderer's (or sensor's) sampling.
    Cells where the log of the coarse image changes faster than ``min_step`` are steps such as
    shadow edges, which do not turn with the wheel.

    Returns:
        (float32 band-passed strip, bool edge band).
    """
    fine = (cfg.fine / cell[0], cfg.fine / cell[1])
    coarse = (cfg.coarse / cell[0], cfg.coarse / cell[1])
    low = _masked_blur(raw, visible, coarse)
    # shading multiplies the tread's albedo: the texture relative to the local level is the same
    # lit or in shadow
    tex = (_masked_blur(raw, visible, fine) - low) / np.maximum(low, cfg.min_level)
    # shadow edges: steps of the log level (a shadow divides the light by the same factor on
    # dark and bright tread), in 1/m
    log_low = np.log(np.maximum(low, cfg.min_level))
    gx = cv2.Sobel(log_low, cv2.CV_32F, 1, 0, ksize=3) / (8 * cell[0])
    gy = cv2.Sobel(log_low, cv2.CV_32F, 0, 1, ksize=3) / (8 * cell[1])
    mag = cv2.magnitude(gx, gy)
    inner = cv2.erode(visible.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    # the band-passed image rings for about a coarse sigma on each side of a step
    grow = (2 * round(cfg.coarse / cell[0]) + 1, 2 * round(cfg.coarse / cell[1]) + 1)
    band = cv2.dilate(((mag > cfg.min_step) & inner).astype(np.uint8), np.ones(grow[::-1], np.uint8)) > 0
    return tex, band


def unwrap_tread(
    gray: np.ndarray,
    model: RoverKinematicModel,
    camera: OmniCamera,
    R: np.ndarray,
    c: np.ndarray,
    dphi: float,
    cfg: TreadConfig,
    wheel: str | None = None,
    shadow_robust: bool = True,
) -> TreadStrip | None:
    """The strip of one wheel's tread in a grey fisheye frame, or None if it is not in view.

    Args:
        gray: (H, W) uint8 grey frame.
        model: Rover geometry.
        camera: The fisheye model.
        R: The wheel's knuckle frame in the body frame (rotation).
        c: Its centre, body frame [m].
        dphi: Column step [rad] (:func:`strip_resolution`; keep it fixed between frames).
        cfg: Parameters.
        wheel: The wheel's name (FL, FR, RL, RR), to leave out its steering arm and tie-rod
            marker, which lie in front of the tread.
        shadow_robust: Band-pass the texture and leave out shadow edges; otherwise the texture
            is the grey level less its mean.
    """
    r = model.wheel_radius
    phi_c = facing_angle(model, R, c)
    reach = math.acos(cfg.min_facing)  # facing cells are within this of phi_c, and then some
    k0 = math.floor((phi_c - reach) / dphi)
    k1 = math.ceil((phi_c + reach) / dphi)
    phi = np.arange(k0, k1 + 1) * dphi
    hw = model.wheel_width / 2 - cfg.edge_margin
    y = np.linspace(-hw, hw, cfg.rows)
    sin, cos_ = np.sin(phi), np.cos(phi)
    origin = camera.T_body_cam[:3, 3]
    ck = R.T @ (origin - c)  # the camera in the knuckle frame
    # cosine between the tread normal (sin, 0, cos) and the view from (r sin, y, r cos) to ck,
    # from 1-D terms over columns (a) and rows (b)
    a = sin * ck[0] + cos_ * ck[2]
    b = y * y - 2 * y * ck[1]
    dist2 = (ck @ ck + r * r - 2 * r * a)[None, :] + b[:, None]
    facing = (a - r)[None, :] > cfg.min_facing * np.sqrt(np.maximum(dist2, 1e-12))
    cols = np.flatnonzero(facing.any(axis=0))
    if len(cols) == 0:
        return None
    sl = slice(cols[0], cols[-1] + 1)  # only the columns that face the camera
    sin, cos_, facing = sin[sl], cos_[sl], facing[:, sl]
    k0 += int(cols[0])
    # camera-frame points: t + M (r sin, y, r cos), summed from rank-one terms
    T_cb = np.linalg.inv(camera.T_body_cam)
    M = T_cb[:3, :3] @ R
    t = T_cb[:3, :3] @ c + T_cb[:3, 3]
    pts = (
        t
        + (r * sin)[None, :, None] * M[:, 0]
        + y[:, None, None] * M[:, 1]
        + (r * cos_)[None, :, None] * M[:, 2]
    )
    px = np.full(facing.shape + (2,), np.nan)
    # the inverse polynomial alone is within ~1e-5 px
    px[facing] = camera.world2cam(pts[facing], refine=False)
    w, h = camera.image_size
    visible = facing & (px[..., 0] >= 0) & (px[..., 0] <= w - 1) & (px[..., 1] >= 0) & (px[..., 1] <= h - 1)
    if wheel is not None:
        occ, radii = model.occluders(wheel, R, c)
        dist = np.linalg.norm(occ - origin, axis=1)
        opx = camera.world2cam((occ - origin) @ camera.T_body_cam[:3, :3], refine=False)
        scale = w / max(camera.max_fov, 1e-6)  # about px per radian
        tread_dist2 = np.einsum("...i,...i->...", pts, pts)  # the camera is the origin
        for (u, v), rad, d in zip(opx, radii, dist, strict=True):
            if np.isfinite(u):  # the part hides the cells behind it, within its image radius
                behind = tread_dist2 > d * d
                visible &= ~behind | (
                    (px[..., 0] - u) ** 2 + (px[..., 1] - v) ** 2 > (rad / d * scale + 2) ** 2
                )
    if visible.sum() < cfg.min_cells:
        return None
    cols = np.flatnonzero(visible.any(axis=0))
    sl = slice(cols[0], cols[-1] + 1)
    visible, px = visible[:, sl], px[:, sl]
    k0 += int(cols[0])
    px = np.where(visible[..., None], px, -1.0)
    px = px.astype(np.float32)
    raw = cv2.remap(gray, px[..., 0], px[..., 1], cv2.INTER_LINEAR).astype(np.float32)
    cell = (r * dphi, float(y[1] - y[0]))  # (column, row) size on the tread [m]
    if shadow_robust:
        tex, band = _band_pass(raw, visible, cell, cfg)
        valid = visible & ~band
    else:
        valid = visible.copy()
        tex = raw - float(raw[visible].mean())
    tex = np.where(valid, tex, np.float32(0.0)).astype(np.float32)
    return TreadStrip(k0, dphi, y, px, visible, valid, tex)


def masked_ncc(
    a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised cross-correlation of ``a`` against ``b`` shifted along columns, over weighted cells.

    For every lag s, the correlation of a[i, j] with b[i, j - s], each pair weighted by
    ma[i, j] mb[i, j - s] (bool masks or weights in [0, 1]; Padfield's masked NCC, summed over
    rows; all lags by FFT).

    Returns:
        (lags, ncc, overlap: the sum of the pair weights) for lags -(cols_b - 1) .. cols_a - 1.
    """
    na, nb = a.shape[1], b.shape[1]
    n = int(cv2.getOptimalDFTSize(na + nb - 1))
    ma, mb = ma.astype(np.float64), mb.astype(np.float64)
    a, b = a.astype(np.float64) * ma, b.astype(np.float64) * mb
    fa = np.fft.rfft(np.stack([ma, a, a * a]), n, axis=2)  # (3, rows, freq)
    fb = np.conj(np.fft.rfft(np.stack([mb, b, b * b]), n, axis=2))
    # sum over rows and j of x[j] y[j - s]: products of the transforms, summed over rows
    pairs = ((0, 0), (1, 0), (0, 1), (2, 0), (0, 2), (1, 1))
    prod = np.stack([(fa[i] * fb[k]).sum(axis=0) for i, k in pairs])
    corr = np.fft.irfft(prod, n, axis=1)
    lags = np.r_[np.arange(-(nb - 1), 0), np.arange(0, na)]
    idx = np.r_[np.arange(n - (nb - 1), n), np.arange(0, na)]
    cnt, sa, sb, saa, sbb, sab = corr[:, idx]
    with np.errstate(invalid="ignore", divide="ignore"):
        num = sab - sa * sb / cnt
        den = np.sqrt(np.clip(saa - sa * sa / cnt, 0, None) * np.clip(sbb - sb * sb / cnt, 0, None))
        ncc = np.where((cnt > 0.5) & (den > 1e-9 * np.maximum(cnt, 1)), num / den, -1.0)
    return lags, ncc, cnt


@dataclass
class Alignment:
    """Rotation between two strips by correlation.

    Attributes:
        alpha: Rotation [rad] (NaN if none is trustworthy).
        ncc: Correlation at alpha.
        margin: How far the best correlation stands above any other rotation's.
        overlap: Cells compared at alpha.
    """

    alpha: float
    ncc: float
    margin: float
    overlap: int


def align_strips(
    prev: TreadStrip, curr: TreadStrip, cfg: TreadConfig, centre: float = 0.0, span: float = 0.8
) -> Alignment:
    """Rotation [rad] carrying the tread of ``prev`` to that of ``curr``, within ``centre`` +- ``span``.

    Shifts where the strips overlap on fewer than ``min_cells`` cells, or on less than
    ``min_overlap`` of the smaller strip, are not candidates: a small overlap can correlate well
    by chance. The integer shift of best correlation is refined by a parabola; the result is
    NaN when another rotation, ``peak_separation`` away, correlates within ``min_peak_margin``.
    """
    if abs(prev.dphi - curr.dphi) > 1e-12 * max(prev.dphi, 1e-12):
        raise ValueError(f"strips with different column steps ({prev.dphi} and {curr.dphi} rad)")
    lags, ncc, cnt = masked_ncc(curr.texture, curr.valid, prev.texture, prev.valid)
    shift = lags + (curr.k0 - prev.k0)  # in columns of the common grid: alpha = shift * dphi
    alpha = shift * curr.dphi
    need = max(cfg.min_cells, cfg.min_overlap * min(curr.valid.sum(), prev.valid.sum()))
    cand = (np.abs(alpha - centre) <= span) & (cnt >= need)
    if not cand.any():
        return Alignment(math.nan, math.nan, 0.0, 0)
    score = np.where(cand, ncc, -np.inf)
    k = int(np.argmax(score))
    others = cand & (np.abs(alpha - alpha[k]) > cfg.peak_separation)
    margin = float(ncc[k] - ncc[others].max()) if others.any() else 1.0
    best = float(alpha[k])
    if 0 < k < len(ncc) - 1 and cand[k - 1] and cand[k + 1]:
        y0, y1, y2 = ncc[k - 1], ncc[k], ncc[k + 1]
        den = y0 - 2 * y1 + y2
        if den < 0:
            best += float(np.clip(0.5 * (y0 - y2) / den, -1, 1)) * curr.dphi
    if margin < cfg.min_peak_margin:  # two rotations fit about as well: do not guess
        return Alignment(math.nan, float(ncc[k]), margin, int(round(cnt[k])))
    return Alignment(best, float(ncc[k]), margin, int(round(cnt[k])))


@dataclass
class RotationMeasurement:
    """Rotation of one wheel between two frames.

    Attributes:
        alpha: Rotation about the wheel axis [rad] (NaN if not measured).
        n_features: Features selected in the earlier strip.
        n_tracked: Features kept by the forward-backward check and on the tread in both frames.
        n_inliers: Features in the largest consistent set.
        valid: Whether alpha can be trusted.
        ncc: Correlation of the alignment (NaN if none).
    """

    alpha: float
    n_features: int
    n_tracked: int
    n_inliers: int
    valid: bool
    ncc: float = math.nan


def _to_u8(texture: np.ndarray, valid: np.ndarray) -> np.ndarray:
    scale = 40.0 / max(float(texture[valid].std()) if valid.any() else 1.0, 1e-3)
    return np.clip(128.0 + scale * texture, 0, 255).astype(np.uint8)


def track_strip_features(
    prev: TreadStrip, curr: TreadStrip, radius: float, cfg: TreadConfig, alpha_prior: float = 0.0
) -> RotationMeasurement:
    """The paper's tread features between two strips: Shi-Tomasi, LK both ways, eq. 6, 1-D RANSAC.

    Features are chosen on the earlier strip's valid cells that, turned by ``alpha_prior``
    [rad], land on the later strip's, and searched there from that position; tracks whose
    backward track misses the start by more than ``fb_threshold`` cells, or that leave the valid
    cells, are dropped. Each track's two cells are cylinder points; their chord gives the arc
    angle of eq. (6). The rotation is the mean of the largest consistent set.
    """
    none = RotationMeasurement(math.nan, 0, 0, 0, False)
    # features only where, turned by the prior, they land on the later strip's valid cells
    cols = np.rint(prev.k0 + np.arange(prev.valid.shape[1]) + alpha_prior / prev.dphi).astype(int) - curr.k0
    inside = (cols >= 0) & (cols < curr.valid.shape[1])
    lands = np.zeros_like(prev.valid)
    lands[:, inside] = curr.valid[:, cols[inside]]
    # and with their whole Lucas-Kanade window on valid cells
    win = np.ones((3, 3), np.uint8)
    mask = cv2.erode((prev.valid & lands).astype(np.uint8), win)
    if not mask.any():
        return none
    # both strips on one column grid (Lucas-Kanade takes images of one size)
    k0 = min(prev.k0, curr.k0)
    n = max(prev.k0 + prev.texture.shape[1], curr.k0 + curr.texture.shape[1]) - k0

    def canvas(strip: TreadStrip) -> np.ndarray:
        out = np.full((strip.texture.shape[0], n), 128, np.uint8)
        j = strip.k0 - k0
        out[:, j : j + strip.texture.shape[1]] = _to_u8(strip.texture, strip.valid)
        return out

    a8, b8 = canvas(prev), canvas(curr)
    off_a, off_b = prev.k0 - k0, curr.k0 - k0
    pts = cv2.goodFeaturesToTrack(
        a8[:, off_a : off_a + mask.shape[1]], cfg.max_features, 0.01, cfg.min_distance, mask=mask, blockSize=5
    )
    if pts is None:
        return none
    p0 = pts.reshape(-1, 2).astype(np.float32) + np.float32((off_a, 0.0))
    guess = p0 + np.float32((alpha_prior / prev.dphi, 0.0))
    lk = dict(
        winSize=(cfg.lk_window, cfg.lk_window),
        maxLevel=0,  # the search starts at the aligned rotation, within a cell or so
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
    )
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        a8,
        b8,
        p0.reshape(-1, 1, 2),
        guess.reshape(-1, 1, 2).copy(),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        **lk,
    )
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(
        b8, a8, p1, p0.reshape(-1, 1, 2).copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
    )
    p1, pb = p1.reshape(-1, 2), pb.reshape(-1, 2)
    fb = np.linalg.norm(pb - p0, axis=1)
    p0 -= np.float32((off_a, 0.0))  # back to each strip's own columns
    p1 -= np.float32((off_b, 0.0))
    j, i = np.rint(np.nan_to_num(p1, nan=-1.0)).astype(int).T
    inside = (j >= 0) & (j < curr.valid.shape[1]) & (i >= 0) & (i < curr.valid.shape[0])
    on = np.zeros(len(p1), dtype=bool)
    on[inside] = curr.valid[i[inside], j[inside]]
    keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_threshold) & on
    n_feat, n_kept = len(p0), int(keep.sum())
    if n_kept < cfg.min_inliers:
        return RotationMeasurement(math.nan, n_feat, n_kept, 0, False)

    def cylinder(strip: TreadStrip, p: np.ndarray) -> np.ndarray:
        phi = (strip.k0 + p[:, 0].astype(np.float64)) * strip.dphi
        y = np.interp(p[:, 1], np.arange(len(strip.y)), strip.y)
        return tread_point(radius, phi, y)

    alpha = arc_angle(cylinder(prev, p0[keep]), cylinder(curr, p1[keep]), radius)
    inl = ransac_1d(alpha, cfg.ransac_tolerance)
    n_in = int(inl.sum())
    valid = n_in >= cfg.min_inliers
    return RotationMeasurement(float(alpha[inl].mean()) if valid else math.nan, n_feat, n_kept, n_in, valid)


def measure_strips(
    prev: TreadStrip | None,
    curr: TreadStrip | None,
    radius: float,
    cfg: TreadConfig,
    alpha_prior: float = 0.0,
    span: float = 0.8,
) -> RotationMeasurement:
    """Rotation of one wheel between two strips [rad], with its validity.

    The rotation is the strips' alignment (:func:`align_strips`, searched around ``alpha_prior``
    +- ``span``): on rendered treads the per-feature arc angles of the paper scatter by a few
    per cent, while the alignment is within 0.5 %. It is valid when no other rotation fits nearly
    as well and either the paper's features (:func:`track_strip_features`, started at the
    aligned rotation) confirm it with a correlation of at least ``min_ncc``, or too few features
    are tracked to tell and the correlation is at least ``strong_ncc``. When at least
    ``min_override`` consistent features settle on another rotation, theirs is taken.
    """
    if prev is None or curr is None:
        return RotationMeasurement(math.nan, 0, 0, 0, False)
    al = align_strips(prev, curr, cfg, alpha_prior, span)
    if not (math.isfinite(al.alpha) and al.ncc >= cfg.min_ncc):
        return RotationMeasurement(math.nan, 0, 0, 0, False, al.ncc)
    feats = track_strip_features(prev, curr, radius, cfg, al.alpha)
    agree = feats.valid and abs(feats.alpha - al.alpha) <= cfg.ransac_tolerance
    if agree or (al.ncc >= cfg.strong_ncc and not feats.valid):
        # two readings of the tread that agree, or a strong correlation and too few tracks to tell
        return RotationMeasurement(al.alpha, feats.n_features, feats.n_tracked, feats.n_inliers, True, al.ncc)
    if feats.valid and feats.n_inliers >= cfg.min_override:
        # many tracks, started at the aligned rotation, settle on another: a shadow or a change of
        # light has pulled the correlation; the tracks follow the tread itself
        return RotationMeasurement(
            feats.alpha, feats.n_features, feats.n_tracked, feats.n_inliers, True, al.ncc
        )
    return RotationMeasurement(math.nan, feats.n_features, feats.n_tracked, 0, False, al.ncc)


def measure_rotation(
    prev_gray: np.ndarray,
    curr_gray: np.ndarray,
    model: RoverKinematicModel,
    camera: OmniCamera,
    prev_frame: tuple[np.ndarray, np.ndarray],
    curr_frame: tuple[np.ndarray, np.ndarray],
    cfg: TreadConfig,
    alpha_prior: float = 0.0,
    span: float = 0.8,
    wheel: str | None = None,
    shadow_robust: bool = True,
) -> RotationMeasurement:
    """Rotation of one wheel between two grey fisheye frames [rad], with its validity.

    Both treads are unwrapped (:func:`unwrap_tread`), then measured by :func:`measure_strips`.

    Args:
        prev_gray: (H, W) uint8 grey earlier frame.
        curr_gray: The later one.
        model: Rover geometry.
        camera: The fisheye model.
        prev_frame: (R, centre) of the wheel's knuckle frame at the earlier frame (body frame).
        curr_frame: The same at the later frame.
        cfg: Parameters.
        alpha_prior: Expected rotation [rad] (e.g. the last one).
        span: Half-width of the search around it [rad].
        wheel: The wheel's name, to leave out its steering arm and tie-rod marker.
        shadow_robust: See :func:`unwrap_tread`.
    """
    dphi = strip_resolution(model, camera, *curr_frame, cfg.column_px)
    strips = [
        unwrap_tread(g, model, camera, *f, dphi, cfg, wheel, shadow_robust)
        for g, f in ((prev_gray, prev_frame), (curr_gray, curr_frame))
    ]
    return measure_strips(*strips, model.wheel_radius, cfg, alpha_prior, span)

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

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from perception.models.cameras import OmniCamera
from perception.models.rover import RoverKinematicModel


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
        boundary: Cells (columns, rows) left out along the edge of the visible tread, where a
            cell's bilinear sample and the fine blur reach past the silhouette, an occluding part
            or the tread's edge into pixels that do not turn with the wheel. On two field-camera
            drives of the loose slope (train preset, 320x240, first 20 s), with ``clip``, the
            wheel rates' error fell from 0.16 to 0.135 rad/s (MAE) and the share of valid
            rotations rose from 0.94 to 0.97; the wheels seen obliquely in the turns gained most.
        clip: The band-passed texture is clipped at this many of its RMS (0: off), so that a
            few bright specks (a marker's edge, a glint) do not outweigh the tread's speckle in
            the correlation.
        noise_cells: Scale of a rotation's standard deviation (:meth:`RotationMeasurement.std`):
            at zero correlation, one column step over this many overlapping cells. Fitted on
            4,652 rotations of two loose-slope drives with field cameras (train preset, 0.5-9
            rad/s, correlations 0.45-0.98 on 150-1,300 cells), where the observed RMS error was
            0.84-1.3 times the model's in every bin of correlation and overlap with 50 or more
            samples; the error scales with 1 / overlap rather than 1 / sqrt(overlap), as a wheel
            seen obliquely shows fewer cells and each of them less of the texture.
        min_cells: Fewest overlapping valid cells for a shift to count.
        min_overlap: Fewest overlapping valid cells, as a share of the smaller strip's.
        min_ncc: Smallest correlation of the alignment for a valid rotation, when the tracked
            features confirm it ...
        strong_ncc: ... and without them (see ``check_strong``).
        check_strong: Track the features also when the correlation is at least ``strong_ncc``,
            so that they may reject or replace it. Off by default for a wheel being tracked
            (the search spans ``track_span`` around its last rotation): on rendered drives
            (rough ground, low sun, 0.5-2 m/s) they changed 3 of 9,093 such alignments,
            rejecting all three though each was within 1.6 % of the true rotation, and they
            cost about a fifth of the estimator's time. A wheel searched for after a loss is
            always confirmed by them (:class:`KinematicStateEstimator`): over the wide span a
            strong false peak on a small overlap is possible (dataset 3 of Table I, 169.3 s:
            NCC 0.77 on 231 cells, 0.38 rad off).
        decisive_ncc: A tracked wheel's alignment is also taken without the features when its
            correlation is at least this ...
        decisive_margin: ... and it beats every other rotation's by at least this. At 320x240
            the correlation of a wheel turning 0.4-0.6 rad per frame falls to 0.45-0.7 (the
            same tread is seen at other angles) and the features often fail to confirm it; on
            rendered drives (train preset, 2,900 alignments) every alignment with a margin of
            at least 0.2 was within 0.033 rad of the truth, and all that were off by more than
            0.05 rad had margins below 0.2.
        prior_ncc: A tracked wheel's alignment is also taken without the features when its
            correlation is at least this ...
        prior_tolerance: ... and it lies within this of the predicted rotation [rad] (the prior
            passed in: for a tracked wheel, its last rotation per frame carried on at its last
            change, :class:`~perception.kinematics.fisheye.KinematicStateEstimator`). A wheel
            spinning up or braking on sand turns 0.3-0.6 rad per frame at 30 Hz, where the
            correlation falls to 0.5-0.7 and the features rarely confirm it; on rendered slip
            drives (train preset, about 6,000 alignments) every alignment taken by this rule
            was within 0.033 rad of the true rotation; the false peaks seen there (the tread's
            shading, which does not turn) lay near zero rotation, 0.2 rad or more from it.
        static_band: An alignment less than this from zero rotation [rad] (0: off) and farther than
            ``prior_tolerance`` from the predicted rotation must be confirmed by the features
            (as ``check`` 2): the tread's shading and the shadows on it do not turn with the
            wheel and can fit there. On a rendered low-sun drive (shadow mission, wheel at 0.23
            rad per frame) the rules above took such peaks (NCC 0.45-0.5, margin 0.2-0.25) at
            -0.03 to 0.
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
    boundary: tuple[int, int] = (1, 1)
    clip: float = 2.5
    noise_cells: float = 375.0
    min_cells: int = 150
    min_overlap: float = 0.25
    min_ncc: float = 0.6
    strong_ncc: float = 0.75
    check_strong: bool = False
    decisive_ncc: float = 0.45
    decisive_margin: float = 0.2
    prior_ncc: float = 0.5
    prior_tolerance: float = 0.03
    static_band: float = 0.04
    min_override: int = 10
    peak_separation: float = 0.1
    min_peak_margin: float = 0.08
    max_features: int = 25
    min_distance: float = 4.0
    lk_window: int = 7
    fb_threshold: float = 0.3
    ransac_tolerance: float = 0.01
    min_inliers: int = 4

    def __post_init__(self) -> None:
        b = self.boundary
        if not (len(b) == 2 and all(isinstance(v, int) and v >= 0 for v in b)):
            raise ValueError(f"TreadConfig.boundary: {b!r}; give (columns, rows), integers >= 0")
        if not (math.isfinite(self.clip) and self.clip >= 0):
            raise ValueError(f"TreadConfig.clip: {self.clip!r} must be finite and >= 0 (0: off)")
        if not (math.isfinite(self.noise_cells) and self.noise_cells > 0):
            raise ValueError(f"TreadConfig.noise_cells: {self.noise_cells!r} must be finite and > 0")


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
            rover's steering arms or tie-rod markers.
        valid: ``visible`` less its outline (``TreadConfig.boundary``) and the shadow-edge
            band: the cells the rotation uses.
        texture: (rows, cols) float32 band-passed grey level (0 where not valid).
    """

    k0: int
    dphi: float
    y: np.ndarray
    pixels: np.ndarray
    visible: np.ndarray
    valid: np.ndarray
    texture: np.ndarray
    # row spectra of (valid, texture, texture^2) for the correlation, kept for the next frame
    _spectrum: tuple | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def n_valid(self) -> int:
        """Number of valid cells."""
        return int(np.count_nonzero(self.valid))

    @property
    def phi(self) -> np.ndarray:
        """(cols,) column angles [rad]."""
        return (self.k0 + np.arange(self.pixels.shape[1])) * self.dphi

    def sample(self, image: np.ndarray) -> np.ndarray:
        """The image (grey or colour) at every cell, bilinear (rows, cols[, channels])."""
        return cv2.remap(image, self.pixels[..., 0], self.pixels[..., 1], cv2.INTER_LINEAR)


@functools.lru_cache(maxsize=16)
def _gaussian(sigma: float) -> np.ndarray:
    """The 1-D kernel cv2.GaussianBlur uses on float images for ``sigma`` (4 sigma each side)."""
    return cv2.getGaussianKernel(int(round(sigma * 8 + 1)) | 1, sigma, cv2.CV_32F)


def _masked_blur(img: np.ndarray, mask: np.ndarray, sigma: tuple[float, float]) -> np.ndarray:
    """Gaussian blur of ``img`` (zero off the mask) over the cells of ``mask`` only.

    Normalised convolution, zero beyond the array; cv2.GaussianBlur's kernels applied by
    sepFilter2D (the same result, in half the time).
    """
    kx, ky = _gaussian(float(sigma[0])), _gaussian(float(sigma[1]))
    both = np.empty(img.shape + (2,), np.float32)  # image and mask as two channels: one call
    both[..., 0], both[..., 1] = img, mask
    out = cv2.sepFilter2D(both, -1, kx, ky, borderType=cv2.BORDER_CONSTANT)
    return out[..., 0] / np.maximum(out[..., 1], 1e-3)


def _band_reach(cell: tuple[float, float], cfg: TreadConfig) -> int:
    """Columns the band-pass reaches (its largest kernel's radius, with a margin)."""
    return math.ceil(4 * cfg.coarse / cell[0]) + 2


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
    lev = np.maximum(low, np.float32(cfg.min_level))
    tex = (_masked_blur(raw, visible, fine) - low) / lev
    # shadow edges: steps of the log level (a shadow divides the light by the same factor on
    # dark and bright tread), in 1/m
    log_low = np.log(lev)
    gx = cv2.Sobel(log_low, cv2.CV_32F, 1, 0, ksize=3, scale=1 / (8 * cell[0]))
    gy = cv2.Sobel(log_low, cv2.CV_32F, 0, 1, ksize=3, scale=1 / (8 * cell[1]))
    inner = cv2.erode(visible.astype(np.uint8), np.ones((3, 3), np.uint8))
    # the band-passed image rings for about a coarse sigma on each side of a step
    grow = (2 * round(cfg.coarse / cell[0]) + 1, 2 * round(cfg.coarse / cell[1]) + 1)
    step = (cv2.magnitude(gx, gy) > cfg.min_step).view(np.uint8) & inner
    band = cv2.dilate(step, np.ones(grow[::-1], np.uint8)) > 0
    return tex, band


class StaticPattern:
    """What stays put on the treads while they turn, learnt per wheel and taken out of the strips.

    A rotation is found by correlating two frames' strips; whatever does not turn with the wheel
    correlates at zero rotation and competes with the tread's own peak: the shadows of the
    rover's arms and body on the treads, shading the band-pass leaves, a renderer's or a
    lens's fixed artefacts, a sensor's fixed pattern. On rendered drives with a low sun such a
    pattern held 20-65 % of the front treads' band-passed variance, and a tenth of the shadow
    mission's frames lost a wheel to it.

    Each wheel keeps, for every cell fixed to its knuckle (column ``k0 + j`` of the common
    column step, row ``i``), running means of the band-passed texture and of its square, fed
    only from frames in which the wheel was measured turning by at least ``min_rotation``: the
    tread's own texture then averages out and what stays is the static pattern. Its estimate
    still holds a share ``rate / (2 - rate)`` of the texture's variance (an exponential mean of
    weight ``rate``), so it is shrunk where it is not clearly above that: the pattern is
    ``g * mean`` with ``g = max(0, 1 - shrink * residual / mean^2)`` (both terms averaged over
    ``box`` cells), zero until a cell has ``min_frames`` samples. It is taken out as strongly
    as the strip shows it (its least-squares scale in the strip, 0 to 1.5): a black or flat
    strip has none of it and keeps no texture, and light that dims or deepens the shadows
    scales it.

    Args:
        n_wheels: Wheels (4).
        rows: Strip rows (``TreadConfig.rows``).
        columns: Columns of a full turn at the column step (cells are indexed modulo this).
        rate: Weight of a new frame in the running means (0-1; after the first 1/rate frames,
            which are averaged evenly).
        min_rotation: Smallest rotation of the wheel in a frame [rad] for the frame to count.
        min_frames: Samples a cell needs before its pattern is taken out.
        shrink: Multiple of the estimate's expected residual texture a pattern must exceed.
        box: (columns, rows) of the local averages of the shrinkage.
    """

    MAX_SCALE = 1.5  # the largest least-squares scale of the pattern in a strip

    def __init__(
        self,
        n_wheels: int,
        rows: int,
        columns: int,
        rate: float = 0.25,
        min_rotation: float = 0.08,
        min_frames: int = 5,
        shrink: float = 2.0,
        box: tuple[int, int] = (5, 3),
    ) -> None:
        if not 0.0 < rate <= 1.0:
            raise ValueError(f"rate={rate!r}: use a weight in (0, 1]")
        self.rate, self.min_rotation, self.min_frames = float(rate), float(min_rotation), int(min_frames)
        self.shrink, self.box, self.columns = float(shrink), box, int(columns)
        self._mean = np.zeros((n_wheels, rows, columns), np.float32)
        self._sq = np.zeros_like(self._mean)
        self._n = np.zeros((n_wheels, rows, columns), np.int32)

    def reset(self) -> None:
        """Forget every pattern."""
        self._mean[:] = 0.0
        self._sq[:] = 0.0
        self._n[:] = 0

    def _cols(self, strip: TreadStrip) -> np.ndarray:
        return (strip.k0 + np.arange(strip.texture.shape[1])) % self.columns

    def remove(self, k: int, strip: TreadStrip | None) -> TreadStrip | None:
        """Wheel ``k``'s strip with its learnt static pattern taken out of the valid cells."""
        if strip is None:
            return None
        cols = self._cols(strip)
        n = self._n[k][:, cols]
        ready = strip.valid & (n >= self.min_frames)
        if not ready.any():
            return strip
        mean = self._mean[k][:, cols]
        resid = np.maximum(self._sq[k][:, cols] - mean * mean, 0.0) * (self.rate / (2.0 - self.rate))
        e_mean = cv2.blur(mean * mean, self.box)
        e_resid = cv2.blur(resid, self.box)
        g = np.clip(1.0 - self.shrink * e_resid / np.maximum(e_mean, 1e-12), 0.0, 1.0)
        pattern = np.where(ready, g * mean, 0.0)
        # as strong as this strip shows it (least squares): a black or flat strip has none, and
        # light that dims or deepens the shadows scales it
        pp = float(np.sum(pattern * pattern))
        if pp <= 0.0:
            return strip
        scale = min(max(float(np.sum(strip.texture * pattern)) / pp, 0.0), self.MAX_SCALE)
        tex = (strip.texture - scale * pattern).astype(np.float32)
        return TreadStrip(strip.k0, strip.dphi, strip.y, strip.pixels, strip.visible, strip.valid, tex)

    def learn(self, k: int, strip: TreadStrip | None, rotation: float) -> None:
        """Feed wheel ``k``'s raw strip (before :meth:`remove`), measured turning by ``rotation`` [rad]."""
        if strip is None or not abs(rotation) >= self.min_rotation:
            return
        cols = self._cols(strip)
        v = strip.valid
        n = self._n[k][:, cols] + v
        w = np.where(v, np.maximum(1.0 / np.maximum(n, 1), self.rate), 0.0).astype(np.float32)
        t = strip.texture
        mean, sq = self._mean[k][:, cols], self._sq[k][:, cols]
        self._mean[k][:, cols] = mean + w * (t - mean)
        self._sq[k][:, cols] = sq + w * (t * t - sq)
        self._n[k][:, cols] = n


@functools.lru_cache(maxsize=8)
def _row_interpolation(rows: int, hw: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(strip rows across the tread [m], five nodes [m], (rows, 5) quartic interpolation to the rows)."""
    nodes = np.linspace(-hw, hw, 5)
    y = np.linspace(-hw, hw, rows)
    vander = np.polynomial.polynomial.polyvander
    y.flags.writeable = nodes.flags.writeable = False  # shared between calls
    return y, nodes, vander(y / hw, 4) @ np.linalg.inv(vander(nodes / hw, 4))


def facing_columns(dphi: float, cfg: TreadConfig) -> int:
    """Columns of the grid searched for tread facing the camera: every strip is at most this wide."""
    return 2 * math.ceil(math.acos(cfg.min_facing) / dphi) + 3


def unwrap_treads(
    gray: np.ndarray | Callable[[int, int, int, int], np.ndarray],
    model: RoverKinematicModel,
    camera: OmniCamera,
    frames: list[tuple[np.ndarray, np.ndarray]],
    dphi: float,
    cfg: TreadConfig,
    wheels: list[str] | None = None,
    shadow_robust: bool = True,
) -> list[TreadStrip | None]:
    """The strips of several wheels' treads in one grey fisheye frame (None for a wheel not in view).

    All wheels go through each step together: one projection of every cell, one occlusion
    raster, one resampling and one band-pass of the strips side by side in a single image, with
    gaps wider than the band-pass's reach between them.

    Args:
        gray: (H, W) grey frame: uint8, or float32 linear levels (:func:`linear_gray`); or a
            function of a rectangle (x0, y0, x1, y1) [px, end exclusive] that returns the
            frame's levels there (each strip is sampled from the rectangle that holds it).
        model: Rover geometry.
        camera: The fisheye model.
        frames: (R, c) of each wheel's knuckle frame in the body frame (rotation, centre [m]).
        dphi: Column step [rad] (:func:`strip_resolution`; keep it fixed between frames).
        cfg: Parameters.
        wheels: The wheels' names (FL, FR, RL, RR), to leave out the cells hidden behind the
            rover's steering arms and tie-rod markers, which lie in front of the treads.
        shadow_robust: Band-pass the texture and leave out shadow edges; otherwise the texture
            is the grey level less its mean.
    """
    n = len(frames)
    if n == 0:
        return []
    r = model.wheel_radius
    ncol = facing_columns(dphi, cfg)
    hw = model.wheel_width / 2 - cfg.edge_margin
    y = _row_interpolation(cfg.rows, hw)[0]
    Rs = np.array([f[0] for f in frames], dtype=np.float64)
    cs = np.array([f[1] for f in frames], dtype=np.float64)
    T = camera.T_body_cam
    origin, Rbc = T[:3, 3], T[:3, :3]
    ck = np.einsum("kij,ki->kj", Rs, origin - cs)  # the camera in each knuckle frame
    phi_c = np.arctan2(ck[:, 0], ck[:, 2])  # the tread point facing the camera
    k0 = np.floor((phi_c - math.acos(cfg.min_facing)) / dphi).astype(int) - 1
    phi = (k0[:, None] + np.arange(ncol)) * dphi
    sin, cos_ = np.sin(phi), np.cos(phi)
    # camera-frame cells: A (a column's point at y = 0) + y M[:, 1], one coordinate at a time
    M = np.einsum("ji,kjl->kil", Rbc, Rs)  # Rbc^T R_k
    t = (cs - origin) @ Rbc
    A = t[:, :, None] + (r * sin)[:, None, :] * M[:, :, :1] + (r * cos_)[:, None, :] * M[:, :, 2:]
    # each column's cells lie on a line across the tread, whose image is smooth: project five
    # of them and interpolate the rest by the quartic through them (within 1e-4 px)
    _, nodes, lagrange = _row_interpolation(cfg.rows, hw)
    X, Y, Z = (A[:, i, None, :] + nodes[None, :, None] * M[:, i, 1, None, None] for i in range(3))
    nu, nv = camera.project_xyz(X, Y, Z)  # (n, 5, ncol)
    w, h = camera.image_size
    # cosine between the tread normal (sin, 0, cos) and the view from (r sin, y, r cos) to ck,
    # from 1-D terms over columns (a) and rows (b)
    a = sin * ck[:, :1] + cos_ * ck[:, 2:]
    b = y * y - 2 * y * ck[:, 1:2]
    dist2 = (np.einsum("ki,ki->k", ck, ck)[:, None] + r * r - 2 * r * a)[:, None, :] + b[:, :, None]
    facing = (a - r)[:, None, :] > cfg.min_facing * np.sqrt(np.maximum(dist2, 1e-12))
    pu, pv = lagrange @ nu, lagrange @ nv  # (n, rows, ncol)
    with np.errstate(invalid="ignore"):
        visible = facing & (pu >= 0) & (pu <= w - 1) & (pv >= 0) & (pv <= h - 1)
    grid = np.stack([np.where(visible, pu, -1.0), np.where(visible, pv, -1.0)], -1).astype(np.float32)
    if wheels is not None:
        # squared distance from the camera: |A + y m|^2 with m = M[:, :, 1] a unit vector
        am = np.einsum("kic,ki->kc", A, M[:, :, 1])
        dist2 = (
            np.einsum("kic,kic->kc", A, A)[:, None, :] + 2 * y[:, None] * am[:, None, :] + (y * y)[:, None]
        )
        hidden = _occluded(model, camera, frames, wheels, dist2, grid)
        visible &= ~hidden
        grid[hidden] = -1.0
    strips: list[TreadStrip | None] = [None] * n
    keep = []
    cols_seen = visible.any(axis=1)  # (n, ncol)
    first, last = cols_seen.argmax(axis=1), ncol - cols_seen[:, ::-1].argmax(axis=1)
    for k, count in enumerate(visible.sum(axis=(1, 2)).tolist()):
        if count >= cfg.min_cells:
            keep.append((k, int(first[k]), int(last[k])))
    if not keep:
        return strips
    cell = (r * dphi, float(y[1] - y[0]))  # (column, row) size on the tread [m]
    rows = cfg.rows
    # the strips side by side, one empty row above and below (the edge steps' 3x3 reach) and
    # columns between them wider than the band-pass's reach
    gap = _band_reach(cell, cfg)
    starts = np.cumsum([0] + [c1 - c0 + gap for _, c0, c1 in keep])[:-1].tolist()
    height, width = rows + 2, starts[-1] + keep[-1][2] - keep[-1][1]
    maps = np.full((height, width, 2), -1.0, np.float32)
    vis = np.zeros((height, width), bool)
    for x0, (k, c0, c1) in zip(starts, keep, strict=True):
        vis[1 : rows + 1, x0 : x0 + c1 - c0] = visible[k, :, c0:c1]
        maps[1 : rows + 1, x0 : x0 + c1 - c0] = grid[k, :, c0:c1]
    blocks = [(x0, x0 + c1 - c0) for x0, (_, c0, c1) in zip(starts, keep, strict=True)]
    raw = _sample_strips(gray, maps, blocks, camera.image_size)
    if any(cfg.boundary):
        # cells whose samples reach past the visible tread (the empty rows around the strips
        # count as its edge)
        kernel = np.ones((2 * cfg.boundary[1] + 1, 2 * cfg.boundary[0] + 1), np.uint8)
        core = cv2.erode(vis.view(np.uint8), kernel, borderValue=0).view(bool)
        raw = np.where(core, raw, np.float32(0.0))  # the band-pass takes the image as 0 off its mask
    else:
        core = vis
    if shadow_robust:
        tex, band = _band_pass(raw, core, cell, cfg)
        valid = core & ~band
    else:
        valid = core
        tex = raw
    tex = np.where(valid, tex, np.float32(0.0))
    for x0, (k, c0, c1) in zip(starts, keep, strict=True):
        blk = np.s_[1 : rows + 1, x0 : x0 + c1 - c0]
        t_k = tex[blk]
        v_k = valid[blk]
        seen = bool(v_k.any())
        if not shadow_robust and seen:
            t_k = np.where(v_k, t_k - np.float32(t_k[v_k].mean()), np.float32(0.0))
        if cfg.clip > 0 and seen:
            lim = np.float32(cfg.clip * math.sqrt(float(np.mean(np.square(t_k[v_k], dtype=np.float64)))))
            t_k = np.clip(t_k, -lim, lim)
        strips[k] = TreadStrip(int(k0[k]) + c0, dphi, y, maps[blk], vis[blk], valid[blk], t_k)
    return strips


def _sample_strips(gray, maps: np.ndarray, blocks: list[tuple[int, int]], size: tuple) -> np.ndarray:
    """The grey frame at the strips' cells (-1: none), bilinear, as float32.

    ``gray``: the frame, or a function of a rectangle (x0, y0, x1, y1) [px, end exclusive]
    that returns the frame's grey levels there, sampled as float32 (each block of columns, one
    strip, is then sampled from the rectangle that holds its cells: cheaper when the levels
    cost time).
    """
    if not callable(gray):
        return cv2.remap(gray, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR).astype(np.float32)
    w, h = size
    raw = np.zeros(maps.shape[:2], np.float32)
    for x0, x1 in blocks:
        m = maps[:, x0:x1]
        ok = m[..., 0] >= 0
        if not ok.any():
            continue
        u, v = m[..., 0][ok], m[..., 1][ok]
        # the bilinear samples' pixels (floor and floor + 1), within the frame
        u0, v0 = max(int(u.min()), 0), max(int(v.min()), 0)
        u1, v1 = min(int(u.max()) + 2, w), min(int(v.max()) + 2, h)
        crop = np.asarray(gray(u0, v0, u1, v1), dtype=np.float32)
        mx = np.where(ok, m[..., 0] - np.float32(u0), np.float32(-1.0))
        my = np.where(ok, m[..., 1] - np.float32(v0), np.float32(-1.0))
        raw[:, x0:x1] = cv2.remap(crop, mx, my, cv2.INTER_LINEAR)
    return raw


def _occluded(model, camera, frames, wheels, dist2: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Which tread points are hidden behind a steering arm or tie-rod marker (of any wheel).

    ``dist2``: (...) squared distances of the points from the camera [m^2]; ``grid``: (..., 2)
    float32 their pixels, in the image or -1 (not tested). Each part is a chain of spheres
    (:meth:`RoverKinematicModel.occluders`); their image discs, with a 2 px margin, are drawn
    farthest first into a label image, so that each pixel holds the nearest part over it, and a
    point is hidden when it is farther from the camera than that part.
    """
    T = camera.T_body_cam
    parts = [model.occluders(wh, R, c) for wh, (R, c) in zip(wheels, frames, strict=True)]
    P = np.vstack([p for p, _ in parts]) - T[:3, 3]
    radii = np.concatenate([rad for _, rad in parts])
    dist = np.linalg.norm(P, axis=1)
    opx = camera.world2cam(P @ T[:3, :3], refine=False)
    w, h = camera.image_size
    disc = radii / dist * (w / max(camera.max_fov, 1e-6)) + 2  # about px per radian
    label = np.zeros((h, w), np.uint8)
    order = np.argsort(-dist)
    order = order[np.isfinite(opx[order]).all(axis=1)]
    fixed = np.rint(np.column_stack([opx[order] * 16, disc[order] * 16])).astype(int).tolist()  # 1/16 px
    for j, (u, v, rad) in zip(order.tolist(), fixed, strict=True):
        cv2.circle(label, (u, v), rad, j + 1, -1, cv2.LINE_8, 4)
    # each point's nearest pixel's label (0 for the points at -1, outside the label image)
    flat = grid.reshape(-1, grid.shape[-2], 2)
    lab = cv2.remap(label, flat, None, cv2.INTER_NEAREST, borderValue=0).reshape(dist2.shape)  # type: ignore[call-overload]
    near = np.concatenate([[np.inf], dist]) ** 2
    return dist2 > near[lab]


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

    :func:`unwrap_treads` for one wheel: ``R``, ``c`` are its knuckle frame in the body frame,
    ``wheel`` its name (to leave out the parts in front of its tread).
    """
    return unwrap_treads(
        gray, model, camera, [(R, c)], dphi, cfg, None if wheel is None else [wheel], shadow_robust
    )[0]


def _row_spectra(stack: np.ndarray, n: int) -> np.ndarray:
    """Complex spectra (..., n // 2 + 1) of the rows of ``stack`` (..., cols), zero-padded to ``n``."""
    lead, cols = stack.shape[:-1], stack.shape[-1]
    pad = np.zeros((int(np.prod(lead)), n), stack.dtype)
    pad[:, :cols] = stack.reshape(-1, cols)
    out = cv2.dft(pad, flags=cv2.DFT_ROWS | cv2.DFT_COMPLEX_OUTPUT)
    cplx = np.complex64 if stack.dtype == np.float32 else np.complex128
    return out.view(cplx)[:, : n // 2 + 1, 0].reshape(*lead, n // 2 + 1)


def _correlate(fa: np.ndarray, fb: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Masked NCC at every circular lag from the row spectra of (mask, x, x^2).

    ``fa``, ``fb``: (pairs, 3, rows, freq). Returns (ncc, overlap), each (pairs, n): index j is
    lag j (j < cols of a) or j - n.
    """
    # sum over rows and j of x[j] y[j - s]: products of the transforms, summed over rows
    cb = np.conj(fb)
    pairs = ((0, 0), (1, 0), (0, 1), (2, 0), (0, 2), (1, 1))
    prod = np.stack([(fa[:, i] * cb[:, k]).sum(axis=1) for i, k in pairs], 1)
    corr = np.fft.irfft(prod, n, axis=2).astype(np.float64)  # (pairs, 6, n)
    cnt, sa, sb, saa, sbb, sab = corr.transpose(1, 0, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        num = sab - sa * sb / cnt
        den = np.sqrt(np.clip(saa - sa * sa / cnt, 0, None) * np.clip(sbb - sb * sb / cnt, 0, None))
        ncc = np.where((cnt > 0.5) & (den > 1e-6 * np.maximum(cnt, 1)), num / den, -1.0)
    return ncc, cnt


def masked_ncc(
    a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised cross-correlation of ``a`` against ``b`` shifted along columns, over weighted cells.

    For every lag s, the correlation of a[i, j] with b[i, j - s], each pair weighted by
    ma[i, j] mb[i, j - s] (bool masks or weights in [0, 1]; Padfield's masked NCC, summed over
    rows; all lags by FFT, in float64).

    Returns:
        (lags, ncc, overlap: the sum of the pair weights) for lags -(cols_b - 1) .. cols_a - 1.
    """
    na, nb = a.shape[1], b.shape[1]
    n = int(cv2.getOptimalDFTSize(na + nb - 1))
    ma, mb = ma.astype(np.float64), mb.astype(np.float64)
    a, b = a.astype(np.float64) * ma, b.astype(np.float64) * mb
    fa = _row_spectra(np.stack([ma, a, a * a]), n)
    fb = _row_spectra(np.stack([mb, b, b * b]), n)
    ncc, cnt = _correlate(fa[None], fb[None], n)
    idx = np.r_[n - (nb - 1) : n, 0:na]
    return np.arange(-(nb - 1), na), ncc[0, idx], cnt[0, idx]


def _strip_spectra(strips: list[TreadStrip], n: int) -> None:
    """Compute (once) each strip's row spectra at DFT size ``n``, all strips in one transform."""
    todo = [s for s in strips if s._spectrum is None or s._spectrum[0] != n]
    if not todo:
        return
    rows = max(s.texture.shape[0] for s in todo)
    cols = max(s.texture.shape[1] for s in todo)
    stack = np.zeros((len(todo), 3, rows, cols), np.float32)
    for i, s in enumerate(todo):
        h, w = s.valid.shape
        stack[i, 0, :h, :w] = s.valid
        x = np.multiply(s.texture, stack[i, 0, :h, :w], out=stack[i, 1, :h, :w])
        np.multiply(x, x, out=stack[i, 2, :h, :w])
    spec = _row_spectra(stack, n)
    for i, s in enumerate(todo):
        s._spectrum = (n, spec[i])


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


def align_pairs(
    pairs: list[tuple[TreadStrip, TreadStrip]], cfg: TreadConfig, centres, spans
) -> list[Alignment]:
    """:func:`align_strips` for several (earlier, later) pairs at once (one transform for all)."""
    for prev, curr in pairs:
        if abs(prev.dphi - curr.dphi) > 1e-12 * max(prev.dphi, 1e-12):
            raise ValueError(f"strips with different column steps ({prev.dphi} and {curr.dphi} rad)")
    if not pairs:
        return []
    widest = max(max(p.texture.shape[1], c.texture.shape[1]) for p, c in pairs)
    # long enough for every lag without wrap-around, rounded up to a multiple of 64: the same size
    # frame after frame, so that each strip is transformed once
    n = 64 * math.ceil((2 * widest - 1) / 64)
    _strip_spectra([s for pair in pairs for s in pair], n)
    rows = max(max(p.texture.shape[0], c.texture.shape[0]) for p, c in pairs)

    def spectra(strips):
        if all(s_.texture.shape[0] == rows for s_ in strips):
            return np.stack([s_._spectrum[1] for s_ in strips])
        out = np.zeros((len(strips), 3, rows, n // 2 + 1), strips[0]._spectrum[1].dtype)
        for i, s_ in enumerate(strips):
            out[i, :, : s_.texture.shape[0]] = s_._spectrum[1]
        return out

    ncc, cnt = _correlate(spectra([c for _, c in pairs]), spectra([p for p, _ in pairs]), n)
    # every pair's candidates at once, on the circular lags
    na = np.array([c.texture.shape[1] for _, c in pairs])[:, None]
    nb = np.array([p.texture.shape[1] for p, _ in pairs])[:, None]
    j = np.arange(n)[None]
    lag = np.where(j < na, j, j - n)
    shift = lag + np.array([c.k0 - p.k0 for p, c in pairs])[:, None]  # columns of the common grid
    dphi = np.array([c.dphi for _, c in pairs])[:, None]
    alpha = shift * dphi
    smaller = np.array([min(c.n_valid, p.n_valid) for p, c in pairs])[:, None]
    need = np.maximum(cfg.min_cells, cfg.min_overlap * smaller)
    within = np.abs(alpha - np.asarray(centres)[:, None]) <= np.asarray(spans)[:, None]
    cand = ((j < na) | (j >= n - (nb - 1))) & within & (cnt >= need - 0.5)
    q = np.arange(len(pairs))
    k = np.argmax(np.where(cand, ncc, -np.inf), axis=1)
    top, at = ncc[q, k], alpha[q, k]
    others = cand & (np.abs(alpha - at[:, None]) > cfg.peak_separation)
    margin = np.where(others.any(axis=1), top - np.where(others, ncc, -np.inf).max(axis=1), 1.0)
    # parabola through the neighbouring lags
    km, kp = (k - 1) % n, (k + 1) % n
    near = cand[q, km] & cand[q, kp] & (lag[q, km] == lag[q, k] - 1) & (lag[q, kp] == lag[q, k] + 1)
    y0, y2 = ncc[q, km], ncc[q, kp]
    den = y0 - 2 * top + y2
    with np.errstate(invalid="ignore", divide="ignore"):
        step = np.where(near & (den < 0), np.clip(0.5 * (y0 - y2) / den, -1, 1), 0.0)
    best = at + step * dphi[:, 0]
    out = []
    for i in range(len(pairs)):
        if not cand[i].any():
            out.append(Alignment(math.nan, math.nan, 0.0, 0))
        else:
            # two rotations that fit about as well: do not guess
            a = float(best[i]) if margin[i] >= cfg.min_peak_margin else math.nan
            out.append(Alignment(a, float(top[i]), float(margin[i]), int(round(cnt[i, k[i]]))))
    return out


def align_strips(
    prev: TreadStrip, curr: TreadStrip, cfg: TreadConfig, centre: float = 0.0, span: float = 0.8
) -> Alignment:
    """Rotation [rad] carrying the tread of ``prev`` to that of ``curr``, within ``centre`` +- ``span``.

    The masked normalised cross-correlation of the two strips' textures at every shift
    (:func:`masked_ncc`). Shifts where the strips overlap on fewer than ``min_cells`` cells, or
    on less than ``min_overlap`` of the smaller strip, are not candidates: a small overlap can
    correlate well by chance. The integer shift of best correlation is refined by a parabola;
    the result is NaN when another rotation, ``peak_separation`` away, correlates within
    ``min_peak_margin``.
    """
    return align_pairs([(prev, curr)], cfg, [centre], [span])[0]


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
        overlap: Cells the alignment compared (0 if none).
    """

    alpha: float
    n_features: int
    n_tracked: int
    n_inliers: int
    valid: bool
    ncc: float = math.nan
    overlap: int = 0

    def std(self, dphi: float, cfg: TreadConfig) -> float:
        """Standard deviation of ``alpha`` [rad] (inf if not valid), from the alignment's quality.

        ``dphi * sqrt(1 - ncc^2) * cfg.noise_cells / overlap`` (``dphi`` the strips' column step
        [rad]): a correlation peak is as sharp as the texture, and moves with the part of the
        strips that does not match. Where the tracked features outvoted the correlation, the
        figures are still the correlation's: the deviation is then only a rough guide.
        """
        if not (self.valid and self.overlap > 0 and math.isfinite(self.ncc)):
            return math.inf
        r = min(max(self.ncc, 0.0), 1.0)
        return dphi * math.sqrt(1.0 - r * r) * cfg.noise_cells / self.overlap


def _to_u8(texture: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The texture in 8 bits for Shi-Tomasi and Lucas-Kanade: 128 + 40 per standard deviation."""
    _, std = cv2.meanStdDev(texture, mask=valid.view(np.uint8))
    scale = 40.0 / max(float(std[0, 0]), 1e-3)
    return cv2.addWeighted(texture, scale, texture, 0.0, 128.0, dtype=cv2.CV_8U)  # rounded, clipped


def track_pairs(
    pairs: list[tuple[TreadStrip, TreadStrip]], radius: float, cfg: TreadConfig, priors
) -> list[RotationMeasurement]:
    """:func:`track_strip_features` for several (earlier, later) pairs at once.

    The pairs' strips are laid in blocks of one image each for the earlier and the later frame
    (every pair on its own column grid, gaps between blocks), so that features are selected by
    one Shi-Tomasi call and tracked by one Lucas-Kanade call each way.
    """
    out = [RotationMeasurement(math.nan, 0, 0, 0, False) for _ in pairs]
    win = np.ones((3, 3), np.uint8)
    blocks = []
    for i, ((prev, curr), prior) in enumerate(zip(pairs, priors, strict=True)):
        # features only where, turned by the prior, they land on the later strip's valid cells
        cols = np.rint(prev.k0 + np.arange(prev.valid.shape[1]) + prior / prev.dphi).astype(int) - curr.k0
        inside = (cols >= 0) & (cols < curr.valid.shape[1])
        lands = np.zeros_like(prev.valid)
        lands[:, inside] = curr.valid[:, cols[inside]]
        # and with their whole Lucas-Kanade window on valid cells
        mask = cv2.erode((prev.valid & lands).view(np.uint8), win)
        if mask.any():
            k0 = min(prev.k0, curr.k0)
            n = max(prev.k0 + prev.texture.shape[1], curr.k0 + curr.texture.shape[1]) - k0
            blocks.append((i, prev, curr, mask, k0, n))
    if not blocks:
        return out
    gap = cfg.lk_window + 2
    rows = max(max(p.texture.shape[0], c.texture.shape[0]) for _, p, c, *_ in blocks)
    height = len(blocks) * (rows + gap) - gap
    width = max(b[5] for b in blocks)
    a8 = np.full((height, width), 128, np.uint8)
    b8 = np.full((height, width), 128, np.uint8)
    mask = np.zeros((height, width), np.uint8)
    on_b = np.zeros((height, width), bool)
    for j, (_, prev, curr, m, k0, _) in enumerate(blocks):
        r0 = j * (rows + gap)
        ja, jb = prev.k0 - k0, curr.k0 - k0
        ha, wa = prev.texture.shape
        hb, wb = curr.texture.shape
        a8[r0 : r0 + ha, ja : ja + wa] = _to_u8(prev.texture, prev.valid)
        b8[r0 : r0 + hb, jb : jb + wb] = _to_u8(curr.texture, curr.valid)
        mask[r0 : r0 + ha, ja : ja + wa] = m
        on_b[r0 : r0 + hb, jb : jb + wb] = curr.valid
    pts = cv2.goodFeaturesToTrack(a8, 0, 0.01, cfg.min_distance, mask=mask, blockSize=5)
    if pts is None:
        return out
    pts = pts.reshape(-1, 2)
    blk = np.rint(pts[:, 1]).astype(int) // (rows + gap)
    # the strongest max_features of each block (the corners come strongest first)
    rank = np.zeros(len(pts), int)
    for j in range(len(blocks)):
        sel = blk == j
        rank[sel] = np.arange(sel.sum())
    take = rank < cfg.max_features
    p0, blk = pts[take].astype(np.float32), blk[take]
    prior_cols = np.array([priors[b[0]] / b[1].dphi for b in blocks], np.float32)
    guess = p0 + np.stack([prior_cols[blk], np.zeros(len(blk), np.float32)], 1)
    lk: dict[str, Any] = dict(
        winSize=(cfg.lk_window, cfg.lk_window),
        maxLevel=0,  # the search starts at the aligned rotation, within a cell or so
        criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(a8, b8, p0.reshape(-1, 1, 2), guess.reshape(-1, 1, 2), **lk)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(b8, a8, p1, p0.reshape(-1, 1, 2).copy(), **lk)
    p1, pb = p1.reshape(-1, 2), pb.reshape(-1, 2)
    fb = np.linalg.norm(pb - p0, axis=1)
    j, i = np.rint(np.nan_to_num(p1, nan=-1.0)).astype(int).T
    inside = (j >= 0) & (j < width) & (i >= 0) & (i < height)
    on = np.zeros(len(p1), dtype=bool)
    on[inside] = on_b[i[inside], j[inside]] & (i[inside] // (rows + gap) == blk[inside])
    keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_threshold) & on
    # each track's two cells are cylinder points (eq. 6 on their chord)
    k0s = np.array([b[4] for b in blocks])[blk]
    dphi = np.array([b[1].dphi for b in blocks])[blk]
    row0 = blk * (rows + gap)
    y0 = np.array([b[1].y[0] for b in blocks])[blk]
    dy = np.array([b[1].y[1] - b[1].y[0] for b in blocks])[blk]
    q0 = tread_point(radius, (k0s + p0[:, 0]) * dphi, y0 + (p0[:, 1] - row0) * dy)
    q1 = tread_point(radius, (k0s + p1[:, 0]) * dphi, y0 + (p1[:, 1] - row0) * dy)
    alpha = arc_angle(q0[keep], q1[keep], radius)
    blk_kept = blk[keep]
    for j, b in enumerate(blocks):
        a_j = alpha[blk_kept == j]
        n_feat, n_kept = int((blk == j).sum()), len(a_j)
        if n_kept < cfg.min_inliers:
            out[b[0]] = RotationMeasurement(math.nan, n_feat, n_kept, 0, False)
            continue
        inl = ransac_1d(a_j, cfg.ransac_tolerance)
        n_in = int(inl.sum())
        valid = n_in >= cfg.min_inliers
        out[b[0]] = RotationMeasurement(
            float(a_j[inl].mean()) if valid else math.nan, n_feat, n_kept, n_in, valid
        )
    return out


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
    return track_pairs([(prev, curr)], radius, cfg, [alpha_prior])[0]


def measure_pairs(
    pairs: list[tuple[TreadStrip | None, TreadStrip | None]],
    radius: float,
    cfg: TreadConfig,
    priors,
    spans,
    check=None,
) -> list[RotationMeasurement]:
    """:func:`measure_strips` for several wheels at once (batched alignment and tracking).

    ``check``: per pair, how the features judge the alignment (default: 1 with
    ``cfg.check_strong``, else 0): 0, strong and decisive alignments (``decisive_ncc``,
    ``decisive_margin``) and those that agree with the prior (``prior_ncc``,
    ``prior_tolerance``) are taken as they are; 1, strong ones are checked too, and taken when
    the features agree or are too few to tell; 2, every
    alignment must be confirmed (or replaced) by the features. A wheel searched for after a
    loss, over a wide span, should be confirmed: there a strong false peak on a small overlap
    is possible.
    """
    out = [RotationMeasurement(math.nan, 0, 0, 0, False) for _ in pairs]
    check = [int(cfg.check_strong)] * len(pairs) if check is None else [int(c) for c in check]
    both = {i: (p, c) for i, (p, c) in enumerate(pairs) if p is not None and c is not None}
    ok = list(both)
    als = align_pairs([both[i] for i in ok], cfg, [priors[i] for i in ok], [spans[i] for i in ok])
    go = []
    for i, al in zip(ok, als, strict=True):
        if abs(al.alpha) < cfg.static_band and abs(al.alpha - priors[i]) > cfg.prior_tolerance:
            check[i] = 2  # the tread's shading and shadows, which do not turn, may fit at 0
        decisive = check[i] == 0 and (
            (al.ncc >= cfg.decisive_ncc and al.margin >= cfg.decisive_margin)
            or (al.ncc >= cfg.prior_ncc and abs(al.alpha - priors[i]) <= cfg.prior_tolerance)
        )
        if not (math.isfinite(al.alpha) and (al.ncc >= cfg.min_ncc or decisive)):
            out[i] = RotationMeasurement(math.nan, 0, 0, 0, False, al.ncc, al.overlap)
        elif check[i] == 0 and (al.ncc >= cfg.strong_ncc or decisive):
            out[i] = RotationMeasurement(al.alpha, 0, 0, 0, True, al.ncc, al.overlap)
        else:
            go.append((i, al))
    feats = track_pairs([both[i] for i, _ in go], radius, cfg, [al.alpha for _, al in go])
    for (i, al), f in zip(go, feats, strict=True):
        agree = f.valid and abs(f.alpha - al.alpha) <= cfg.ransac_tolerance
        if agree or (al.ncc >= cfg.strong_ncc and not f.valid and check[i] < 2):
            # two readings of the tread that agree, or a strong correlation and too few tracks
            out[i] = RotationMeasurement(
                al.alpha, f.n_features, f.n_tracked, f.n_inliers, True, al.ncc, al.overlap
            )
        elif f.valid and f.n_inliers >= cfg.min_override:
            # many tracks, started at the aligned rotation, settle on another: a shadow or a
            # change of light has pulled the correlation; the tracks follow the tread itself
            out[i] = RotationMeasurement(
                f.alpha, f.n_features, f.n_tracked, f.n_inliers, True, al.ncc, al.overlap
            )
        else:
            out[i] = RotationMeasurement(math.nan, f.n_features, f.n_tracked, 0, False, al.ncc, al.overlap)
    return out


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
    as well and either its correlation is at least ``strong_ncc``, or it is at least ``min_ncc``
    and the paper's features (:func:`track_strip_features`, started at the aligned rotation)
    confirm it. When at least ``min_override`` consistent features settle on another rotation,
    theirs is taken. With ``check_strong``, strong alignments are checked by the features too
    (valid when they agree or too few are tracked to tell).
    """
    return measure_pairs([(prev, curr)], radius, cfg, [alpha_prior], [span])[0]


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
    return measure_strips(strips[0], strips[1], model.wheel_radius, cfg, alpha_prior, span)

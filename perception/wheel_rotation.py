"""Wheel rotation from the treads in the fisheye image (kinematics paper, section V-C).

Each wheel is a cylinder of the tread radius about its knuckle's y axis, placed by the axle roll,
height and steering. A fixed-size observation window follows the tread point that faces the
camera (the paper's w60 point, chosen here by geometry). In it, Shi-Tomasi features on the tread
are tracked by pyramidal Lucas-Kanade forward and backward between frames, and inconsistent
tracks dropped. Each feature's ray is intersected with the cylinder at both instants, in the
knuckle frame, so that roll, height and steering changes cancel; the arc angle between the two
points is eq. (6), signed by their cross product. A 1-D RANSAC over the angles keeps the
consistent ones, whose mean is the rotation between the frames.
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
    """Tread tracking.

    Attributes:
        window_frac: Observation-window edge as a share of the image width.
        max_features: Shi-Tomasi features per window.
        min_distance_frac: Minimum feature spacing, share of the image width.
        lk_window_frac: Lucas-Kanade window, share of the image width (odd size, >= 7 px). Small:
            the tread's image motion is not a translation over a large window (a 21 px window
            reads a 0.04 rad turn 1.6 % short, a 9 px one 0.6 %).
        fb_threshold: Largest forward-backward error [px].
        edge_margin: Features this close to a tread edge are not used [m].
        ransac_tolerance: 1-D RANSAC inlier band [rad].
        min_inliers: Fewest consistent features for a valid rotation.
        min_ncc: Smallest correlation of the direct tread alignment for a valid rotation.
        min_facing: Smallest cosine between the tread normal and the view direction of a pixel
            used (keeps away from the silhouette).
        peak_separation: Rotations this far from the best one count as other candidates [rad].
        min_peak_margin: The best correlation must beat every other candidate's by this much.
    """

    window_frac: float = 0.16
    max_features: int = 25
    min_distance_frac: float = 0.008
    lk_window_frac: float = 0.014
    fb_threshold: float = 0.5
    edge_margin: float = 0.006
    ransac_tolerance: float = 0.01
    min_inliers: int = 4
    min_ncc: float = 0.6
    min_facing: float = 0.3
    peak_separation: float = 0.1
    min_peak_margin: float = 0.08


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


def ransac_1d(values: np.ndarray, tolerance: float, rng: np.random.Generator | None = None) -> np.ndarray:
    """Largest set of values within ``tolerance`` of one of them (every value is tried: n <= ~50)."""
    v = np.asarray(values, dtype=np.float64)
    if len(v) == 0:
        return np.zeros(0, dtype=bool)
    close = np.abs(v[:, None] - v[None, :]) <= tolerance
    return close[int(np.argmax(close.sum(axis=1)))]


def facing(points: np.ndarray, camera_knuckle: np.ndarray, min_cos: float) -> np.ndarray:
    """Tread points (knuckle frame, (..., 3)) whose surface faces the camera by more than ``min_cos``.

    Near the silhouette the tread is seen edge-on: its pixels mix with what lies behind, which
    does not turn with the wheel.
    """
    n = points * np.array([1.0, 0.0, 1.0])
    v = camera_knuckle - points
    with np.errstate(invalid="ignore"):
        cos = np.einsum("...i,...i->...", n, v) / (np.linalg.norm(n, axis=-1) * np.linalg.norm(v, axis=-1))
    return cos > min_cos


def facing_angle(model: RoverKinematicModel, R: np.ndarray, c: np.ndarray) -> float:
    """Angle about the wheel axis (from the knuckle's +z, toward +x) of the tread point facing the camera."""
    cam = R.T @ (model.T_body_cam[:3, 3] - c)
    return math.atan2(cam[0], cam[2])


@dataclass
class TreadWindow:
    """The observation window of one wheel in one frame.

    Attributes:
        box: (x0, y0, x1, y1) pixel bounds (x1, y1 exclusive).
        mask: (y1 - y0, x1 - x0) bool, pixels whose ray meets the tread (away from its edges).
        centre: Pixel of the tread point facing the camera.
        phi: Angle of that point about the wheel axis [rad].
    """

    box: tuple[int, int, int, int]
    mask: np.ndarray
    centre: np.ndarray
    phi: float


def tread_window(
    model: RoverKinematicModel,
    camera: OmniCamera,
    R: np.ndarray,
    c: np.ndarray,
    cfg: TreadConfig,
    wheel: str | None = None,
) -> TreadWindow | None:
    """The window around the facing tread point, or None if it is outside the image.

    With ``wheel`` given, pixels covered by that wheel's steering arm and tie-rod marker are
    left out of the mask.
    """
    phi = facing_angle(model, R, c)
    r = model.wheel_radius
    p_body = R @ np.array([r * math.sin(phi), 0.0, r * math.cos(phi)]) + c
    T_cb = np.linalg.inv(camera.T_body_cam)
    px = camera.world2cam(T_cb[:3, :3] @ p_body + T_cb[:3, 3])
    if not np.all(np.isfinite(px)):
        return None
    w, h = camera.image_size
    half = max(8, int(round(cfg.window_frac * w / 2)))
    x0, y0 = int(round(px[0])) - half, int(round(px[1])) - half
    x1, y1 = x0 + 2 * half, y0 + 2 * half
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 8 or y1 - y0 < 8:
        return None
    gx, gy = np.meshgrid(np.arange(x0, x1, dtype=np.float64), np.arange(y0, y1, dtype=np.float64))
    rays = camera.pixel_rays[y0:y1, x0:x1].reshape(-1, 3) @ camera.T_body_cam[:3, :3].T
    ok = np.isfinite(rays[:, 0])
    rays[~ok] = (0.0, 0.0, -1.0)  # a copy: the matrix product above
    origin = camera.T_body_cam[:3, 3]
    pts, hit = ray_cylinder(origin, rays, R, c, r, model.wheel_width / 2 - cfg.edge_margin)
    hit &= facing(pts, R.T @ (origin - c), cfg.min_facing)  # not near the tread's silhouette
    mask = (hit & ok).reshape(y1 - y0, x1 - x0)
    if wheel is not None:  # leave out the steering arm and tie-rod marker in front of the tread
        occ, radii = model.occluders(wheel, R, c)
        dist = np.linalg.norm(occ - origin, axis=1)
        opx = camera.world2cam((occ - origin) @ camera.T_body_cam[:3, :3])
        scale = camera.image_size[0] / max(camera.max_fov, 1e-6)  # about px per radian
        for (u, v), rad, d in zip(opx, radii, dist, strict=True):
            if np.isfinite(u):
                r_px = rad / d * scale + 2.0
                mask &= (gx - u) ** 2 + (gy - v) ** 2 > r_px**2
    return TreadWindow((x0, y0, x1, y1), mask, px, phi)


def shading_free(
    gray: np.ndarray, fine: float = 1.2, coarse: float = 5.0, edge_factor: float = 4.0, min_step: float = 12.0
) -> tuple[np.ndarray, np.ndarray]:
    """Tread texture without shading or pixel noise, and the band of strong steps to leave out.

    A difference of Gaussians (``fine`` and ``coarse`` px) keeps the speckle a few pixels across:
    the coarse blur removes smooth shading and the levels of lit and shadowed areas, the fine
    one the pixel-scale flicker of a renderer's (or sensor's) sampling. Pixels where the
    coarsely blurred image's gradient exceeds ``edge_factor`` times its median (and ``min_step``
    grey levels per pixel) are steps such as shadow edges, and are excluded (the odometry
    paper's idea of masking shadow edges, applied to the treads).

    Returns:
        (float32 band-passed image, bool edge band).
    """
    g = gray.astype(np.float32)
    blur = cv2.GaussianBlur(g, (0, 0), coarse)
    gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)
    mag = cv2.magnitude(gx, gy)
    thr = max(edge_factor * float(np.median(mag)), min_step)
    band = cv2.dilate((mag > thr).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return cv2.GaussianBlur(g, (0, 0), fine) - blur, band


def _rot_y(a) -> np.ndarray:
    """(..., 3, 3) rotations about +y by angles ``a``."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def align_rotation(
    prev_gray: np.ndarray,
    curr_gray: np.ndarray,
    model: RoverKinematicModel,
    camera: OmniCamera,
    prev_frame: tuple[np.ndarray, np.ndarray],
    curr_frame: tuple[np.ndarray, np.ndarray],
    cfg: TreadConfig,
    centre: float = 0.0,
    span: float = 0.8,
    prev_edges: np.ndarray | None = None,
    curr_edges: np.ndarray | None = None,
    wheel: str | None = None,
    window: TreadWindow | None = None,
) -> tuple[float, float]:
    """Rotation that best maps the tread in the window of ``curr_gray`` back onto ``prev_gray``.

    Every tread pixel of the current window is a point on the cylinder; turned back by a trial
    angle and projected into the previous frame, it should see the same grey level. A coarse
    grid over ``centre`` +- ``span`` on a subsample of the pixels, then a fine grid around the
    best and a parabola through the top three, maximise the normalised cross-correlation. This
    bounds the search of the feature tracking, which alone loses wheels that turn fast.

    The images may be grey levels or, better, :func:`shading_free` images with their edge
    bands (``prev_edges``, ``curr_edges``): a shadow edge across a tread does not turn with the
    wheel and would otherwise pull the alignment toward no rotation.

    Returns:
        (alpha [rad], correlation at alpha); alpha is NaN without a usable window or when
        another rotation, ``peak_separation`` away, correlates nearly as well (the best must win
        by ``min_peak_margin``).
    """
    win = window if window is not None else tread_window(model, camera, *curr_frame, cfg, wheel)
    if win is None or win.mask.sum() < 30:
        return math.nan, math.nan
    x0, y0, x1, y1 = win.box
    use = win.mask if curr_edges is None else win.mask & ~curr_edges[y0:y1, x0:x1]
    if use.sum() < 30:
        return math.nan, math.nan
    ys, xs = np.nonzero(use)
    vals = curr_gray[ys + y0, xs + x0].astype(np.float64)
    if vals.std() < 1.0:
        return math.nan, math.nan
    origin = camera.T_body_cam[:3, 3]
    q, hit = ray_cylinder(
        origin,
        camera.pixel_rays[ys + y0, xs + x0] @ camera.T_body_cam[:3, :3].T,
        *curr_frame,
        model.wheel_radius,
        model.wheel_width / 2,
    )
    q, vals = q[hit], vals[hit]
    Rp, cp = prev_frame
    T_cb = np.linalg.inv(camera.T_body_cam)
    M = T_cb[:3, :3] @ Rp
    t = T_cb[:3, :3] @ cp + T_cb[:3, 3]
    cam_in_prev = Rp.T @ (origin - cp)

    prev_f = prev_gray.astype(np.float32)
    if prev_edges is not None:
        prev_f = np.where(prev_edges, np.float32(np.nan), prev_f)  # samples there are not used

    def score(alphas: np.ndarray, idx: np.ndarray) -> np.ndarray:
        pts = np.einsum("kab,nb->kna", _rot_y(-alphas), q[idx])  # the same tread points, earlier
        visible = facing(pts, cam_in_prev, cfg.min_facing)
        uv = camera.world2cam(pts @ M.T + t).astype(np.float32)
        samp = cv2.remap(prev_f, uv[..., 0], uv[..., 1], cv2.INTER_LINEAR, borderValue=np.nan)
        ok = visible & np.isfinite(uv).all(-1) & np.isfinite(samp)
        samp = np.where(ok, samp, 0.0)
        a = np.broadcast_to(vals[idx], samp.shape)
        cnt = ok.sum(axis=1)
        ma = np.where(ok, a, 0.0).sum(axis=1) / np.maximum(cnt, 1)
        mb = np.where(ok, samp, 0.0).sum(axis=1) / np.maximum(cnt, 1)
        x = np.where(ok, a - ma[:, None], 0.0)
        y = np.where(ok, samp - mb[:, None], 0.0)
        den = np.sqrt((x * x).sum(axis=1) * (y * y).sum(axis=1))
        with np.errstate(invalid="ignore", divide="ignore"):
            ncc = (x * y).sum(axis=1) / den
        return np.where((cnt >= 20) & (den > 0), ncc, -1.0)

    n = len(q)
    best = centre
    margin = 1.0
    # coarse to fine: (half-width of the grid, candidates, pixels used)
    for half, count, used in ((span, 41, 150), (span / 16, 9, 300), (span / 128, 7, n)):
        grid = best + np.linspace(-half, half, count)
        sc = score(grid, np.arange(0, n, max(1, n // used)))
        k = int(np.argmax(sc))
        best = grid[k]
        if half == span:  # how far the best peak stands above any other rotation
            others = sc[np.abs(grid - best) > cfg.peak_separation]
            margin = float(sc[k] - others.max()) if len(others) else 1.0
    if margin < cfg.min_peak_margin:  # two rotations fit about as well: do not guess
        return math.nan, float(sc[k])
    k = int(np.clip(k, 1, count - 2))
    y0_, y1_, y2_ = sc[k - 1], sc[k], sc[k + 1]
    den = y0_ - 2 * y1_ + y2_
    shift = 0.5 * (y0_ - y2_) / den if den < 0 else 0.0
    h = grid[1] - grid[0]
    return float(grid[k] + np.clip(shift, -1, 1) * h), float(y1_)


@dataclass
class RotationMeasurement:
    """Rotation of one wheel between two frames.

    Attributes:
        alpha: Rotation about the wheel axis [rad] (NaN if not measured).
        n_features: Features selected in the window.
        n_tracked: Features kept by the forward-backward check and on the tread in both frames.
        n_inliers: Features in the largest consistent set.
        valid: Whether alpha can be trusted.
    """

    alpha: float
    n_features: int
    n_tracked: int
    n_inliers: int
    valid: bool


def track_tread_features(
    prev_gray: np.ndarray,
    curr_gray: np.ndarray,
    model: RoverKinematicModel,
    camera: OmniCamera,
    prev_frame: tuple[np.ndarray, np.ndarray],
    curr_frame: tuple[np.ndarray, np.ndarray],
    cfg: TreadConfig,
    forbidden: np.ndarray | None = None,
    alpha_prior: float = 0.0,
    wheel: str | None = None,
    window: TreadWindow | None = None,
) -> RotationMeasurement:
    """The paper's tread tracking: per-feature arc angles between two frames, 1-D RANSAC, mean.

    Args:
        prev_gray: The earlier grey fisheye frame.
        curr_gray: The later one.
        model: Rover geometry.
        camera: The fisheye model.
        prev_frame: (R, centre) of the wheel's knuckle frame at the earlier frame (body frame).
        curr_frame: The same at the later frame.
        cfg: Parameters.
        forbidden: Optional (H, W) bool of pixels where features may not be chosen (the odometry
            paper's shadow-edge mask, so that moving wheel shadows are not tracked).
        alpha_prior: Expected rotation [rad] (e.g. the last one): each feature's search starts at
            its tread point turned by this much, so that fast wheels stay trackable.
        wheel: The wheel's name, to leave its steering arm and tie-rod marker out of the window.
        window: The tread window of the earlier frame, if already computed.
    """
    none = RotationMeasurement(math.nan, 0, 0, 0, False)
    win = window if window is not None else tread_window(model, camera, *prev_frame, cfg, wheel)
    if win is None or not win.mask.any():
        return none
    x0, y0, x1, y1 = win.box
    mask = win.mask.copy()
    if forbidden is not None:
        mask &= ~forbidden[y0:y1, x0:x1]
    w = camera.image_size[0]
    pts = cv2.goodFeaturesToTrack(
        prev_gray[y0:y1, x0:x1],
        maxCorners=cfg.max_features,
        qualityLevel=0.01,
        minDistance=max(2.0, cfg.min_distance_frac * w),
        mask=mask.astype(np.uint8),
        blockSize=5,
    )
    if pts is None:
        return none
    p0 = (pts.reshape(-1, 2) + (x0, y0)).astype(np.float32)
    origin = camera.T_body_cam[:3, 3]
    Rbc = camera.T_body_cam[:3, :3]
    half = model.wheel_width / 2
    q0, h0 = ray_cylinder(
        origin, camera.cam2world(p0.astype(np.float64)) @ Rbc.T, *prev_frame, model.wheel_radius, half
    )
    # start of each search: the tread point turned by the prior, seen in the current frame
    ca, sa = math.cos(alpha_prior), math.sin(alpha_prior)
    turned = q0 @ np.array([[ca, 0.0, sa], [0.0, 1.0, 0.0], [-sa, 0.0, ca]]).T
    R1, c1 = curr_frame
    T_cb = np.linalg.inv(camera.T_body_cam)
    guess = camera.world2cam((turned @ R1.T + c1) @ T_cb[:3, :3].T + T_cb[:3, 3])
    guess = np.where(np.isfinite(guess), guess, p0).astype(np.float32)
    win_px = max(7, int(round(cfg.lk_window_frac * w)) | 1)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    lk = dict(winSize=(win_px, win_px), maxLevel=2, criteria=crit)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        prev_gray,
        curr_gray,
        p0.reshape(-1, 1, 2),
        guess.reshape(-1, 1, 2).copy(),
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        **lk,
    )
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(curr_gray, prev_gray, p1, None, **lk)
    fb = np.linalg.norm((pb - p0.reshape(-1, 1, 2)).reshape(-1, 2), axis=1)
    keep = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_threshold) & h0
    n_feat = len(p0)
    if keep.sum() < cfg.min_inliers:
        return RotationMeasurement(math.nan, n_feat, int(keep.sum()), 0, False)
    d1 = camera.cam2world(p1.reshape(-1, 2)[keep].astype(np.float64)) @ Rbc.T
    q1, h1 = ray_cylinder(origin, np.nan_to_num(d1), *curr_frame, model.wheel_radius, half)
    q0 = q0[keep]
    both = h1
    if both.sum() < cfg.min_inliers:
        return RotationMeasurement(math.nan, n_feat, int(both.sum()), 0, False)
    alpha = arc_angle(q0[both], q1[both], model.wheel_radius)
    inl = ransac_1d(alpha, cfg.ransac_tolerance)
    n_in = int(inl.sum())
    valid = n_in >= cfg.min_inliers
    return RotationMeasurement(
        float(alpha[inl].mean()) if valid else math.nan, n_feat, int(both.sum()), n_in, valid
    )


def measure_rotation(
    prev_gray: np.ndarray,
    curr_gray: np.ndarray,
    model: RoverKinematicModel,
    camera: OmniCamera,
    prev_frame: tuple[np.ndarray, np.ndarray],
    curr_frame: tuple[np.ndarray, np.ndarray],
    cfg: TreadConfig,
    forbidden: np.ndarray | None = None,
    alpha_prior: float = 0.0,
    span: float = 0.8,
    shading: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    wheel: str | None = None,
    windows: tuple[TreadWindow | None, TreadWindow | None] | None = None,
) -> RotationMeasurement:
    """Rotation of one wheel between two frames [rad], with its validity.

    The rotation is the direct alignment of the tread (:func:`align_rotation`, searched around
    ``alpha_prior``): on rendered treads the per-feature arc angles of the paper scatter by a few
    per cent and their mean is biased by as much, while the alignment is within 0.5 %. The
    paper's features (:func:`track_tread_features`, started at the aligned rotation) then count
    how many tracks agree with it; the rotation is valid when the alignment's correlation is at
    least ``min_ncc``.

    Args: as :func:`track_tread_features`; ``span``: the half-width of the search around
    ``alpha_prior`` [rad] (narrow once a wheel is being tracked, wide to acquire it); ``shading``:
    the two frames' :func:`shading_free` images, if already computed; ``wheel``: its name, so
    that its steering arm and tie-rod marker are left out of the window; ``windows``: the
    (earlier, later) frames' tread windows, if already computed.
    """
    if shading is None:  # plain grey levels, no edge bands
        shading = ((prev_gray, None), (curr_gray, None))
    (hp_prev, band_prev), (hp_curr, band_curr) = shading
    prev_win, curr_win = windows if windows is not None else (None, None)
    frames = (prev_frame, curr_frame)
    edges = (band_prev, band_curr)
    alpha, ncc = align_rotation(
        hp_prev, hp_curr, model, camera, *frames, cfg, alpha_prior, span, *edges, wheel, curr_win
    )
    if not (ncc >= cfg.min_ncc and math.isfinite(alpha)):
        return RotationMeasurement(math.nan, 0, 0, 0, False)
    feats = track_tread_features(
        prev_gray, curr_gray, model, camera, *frames, cfg, forbidden, alpha, wheel, prev_win
    )
    agree = feats.n_inliers if feats.valid and abs(feats.alpha - alpha) <= cfg.ransac_tolerance else 0
    return RotationMeasurement(alpha, feats.n_features, feats.n_tracked, agree, True)

"""Optical-flow odometry from a downward camera, robust to the robot's own shadow.

Seegmiller and Wettergreen, "Optical Flow Odometry with Robustness to Self-shadowing" (Algorithm 1):

1. ``I_prev``; an image pyramid whose smallest level (>= 80 x 60) is used for the mask.
2. Shadow presence: two-cluster K-means on the smallest level's intensities and the bimodality
   test |c1 - c2| > lambda (sigma1 + sigma2) (eq. 3).
3. Shadow edges: Canny with thresholds proportional to |c1 - c2|; the K-means label image with
   shadow segments that do not touch the image border removed (4-connected growth from border
   seeds); the gradient of that image, unthinned and dilated 3 x 3, masks the Canny output; the
   masked edges, dilated by the radius of eq. (4), are where features may not be selected.
4. Harris features under the mask, inside a central region of interest, a minimum distance apart
   (on the finest pyramid level at most 320 px wide, then scaled to full resolution).
5. ``I_curr``; pyramidal Lucas-Kanade, kept only where tracking back from ``I_curr`` returns to
   the start (forward-backward check; the backward track starts at the feature itself).
6. Undistortion and the ground homography H = K M* into the body frame (eqs. 5-8).
7. RANSAC over 3-point samples: centroid normalisation, the SVD rotation and the rigid-motion
   error of eqs. (10)-(17); inlier threshold in metres.
8. Velocity (v_x, v_y, omega) by least squares over the inliers (eqs. 18-19), with a quality
   value and a validity decision that gives its reason when invalid. An invalid estimate has
   NaN velocities: the estimator never reports a confident zero.

Frames: body x forward, y left, z up; velocities are of the body origin in the body frame [m/s],
omega about body z [rad/s].
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Literal, overload

import cv2
import numpy as np

from perception.models.cameras import PinholeCamera
from perception.models.photometry import flat_field, flat_field_gain

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------- steps
def pyramid_levels(width: int, height: int, min_size: tuple[int, int] = (80, 60)) -> int:
    """How many levels :func:`build_pyramid` builds for a ``width`` x ``height`` image [px]."""
    n = 1
    while width // 2 >= min_size[0] and height // 2 >= min_size[1]:
        n, width, height = n + 1, (width + 1) // 2, (height + 1) // 2  # cv2.pyrDown's size
    return n


def build_pyramid(gray: np.ndarray, min_size: tuple[int, int] = (80, 60)) -> list[np.ndarray]:
    """Gaussian pyramid of ``gray``: level 0 is the image, each level half the last.

    Levels are added while the next one would still be at least ``min_size`` (W, H).
    """
    levels = [gray]
    for _ in range(pyramid_levels(gray.shape[1], gray.shape[0], min_size) - 1):
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def kmeans_1d(values: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-cluster K-means of intensities.

    Returns:
        labels (same shape as ``values``; 0 = dark cluster, 1 = bright), centres (c_dark,
        c_bright) and standard deviations (sigma_dark, sigma_bright).
    """
    values = np.asarray(values)
    if values.dtype == np.uint8 and values.size:
        return _kmeans_u8(values, iterations)
    v = values.astype(np.float32).ravel()
    c = np.percentile(v, [10.0, 90.0]).astype(np.float64)
    if c[1] - c[0] < 1e-6:
        c = np.array([v.min() - 0.5, v.max() + 0.5])
    for _ in range(iterations):
        bright = v > 0.5 * (c[0] + c[1])
        new = np.array(
            [v[~bright].mean() if (~bright).any() else c[0], v[bright].mean() if bright.any() else c[1]]
        )
        if np.allclose(new, c, atol=1e-3):
            c = new
            break
        c = new
    bright = v > 0.5 * (c[0] + c[1])
    sig = np.array([v[~bright].std() if (~bright).any() else 0.0, v[bright].std() if bright.any() else 0.0])
    return bright.reshape(np.shape(values)).astype(np.uint8), c, sig


def _kmeans_u8(values: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`kmeans_1d` of 8-bit values, on their histogram (the same clusters, far fewer operations)."""
    hist = np.bincount(values.ravel(), minlength=256).astype(np.float64)
    g = np.arange(256, dtype=np.float64)
    cum_n, cum_s, cum_q = np.cumsum(hist), np.cumsum(hist * g), np.cumsum(hist * g * g)
    n = cum_n[-1]
    # the 10th and 90th percentiles (linear between order statistics, as np.percentile)
    pos = np.array([0.1, 0.9]) * (n - 1)
    lo = np.floor(pos)
    v_lo = np.searchsorted(cum_n, lo, side="right")
    v_hi = np.searchsorted(cum_n, np.minimum(lo + 1, n - 1), side="right")
    c = v_lo + (pos - lo) * (v_hi - v_lo)
    if c[1] - c[0] < 1e-6:
        nz = np.flatnonzero(hist)
        c = np.array([nz[0] - 0.5, nz[-1] + 0.5])

    # the iterations in Python floats (the same float64 arithmetic, without numpy's per-call cost)
    cn, cs, cq = cum_n.tolist(), cum_s.tolist(), cum_q.tolist()
    n = cn[-1]

    def split(c):  # grey levels <= k are dark
        return int(min(max(math.floor(0.5 * (c[0] + c[1])), -1), 255))

    def stats(k):
        nd = cn[k] if k >= 0 else 0.0
        sd = cs[k] if k >= 0 else 0.0
        qd = cq[k] if k >= 0 else 0.0
        return nd, sd, qd, n - nd, cs[-1] - sd, cq[-1] - qd

    c = [float(c[0]), float(c[1])]
    for _ in range(iterations):
        nd, sd, _, nb, sb, _ = stats(split(c))
        new = [sd / nd if nd else c[0], sb / nb if nb else c[1]]
        # np.allclose(new, c, atol=1e-3)
        done = all(abs(a - b) <= 1e-3 + 1e-5 * abs(b) for a, b in zip(new, c, strict=True))
        c = new
        if done:
            break
    c = np.array(c)
    k = split(c)
    nd, sd, qd, nb, sb, qb = stats(k)
    sig = np.array(
        [math.sqrt(max(qd / nd - (sd / nd) ** 2, 0.0)) if nd else 0.0,
         math.sqrt(max(qb / nb - (sb / nb) ** 2, 0.0)) if nb else 0.0]
    )  # fmt: skip
    return (values > k).astype(np.uint8), c, sig


def shadow_detected(centres: np.ndarray, sigmas: np.ndarray, lam: float) -> bool:
    """Bimodality test of eq. (3): |c1 - c2| > lambda (sigma1 + sigma2)."""
    return bool(abs(centres[1] - centres[0]) > lam * (sigmas[0] + sigmas[1]))


def label_fragmentation(labels: np.ndarray) -> float:
    """Share of an image's 4-neighbour pixel pairs whose labels differ (0: one region; 0.5: noise)."""
    lab = np.asarray(labels)
    pairs = lab[1:, :].size + lab[:, 1:].size
    if pairs == 0:
        return 0.0
    changes = np.count_nonzero(lab[1:, :] != lab[:-1, :]) + np.count_nonzero(lab[:, 1:] != lab[:, :-1])
    return float(changes) / pairs


def keep_border_segments(shadow: np.ndarray) -> np.ndarray:
    """Shadow pixels (nonzero) whose 4-connected segment touches the image border.

    The robot's shadow reaches the image border; isolated dark spots are ground texture.
    """
    mask = (np.asarray(shadow) > 0).astype(np.uint8)
    n, labels = cv2.connectedComponents(mask, connectivity=4)
    if n <= 1:
        return mask.astype(bool)
    border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.zeros(n, dtype=bool)
    keep[border] = True
    keep[0] = False
    return keep[labels]


def shadow_edge_mask(clean_shadow: np.ndarray) -> np.ndarray:
    """Edges of the cleaned label image: morphological gradient (no thinning), dilated 3 x 3."""
    img = np.asarray(clean_shadow, dtype=np.uint8)
    k = np.ones((3, 3), np.uint8)
    grad = cv2.morphologyEx(img, cv2.MORPH_GRADIENT, k)
    return cv2.dilate(grad, k) > 0


def mask_radius(max_disp: float, window: int, level: int) -> int:
    """Dilation radius of eq. (4), in pixels of pyramid level ``level``: (maxDisp + win/2) / 2^L."""
    return int(math.ceil((max_disp + window / 2.0) / 2**level))


def rigid_ransac(
    P: np.ndarray,
    C: np.ndarray,
    threshold: float,
    iterations: int = 100,
    rng: np.random.Generator | None = None,
    sample_size: int = 3,
) -> np.ndarray:
    """Largest set of 2-D points that move as one rigid pattern from ``P`` to ``C`` (eqs. 10-17).

    Each iteration samples ``sample_size`` pairs, subtracts their centroids, takes the rotation
    R = U V^T from the SVD of the covariance c' p'^T / n_s (in its 2-D closed form), and counts
    the points whose error C' - R P' (all points about the sample centroids) is under
    ``threshold``. The iterations are
    evaluated together as arrays; the first sample with the most inliers wins.

    Args:
        P: (n, 2) positions in the first frame [m].
        C: (n, 2) positions in the second frame [m].
        threshold: Inlier distance [m].
        iterations: RANSAC iterations.
        rng: Random generator (fixed seed by default, so results repeat).
        sample_size: Points per sample (3 in the paper).

    Returns:
        (n,) bool inlier mask (all False if there are fewer points than a sample).
    """
    P = np.asarray(P, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    n = len(P)
    if n < sample_size:
        return np.zeros(n, dtype=bool)
    rng = rng or np.random.default_rng(0)
    # all iterations at once: (iterations, sample_size) indices, distinct within a sample
    s = np.argpartition(rng.random((iterations, n)), sample_size - 1, axis=1)[:, :sample_size]
    p_bar, c_bar = P[s].mean(axis=1), C[s].mean(axis=1)  # eqs. 10-11
    p_s = P[s] - p_bar[:, None]  # eq. 12
    c_s = C[s] - c_bar[:, None]
    # eqs. 14-16: the rotation U V^T from the SVD of c' p'^T, with a reflection turned into a
    # rotation, is in 2-D the angle atan2(sum p' x c', sum p' . c')
    dot = np.einsum("kia,kia->k", p_s, c_s)
    cross = np.einsum("ki,ki->k", p_s[..., 0], c_s[..., 1]) - np.einsum("ki,ki->k", p_s[..., 1], c_s[..., 0])
    theta = np.arctan2(cross, dot)  # 0 for coincident points
    cos, sin = np.cos(theta), np.sin(theta)
    # eq. 17: C' - R P', all points about the sample centroids
    dx, dy = P[:, 0] - p_bar[:, :1], P[:, 1] - p_bar[:, 1:]  # (iterations, n)
    ex = C[:, 0] - c_bar[:, :1] - (cos[:, None] * dx - sin[:, None] * dy)
    ey = C[:, 1] - c_bar[:, 1:] - (sin[:, None] * dx + cos[:, None] * dy)
    inl = ex * ex + ey * ey < threshold**2
    return inl[int(np.argmax(inl.sum(axis=1)))]


@overload
def velocity_from_points(
    P: np.ndarray, C: np.ndarray, dt: float, return_cov: Literal[False] = False, rate_xy=None, weights=None
) -> tuple[np.ndarray, float]: ...
@overload
def velocity_from_points(
    P: np.ndarray, C: np.ndarray, dt: float, return_cov: Literal[True], rate_xy=None, weights=None
) -> tuple[np.ndarray, float, np.ndarray]: ...
def velocity_from_points(
    P: np.ndarray, C: np.ndarray, dt: float, return_cov: bool = False, rate_xy=None, weights=None
) -> tuple[np.ndarray, float] | tuple[np.ndarray, float, np.ndarray]:
    """(v_x, v_y, omega) of the body from ground points seen at P then C (body frame, m), eqs. 18-19.

    Point velocity is the negative of the displacement over ``dt``; each point gives the rows
    [1, 0, -r_y; 0, 1, r_x] with r its position. r is the midpoint of P and C, which makes the
    linear model exact to second order in omega dt.

    With 3-D points (n, 3) (each frame's points on that frame's ground plane), the fit is of the
    full rigid motion, v + omega x r with omega = (omega_x, omega_y, omega_z): the body's roll and
    pitch between the frames (which move the ground under a mast camera like a translation)
    are then told apart from its planar motion; (v_x, v_y, omega_z) is returned.

    ``rate_xy``: the body's roll and pitch rates (omega_x, omega_y) over the interval if measured
    (a gyro) [rad/s], for 3-D points. The fit's omega_x and omega_y are otherwise told only by
    how the two ground planes differ, and a ground nearly level under a camera at height h
    leaves v_x - h omega_y (and v_y + h omega_x) far better known than either: an error of the
    planes' tilt rate goes into the velocity times h. With them given, the fit is of
    (v_x, v_y, v_z, omega_z).

    ``weights``: (n,) relative weights of the points (None: equal); the fit is then weighted
    least squares, its RMS residual and covariance those of the weighted problem rescaled to
    the points' mean weight.

    Returns:
        (3,) velocity [m/s, m/s, rad/s] and the RMS residual of the fit (per horizontal
        coordinate) [m/s]; with ``return_cov`` also the velocity's (3, 3) covariance from the
        fit's residuals, s^2 (A^T A)^-1 (independent point errors assumed).
    """
    P = np.asarray(P, dtype=np.float64)
    C = np.asarray(C, dtype=np.float64)
    v = -(C - P) / dt
    r = 0.5 * (P + C)
    n = len(P)
    if weights is None:
        sw = None
    else:
        w = np.asarray(weights, dtype=np.float64).reshape(-1)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0) or not w.sum() > 0:
            raise ValueError(f"weights: give {n} finite weights >= 0, not all 0")
        sw = np.sqrt(w / w.mean())
    if P.shape[1] == 2:
        A = _planar_design(r)
        b = v.reshape(-1)
        if sw is not None:
            A, b = A * np.repeat(sw, 2)[:, None], b * np.repeat(sw, 2)
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
        res = A @ sol - b
        rms = float(np.sqrt(np.mean(res**2)))
        return (sol, rms, _covariance(A, res)) if return_cov else (sol, rms)
    # unknowns (v_x, v_y, v_z, w_x, w_y, w_z); point velocity v + w x r
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    one, zero = np.ones(n), np.zeros(n)
    A = np.empty((3 * n, 6))
    A[0::3] = np.column_stack([one, zero, zero, zero, z, -y])
    A[1::3] = np.column_stack([zero, one, zero, -z, zero, x])
    A[2::3] = np.column_stack([zero, zero, one, y, -x, zero])
    b = v.reshape(-1)
    if sw is not None:
        A, b = A * np.repeat(sw, 3)[:, None], b * np.repeat(sw, 3)
    if rate_xy is None:
        sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    else:  # the known roll and pitch rates moved to the right-hand side
        w = np.asarray(_rates(rate_xy))
        part, *_ = np.linalg.lstsq(A[:, [0, 1, 2, 5]], b - A[:, 3:5] @ w, rcond=None)
        sol = np.array([part[0], part[1], part[2], w[0], w[1], part[3]])
    res = (A @ sol - b).reshape(n, 3)[:, :2].reshape(-1)
    rms = float(np.sqrt(np.mean(res**2)))
    if not return_cov:
        return sol[[0, 1, 5]], rms
    # the horizontal rows carry the noise (the heights follow from the planes)
    Ah = _planar_design(r) if sw is None else _planar_design(r) * np.repeat(sw, 2)[:, None]
    return sol[[0, 1, 5]], rms, _covariance(Ah, res)


# ---------------------------------------------------------------------------------------- local plane
@dataclass(frozen=True)
class LocalPlaneFit:
    """Result of :func:`local_plane_motion`.

    Attributes:
        twist: (v_x, v_y, v_z, omega_x, omega_y, omega_z) of the body over the pair [m/s, rad/s].
        plane: The ground under the view in the first frame, (a, b, c) of z = a x + b y + c in
            the body frame [-, -, m].
        P: (n, 3) the tracked ground points in the first frame's body frame [m].
        C: (n, 3) the same points as seen in the second frame (its body frame) [m].
        rms_px: RMS reprojection residual [px].
        kept: (n_tracks,) bool, the tracks that ``P`` and ``C`` hold (``FlowOdometry`` drops those
            that its plane's fits leave unexplained, ``plane_outlier``); None: all of them.
    """

    twist: np.ndarray
    plane: tuple[float, float, float]
    P: np.ndarray
    C: np.ndarray
    rms_px: float
    kept: np.ndarray | None = None


def local_plane_motion(
    und_prev: np.ndarray,
    und_curr: np.ndarray,
    camera: PinholeCamera,
    ground_plane: tuple[float, float, float],
    dt: float,
    init: tuple[float, float, float],
    *,
    anchor: tuple[float, float] | None = None,
    rate_xy=None,
    hold_tilt: bool = False,
    tilt_std: float = 0.1,
    rate_std: float = 0.3,
    pixel_std: float = 0.05,
    iterations: int = 6,
) -> LocalPlaneFit | None:
    """The body's motion over a frame pair and the tilt of the ground the camera sees (MAP fit).

    Rough ground under a mast camera is not the plane under the wheels: the patch in view is
    tilted against it, and the body pitches and rolls as it drives over it. Both move the ground
    points as a planar translation would (the camera at height h moves by v_x - h omega_y), so a
    fit on the wheels' plane takes the pitch rate and the patch's tilt into the speed. Here each
    tracked feature is a ray to one plane z = a x + b y + c (body frame, first frame) that keeps
    the given plane's height at ``anchor`` and takes its own tilt (a, b); the body moves by
    (v, omega) over ``dt``; the features of the second frame are that plane's points reprojected
    (exact rigid motion, pinhole). Tilt and motion are fitted by Gauss-Newton on the pixel
    residuals (weight 1 / ``pixel_std``), with Gaussian priors that keep the problem posed on
    sparse or short tracks: the tilt about the given plane's (``tilt_std``), the roll and pitch
    rates about zero (``rate_std``) unless measured (``rate_xy``, then held). The pitch rate is
    told from the translation by the perspective of the view only, and the camera's height over
    the patch by nothing a single camera sees: the plane's height stays the given one at the
    anchor (the front axle on a rover, whose wheels stand on the ground next to the view).

    Args:
        und_prev: (n, 2) undistorted pixels of the features in the first frame [px].
        und_curr: (n, 2) the same features in the second frame [px].
        camera: The calibrated camera (``K``, ``T_body_cam``).
        ground_plane: The ground under the wheels in the first frame, (a, b, c) [-, -, m].
        dt: Time between the frames [s].
        init: (v_x, v_y, omega_z) to start from (a planar fit) [m/s, m/s, rad/s].
        anchor: Body (x, y) where the plane keeps ``ground_plane``'s height [m]; None: where the
            optical axis meets ``ground_plane``.
        rate_xy: Measured (omega_x, omega_y) over the pair [rad/s], or None.
        hold_tilt: Keep the tilt of ``ground_plane`` (fit the motion only).
        tilt_std: Prior standard deviation of the tilt about ``ground_plane``'s [-].
        rate_std: Prior standard deviation of omega_x and omega_y [rad/s].
        pixel_std: Standard deviation of a tracked feature's position, per axis [px].
        iterations: Most Gauss-Newton steps (the Jacobian is kept while the steps converge).

    Returns:
        The fit, or None when the rays do not all meet the plane in front of the camera (the
        caller keeps its planar fit).
    """
    problem = _LocalPlane(und_prev, und_curr, camera, ground_plane, dt, anchor, tilt_std, rate_std, pixel_std)
    rates = _rates(rate_xy)
    theta = problem.start(init, (0.0, 0.0) if rates is None else rates)
    free = np.ones(8, dtype=bool)
    free[5:7] = rates is None
    free[0:2] = not hold_tilt
    out = problem.fit(theta, free, iterations=iterations)
    return None if out is None else problem.result(*out)


class _LocalPlane:
    """The pixel residuals of :func:`local_plane_motion` and their Gauss-Newton fit.

    Parameters theta = (a, b, v_x, v_y, v_z, omega_x, omega_y, omega_z); residuals: the 2n pixel
    errors over ``pixel_std``, then the four prior rows of (a, b, omega_x, omega_y).
    """

    def __init__(self, und_prev, und_curr, camera, ground_plane, dt, anchor, tilt_std, rate_std, pixel_std):
        K = camera.K
        self.K, self.dt, self.pixel_std = K, dt, pixel_std
        self.R_bc, self.o = camera.T_body_cam[:3, :3], camera.T_body_cam[:3, 3]
        self.n = n = len(und_prev)
        self.und_curr = und_curr
        self.rays = self._rays(und_prev)
        a0, b0, c0 = ground_plane
        o = self.o
        if anchor is None:
            axis = self.R_bc[:, 2]
            s = (c0 + a0 * o[0] + b0 * o[1] - o[2]) / (axis[2] - a0 * axis[0] - b0 * axis[1])
            anchor = (float(o[0] + s * axis[0]), float(o[1] + s * axis[1]))
        self.xa, self.ya = anchor
        self.za = a0 * self.xa + b0 * self.ya + c0
        self.tilt0 = (a0, b0)
        self.prior_mu = np.array([a0, b0, 0.0, 0.0])
        self.prior_w = np.array([1 / tilt_std, 1 / tilt_std, 1 / rate_std, 1 / rate_std])
        self.target = und_curr.reshape(-1)
        self.J_prior = np.zeros((4, 8))
        self.J_prior[[0, 1, 2, 3], [0, 1, 5, 6]] = self.prior_w
        self.Jp = np.empty((n, 2, 8))

    def _rays(self, und: np.ndarray) -> np.ndarray:
        K = self.K
        r = np.ones((len(und), 3))
        r[:, 0] = (und[:, 0] - K[0, 2]) / K[0, 0]
        r[:, 1] = (und[:, 1] - K[1, 2]) / K[1, 1]
        return r @ self.R_bc.T

    def start(self, init, rates) -> np.ndarray:
        """The parameters of the given plane's tilt, ``init`` (v_x, v_y, omega_z) and ``rates``."""
        return np.array([*self.tilt0, init[0], init[1], 0.0, rates[0], rates[1], init[2]], dtype=np.float64)

    def _depth(self, a: float, b: float) -> tuple[np.ndarray, float, np.ndarray]:
        o, rays = self.o, self.rays
        num = self.za + a * (o[0] - self.xa) + b * (o[1] - self.ya) - o[2]
        den = rays[:, 2] - a * rays[:, 0] - b * rays[:, 1]
        return num / den, num, den

    def residual(self, th: np.ndarray, jacobian: bool):
        """Residuals at ``th`` (None: a ray misses the plane) and, if asked, their (2n + 4, 8) Jacobian."""
        K, dt, o, n = self.K, self.dt, self.o, self.n
        s, num, den = self._depth(th[0], th[1])
        if not np.all(s > 0):
            return None, None
        Y = o + s[:, None] * self.rays - th[2:5] * dt
        A = self.R_bc.T @ _rotation(th[5:8] * dt).T  # body frame 1 (moved) -> camera 2
        Xc = (Y @ A.T) - self.R_bc.T @ o
        z = Xc[:, 2]
        if not np.all(z > 0):
            return None, None
        xn, yn = Xc[:, 0] / z, Xc[:, 1] / z
        res = np.empty(2 * n + 4)
        res[0 : 2 * n : 2] = (K[0, 0] * xn + K[0, 2] - self.target[0::2]) / self.pixel_std
        res[1 : 2 * n : 2] = (K[1, 1] * yn + K[1, 2] - self.target[1::2]) / self.pixel_std
        res[2 * n :] = (th[[0, 1, 5, 6]] - self.prior_mu) * self.prior_w
        if not jacobian:
            return res, None
        # d(camera-2 point) / d(a, b, v, omega), (n, 3, 8); omega to first order: R^T (Y + Y x w dt)
        dC = np.empty((n, 3, 8))
        ds_da = ((o[0] - self.xa) * den + num * self.rays[:, 0]) / den**2
        ds_db = ((o[1] - self.ya) * den + num * self.rays[:, 1]) / den**2
        rays_c = self.rays @ A.T
        dC[:, :, 0] = rays_c * ds_da[:, None]
        dC[:, :, 1] = rays_c * ds_db[:, None]
        dC[:, :, 2:5] = -dt * A
        zero = np.zeros(n)
        for k, col in enumerate(
            (np.column_stack([zero, Y[:, 2], -Y[:, 1]]), np.column_stack([-Y[:, 2], zero, Y[:, 0]]),
             np.column_stack([Y[:, 1], -Y[:, 0], zero]))
        ):  # fmt: skip
            dC[:, :, 5 + k] = dt * (col @ A.T)
        Jp = self.Jp
        Jp[:, 0] = K[0, 0] * (dC[:, 0] - xn[:, None] * dC[:, 2]) / z[:, None]
        Jp[:, 1] = K[1, 1] * (dC[:, 1] - yn[:, None] * dC[:, 2]) / z[:, None]
        return res, np.vstack([Jp.reshape(2 * n, 8) / self.pixel_std, self.J_prior])

    def fit(self, theta: np.ndarray, free: np.ndarray, first=None, iterations: int = 6):
        """Gauss-Newton over the ``free`` parameters from ``theta`` (``first``: its residuals, Jacobian).

        Returns:
            The parameters and their residuals, or None (a ray misses the plane at the start).
        """
        r, J = first if first is not None else self.residual(theta, True)
        if r is None or J is None:
            return None
        cols = np.flatnonzero(free)
        J = J[:, cols]
        cost = float(r @ r)
        fresh = True  # the Jacobian is of the current estimate (chord steps reuse an older one)
        for _ in range(iterations):
            JtJ = J.T @ J
            delta = np.linalg.solve(JtJ + 1e-9 * np.diag(np.diag(JtJ)), -J.T @ r)
            th = theta.copy()
            th[cols] += delta
            rn, _ = self.residual(th, False)
            if rn is None or float(rn @ rn) >= cost:
                if fresh:
                    break
                r, Jf = self.residual(theta, True)
                if r is None or Jf is None:  # cannot happen: its residuals were computed
                    return None
                J, fresh = Jf[:, cols], True
                continue
            converged = float(rn @ rn) > cost * (1.0 - 1e-3)
            theta, r, cost, fresh = th, rn, float(rn @ rn), False
            if converged:
                break
        return theta, r

    def chi2(self, r: np.ndarray) -> float:
        """Sum of the squared pixel residuals of ``r`` in units of ``pixel_std``."""
        return float(r[: 2 * self.n] @ r[: 2 * self.n])

    def result(self, theta: np.ndarray, r: np.ndarray) -> LocalPlaneFit:
        """The fit of ``theta`` (residuals ``r``): the points in both frames, the plane, the RMS."""
        n, o, dt = self.n, self.o, self.dt
        rms_px = math.sqrt(self.chi2(r) / (2 * n)) * self.pixel_std
        a, b = theta[0], theta[1]
        X1 = o + self._depth(a, b)[0][:, None] * self.rays
        # the second frame's rays on the plane moved into its body frame
        R = _rotation(theta[5:8] * dt)
        normal = np.array([-a, -b, 1.0])
        d1 = self.za - a * self.xa - b * self.ya
        n2 = R.T @ normal
        d2 = d1 - normal @ theta[2:5] * dt
        rays2 = self._rays(self.und_curr)
        C = o + ((d2 - n2 @ o) / (rays2 @ n2))[:, None] * rays2
        return LocalPlaneFit(theta[2:].copy(), (float(a), float(b), float(d1)), X1, C, rms_px)


def _rotation(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector [rad] (Rodrigues)."""
    x, y, z = float(rotvec[0]), float(rotvec[1]), float(rotvec[2])
    angle = math.sqrt(x * x + y * y + z * z)
    if angle < 1e-12:
        return np.eye(3)
    x, y, z = x / angle, y / angle, z / angle
    c, s = math.cos(angle), math.sin(angle)
    t = 1.0 - c
    return np.array(
        [
            [c + t * x * x, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, c + t * y * y, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, c + t * z * z],
        ]
    )


#: Rounds of dropping the tracks that the local plane's fits do not explain (``plane_outlier``).
PLANE_OUTLIER_ROUNDS = 3


def _unexplained(problem: _LocalPlane, theta: np.ndarray, k: float) -> np.ndarray:
    """(n,) bool: the tracks whose pixel residual at ``theta`` exceeds ``k`` times the median's."""
    r, _ = problem.residual(theta, False)
    if r is None:
        return np.zeros(problem.n, dtype=bool)
    norm = np.hypot(r[0 : 2 * problem.n : 2], r[1 : 2 * problem.n : 2])
    return norm > k * float(np.median(norm))


def _planar_design(r: np.ndarray) -> np.ndarray:
    """Rows [1, 0, -r_y; 0, 1, r_x] of the planar velocity model for points r (n, >= 2) [m]."""
    A = np.zeros((2 * len(r), 3))
    A[0::2, 0] = 1.0
    A[0::2, 2] = -r[:, 1]
    A[1::2, 1] = 1.0
    A[1::2, 2] = r[:, 0]
    return A


def _centroid_std(P: np.ndarray, C: np.ndarray, cov: np.ndarray) -> float:
    """Largest standard deviation of the ground velocity (x or y) at the points' centroid [m/s]."""
    xc, yc = 0.5 * (P[:, :2] + C[:, :2]).mean(axis=0)
    J = np.array([[1.0, 0.0, -yc], [0.0, 1.0, xc]])
    return float(np.sqrt(np.max(np.diag(J @ cov @ J.T))))


def _covariance(A: np.ndarray, res: np.ndarray) -> np.ndarray:
    """Covariance of a least-squares solution: s^2 (A^T A)^-1 with s^2 = SSR / dof."""
    dof = max(A.shape[0] - A.shape[1], 1)
    return np.linalg.pinv(A.T @ A) * (float(res @ res) / dof)


# ---------------------------------------------------------------------------------------- estimator
@dataclass(frozen=True)
class FlowOdometryConfig:
    """Parameters of :class:`FlowOdometry` (pixel sizes are at full resolution).

    Attributes:
        min_level_size: Smallest pyramid level used for the mask, (W, H) [px] (>= 80 x 60).
        bimodality_lambda: lambda of eq. (3); low so that shadows are never missed (false
            positives only exclude a few edges).
        shadow_max_fragmentation: A bimodal image is a shadow only if its two clusters are
            coherent regions: at most this share of the smallest level's pixel boundaries
            (4-neighbours) joins pixels of different clusters (:func:`label_fragmentation`). A
            coarse ground (gravel, at a grazing sun) can split in two clusters that percolate,
            touch the border everywhere and fence off every feature; the robot's shadow splits
            0.01-0.06 of the boundaries (5th to 95th percentile), such ground 0.24-0.26, and
            two clusters of independent pixels 0.5.
        canny_high: Canny high threshold as a multiple of |c1 - c2| (Sobel magnitude units).
        canny_low: Canny low threshold as a share of the high one.
        max_disp: Largest feature displacement between frames [px] (eq. 4).
        window: Lucas-Kanade window [px].
        lk_levels: Lucas-Kanade pyramid levels above the base.
        max_features: Harris features selected per frame.
        harris_width: Harris runs on the finest pyramid level at most this wide [px] (block
            7 px at full resolution, 3 px on a coarser level) and the corners are scaled to full
            resolution. At 640 px the half-resolution corners track as accurately (velocity
            errors within 1 % on flat and rough ground, 2 x 360 frames) and cost a quarter.
        min_distance: Minimum distance between features [px].
        quality_level: Harris quality level (share of the strongest corner).
        quality_percentile: Where that leaves fewer than ``max_features // 2`` corners, the
            region is searched again with the quality level taken as a share of this
            percentile of its Harris response instead of its maximum [%] (0: off). A small,
            high-contrast object, such as the shadow of the rover's mast cast as a blob at the
            view's edge, holds the strongest corner and the lit ground's faint texture then
            never reaches its share: on a randomised world's pale sand (flat mission, seed 8,
            train preset) 3-11 corners were found a frame where the ground held a hundred, and
            two of three frame pairs were invalid for half a minute.
        roi_margin: Share of the width and height kept clear of features at each border.
        fb_threshold: Largest forward-backward tracking error [px].
        fb_levels: Pyramid levels above the base of the backward track. It starts at the
            feature's own position, so it refines a correct forward track in a step or two; a
            wrong one (off by up to about half the window) ends away from the start.
        ransac_threshold: RANSAC inlier distance [m].
        ransac_iterations: RANSAC iterations.
        min_inliers: Fewest inliers for a valid estimate.
        min_inlier_ratio: Smallest inlier share of the tracked features for a valid estimate.
        max_std: Largest standard deviation of the ground velocity at the inliers' centroid
            (either axis, from ``twist_cov``) for a valid estimate [m/s]: it catches fits that
            went wrong; a usable fit's uncertainty goes with it in the covariance.
        noise_scale: Factor on the fit's standard deviations for errors that the residuals do
            not show (point errors are not independent: they share the texture's aliasing and
            the ground's relief); 1.5 makes the deviations about right at 160 px on flat,
            shadowed and rough ground.
        shadow_split: Where a shadow is detected, select features in it too, on their own (up to
            its share of the allowed area, at most half of ``max_features``, at a tenth of the
            quality level), besides ``max_features`` on the lit ground: Harris's quality level is
            relative to the strongest corner, which the lit ground holds, so a dark shadow
            otherwise gets none and the features crowd on one side of the view (which the
            ground's tilt is then fitted from).
        shadow_residual_ratio: The shadow's features are dropped from a pair when the RMS of
            their residuals about the planar fit exceeds this multiple of the lit ones' (on dim,
            noisy shadow they track noise).
        local_plane: With the ground planes of both frames given (3-D mode), fit the tilt of the
            ground in view and the body's roll and pitch rates with the velocity
            (:func:`local_plane_motion`); without it the features lie on the planes given (the
            wheels' plane) and the rates come from how those planes differ. On rough ground the
            patch in view tilts against the wheels' plane (4.5 degrees RMS on
            ``RoverRoughSlippery-v0``) and the body pitches at 0.13 rad/s RMS, which the speed
            took up: speed MAE 0.074 against 0.051 m/s, yaw rate 0.045 against 0.026 rad/s
            (eval preset, scripted slip drive, docs/odometry.md). Measured roll and pitch rates
            (``rate_xy``) are held in the fit.
        plane_anchor: Body (x, y) [m] where the fitted plane keeps the given plane's height (one
            camera cannot see its height over the ground): None, where the optical axis meets
            the given plane; :class:`perception.RoverEstimator` sets the front axle, whose
            wheels stand on the ground next to the view.
        tilt_std: Prior standard deviation of the fitted tilt about the given plane's [-].
        rate_std: Prior standard deviation of the fitted roll and pitch rates [rad/s].
        track_std: Standard deviation of a tracked feature's position, per axis [px] (weighs the
            priors against the tracks).
        plane_test: The fitted tilt and rates are used where they explain the tracks: where the
            F statistic of the drop in the squared pixel residuals against the fit held to the
            wheels' plane (and its rates) reaches this; else the held fit is used (on flat
            ground the extra freedom only adds noise). 0: always the fitted plane.
        plane_outlier: A track whose pixel residual under the fit taken (where the free one is
            taken, under either fit) exceeds this multiple of the median track's is dropped, and
            a free fit is made again (at most ``PLANE_OUTLIER_ROUNDS`` times; 0: none dropped).
            Features on the edge of the rover's own shadow move with the camera, and RANSAC's
            ground threshold (1.5 px at the train preset) keeps them while the flow is a few
            pixels a frame; the free fit took their lag as a tilt of 0.2-0.4 and the speed fell
            by a third (randomised worlds, ``RoverRoughSlippery-v0``, docs/odometry.md).
        plane_iterations: Most Gauss-Newton steps of the held and the free fit (the problem is
            nearly linear from the planar fit: more steps change the speed by under 1 mm/s).
        plane_max_points: The plane is fitted on at most this many of the inliers (spread over
            them); all of them are then put on it.
        use_mask: Ablation switch: the shadow-edge feature mask.
        use_ransac: Ablation switch: RANSAC (off: every tracked feature is used).
        history_frames: Earlier frames' features kept for :meth:`FlowOdometry.track_back`.
        repeated_frames: What two bit-identical frames mean. ``"invalid"`` (the default): a real
            camera's frames always differ by sensor noise, so an identical pair is a frozen
            camera or a repeated frame, and no motion is observable. ``"still"``: the camera is
            noise-free and renders every frame anew (the simulation's), so the rover stands
            still and the pair is tracked as any other (a valid zero).
        static_rate: In a chained stream (:meth:`FlowOdometry.update`), the weight of a frame
            in the running means of the static image: each grey frame's fine texture (the frame
            less its Gaussian blur of ``static_sigma``) and its square. They are fed while the
            last valid estimate moved at ``static_min_speed`` or more, when the ground's
            texture averages out and what stays is what does not move with it: a sensor's
            fixed pattern, the edges of the rover's own shadow and parts in view, which on
            low-texture ground pull the tracks toward zero motion. The mean still holds a share
            ``rate / (2 - rate)`` of the texture's variance, and a shadow that moves across the
            view varies far more than that: the pattern is shrunk to ``g * mean`` with
            ``g = max(0, 1 - static_shrink * residual / mean^2)`` (both local means), so a
            moving shadow's trail is not taken out (taking it out drew false edges that held
            the tracks). The pattern is taken out of each frame at its least-squares strength
            in the frame's fine texture (0 to 1.5). 0 (the default): off. Measured in
            docs/odometry.md.
        static_min_speed: See ``static_rate`` [m/s].
        static_min_frames: Frames the static image needs before it is taken out.
        static_sigma: Width of the blur that splits off the fine texture, as a share of the
            image width (0.025: 4 px at 160 px).
        static_shrink: Multiple of the mean's expected residual texture a pattern must exceed.
    """

    min_level_size: tuple[int, int] = (80, 60)
    bimodality_lambda: float = 1.5
    shadow_max_fragmentation: float = 0.15
    canny_high: float = 2.0
    canny_low: float = 0.5
    max_disp: float = 25.0
    window: int = 21
    lk_levels: int = 3
    max_features: int = 50
    harris_width: int = 320
    min_distance: float = 20.0
    quality_level: float = 0.01
    quality_percentile: float = 95.0
    roi_margin: float = 0.15
    fb_threshold: float = 0.5
    fb_levels: int = 0
    ransac_threshold: float = 0.003
    ransac_iterations: int = 100
    min_inliers: int = 8
    min_inlier_ratio: float = 0.3
    max_std: float = 0.02
    noise_scale: float = 1.5
    shadow_split: bool = True
    shadow_residual_ratio: float = 2.0
    local_plane: bool = True
    plane_anchor: tuple[float, float] | None = None
    tilt_std: float = 0.1
    rate_std: float = 0.3
    track_std: float = 0.05
    plane_test: float = 10.0
    plane_outlier: float = 4.0
    plane_iterations: tuple[int, int] = (1, 2)
    plane_max_points: int = 60
    use_mask: bool = True
    use_ransac: bool = True
    history_frames: int = 15
    repeated_frames: str = "invalid"
    static_rate: float = 0.0
    static_min_speed: float = 0.05
    static_min_frames: int = 10
    static_sigma: float = 0.025
    static_shrink: float = 2.0

    @classmethod
    def for_camera(cls, width: int, rate_hz: float, **overrides) -> FlowOdometryConfig:
        """The defaults (tuned at 640 px and 60 Hz) with pixel sizes scaled to another camera.

        Displacements scale with the width and with the frame period; feature spacing and the
        tracking window with the width (the window stays odd and >= 9 px: at 160 px a 7 px window
        tracks more noisily, and often runs all 30 iterations: twice the time). Ground distances
        scale with the ground size of a pixel (1/width): the RANSAC inlier distance, and the
        residual bound with it and the frame rate (a residual in m/s is a pixel error times
        metres per pixel times the rate). The Harris quality level scales with
        the pixel area: a small image holds far fewer corners near its strongest one, and at
        160 px the default level keeps only ~20 features, too few for RANSAC.

        Args:
            width: Image width [px].
            rate_hz: Frame rate [Hz].
            overrides: Fields to set explicitly.
        """
        if not (width > 0 and rate_hz > 0):
            raise ValueError(f"width={width!r}, rate_hz={rate_hz!r}: both must be > 0")
        s = width / 640.0
        base = cls()
        window = max(9, int(round(base.window * s)) | 1)
        scaled: dict[str, Any] = dict(
            max_disp=base.max_disp * s * 60.0 / rate_hz,
            window=window,
            min_distance=max(3.0, base.min_distance * s),
            quality_level=base.quality_level * min(1.0, s * s),
            ransac_threshold=base.ransac_threshold / s,
            max_std=base.max_std / s * rate_hz / 60.0,
        )
        scaled.update(overrides)
        return cls(**scaled)

    def __post_init__(self) -> None:
        if not (isinstance(self.history_frames, int) and 0 <= self.history_frames <= 120):
            raise ValueError(
                f"history_frames: {self.history_frames!r}; give a whole number of frames in [0, 120]"
            )
        w, h = self.min_level_size
        if w < 80 or h < 60:
            raise ValueError(f"min_level_size: {self.min_level_size} is below the paper's 80 x 60 minimum")
        for name in (
            "bimodality_lambda",
            "shadow_max_fragmentation",
            "canny_high",
            "max_disp",
            "ransac_threshold",
            "max_std",
            "noise_scale",
            "shadow_residual_ratio",
            "tilt_std",
            "rate_std",
            "track_std",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: {getattr(self, name)!r} must be > 0")
        if not (isinstance(self.plane_max_points, int) and self.plane_max_points >= 8):
            raise ValueError(f"plane_max_points: {self.plane_max_points!r}; use an integer >= 8")
        its = tuple(self.plane_iterations)
        if len(its) != 2 or not all(isinstance(k, int) and k >= 1 for k in its):
            raise ValueError(f"plane_iterations: {self.plane_iterations!r}; use two integers >= 1")
        if not self.plane_test >= 0:
            raise ValueError(f"plane_test: {self.plane_test!r}; use an F statistic >= 0")
        if not (self.plane_outlier == 0 or self.plane_outlier > 1):
            raise ValueError(f"plane_outlier: {self.plane_outlier!r}; use a multiple of the median > 1, or 0")
        if not (self.window >= 5 and self.window % 2 == 1):
            raise ValueError(f"window: {self.window} px; use an odd size >= 5")
        if not self.harris_width >= 80:
            raise ValueError(f"harris_width: {self.harris_width!r} px; use >= 80 (the paper's smallest)")
        if not (isinstance(self.fb_levels, int) and 0 <= self.fb_levels <= self.lk_levels):
            raise ValueError(f"fb_levels: {self.fb_levels!r}; use an integer from 0 to {self.lk_levels}")
        if not 0.0 <= self.quality_percentile < 100.0:
            raise ValueError(
                f"quality_percentile: {self.quality_percentile!r}; use a percentile in [0, 100), 0 for off"
            )
        if not 0.0 <= self.roi_margin < 0.5:
            raise ValueError(f"roi_margin: {self.roi_margin}; use a share in [0, 0.5)")
        if self.min_inliers < 2:
            raise ValueError("min_inliers: at least 2 features are needed for (v_x, v_y, omega)")
        if not (
            0.0 <= self.static_rate <= 1.0 and self.static_min_speed >= 0 and self.static_min_frames >= 1
        ):
            raise ValueError(
                f"static_rate={self.static_rate!r}, static_min_speed={self.static_min_speed!r}, "
                f"static_min_frames={self.static_min_frames!r}: use a weight in [0, 1], a speed >= 0 "
                "[m/s] and at least 1 frame"
            )
        if not (0.0 < self.static_sigma <= 0.25 and self.static_shrink >= 0.0):
            raise ValueError(
                f"static_sigma={self.static_sigma!r}, static_shrink={self.static_shrink!r}: use a share of "
                "the image width in (0, 0.25] and a multiple >= 0"
            )
        if self.plane_anchor is not None:
            anchor = tuple(float(v) for v in self.plane_anchor)
            if len(anchor) != 2 or not all(math.isfinite(v) for v in anchor):
                raise ValueError(f"plane_anchor: {self.plane_anchor!r}; use a finite body (x, y) [m] or None")
            object.__setattr__(self, "plane_anchor", anchor)
        if self.repeated_frames not in ("invalid", "still"):
            raise ValueError(f"repeated_frames: {self.repeated_frames!r}; use 'invalid' or 'still'")


@dataclass
class MaskDiagnostics:
    """Intermediate images of the feature-selection mask (the paper's Fig. 3), at pyramid ``level``.

    Attributes:
        level: Pyramid level of the images.
        small: The grey image at that level.
        centres: K-means centres (dark, bright).
        sigmas: K-means standard deviations.
        shadow: Whether eq. (3) detected a shadow.
        labels: K-means labels (1 = shadow).
        clean: Labels with shadow segments not touching the border removed.
        edge_mask: Shadow-edge mask (gradient of ``clean``, dilated 3 x 3).
        canny: Raw Canny output.
        parsed: Canny output inside the shadow-edge mask.
        forbidden: Parsed edges dilated by the radius of eq. (4).
    """

    level: int
    small: np.ndarray
    centres: np.ndarray
    sigmas: np.ndarray
    shadow: bool
    labels: np.ndarray
    clean: np.ndarray
    edge_mask: np.ndarray
    canny: np.ndarray
    parsed: np.ndarray
    forbidden: np.ndarray


@dataclass
class Selection:
    """Features chosen on ``I_prev`` before ``I_curr`` exists (Algorithm 1, lines 2-4).

    Attributes:
        gray: ``I_prev`` as grey levels.
        features: (n, 2) float32 pixel positions.
        mask: (H, W) bool, where features were allowed.
        t: Time of ``I_prev`` [s] (None if not given).
        diagnostics: Intermediate images of the mask.
        ground_plane: The ground under the body when ``I_prev`` was taken, (a, b, c) of
            z = a x + b y + c in the body frame [-, -, m] (None: not given).
        in_shadow: (n,) bool: the feature was chosen in the detected shadow (``shadow_split``).
    """

    gray: np.ndarray
    features: np.ndarray
    mask: np.ndarray
    t: float | None = None
    diagnostics: MaskDiagnostics | None = None
    ground_plane: tuple[float, float, float] | None = None
    in_shadow: np.ndarray | None = None


@dataclass
class OdometryEstimate:
    """One velocity estimate from a frame pair.

    Attributes:
        v_x: Forward velocity of the body origin [m/s] (NaN when invalid).
        v_y: Leftward velocity [m/s] (NaN when invalid).
        omega: Yaw rate [rad/s] (NaN when invalid).
        valid: Whether the estimate can be trusted.
        reason: Why it is invalid ("" when valid).
        quality: 0 (invalid) to 1: inlier count against ``2 * min_inliers`` times inlier ratio.
        n_features: Features selected on ``I_prev``.
        n_tracked: Features that passed the forward-backward check.
        n_inliers: RANSAC inliers.
        inlier_ratio: n_inliers / n_tracked.
        residual: RMS residual of the velocity fit [m/s].
        dt: Time between the frames [s].
        twist_cov: (3, 3) covariance of (v_x, v_y, omega): the fit's, scaled by
            ``FlowOdometryConfig.noise_scale`` squared (NaN when invalid). The yaw rate is the
            least certain part (the camera sees a patch about a metre across) and its error
            moves v_y the opposite way, which the covariance carries.
        t: Time of ``I_curr`` [s] (None if not given).
        prev_px: (n_tracked, 2) tracked features in ``I_prev`` [px].
        curr_px: (n_tracked, 2) their positions in ``I_curr`` [px].
        inliers: (n_tracked,) bool.
        selection: The selection the estimate started from (its diagnostics included).
    """

    v_x: float
    v_y: float
    omega: float
    valid: bool
    reason: str
    quality: float
    n_features: int
    n_tracked: int
    n_inliers: int
    inlier_ratio: float
    residual: float
    dt: float
    t: float | None = None
    twist_cov: np.ndarray = field(default_factory=lambda: np.full((3, 3), math.nan))
    prev_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    curr_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), repr=False)
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool), repr=False)
    selection: Selection | None = field(default=None, repr=False)

    @property
    def twist(self) -> np.ndarray:
        """(v_x, v_y, omega)."""
        return np.array([self.v_x, self.v_y, self.omega])

    @property
    def twist_std(self) -> np.ndarray:
        """(3,) standard deviations of (v_x, v_y, omega) [m/s, m/s, rad/s] (NaN when invalid)."""
        return np.sqrt(np.diag(self.twist_cov))


def to_gray(image: np.ndarray, size: tuple[int, int] | None = None) -> np.ndarray:
    """uint8 grey image from an (H, W) or (H, W, 3) RGB uint8 image, checked against ``size`` (W, H)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"image: dtype {img.dtype}; expected uint8 grey or RGB")
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif img.ndim != 2:
        raise ValueError(f"image: shape {img.shape}; expected (H, W) or (H, W, 3)")
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise ValueError(
            f"image: {img.shape[1]}x{img.shape[0]} px, but the camera calibration is {size[0]}x{size[1]} px; "
            "use the calibration of this camera and resolution"
        )
    return img


class FlowOdometry:
    """Shadow-robust optical-flow odometry (Algorithm 1 of the odometry paper).

    Use :meth:`select` on ``I_prev`` (before ``I_curr`` is captured), then :meth:`track` with
    ``I_curr``; or :meth:`estimate` for a pair; or :meth:`update` for a chained stream in which
    each frame is ``I_curr`` of one pair and ``I_prev`` of the next.

    Args:
        camera: Calibrated downward camera (intrinsics, distortion, ``T_body_cam`` and the ground
            plane in the body frame).
        config: Parameters.
        vignetting: The lens's relative illumination at the image corners
            (:attr:`perception.rig.SensorSpec.vignetting`; 1: none). Each frame is flat-fielded
            before anything else: the shading is fixed to the sensor and would pull the flow of
            faint texture towards zero.
        gamma: The camera's response exponent (:attr:`perception.rig.SensorSpec.gamma`), with
            which the shading reaches the encoded values.
    """

    def __init__(
        self,
        camera: PinholeCamera,
        config: FlowOdometryConfig | None = None,
        *,
        vignetting: float = 1.0,
        gamma: float = 1.0,
    ) -> None:
        if camera.ground_plane is None:
            from perception.models.cameras import GROUND_PLANE_MISSING

            raise ValueError(GROUND_PLANE_MISSING)
        self.camera = camera
        self.config = cfg = config or FlowOdometryConfig()
        w, h = camera.image_size
        self._H_inv = np.linalg.inv(camera.ground_homography())
        self._flat = flat_field_gain((w, h), float(vignetting), float(gamma))
        mx, my = int(cfg.roi_margin * w), int(cfg.roi_margin * h)
        self._roi = np.zeros((h, w), dtype=bool)
        self._roi[my : h - my, mx : w - mx] = True
        # Harris on pyramid level L (the mask's level is the coarsest one built)
        top = pyramid_levels(w, h, cfg.min_level_size) - 1
        L = 0
        while w >> L > cfg.harris_width and L < top:
            L += 1
        self._harris_level, self._harris_block = L, 7 if L == 0 else 3
        # its crop: the region of interest at level L and the detector's block radius + 1 about
        # it, so the crop's edge responses equal the whole level's
        b = self._harris_block // 2 + 1
        hl, wl = (h + (1 << L) - 1) >> L, (w + (1 << L) - 1) >> L  # pyrDown rounds up
        my_l, mx_l = -(-my >> L), -(-mx >> L)
        self._roi_box = (max(0, my_l - b), min(hl, hl - my_l + b), max(0, mx_l - b), min(wl, wl - mx_l + b))
        self._last: Selection | None = None
        self._history: deque[Selection] = deque(maxlen=cfg.history_frames + 1)
        self._rng = np.random.default_rng(0)
        # running means of the grey frames' fine texture and its square (static_rate)
        self._static: np.ndarray | None = None
        self._static_sq: np.ndarray | None = None
        self._static_n = 0
        self._static_sigma = cfg.static_sigma * w  # [px]
        self._static_box = 2 * max(1, round(0.6 * self._static_sigma)) + 1  # the shrinkage's local means [px]
        self._moving = False  # the last valid estimate moved at static_min_speed or more
        self._raw: tuple[np.ndarray, np.ndarray] | None = None  # (last grey frame, as tracked)

    def _gray(self, image: np.ndarray) -> np.ndarray:
        """uint8 grey of ``image`` (checked against the calibration's size), flat-fielded."""
        return flat_field(to_gray(image, self.camera.image_size), self._flat)

    # ------------------------------------------------------------------ Algorithm 1, lines 3-4

    def _feature_mask(self, pyr: list[np.ndarray]) -> tuple[np.ndarray, MaskDiagnostics]:
        cfg = self.config
        gray = pyr[0]
        level = len(pyr) - 1
        small = pyr[level]
        labels_bright, centres, sigmas = kmeans_1d(small)
        labels = (labels_bright == 0).astype(np.uint8)  # 1 = shadow (dark cluster)
        shadow = shadow_detected(centres, sigmas, cfg.bimodality_lambda) and (
            label_fragmentation(labels) <= cfg.shadow_max_fragmentation
        )
        h0, w0 = small.shape
        empty = np.zeros((h0, w0), dtype=bool)
        if shadow:
            clean = keep_border_segments(labels)
            edge_mask = shadow_edge_mask(clean)
            delta = abs(centres[1] - centres[0])
            hi = cfg.canny_high * delta
            canny = cv2.Canny(small, cfg.canny_low * hi, hi, L2gradient=True) > 0
            parsed = canny & edge_mask
            r = mask_radius(cfg.max_disp, cfg.window, level)
            forbidden = cv2.dilate(parsed.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0
        else:
            clean, edge_mask, canny, parsed, forbidden = empty, empty, empty, empty, empty
        diag = MaskDiagnostics(
            level,
            small,
            centres,
            sigmas,
            shadow,
            labels.astype(bool),
            clean,
            edge_mask,
            canny,
            parsed,
            forbidden,
        )
        h, w = gray.shape
        full = cv2.resize(forbidden.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        allowed = self._roi & ~full if cfg.use_mask else self._roi.copy()
        return allowed, diag

    def select(self, image: np.ndarray, t: float | None = None, ground_plane=None) -> Selection:
        """Choose features on ``I_prev`` (call before ``I_curr`` is captured).

        Args:
            image: ``I_prev``, uint8 grey or RGB at the camera's resolution.
            t: Its time [s].
            ground_plane: The ground z = a x + b y + c in the body frame when ``I_prev`` was
                taken, if known (see :meth:`track`).
        """
        return self._select(self._gray(image), t, ground_plane)

    def _select(self, gray: np.ndarray, t, ground_plane) -> Selection:
        cfg = self.config
        pyr = build_pyramid(gray, cfg.min_level_size)
        mask, diag = self._feature_mask(pyr)
        # Harris only inside the region of interest (the rest is masked anyway), on level L whose
        # pixel i is centred on full-resolution pixel 2^L i
        L = self._harris_level
        y0, y1, x0, x1 = self._roi_box
        step = 1 << L
        allowed = mask[y0 * step : y1 * step : step, x0 * step : x1 * step : step]
        dark = None
        if cfg.shadow_split and diag is not None and diag.shadow and diag.clean.any():
            h, w = pyr[L].shape
            dark = cv2.resize(diag.clean.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
            dark = dark[y0:y1, x0:x1]
        found, shaded = [], []
        regions = [(allowed if dark is None else allowed & ~dark, cfg.max_features, cfg.quality_level, False)]
        if dark is not None:
            # Harris's quality is relative to the strongest corner, which the lit ground holds: the
            # shadow's features are chosen on their own, at a tenth of the level, as extra ones
            share = float((allowed & dark).sum()) / max(float(allowed.sum()), 1.0)
            n_dark = min(int(round(cfg.max_features * share)), cfg.max_features // 2)
            if n_dark > 0:
                regions.append((allowed & dark, n_dark, 0.1 * cfg.quality_level, True))
        level = pyr[L][y0:y1, x0:x1]
        for region, n_max, quality, in_shadow in regions:
            pts = self._corners(level, region, n_max, quality, step)
            if cfg.quality_percentile > 0 and (0 if pts is None else len(pts)) < n_max // 2:
                response = cv2.cornerHarris(level, self._harris_block, 3, 0.04)[region]
                top = float(response.max()) if response.size else 0.0
                if top > 0:
                    ref = float(np.percentile(response, cfg.quality_percentile))
                    if 0 < ref < top:
                        pts = self._corners(level, region, n_max, quality * ref / top, step)
            if pts is not None:
                found.append(pts.reshape(-1, 2))
                shaded.append(np.full(len(found[-1]), in_shadow))
        feats = np.concatenate(found).astype(np.float32) if found else np.zeros((0, 2), np.float32)
        in_dark = np.concatenate(shaded) if shaded else np.zeros(0, dtype=bool)
        feats = (feats + np.array([x0, y0], np.float32)) * np.float32(step)
        # Harris on a textureless or saturated image returns corners of noise-free flat areas: drop
        # features whose 7 x 7 neighbourhood has no contrast (grey-level variance about its local
        # 7 x 7 means, averaged over the neighbourhood, <= 1)
        if len(feats):
            keep = _local_contrast(gray, feats) > 1.0
            feats, in_dark = feats[keep], in_dark[keep]
        plane = None if ground_plane is None else _plane(ground_plane)
        return Selection(
            gray=gray, features=feats, mask=mask, t=t, diagnostics=diag, ground_plane=plane, in_shadow=in_dark
        )

    def _corners(self, level: np.ndarray, region: np.ndarray, n_max: int, quality: float, step: int):
        """Harris corners of ``level`` inside ``region`` (OpenCV's (n, 1, 2) array or None)."""
        return cv2.goodFeaturesToTrack(
            level,
            maxCorners=n_max,
            qualityLevel=quality,
            minDistance=self.config.min_distance / step,
            mask=region.astype(np.uint8),
            blockSize=self._harris_block,
            useHarrisDetector=True,
            k=0.04,
        )

    # ------------------------------------------------------------------ lines 5-10
    def track(
        self,
        selection: Selection,
        image: np.ndarray,
        dt: float,
        t: float | None = None,
        ground_plane: tuple[float, float, float] | None = None,
        rate_xy=None,
    ) -> OdometryEstimate:
        """Track the selected features into ``I_curr`` and estimate the body velocity.

        Args:
            selection: From :meth:`select` on ``I_prev``.
            image: ``I_curr``.
            dt: Time from ``I_prev`` to ``I_curr`` [s].
            t: Time of ``I_curr`` [s].
            ground_plane: The ground z = a x + b y + c in the body frame now, if known (a body on
                soft suspension rolls and pitches over the ground; see
                :func:`ground_plane_from_wheels`). Default: the camera's calibrated plane. When
                the selection carries the plane of ``I_prev`` too, each frame's features go to
                the ground on their own frame's plane and the fit is of the 3-D rigid motion
                (:func:`velocity_from_points`), so the body's roll and pitch between the frames
                are not mistaken for a translation.
            rate_xy: The body's mean roll and pitch rates (omega_x, omega_y) from ``I_prev`` to
                ``I_curr`` if measured, by a gyro [rad/s, body frame]; used in the 3-D fit
                (:func:`velocity_from_points`). None: estimated from the two planes.
        """
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"dt: {dt!r} s; frames must be a positive, finite time apart")
        return self._track(selection, self._gray(image), dt, t, ground_plane, _rates(rate_xy))

    def _track(self, selection: Selection, gray, dt, t, ground_plane, rate_xy=None) -> OdometryEstimate:
        cfg = self.config
        n_feat = len(selection.features)

        def invalid(reason: str, **kw) -> OdometryEstimate:
            base: dict[str, Any] = dict(
                n_features=n_feat, n_tracked=0, n_inliers=0, inlier_ratio=0.0, residual=math.nan
            )
            base.update(kw)
            return OdometryEstimate(
                math.nan, math.nan, math.nan, False, reason, 0.0, dt=dt, t=t, selection=selection, **base
            )

        if n_feat < cfg.min_inliers:
            return invalid(f"too few features ({n_feat}): dark, saturated or textureless image")
        if cfg.repeated_frames == "invalid" and np.array_equal(selection.gray, gray):
            return invalid("no motion observable: the frame repeats the last one exactly (a frozen camera?)")
        p0 = selection.features.reshape(-1, 1, 2)
        lk: dict[str, Any] = dict(
            winSize=(cfg.window, cfg.window),
            maxLevel=cfg.lk_levels,
            criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        )
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(selection.gray, gray, p0, None, **lk)  # type: ignore[call-overload]
        # the backward track only checks the forward one: it starts at the feature, on fb_levels
        # levels, and a tenth of the threshold is precise enough
        lk["criteria"] = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.1 * cfg.fb_threshold)
        lk["maxLevel"] = cfg.fb_levels
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(
            gray, selection.gray, p1, p0.copy(), flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk
        )
        fb = np.linalg.norm((p0r - p0).reshape(-1, 2), axis=1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_threshold)
        prev_px = p0.reshape(-1, 2)[ok].astype(np.float64)
        curr_px = p1.reshape(-1, 2)[ok].astype(np.float64)
        n_tr = len(prev_px)
        if n_tr < cfg.min_inliers:
            return invalid(f"too few tracked features ({n_tr} of {n_feat})", n_tracked=n_tr)
        plane_curr = None if ground_plane is None else _plane(ground_plane)
        for which, plane in (("this", plane_curr), ("the last", selection.ground_plane)):
            if plane is not None and (problem := self.camera.ground_view_error(plane)):
                return invalid(f"the ground is not in view in {which} frame: {problem}", n_tracked=n_tr)
        # both frames' features undistorted at once
        und = self.camera.undistort_points(np.concatenate([prev_px, curr_px]))
        und_prev, und_curr = und[:n_tr], und[n_tr:]
        if plane_curr is not None and selection.ground_plane is not None:
            # each frame on its own ground plane, as 3-D body-frame points
            P = self._to_ground_3d(und_prev, selection.ground_plane)
            C = self._to_ground_3d(und_curr, plane_curr)
        else:
            H_inv = (
                self._H_inv
                if plane_curr is None
                else np.linalg.inv(self.camera.ground_homography(plane_curr))
            )
            P = self._to_ground(und_prev, H_inv)
            C = self._to_ground(und_curr, H_inv)
        if cfg.use_ransac:
            inl = rigid_ransac(P[:, :2], C[:, :2], cfg.ransac_threshold, cfg.ransac_iterations, self._rng)
        else:
            inl = np.ones(n_tr, dtype=bool)
        n_in = int(inl.sum())
        ratio = n_in / n_tr
        common: dict[str, Any] = dict(n_tracked=n_tr, n_inliers=n_in, inlier_ratio=ratio)
        if n_in < cfg.min_inliers:
            return invalid(f"too few inliers ({n_in} of {n_tr})", **common)
        rates = rate_xy if P.shape[1] == 3 else None
        shaded = None if selection.in_shadow is None else selection.in_shadow[ok]
        if shaded is not None and shaded[inl].any() and (~shaded[inl]).sum() >= cfg.min_inliers:
            inl = self._without_noisy_shadow(P, C, dt, inl, shaded)
        P, C = P[inl], C[inl]
        fit = None
        if (
            P.shape[1] == 3
            and cfg.local_plane
            and selection.ground_plane is not None
            and plane_curr is not None
        ):
            start, _ = velocity_from_points(P, C, dt, rate_xy=rates)
            fit = self._local_plane(
                und_prev[inl], und_curr[inl], selection.ground_plane, plane_curr, dt, start, rates
            )
        if fit is not None:  # the features on the plane in view, the roll and pitch rates fitted
            P, C = fit.P, fit.C
            if fit.kept is not None:  # tracks the plane's fits did not explain are outliers too
                inl = inl.copy()
                inl[np.flatnonzero(inl)[~fit.kept]] = False
                n_in = int(inl.sum())
                ratio = n_in / n_tr
                common.update(n_inliers=n_in, inlier_ratio=ratio)
            vel, residual, cov = velocity_from_points(P, C, dt, return_cov=True, rate_xy=fit.twist[3:5])
        else:
            vel, residual, cov = velocity_from_points(P, C, dt, return_cov=True, rate_xy=rates)
        cov = cov * cfg.noise_scale**2
        reason = ""
        if ratio < cfg.min_inlier_ratio:
            reason = f"inlier ratio {ratio:.2f} below {cfg.min_inlier_ratio}"
        elif (sc := _centroid_std(P, C, cov)) > cfg.max_std:
            reason = f"velocity standard deviation {sc:.3f} m/s above {cfg.max_std}"
        valid = reason == ""
        quality = min(1.0, n_in / (2.0 * cfg.min_inliers)) * ratio if valid else 0.0
        if not valid:
            vel, cov = np.full(3, math.nan), np.full((3, 3), math.nan)
        return OdometryEstimate(
            float(vel[0]),
            float(vel[1]),
            float(vel[2]),
            valid,
            reason,
            quality,
            n_features=n_feat,
            residual=residual,
            dt=dt,
            t=t,
            twist_cov=cov,
            prev_px=prev_px,
            curr_px=curr_px,
            inliers=inl,
            selection=selection,
            **common,
        )

    def _without_noisy_shadow(self, P, C, dt, inl, shaded) -> np.ndarray:
        """``inl`` without the shadow's tracks if they fit the lit ground's motion worse than it.

        On dim, noisy shadow the extra features track noise: their residuals (about the planar fit
        of all inliers) have an RMS above ``shadow_residual_ratio`` times the lit ones'.
        """
        P2, C2 = P[inl, :2], C[inl, :2]
        (vx, vy, w), _ = velocity_from_points(P2, C2, dt)
        r = 0.5 * (P2 + C2)
        err = -(C2 - P2) / dt - np.column_stack([vx - w * r[:, 1], vy + w * r[:, 0]])
        e2 = np.sum(err * err, axis=1)
        dark = shaded[inl]
        if math.sqrt(e2[dark].mean()) <= self.config.shadow_residual_ratio * math.sqrt(e2[~dark].mean()):
            return inl
        out = inl.copy()
        out[inl] = ~dark
        return out

    def _local_plane(
        self, und_prev, und_curr, plane_prev, plane_curr, dt, vel, rates
    ) -> LocalPlaneFit | None:
        """The tracks on the ground plane that explains them, with its roll and pitch rates.

        Two fits of the same tracks (:func:`local_plane_motion`, on at most ``plane_max_points``
        of them): one held to the wheels' plane, its roll and pitch rates those of how the two
        frames' planes differ (or the measured ones); one free. The free one is taken when its
        extra parameters explain the tracks (F statistic of the drop in the squared pixel
        residuals at least ``plane_test``): on flat ground it would add their noise (yaw rate
        MAE 0.0019 against 0.0064 rad/s on ``Rover-v0``). Tracks that the fit taken leaves
        unexplained (``plane_outlier``) are dropped; where the free one is taken, those of either
        fit, and both are made again without them (the held plane does not depend on the
        tracks). The kept tracks are then put on the chosen plane. None: a ray misses the plane
        (the caller keeps its planar fit).
        """
        cfg = self.config
        args = (self.camera, plane_prev, dt, cfg.plane_anchor, cfg.tilt_std, cfg.rate_std, cfg.track_std)
        if rates is None:  # the planes' turn between the frames (small angles)
            (a0, b0, _), (a1, b1, _) = plane_prev, plane_curr
            held = ((b0 - b1) / dt, (a1 - a0) / dt)
        else:
            held = tuple(rates)
        every = _LocalPlane(und_prev, und_curr, *args)
        fits = self._plane_fits(every, und_prev, und_curr, args, vel, held, rates is None)
        if fits is None:
            return None
        theta, fixed, free, took_free = fits
        kept = np.ones(len(und_prev), dtype=bool)
        for _ in range(PLANE_OUTLIER_ROUNDS if cfg.plane_outlier > 0 else 0):
            if fixed is None:
                break
            k = cfg.plane_outlier
            if took_free:
                bad = _unexplained(every, fixed, k) | _unexplained(every, free, k)
            else:
                bad = _unexplained(every, theta, k)
            if not bad.any() or (~bad).sum() < cfg.min_inliers:
                break
            kept[np.flatnonzero(kept)[bad]] = False
            every = _LocalPlane(und_prev[kept], und_curr[kept], *args)
            if not took_free:  # the held plane does not depend on the tracks: no fit again
                break
            fits = self._plane_fits(every, und_prev[kept], und_curr[kept], args, vel, held, rates is None)
            if fits is None:
                return None
            theta, fixed, free, took_free = fits
        r, _ = every.residual(theta, False)  # the kept tracks on the chosen plane
        if r is None:
            return None
        fit = every.result(theta, r)
        return fit if kept.all() else replace(fit, kept=kept)

    def _plane_fits(self, every, und_prev, und_curr, args, vel, held, free_rates):
        """The held and the free fit of :meth:`_local_plane` and the parameters it takes.

        Returns:
            (theta taken, the held fit's parameters or None, the free fit's, whether the free
            one is taken), or None (a ray misses the plane at the start).
        """
        cfg = self.config
        problem = every
        if len(und_prev) > cfg.plane_max_points:  # fitted on a spread subset (the order is Harris's)
            pick = np.linspace(0, len(und_prev) - 1, cfg.plane_max_points).round().astype(int)
            problem = _LocalPlane(und_prev[pick], und_curr[pick], *args)
        n = problem.n
        theta = problem.start(vel, held)
        first = problem.residual(theta, True)
        mask = np.zeros(8, dtype=bool)
        mask[[2, 3, 4, 7]] = True  # the held fit: the wheels' plane, its (or the measured) rates
        fixed = problem.fit(theta, mask, first, iterations=cfg.plane_iterations[0])
        mask[[0, 1]] = True
        mask[[5, 6]] = free_rates
        free = problem.fit(theta, mask, first, iterations=cfg.plane_iterations[1])
        if free is None:
            return None
        took_free = True
        if fixed is not None:
            extra = int(mask.sum()) - 4
            chi_free, chi_fixed = problem.chi2(free[1]), problem.chi2(fixed[1])
            f_stat = ((chi_fixed - chi_free) / extra) / max(chi_free / max(2 * n - int(mask.sum()), 1), 1e-12)
            took_free = f_stat >= cfg.plane_test
        taken = free[0] if took_free or fixed is None else fixed[0]
        return taken, None if fixed is None else fixed[0], free[0], took_free

    @staticmethod
    def _to_ground(und: np.ndarray, H_inv: np.ndarray) -> np.ndarray:
        """(n, 2) body-frame ground points (x, y) [m] of undistorted pixels ``und`` via ``H_inv``."""
        q = np.column_stack([und, np.ones(len(und))]) @ H_inv.T
        return q[:, :2] / q[:, 2:3]

    def _to_ground_3d(self, und: np.ndarray, plane: tuple[float, float, float]) -> np.ndarray:
        """(n, 3) body-frame points of undistorted pixels on the ground z = a x + b y + c [m]."""
        xy = self._to_ground(und, np.linalg.inv(self.camera.ground_homography(plane)))
        a, b, c = plane
        return np.column_stack([xy, a * xy[:, 0] + b * xy[:, 1] + c])

    # ------------------------------------------------------------------ conveniences
    def estimate(self, prev: np.ndarray, curr: np.ndarray, dt: float, ground_plane=None) -> OdometryEstimate:
        """Velocity from one frame pair (``I_prev``, ``I_curr``) ``dt`` seconds apart."""
        return self.track(self.select(prev), curr, dt, ground_plane=ground_plane)

    def update(self, image: np.ndarray, t: float, ground_plane=None, rate_xy=None) -> OdometryEstimate | None:
        """Chained mode: ``image`` is ``I_curr`` of the last pair and ``I_prev`` of the next.

        Args:
            image: The new frame.
            t: Its time [s].
            ground_plane: See :meth:`track`.
            rate_xy: See :meth:`track` (over the interval since the last frame).

        Returns:
            The estimate from the previous frame to this one (None for the first frame).
        """
        gray = self._gray(image)  # converted once for both uses
        rates = _rates(rate_xy)
        raw = gray
        if self.config.static_rate > 0:
            gray = self._without_static(raw)
        out = None
        if self._last is not None:
            dt = t - (math.nan if self._last.t is None else self._last.t)
            if not (dt > 0 and math.isfinite(dt)):
                raise ValueError(f"t: {t!r} s is not after the last frame's {self._last.t!r} s")
            out = self._track(self._last, gray, dt, t, ground_plane, rates)
        self._last = self._select(gray, t, ground_plane)
        self._history.append(self._last)
        if self.config.static_rate > 0:
            self._learn_static(raw, out)
        return out

    def track_back(self, frames: int) -> OdometryEstimate | None:
        """The motion from the frame ``frames`` before the last one to the last (chained mode).

        The features chosen on that earlier frame, tracked into the last one, over their time
        apart: the mean velocity over a longer baseline. Between consecutive frames a crawl moves
        the ground a pixel or two, and what does not move with the ground (the image's grid, its
        aliasing) weighs on the flow: on the soft-sand mission (ideal cameras, train preset, 0.09
        m/s) the speed read 0.963 of the truth frame to frame, 0.996 over eight frames. None
        when fewer frames are kept (``history_frames``).
        """
        if not 1 <= frames < len(self._history):
            return None
        old, last = self._history[-1 - frames], self._history[-1]
        assert old.t is not None and last.t is not None
        return self._track(old, last.gray, last.t - old.t, last.t, last.ground_plane)

    def _fine(self, gray: np.ndarray) -> np.ndarray:
        """The fine texture of a grey frame: less its Gaussian blur of ``static_sigma``, float32."""
        g = gray.astype(np.float32)
        return g - cv2.GaussianBlur(g, (0, 0), self._static_sigma)

    def _without_static(self, raw: np.ndarray) -> np.ndarray:
        """``raw`` less the static pattern at its strength in ``raw``, uint8; a repeated frame as before."""
        if self._raw is not None and np.array_equal(raw, self._raw[0]):
            return self._raw[1]  # the same frame tracks as the same image (a frozen camera shows)
        out = raw
        cfg = self.config
        mean, sq = self._static, self._static_sq
        if mean is not None and sq is not None and self._static_n >= cfg.static_min_frames:
            r = cfg.static_rate
            resid = np.maximum(sq - mean * mean, 0.0) * np.float32(r / (2.0 - r))
            box = (self._static_box, self._static_box)
            e_mean = cv2.blur(mean * mean, box)
            g = np.clip(1.0 - cfg.static_shrink * cv2.blur(resid, box) / np.maximum(e_mean, 1e-6), 0.0, 1.0)
            pattern = g * mean
            pp = float(np.sum(pattern * pattern))
            if pp > 0.0:
                # as strong as this frame shows it: a black or flat frame has none of it
                scale = min(max(float(np.sum(self._fine(raw) * pattern)) / pp, 0.0), 1.5)
                out = np.clip(raw.astype(np.float32) - scale * pattern + 0.5, 0, 255).astype(np.uint8)
        self._raw = (raw, out)
        return out

    def _learn_static(self, raw: np.ndarray, est: OdometryEstimate | None) -> None:
        """Feed ``raw`` to the static image while the rover moves (see ``static_rate``)."""
        cfg = self.config
        if est is not None and est.valid:
            self._moving = math.hypot(est.v_x, est.v_y) >= cfg.static_min_speed
        if not self._moving:
            return
        self._static_n += 1
        w = np.float32(max(1.0 / self._static_n, cfg.static_rate))
        fine = self._fine(raw)
        if self._static is None or self._static_sq is None:
            self._static, self._static_sq = fine, fine * fine
        else:
            self._static += w * (fine - self._static)
            self._static_sq += w * (fine * fine - self._static_sq)

    def reset(self) -> None:
        """Forget the chained stream's last frame and restart RANSAC's random stream."""
        self._last = None
        self._history.clear()
        self._rng = np.random.default_rng(0)
        self._static, self._static_sq, self._static_n, self._moving, self._raw = None, None, 0, False, None


def _local_contrast(gray: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The local grey-level variance at each (x, y) of ``pts`` [px] [grey levels^2].

    The mean over the 7 x 7 neighbourhood of the squared difference between each pixel and its
    own 7 x 7 mean: the same value as blurring the whole image's (I - blur(I))^2, computed on
    13 x 13 patches only.
    """
    h, w = gray.shape
    xy = np.clip(np.rint(pts).astype(np.int64), 0, [w - 1, h - 1])
    if h * w <= 8 * 169 * len(pts):  # a small image: blurring all of it costs less
        g = gray.astype(np.float32)
        var = cv2.blur((g - cv2.blur(g, (7, 7))) ** 2, (7, 7))
        return var[xy[:, 1], xy[:, 0]]
    off = np.arange(-6, 7)

    def reflect(i, n):  # cv2.BORDER_REFLECT_101, the default border of cv2.blur
        i = np.abs(i)
        return np.where(i >= n, 2 * (n - 1) - i, i)

    rows = reflect(xy[:, 1, None] + off, h)
    cols = reflect(xy[:, 0, None] + off, w)
    patch = gray[rows[:, :, None], cols[:, None, :]].astype(np.float64)  # (n, 13, 13)
    # 7 x 7 box means at the central 7 x 7 pixels from a summed-area table
    sat = np.zeros((len(pts), 14, 14))
    sat[:, 1:, 1:] = patch.cumsum(axis=1).cumsum(axis=2)
    box = (sat[:, 7:, 7:] - sat[:, :-7, 7:] - sat[:, 7:, :-7] + sat[:, :-7, :-7]) / 49.0
    return ((patch[:, 3:10, 3:10] - box) ** 2).mean(axis=(1, 2)).astype(np.float32)


def _rates(rate_xy) -> np.ndarray | None:
    """``rate_xy`` checked: None, or finite (omega_x, omega_y) [rad/s]."""
    if rate_xy is None:
        return None
    w = np.asarray(rate_xy, dtype=np.float64).reshape(-1)
    if w.shape != (2,) or not np.all(np.isfinite(w)):
        raise ValueError(f"rate_xy={rate_xy!r}: give the finite (omega_x, omega_y) [rad/s], or None")
    return w


def _plane(ground_plane) -> tuple[float, float, float]:
    g = np.asarray(ground_plane, dtype=np.float64).reshape(-1)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(
            f"ground_plane: {ground_plane!r}; give finite (a, b, c) of z = a x + b y + c [-, -, m]"
        )
    return float(g[0]), float(g[1]), float(g[2])


def ground_plane_from_wheels(wheel_centres_body, wheel_radius: float) -> tuple[float, float, float]:
    """The ground under the wheels, z = a x + b y + c in the body frame [-, -, m].

    The plane through the wheel centres (least squares for four wheels), moved one wheel radius
    along its normal toward the ground. The wheel centres come from the axle roll, axle height
    and steering (the fisheye kinematics estimator, or the simulator).

    Args:
        wheel_centres_body: (n >= 3, 3) wheel centres in the body frame [m].
        wheel_radius: [m].
    """
    W = np.asarray(wheel_centres_body, dtype=np.float64).reshape(-1, 3)
    if len(W) < 3:
        raise ValueError(f"wheel_centres_body: {len(W)} wheels; a plane needs at least 3")
    A = np.column_stack([W[:, 0], W[:, 1], np.ones(len(W))])
    (a, b, c), *_ = np.linalg.lstsq(A, W[:, 2], rcond=None)
    return float(a), float(b), float(c - wheel_radius * math.sqrt(1.0 + a * a + b * b))


def integrate_twist(
    t: np.ndarray, twist: np.ndarray, pose0=(0.0, 0.0, 0.0), max_hold: float | None = None
) -> np.ndarray:
    """Planar poses (x, y, yaw) from body twists (v_x, v_y, omega) held between samples.

    Each interval [t_k, t_{k+1}] uses the twist at t_{k+1} (the estimate over that interval),
    integrated exactly as a constant-curvature arc. NaN twists (invalid estimates) hold the
    previous valid twist, for at most ``max_hold`` seconds after it if given (then the pose
    stays: a long gap is not filled with made-up motion).

    Args:
        t: (n,) times [s].
        twist: (n, 3) body twists [m/s, m/s, rad/s].
        pose0: Pose at t[0] (x [m], y [m], yaw [rad]).
        max_hold: Longest time a valid twist is held over invalid ones [s] (None: no limit).

    Returns:
        (n, 3) poses.
    """
    t = np.asarray(t, dtype=np.float64)
    tw = np.asarray(twist, dtype=np.float64)
    out = np.zeros((len(t), 3))
    out[0] = pose0
    last = np.zeros(3)
    held_until = math.inf  # the end of the last valid twist's hold [s]
    for k in range(1, len(t)):
        if np.all(np.isfinite(tw[k])):
            last = tw[k]
            out[k] = arc_step(out[k - 1], last, t[k] - t[k - 1])
            held_until = t[k] + max_hold if max_hold is not None else math.inf
        else:
            dt = min(t[k], held_until) - t[k - 1]
            out[k] = arc_step(out[k - 1], last, dt) if dt > 0 else out[k - 1]
    return out


def arc_step(pose, twist, dt: float) -> np.ndarray:
    """Planar pose (x, y, yaw) after holding the body twist (v_x, v_y, omega) for ``dt`` [s].

    The exact constant-curvature arc; world frame for the pose, body frame for the twist.
    """
    x, y, th = (float(v) for v in pose)
    vx, vy, w = (float(v) for v in twist)
    dth = w * dt
    if abs(dth) < 1e-9:
        a, b = dt * (1 - dth**2 / 6), dt * dth / 2
    else:
        a, b = math.sin(dth) / w, (1 - math.cos(dth)) / w
    dx, dy = a * vx - b * vy, b * vx + a * vy  # body-frame displacement over the arc
    c, s = math.cos(th), math.sin(th)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, th + dth])

"""Visual odometry from the downward fisheye: ground features through the omnidirectional model.

The fisheye paper proposes that its downward fisheye also track terrain features, so that one
camera gives both the joints and the odometry. This module does the odometry part: features
on the ground in the fisheye image, tracked from frame to frame (pyramidal Lucas-Kanade with a
forward-backward check), their pixels turned into viewing rays by the exact
:class:`~perception.cameras.OmniCamera` model (Scaramuzza's polynomial) and the rays met with
the ground plane (``z = a x + b y + c`` in the body frame, as the downward camera's
``ground_plane``). The ground points' rigid motion (RANSAC and least squares, the odometry
paper's eqs. 10-19, shared with :mod:`perception.odometry`) is the body's planar twist.

What a fisheye sees that a downward pinhole does not, and what is done about it:

- **The rover's own parts** (wheels, arms, body) and **its shadow** stand still in the image
  while the ground moves. An optional mask image (True where ground may be seen) leaves the
  parts out; without one, features that stay put while the inliers move are counted per cell
  of the image (``static_cell`` px) and a cell counted ``static_hits`` times is left out of
  the selection from then on (the learned mask; :meth:`FisheyeOdometry.reset` forgets it).
  The fixed features cannot join the rigid ground motion either way: they fail RANSAC.
- **Grazing rays**: far from the optical axis a pixel's ground point moves by metres per pixel;
  only rays at least ``min_depression_deg`` below the camera's horizon and ground points within
  ``max_range`` of the camera (horizontally) are used.

The estimate is an :class:`~perception.odometry.OdometryEstimate` with the same validity rules
as :class:`~perception.odometry.FlowOdometry`: at least ``min_inliers`` RANSAC inliers and an
inlier ratio of ``min_inlier_ratio``; the quality is the inlier count against twice the
minimum times the ratio; the covariance is the fit's.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np

from perception.cameras import OmniCamera
from perception.odometry import (
    OdometryEstimate,
    _plane,
    kmeans_1d,
    label_fragmentation,
    mask_radius,
    rigid_ransac,
    shadow_detected,
    shadow_edge_mask,
    to_gray,
    velocity_from_points,
)

__all__ = ["FisheyeOdometryConfig", "FisheyeOdometry", "rays_to_ground"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FisheyeOdometryConfig:
    """Settings of :class:`FisheyeOdometry`.

    Attributes:
        max_features: Corners selected per frame.
        quality_level: Shi-Tomasi quality level (a share of the strongest corner's response).
        min_distance: Least distance between corners [px].
        window: Lucas-Kanade window [px] (odd).
        levels: Pyramid levels above the full image.
        fb_max: Largest forward-backward tracking error [px].
        min_depression_deg: Rays nearer than this to the camera's horizon are not used [deg].
        max_range: Ground points farther than this from the camera, horizontally, are not used [m].
        ransac_threshold: Inlier distance of the rigid ground motion [m].
        ransac_iterations: RANSAC iterations.
        min_inliers: Fewest inliers of a valid estimate.
        min_inlier_ratio: Least inlier share of the tracked ground features of a valid estimate.
        static_px: A feature moving less than this [px] while the inliers' median moves at
            least four times as far is fixed to the rover (its parts or its shadow).
        static_cell: Cell size of the learned mask [px].
        static_hits: Fixed features seen in a cell before the cell is left out.
        shadow_mask: Leave out the edges of the rover's shadow (the odometry paper's mask).
        shadow_level_px: Width of the image the shadow is segmented at [px] (a pyramid level).
        bimodality_lambda: lambda of the paper's eq. (3): the grey levels are a shadow's two
            clusters when their centres differ by lambda times their deviations' sum.
        shadow_max_fragmentation: ... and when their labels are not noise (a share of
            neighbouring pixel pairs that differ, :func:`~perception.odometry.label_fragmentation`).
        min_shadow_area: A dark segment is the rover's shadow (or part) when it covers at least
            this share of the view; smaller dark spots are the ground's texture. (The fisheye
            sees the shadow under the rover, which need not reach the image border, so the
            paper's border rule is replaced by this one.)
        canny_high, canny_low: Canny thresholds on the shadow's edges, as the paper's.
        max_disp: Largest feature displacement between frames [px] (the paper's eq. 4 sizes the
            forbidden band around the shadow's edges with it and the window).
        noise_scale: Factor on the fit's covariance.
    """

    max_features: int = 400
    quality_level: float = 0.005
    min_distance: int = 6
    window: int = 21
    levels: int = 3
    fb_max: float = 0.5
    min_depression_deg: float = 20.0
    max_range: float = 1.5
    ransac_threshold: float = 0.01
    ransac_iterations: int = 100
    min_inliers: int = 12
    min_inlier_ratio: float = 0.4
    static_px: float = 0.25
    static_cell: int = 16
    static_hits: int = 3
    shadow_mask: bool = True
    shadow_level_px: int = 100
    bimodality_lambda: float = 1.5
    shadow_max_fragmentation: float = 0.15
    min_shadow_area: float = 0.01
    canny_high: float = 2.0
    canny_low: float = 0.5
    max_disp: float = 12.0
    noise_scale: float = 1.0

    def __post_init__(self) -> None:
        checks = {
            "max_features": self.max_features >= 10,
            "quality_level": 0.0 < self.quality_level < 1.0,
            "min_distance": self.min_distance >= 1,
            "window": self.window >= 5 and self.window % 2 == 1,
            "levels": 0 <= self.levels <= 8,
            "fb_max": self.fb_max > 0.0,
            "min_depression_deg": 0.0 <= self.min_depression_deg < 90.0,
            "max_range": self.max_range > 0.0,
            "ransac_threshold": self.ransac_threshold > 0.0,
            "ransac_iterations": self.ransac_iterations >= 1,
            "min_inliers": self.min_inliers >= 3,
            "min_inlier_ratio": 0.0 < self.min_inlier_ratio <= 1.0,
            "static_px": self.static_px >= 0.0,
            "static_cell": self.static_cell >= 2,
            "static_hits": self.static_hits >= 1,
            "shadow_level_px": self.shadow_level_px >= 16,
            "bimodality_lambda": self.bimodality_lambda > 0.0,
            "shadow_max_fragmentation": 0.0 < self.shadow_max_fragmentation <= 0.5,
            "min_shadow_area": 0.0 <= self.min_shadow_area < 1.0,
            "canny_high": self.canny_high > 0.0,
            "canny_low": 0.0 < self.canny_low <= 1.0,
            "max_disp": self.max_disp >= 0.0,
            "noise_scale": self.noise_scale > 0.0,
        }
        for key, ok in checks.items():
            value = getattr(self, key)
            if not (ok and math.isfinite(float(value))):
                raise ValueError(f"FisheyeOdometryConfig.{key}: {value!r} is out of range")


def rays_to_ground(
    camera: OmniCamera,
    pixels: np.ndarray,
    ground_plane: tuple[float, float, float],
    min_depression_deg: float = 0.0,
) -> np.ndarray:
    """Body-frame ground points (n, 3) [m] seen at fisheye ``pixels`` (n, 2); NaN rows where none.

    The pixel's viewing ray (:meth:`OmniCamera.cam2world`), turned into the body frame by
    ``T_body_cam``, met with the plane z = a x + b y + c. Rows are NaN where the ray misses the
    plane in front of the camera, leaves the field of view, or lies within
    ``min_depression_deg`` of the camera's horizon (the plane's).
    """
    a, b, c = (float(v) for v in ground_plane)
    rays = camera.cam2world(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    R, o = camera.T_body_cam[:3, :3], camera.T_body_cam[:3, 3]
    d = rays @ R.T
    n = np.array([-a, -b, 1.0]) / math.sqrt(1.0 + a * a + b * b)  # upward normal
    down = -(d @ n)  # sine of the ray's depression below the plane's horizon
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (c + a * o[0] + b * o[1] - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    ok = np.isfinite(s) & (s > 0.0) & (down >= math.sin(math.radians(min_depression_deg)))
    out = o + s[:, None] * d
    out[~ok] = np.nan
    return out


class FisheyeOdometry:
    """The body's planar twist from consecutive downward-fisheye frames.

    Args:
        camera: The fisheye's calibration (``T_body_cam`` places it on the body).
        config: Settings.
        ground_plane: The ground z = a x + b y + c in the body frame [-, -, m], used when
            :meth:`update` is given none (the calibration's, or the wheels' from the kinematics).
        mask: Optional (H, W) image, True (non-zero) where the ground may be seen; the rover's
            parts False. Without it the parts are learned (the module's docstring).

    Raises:
        ValueError: A mask whose size is not the camera's, or a ground plane that is not finite.
    """

    def __init__(
        self,
        camera: OmniCamera,
        config: FisheyeOdometryConfig | None = None,
        ground_plane: tuple[float, float, float] | None = None,
        mask: np.ndarray | None = None,
    ) -> None:
        self.camera = camera
        self.cfg = config or FisheyeOdometryConfig()
        w, h = camera.image_size
        self.ground_plane = None if ground_plane is None else _plane(ground_plane)
        if mask is not None:
            m = np.asarray(mask)
            if m.ndim == 3:
                m = m[..., 0]
            if m.shape != (h, w):
                raise ValueError(
                    f"mask: {m.shape[1] if m.ndim == 2 else '?'} x {m.shape[0]} px, but the fisheye's "
                    f"images are {w} x {h} px; give a mask of the camera's image size (True or non-zero "
                    "where the ground may be seen)"
                )
            self._mask = np.where(m != 0, 255, 0).astype(np.uint8)
        else:
            self._mask = np.full((h, w), 255, np.uint8)
        # the rays' own limit: pixels inside the field of view only
        yy, xx = np.mgrid[0:h, 0:w]
        inside = np.isfinite(camera.cam2world(np.column_stack([xx.ravel(), yy.ravel()]))[:, 0]).reshape(h, w)
        self._mask[~inside] = 0
        self._view: np.ndarray | None = None  # the mask at the shadow's pyramid level
        cell = self.cfg.static_cell
        self._hits = np.zeros((-(-h // cell), -(-w // cell)), np.int32)
        self.reset()

    def reset(self) -> None:
        """Forget the last frame and the learned mask of the rover's parts."""
        self._prev: np.ndarray | None = None
        self._t_prev: float | None = None
        self._prev_plane: tuple[float, float, float] | None = None
        self._hits[:] = 0
        self._allowed: np.ndarray | None = None  # the selection mask, until a cell is learned

    @property
    def learned_mask(self) -> np.ndarray:
        """(H, W) bool: where features are still selected (the given mask less the learned cells)."""
        return self._selection_mask() > 0

    def _selection_mask(self) -> np.ndarray:
        if self._allowed is not None:
            return self._allowed
        cell = self.cfg.static_cell
        h, w = self._mask.shape
        bad = np.kron(self._hits >= self.cfg.static_hits, np.ones((cell, cell), bool))[:h, :w]
        self._allowed = np.where(bad, 0, self._mask).astype(np.uint8)
        self._allowed.setflags(write=False)
        return self._allowed

    def update(self, image: np.ndarray, t: float, ground_plane=None) -> OdometryEstimate | None:
        """Add a frame taken at ``t`` [s]; the estimate over the interval since the last, or None.

        Args:
            image: (H, W) or (H, W, 3) uint8 fisheye image of the camera's size.
            t: Its time [s], increasing.
            ground_plane: The ground z = a x + b y + c (body frame) [-, -, m] now (default the
                constructor's).

        Raises:
            ValueError: Neither a ground plane here nor in the constructor (the fisheye's
                calibration needs ``ground_plane`` for odometry), or a non-increasing time.
        """
        gray = to_gray(image, self.camera.image_size)
        plane = _plane(ground_plane) if ground_plane is not None else self.ground_plane
        if plane is None:
            raise ValueError(
                "ground_plane: the fisheye odometry needs the ground under the camera, z = a x + b y + c "
                "in the body frame [-, -, m]: give it here or in the constructor (the fisheye "
                "calibration's ground_plane; measure c as minus the body origin's height above flat "
                "ground with a, b = 0, or take it from the wheels' kinematics)"
            )
        est = None
        if self._prev is not None and self._t_prev is not None:
            dt = float(t) - self._t_prev
            if not dt > 0.0:
                raise ValueError(f"t: {t!r} s is not after the last frame's {self._t_prev!r} s")
            est = self.estimate(self._prev, gray, dt, plane, t=t, prev_plane=self._prev_plane)
        self._prev, self._t_prev, self._prev_plane = gray, float(t), plane
        return est

    def estimate(
        self,
        prev: np.ndarray,
        curr: np.ndarray,
        dt: float,
        ground_plane,
        t: float | None = None,
        prev_plane=None,
    ) -> OdometryEstimate:
        """The twist between two grey frames ``dt`` [s] apart over the ground plane (body frame).

        ``ground_plane`` is the ground under ``curr``; ``prev_plane`` under ``prev`` (default the
        same). With two planes each frame's points lie on its own, and the fit is of the full
        rigid motion (the body's roll and pitch between the frames, which a camera this close
        to the ground sees as much as its travel, are told apart from its planar motion).
        """
        c = self.cfg
        prev = to_gray(prev, self.camera.image_size)
        curr = to_gray(curr, self.camera.image_size)
        plane = _plane(ground_plane)
        plane0 = plane if prev_plane is None else _plane(prev_plane)

        def invalid(reason: str, **kw) -> OdometryEstimate:
            base = dict(n_features=0, n_tracked=0, n_inliers=0, inlier_ratio=0.0, residual=math.nan)
            return OdometryEstimate(
                math.nan, math.nan, math.nan, False, reason, 0.0, dt=dt, t=t, **(base | kw)
            )

        allowed = self._selection_mask()
        if c.shadow_mask:
            edges = self._shadow_edges(prev)
            if edges.any():
                allowed = np.where(edges, 0, allowed).astype(np.uint8)
        pts = cv2.goodFeaturesToTrack(
            prev, c.max_features, c.quality_level, c.min_distance, mask=allowed, blockSize=5
        )
        if pts is None or len(pts) < c.min_inliers:
            return invalid("too few features", n_features=0 if pts is None else len(pts))
        p0 = pts.reshape(-1, 2).astype(np.float32)
        n_feat = len(p0)
        win, crit = (c.window, c.window), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        lk = {"winSize": win, "maxLevel": c.levels, "criteria": crit}
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, curr, p0, None, **lk)  # type: ignore[call-overload]
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(curr, prev, p1, None, **lk)  # type: ignore[call-overload]
        fb = np.linalg.norm(p0 - p0b, axis=1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < c.fb_max)
        P0, P1 = p0[ok].astype(np.float64), p1[ok].astype(np.float64)
        G0 = rays_to_ground(self.camera, P0, plane0, c.min_depression_deg)
        G1 = rays_to_ground(self.camera, P1, plane, c.min_depression_deg)
        o = self.camera.T_body_cam[:3, 3]
        near = (
            np.isfinite(G0[:, 0])
            & np.isfinite(G1[:, 0])
            & (np.hypot(G0[:, 0] - o[0], G0[:, 1] - o[1]) <= c.max_range)
            & (np.hypot(G1[:, 0] - o[0], G1[:, 1] - o[1]) <= c.max_range)
        )
        P0, P1, G0, G1 = P0[near], P1[near], G0[near], G1[near]
        n_tr = len(P0)
        if n_tr < c.min_inliers:
            return invalid("too few tracked ground features", n_features=n_feat, n_tracked=n_tr)
        inl = rigid_ransac(G0[:, :2], G1[:, :2], c.ransac_threshold, c.ransac_iterations)
        n_inl = int(inl.sum())
        ratio = n_inl / n_tr
        if n_inl < c.min_inliers or ratio < c.min_inlier_ratio:
            return invalid(
                f"too few inliers ({n_inl} of {n_tr})",
                n_features=n_feat,
                n_tracked=n_tr,
                n_inliers=n_inl,
                inlier_ratio=ratio,
                prev_px=P0,
                curr_px=P1,
                inliers=inl,
            )
        dims = 3 if plane0 != plane else 2  # 3-D: each frame on its own plane
        vel, rms, cov = velocity_from_points(G0[inl, :dims], G1[inl, :dims], dt, return_cov=True)
        self._learn_static(P0, P1, inl)
        quality = min(1.0, n_inl / (2.0 * c.min_inliers)) * ratio
        return OdometryEstimate(
            float(vel[0]),
            float(vel[1]),
            float(vel[2]),
            True,
            "",
            float(quality),
            residual=rms,
            dt=dt,
            t=t,
            twist_cov=cov * c.noise_scale**2,
            prev_px=P0,
            curr_px=P1,
            inliers=inl,
            n_features=n_feat,
            n_tracked=n_tr,
            n_inliers=n_inl,
            inlier_ratio=ratio,
        )

    def _shadow_edges(self, gray: np.ndarray) -> np.ndarray:
        """(H, W) bool: the band about the rover's shadow's edges where no feature is selected.

        The odometry paper's mask (its eqs. 2-4) on a pyramid level about ``shadow_level_px``
        wide: two grey-level clusters (k-means), a bimodality and a fragmentation test, the dark
        segments large enough to be the rover's shadow, their edges where Canny finds them,
        dilated by (max_disp + window / 2) at that level. A corner there straddles an edge that
        stands still while the ground under it moves.
        """
        c = self.cfg
        h, w = gray.shape
        level = max(0, int(math.floor(math.log2(max(w / c.shadow_level_px, 1.0)))))
        small = gray
        for _ in range(level):
            small = cv2.pyrDown(small)
        view = self._view_at(small.shape)
        if view.sum() < 16:
            return np.zeros((h, w), bool)
        labels_bright, centres, sigmas = kmeans_1d(small[view])
        dark_value = np.max(small[view][labels_bright == 0]) if np.any(labels_bright == 0) else -1
        dark = ((small <= dark_value) & view).astype(np.uint8)
        if not (
            shadow_detected(centres, sigmas, c.bimodality_lambda)
            and label_fragmentation(dark) <= c.shadow_max_fragmentation
        ):
            return np.zeros((h, w), bool)
        n, lab, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=4)
        big = np.zeros(n, bool)
        big[1:] = stats[1:, cv2.CC_STAT_AREA] >= c.min_shadow_area * view.sum()
        clean = big[lab].astype(np.uint8)
        if not clean.any():
            return np.zeros((h, w), bool)
        delta = abs(float(centres[1]) - float(centres[0]))
        hi = c.canny_high * delta
        canny = cv2.Canny(small, c.canny_low * hi, hi, L2gradient=True) > 0
        parsed = canny & shadow_edge_mask(clean)
        r = mask_radius(c.max_disp, c.window, level)
        band = cv2.dilate(parsed.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)) > 0
        return cv2.resize(band.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0

    def _view_at(self, shape: tuple[int, ...]) -> np.ndarray:
        """The given mask (and the field of view) at a pyramid level's ``shape``, made once."""
        if self._view is None or self._view.shape != shape[:2]:
            small = cv2.resize(self._mask, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST)
            self._view = small > 0
        return self._view

    def _learn_static(self, P0: np.ndarray, P1: np.ndarray, inl: np.ndarray) -> None:
        """Count features that stayed put while the ground moved, per cell of the image."""
        c = self.cfg
        flow = np.linalg.norm(P1 - P0, axis=1)
        if not np.any(inl) or np.median(flow[inl]) < 4.0 * c.static_px or c.static_px <= 0.0:
            return
        fixed = (~inl) & (flow < c.static_px)
        if not np.any(fixed):
            return
        cells = np.floor(P0[fixed] / c.static_cell).astype(int)
        np.add.at(self._hits, (cells[:, 1], cells[:, 0]), 1)
        self._allowed = None  # built again at the next selection

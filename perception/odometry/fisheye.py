"""Visual odometry from the downward fisheye: ground features through the omnidirectional model.

The fisheye paper proposes that its downward fisheye also track terrain features, so that one
camera gives both the joints and the odometry. This module does the odometry part: features
on the ground in the fisheye image, tracked from frame to frame (pyramidal Lucas-Kanade with a
forward-backward check), their pixels turned into viewing rays by the exact
:class:`~perception.models.cameras.OmniCamera` model (Scaramuzza's polynomial) and the rays met with
the ground plane (``z = a x + b y + c`` in the body frame, as the downward camera's
``ground_plane``). The ground points' rigid motion (RANSAC and least squares, the odometry
paper's eqs. 10-19, shared with :mod:`perception.odometry.flow`) is the body's planar twist.

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

The estimate is an :class:`~perception.odometry.flow.OdometryEstimate` with the same validity rules
as :class:`~perception.odometry.flow.FlowOdometry`: at least ``min_inliers`` RANSAC inliers and an
inlier ratio of ``min_inlier_ratio``; the quality is the inlier count against twice the
minimum times the ratio; the covariance is the fits' with the scale's error on the speed
(``FisheyeOdometryConfig.scale_std``). With ``two_view`` the motion is refined by
:func:`two_view_motion` (each point's height off the plane free; docs/fisheye_odometry.md).
"""

from __future__ import annotations

import collections
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from perception.models.cameras import OmniCamera
from perception.odometry.flow import (
    OdometryEstimate,
    _plane,
    _rotation,
    kmeans_1d,
    label_fragmentation,
    mask_radius,
    rigid_ransac,
    shadow_detected,
    shadow_edge_mask,
    to_gray,
    velocity_from_points,
)
from perception.odometry.wheel_tracks import WheelTracks

#: The scale's error model takes the ground's roughness (the plane test's ratio, its median) over
#: this long [s] (FisheyeOdometryConfig.scale_std).
ROUGHNESS_S = 5.0

#: FisheyeOdometryConfig.for_ground_view: the motion is fitted to features within this angle of
#: the body's -z [deg]; a wider view's ring beyond it serves the wheels' tracks alone (at the
#: train preset's 320 px the ring's features took the yaw rate's error on flat ground from
#: 0.0078 to 0.0097 rad/s).
TRACK_FREE_DEG = 60.0

#: The last twist predicts the features' motion over at most this long [s].
MAX_PREDICTION_S = 0.2

#: Speeds below this [m/s] keep the two-view fit's own translation (its scale is undefined at rest).
_SCALE_EPS = 0.01

#: The plane's fit and the rays' disagree (the refinement is not used) where, both moving faster
#: than _DIRECTION_SPEED [m/s], their directions differ by more than _MAX_TURN [rad], or where
#: the scale between them leaves _SCALE_RANGE (the rays alone leave the scale free: a fit whose
#: heights drifted toward the camera reads a shorter move, by a factor of 3 on the rough missions).
_DIRECTION_SPEED = 0.05
_MAX_TURN = math.radians(30.0)
_SCALE_RANGE = (0.1, 10.0)

__all__ = [
    "FisheyeOdometry",
    "FisheyeOdometryConfig",
    "TwoViewFit",
    "rays_to_ground",
    "read_mask",
    "two_view_motion",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FisheyeOdometryConfig:
    """Settings of :class:`FisheyeOdometry`.

    Attributes:
        max_features: Corners selected per frame.
        quality_level: Shi-Tomasi quality level (a share of the strongest corner's response).
        min_distance: Least distance between corners [px].
        window: Lucas-Kanade window [px] (odd). Small: a ground patch this close to the camera
            changes its shape between frames (at the train preset 11 px gave a third less speed
            error than 21 px, and took half the time).
        levels: Pyramid levels above the full image.
        predict_levels: Pyramid levels when the features are tracked from where the last
            estimate's twist puts them (the ground plane's points moved by it and projected):
            the residual motion is small, and a coarse level would see the edge of a fisheye's
            region of interest rather than the ground (the one-camera rig's).
        fb_max: Largest forward-backward tracking error [px].
        min_depression_deg: Rays nearer than this to the ground plane's horizon are not used [deg].
        view_limit_deg: Features are selected only where the ray is within this angle of the
            body's -z [deg]; None: ``95 - min_depression_deg``, at most 90 (5 degrees to spare for
            a tilted plane). A fisheye that renders only the ground near the axis (the one-camera rig's
            region of interest) sets it inside that region, so that no corner is taken on its
            edge.
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
            neighbouring pixel pairs that differ, :func:`~perception.odometry.flow.label_fragmentation`).
        min_shadow_area: A dark segment is the rover's shadow (or part) when it covers at least
            this share of the view; smaller dark spots are the ground's texture. (The fisheye
            sees the shadow under the rover, which need not reach the image border, so the
            paper's border rule is replaced by this one.)
        canny_high, canny_low: Canny thresholds on the shadow's edges, as the paper's.
        max_disp: Largest feature displacement between frames [px] (the paper's eq. 4 sizes the
            forbidden band around the shadow's edges with it and the window).
        noise_scale: Factor on the fit's covariance.
        two_view: Refine the motion by :func:`two_view_motion` (each point's height off the plane
            free): the rotation and the translation's direction from the rays, unbiased by the
            ground's relief, the translation's length from the ground plane (below). False: the
            rigid fit of the points on the plane alone.
        pixel_std: A tracked feature's position error [px] (the two-view fit's weights).
        height_std: Prior standard deviation of a point's height off the ground plane [m] (loose:
            the relief is for the rays to tell).
        plane_test: After the first fit the heights are held near the plane (``min_height_std``)
            and the fit repeated; that one is kept when its mean squared residual is at most this
            many times the free fit's (the plane holds): on flat ground the heights' freedom only
            adds noise (the yaw rate's error fell by a third), on rough ground it is what keeps
            the relief out of the yaw rate. 0: the free fit always.
        min_height_std: The heights' prior in the held fit [m].
        scale_std: The speed's relative error from the scale (the ground in view off the wheels'
            plane) on ground the plane holds [-], in the estimate's covariance (0.05 without
            the plane test), growing by ``scale_std_relief`` times the square root of how far
            the held fit's mean squared residual exceeds 1.3 times the free fit's, this pair's or
            its median over the last ``ROUGHNESS_S`` if larger (at most 0.3). On the train
            preset's missions the speed errs by 1 % (flat) to 17 % as that ratio goes from 1.2
            to 10, and for a second at a time on rough ground, where a patch that is a plane
            but lies off the wheels' passes the test: a filter that fuses 30 such estimates a
            second must not take them as independent (slip-unaware drives on the rough mission
            with an IMU, seeds 0-5: 5.0 false slip events a run with 0.06 and this pair's ratio,
            1.7 with 0.15 and a second's mean, 1.0 with 0.15 and five seconds'). The median, not
            the mean: one pair's ratio of 14 (braking on the loose slope) or the first pair's
            held the mean up for seconds, and the speed's deviation at 0.08-0.14 m/s where it
            erred by 0.003 (the loose slope's slip-aware drives, seeds 200-205: false slip
            events 10 with the mean, 8 with the median; the rough mission's slip-unaware drives 3
            and 2).
        scale_std_relief: See ``scale_std``.
        rate_std: Prior standard deviation of the roll and pitch rates [rad/s] without a gyro.
        gyro_rate_std: ... and about the gyro's roll and pitch rates when they are given [rad/s].
        outlier_px: Points whose two-view residual exceeds this [px] are dropped and the fit is
            repeated once.
        height_cut: Points whose two-view height lies more than this many robust deviations
            (1.4826 MAD) from the median are left out of the scale: the features on a shadow's
            edge that stands still move less than the ground and look farther off, and so do
            bumps and hollows that the plane does not follow.
        scale_weight_power: The translation's length is the rigid fit of the remaining points on
            the ground plane, each weighted by its horizontal distance from the camera to this
            power: the plane is that of the wheels, and the ground nearer the wheels follows it
            best (on the rough missions the speed's error fell by a fifth with 2).
        track_view_deg: With the wheels' contacts given (:meth:`FisheyeOdometry.update`), corners
            are also looked for on the wheels' tracks in the ring between ``view_limit_deg`` and
            this angle off the body's -z [deg] (None: not): kept out of the motion's fit, their
            heights follow from it, and the ground's known height there sets the scale.
        track_features: Most corners on the tracks per frame.
        track_half_width: A point within this of a track's centre line lies on it [m] (the
            rover's treads are 8 cm wide).
        track_min_points: Fewest points on the tracks that set a scale.
        track_std: The tracks' height error where a wheel has just rolled [m] (the kinematics'
            contacts against the terrain on the rough mission: 1 mm) ...
        track_std_per_m: ... growing by this per metre the body has travelled since [m/m] (the
            motion that carries them; against the terrain on the rough mission at the train
            preset, before the loop's closure: 1.5 +- 4 mm after 0.2-0.4 m, 4 +- 6 mm after
            0.4-0.6 m, with a 5 cm grid of the truth interpolated).
    """

    max_features: int = 300
    quality_level: float = 0.005
    min_distance: int = 6
    window: int = 11
    levels: int = 3
    predict_levels: int = 1
    fb_max: float = 0.5
    min_depression_deg: float = 20.0
    view_limit_deg: float | None = None
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
    two_view: bool = True
    pixel_std: float = 0.3
    height_std: float = 0.2
    plane_test: float = 1.4
    min_height_std: float = 0.005
    scale_std: float = 0.005
    scale_std_relief: float = 0.15
    rate_std: float = 1.0
    gyro_rate_std: float = 0.02
    outlier_px: float = 1.2
    height_cut: float = 3.0
    scale_weight_power: float = 2.0
    track_view_deg: float | None = None
    track_features: int = 100
    track_half_width: float = 0.03
    track_min_points: int = 5
    track_std: float = 0.002
    track_std_per_m: float = 0.005

    @classmethod
    def for_ground_view(
        cls, ground_view_deg: float | None, image_width: int | None = None, **overrides
    ) -> FisheyeOdometryConfig:
        """The settings for a fisheye that delivers the ground within ``ground_view_deg`` of the body's -z.

        Features are selected 5 degrees inside that view (clear of its edge), on rays down to the
        depression of its edge (5 degrees less than the selection's, for a tilted plane); None:
        the whole view. With
        ``image_width`` [px], ``max_features`` grows with it from 300 at 320 px (at 640 px, 600
        features took the yaw rate's error on flat ground from 0.0028 to 0.0021 rad/s).
        """
        base: dict = {}
        if image_width is not None:
            base["max_features"] = int(np.clip(round(300 * image_width / 320), 100, 1200))
        if ground_view_deg is not None:
            view = float(ground_view_deg) - 5.0
            inner = min(view, TRACK_FREE_DEG)
            base |= {"view_limit_deg": inner, "min_depression_deg": float(np.clip(85.0 - inner, 0.0, 89.0))}
            if view > TRACK_FREE_DEG:
                base["track_view_deg"] = view
        return cls(**(base | overrides))

    def __post_init__(self) -> None:
        checks = {
            "max_features": self.max_features >= 10,
            "quality_level": 0.0 < self.quality_level < 1.0,
            "min_distance": self.min_distance >= 1,
            "window": self.window >= 5 and self.window % 2 == 1,
            "levels": 0 <= self.levels <= 8,
            "predict_levels": 0 <= self.predict_levels <= 8,
            "fb_max": self.fb_max > 0.0,
            "min_depression_deg": 0.0 <= self.min_depression_deg < 90.0,
            "view_limit_deg": self.view_limit_deg is None or 0.0 < self.view_limit_deg <= 180.0,
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
            "pixel_std": self.pixel_std > 0.0,
            "height_std": self.height_std > 0.0,
            "plane_test": self.plane_test >= 0.0,
            "min_height_std": 0.0 < self.min_height_std <= self.height_std,
            "scale_std": 0.0 <= self.scale_std <= 1.0,
            "scale_std_relief": self.scale_std_relief >= 0.0,
            "rate_std": self.rate_std > 0.0,
            "gyro_rate_std": self.gyro_rate_std > 0.0,
            "outlier_px": self.outlier_px > 0.0,
            "height_cut": self.height_cut > 0.0,
            "scale_weight_power": 0.0 <= self.scale_weight_power <= 8.0,
            "track_view_deg": self.track_view_deg is None or 0.0 < self.track_view_deg < 90.0,
            "track_features": self.track_features >= 1,
            "track_half_width": self.track_half_width > 0.0,
            "track_min_points": self.track_min_points >= 1,
            "track_std": self.track_std > 0.0,
            "track_std_per_m": self.track_std_per_m >= 0.0,
        }
        for key, ok in checks.items():
            value = getattr(self, key)
            if not (ok and (value is None or math.isfinite(float(value)))):
                raise ValueError(f"FisheyeOdometryConfig.{key}: {value!r} is out of range")


def read_mask(path: str | Path) -> np.ndarray:
    """(H, W) bool mask image: True (non-zero) where the ground may be seen, False on the rover's parts.

    The image is read as stored (8 or 16 bits): grey, non-zero on the ground; colour, any
    channel non-zero; with an alpha channel, also opaque (a part marked by transparency is a part).

    Raises:
        CalibrationError: The file is missing or not an image, or it marks no ground at all.
    """
    from perception.models.calib_io import CalibrationError

    p = Path(path)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED) if p.is_file() else None
    if img is None or img.ndim not in (2, 3):
        raise CalibrationError(
            f"mask: {p} is {'not a readable image' if p.exists() else 'missing'}; give an image of the "
            "fisheye's size, non-zero where the ground may be seen and zero on the rover's parts"
        )
    if img.ndim == 2:
        mask = img != 0
    elif img.shape[2] == 4:
        mask = np.any(img[..., :3] != 0, axis=2) & (img[..., 3] != 0)
    else:
        mask = np.any(img != 0, axis=2)
    if not mask.any():
        raise CalibrationError(
            f"mask: {p} is zero everywhere, so no ground is left to track; it must be non-zero where "
            "the ground may be seen and zero only on the rover's parts"
        )
    return mask


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
    rays = camera.cam2world(np.asarray(pixels, dtype=np.float64).reshape(-1, 2))
    return _rays_to_ground(camera.T_body_cam, rays, ground_plane, min_depression_deg)


def _rays_to_ground(T_body_cam: np.ndarray, rays: np.ndarray, ground_plane, min_depression_deg: float = 0.0):
    """:func:`rays_to_ground` of camera-frame unit ``rays`` (n, 3)."""
    a, b, c = (float(v) for v in ground_plane)
    R, o = T_body_cam[:3, :3], T_body_cam[:3, 3]
    d = rays @ R.T
    n = np.array([-a, -b, 1.0]) / math.sqrt(1.0 + a * a + b * b)  # upward normal
    down = -(d @ n)  # sine of the ray's depression below the plane's horizon
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (c + a * o[0] + b * o[1] - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    ok = np.isfinite(s) & (s > 0.0) & (down >= math.sin(math.radians(min_depression_deg)))
    out = o + s[:, None] * d
    out[~ok] = np.nan
    return out


@dataclass(frozen=True)
class TwoViewFit:
    """Result of :func:`two_view_motion`.

    Attributes:
        motion: (v_x, v_y, v_z, omega_x, omega_y, omega_z) of the body over the pair, in the
            first frame's body frame [m/s, rad/s]: v is the chord (displacement over ``dt``),
            which the velocity at mid-pair is turned from by omega dt / 2.
        heights: (n,) each point's height off the first frame's ground plane, along its normal's
            vertical [m] (positive: above).
        residual_px: (n,) each point's reprojection error in the second frame [px] (angular
            error times the camera's radial scale).
        cov: (6, 6) covariance of ``motion`` with the heights eliminated, from the residuals.
        iterations: Gauss-Newton steps taken.
        camera_shift: (3,) the camera's displacement over the pair, first body frame [m]: what
            the rays fix up to scale (the body origin's moves by it less the rotation's lever on
            the mount, ``(R - I) o``).
        height_noise: (n,) each height's standard deviation from the rays alone, the motion
            held [m] (what the heights' prior is weighed against).
    """

    motion: np.ndarray
    heights: np.ndarray
    residual_px: np.ndarray
    cov: np.ndarray
    iterations: int
    camera_shift: np.ndarray
    height_noise: np.ndarray


def _with_speed_error(cov: np.ndarray, v: np.ndarray, rel: float) -> np.ndarray:
    """``cov`` of (v_x, v_y, omega) with a relative error ``rel`` of the speed along ``v`` added."""
    out = np.array(cov, dtype=np.float64)
    out[:2, :2] += rel**2 * np.outer(v, v)
    return out


def _tangent_basis(b: np.ndarray) -> np.ndarray:
    """(n, 3, 2) two orthonormal vectors perpendicular to each unit vector of ``b`` (n, 3)."""
    x, y, z = b[:, 0], b[:, 1], b[:, 2]
    far = np.abs(z) < 0.9  # b x (0, 0, 1) where b is far from the z axis, else b x (1, 0, 0)
    u1 = np.where(
        far[:, None], np.column_stack([y, -x, np.zeros_like(x)]), np.column_stack([np.zeros_like(x), z, -y])
    )
    u1 /= np.sqrt(np.einsum("ij,ij->i", u1, u1))[:, None]
    u2 = np.column_stack(
        [y * u1[:, 2] - z * u1[:, 1], z * u1[:, 0] - x * u1[:, 2], x * u1[:, 1] - y * u1[:, 0]]
    )  # b x u1
    return np.stack([u1, u2], axis=2)


def two_view_motion(
    rays0: np.ndarray,
    rays1: np.ndarray,
    dt: float,
    T_body_cam: np.ndarray,
    ground_plane: tuple[float, float, float],
    init,
    *,
    px_per_rad: float,
    pixel_std: float = 0.3,
    height_std: float = 0.2,
    rate_xy=None,
    rate_std: float = 1.0,
    iterations: int = 8,
) -> TwoViewFit | None:
    """The body's rigid motion between two frames from the rays of points tracked in both.

    Each point lies on its ray from the first frame's camera, at a height h off the ground plane
    z = a x + b y + c (body frame) that is its own unknown, with the prior h ~ N(0, height_std);
    the body moves by (v, omega) over ``dt`` (v dt the body origin's displacement, the chord, in
    the first frame's axes; omega its rotation rate: the moved frame is R(omega dt) = exp(omega
    dt) and a point X there is R^T (X - v dt)); the point seen from the moved camera gives the
    second ray. The motion and the heights
    are fitted by Gauss-Newton on the angles between the predicted and the observed second rays
    (as pixels: ``px_per_rad``, each of weight 1 / ``pixel_std``), the heights eliminated by
    their Schur complement (each touches only its own point). With free heights the rotation,
    and the translation's direction, follow from the rays alone: relief off the plane, which a
    camera this close to the ground sees as a fifth of its height, does not bias them. The
    translation's length (the scale) rests on the heights' prior: with a loose prior it is weakly
    set, and :class:`FisheyeOdometry` takes it from the ground plane instead.

    Args:
        rays0: (n, 3) unit rays of the points in the first frame, camera frame.
        rays1: (n, 3) unit rays of the same points in the second frame, camera frame.
        dt: Time between the frames [s].
        T_body_cam: (4, 4) the camera in the body frame.
        ground_plane: (a, b, c) of the ground under the first frame, body frame [-, -, m].
        init: (v_x, v_y, v_z, omega_x, omega_y, omega_z) to start from [m/s, rad/s].
        px_per_rad: The camera's image scale [px/rad] (an equidistant fisheye's radius per angle).
        pixel_std: Standard deviation of a tracked point's position [px].
        height_std: Prior standard deviation of a point's height off the plane [m].
        rate_xy: Measured (omega_x, omega_y) over the pair (a gyro) [rad/s], or None: prior 0.
        rate_std: Prior standard deviation of omega_x and omega_y [rad/s] (about ``rate_xy``
            when given: its noise).
        iterations: Most Gauss-Newton steps.

    Returns:
        The fit, or None if fewer than 6 points or a point's ray misses the plane.
    """
    r0 = np.asarray(rays0, dtype=np.float64).reshape(-1, 3)
    r1 = np.asarray(rays1, dtype=np.float64).reshape(-1, 3)
    n = len(r0)
    if n < 6 or r1.shape != r0.shape:
        return None
    a, b, c = (float(v) for v in ground_plane)
    R_bc, o = T_body_cam[:3, :3], T_body_cam[:3, 3]
    d = r0 @ R_bc.T  # body-frame rays of the first frame
    den = d[:, 2] - a * d[:, 0] - b * d[:, 1]  # d(height)/d(distance along the ray)
    s0 = (c + a * o[0] + b * o[1] - o[2]) / den  # distance to the plane along the ray
    if not np.all(np.isfinite(s0) & (s0 > 0.0)):
        return None
    dh = d / den[:, None]  # d(point)/d(height)
    U = _tangent_basis(r1)
    U1, U2 = np.ascontiguousarray(U[:, :, 0]), np.ascontiguousarray(U[:, :, 1])
    w_ang = px_per_rad / pixel_std
    mu = np.zeros(2) if rate_xy is None else np.asarray(rate_xy, dtype=np.float64).reshape(2)
    theta = np.asarray(init, dtype=np.float64).reshape(6).copy()
    h = np.zeros(n)
    inv_h2 = 1.0 / height_std**2
    inv_r = 1.0 / rate_std
    X0 = o + s0[:, None] * d  # the points on the plane
    o_cam = R_bc.T @ o

    def predict(th: np.ndarray, hh: np.ndarray):
        Y = X0 + hh[:, None] * dh - th[0:3] * dt
        A = R_bc.T @ _rotation(th[3:6] * dt).T  # body (moved) -> second camera
        Xc = Y @ A.T - o_cam
        norm = np.sqrt(np.einsum("ij,ij->i", Xc, Xc))
        bp = Xc / norm[:, None]
        e = np.empty((len(bp), 2))
        e[:, 0] = np.einsum("ij,ij->i", U1, bp) * w_ang
        e[:, 1] = np.einsum("ij,ij->i", U2, bp) * w_ang
        return e, Y, A, norm, bp

    def cost(e: np.ndarray, th: np.ndarray, hh: np.ndarray) -> float:
        prior = (th[3:5] - mu) * inv_r
        return float(np.einsum("ij,ij->", e, e) + inv_h2 * (hh @ hh) + prior @ prior)

    e, Y, A, norm, bp = predict(theta, h)
    current = cost(e, theta, h)
    S = np.eye(6)
    info = np.zeros(n)
    steps = 0
    J = np.empty((2, n, 6))  # d e / d(v, omega), one block per tangent direction
    Jh = np.empty((2, n))  # d e / d(height)
    for step in range(1, iterations + 1):
        steps = step
        # d e / d Xc = U^T (I - b b^T) / |Xc|, then through A to the moved body point
        k = w_ang / norm
        for j, Uj in enumerate((U1, U2)):
            g = (Uj - (e[:, j] / w_ang)[:, None] * bp) * k[:, None]
            GA = g @ A  # (n, 3)
            Jh[j] = np.einsum("ij,ij->i", GA, dh)
            J[j, :, 0:3] = -dt * GA
            # d(Y rotated)/d(omega) ~ dt [Y]x (first order in omega dt): GA x Y
            J[j, :, 3] = dt * (GA[:, 1] * Y[:, 2] - GA[:, 2] * Y[:, 1])
            J[j, :, 4] = dt * (GA[:, 2] * Y[:, 0] - GA[:, 0] * Y[:, 2])
            J[j, :, 5] = dt * (GA[:, 0] * Y[:, 1] - GA[:, 1] * Y[:, 0])
        Jf = J.reshape(2 * n, 6)
        Umat = Jf.T @ Jf
        Umat[3, 3] += inv_r**2
        Umat[4, 4] += inv_r**2
        gm = J[0].T @ e[:, 0] + J[1].T @ e[:, 1]
        gm[3:5] += (theta[3:5] - mu) * inv_r**2
        W = J[0] * Jh[0][:, None] + J[1] * Jh[1][:, None]  # (n, 6)
        info = Jh[0] * Jh[0] + Jh[1] * Jh[1]
        V = info + inv_h2
        gh = Jh[0] * e[:, 0] + Jh[1] * e[:, 1] + h * inv_h2
        S = Umat - (W / V[:, None]).T @ W
        rhs = -(gm - W.T @ (gh / V))
        try:
            dm = np.linalg.solve(S + 1e-12 * np.trace(S) * np.eye(6), rhs)
        except np.linalg.LinAlgError:
            return None
        dhh = -(gh + W @ dm) / V
        lam, accepted = 1.0, False
        for _ in range(6):  # step halving
            th2, h2 = theta + lam * dm, h + lam * dhh
            out = predict(th2, h2)
            c2 = cost(out[0], th2, h2)
            if np.isfinite(c2) and c2 < current:
                accepted = True
                break
            lam *= 0.5
        if not accepted:
            break
        # converged: the cost (in units of chi-square) fell by under 0.05, or a thousandth of it
        # (what the next step could still change is then well inside the fit's deviations)
        converged = current - c2 < max(0.05, 1e-3 * current)
        theta, h, current = th2, h2, c2
        e, Y, A, norm, bp = out
        if converged:
            break
    res_px = np.linalg.norm(e, axis=1) * pixel_std
    dof = max(2 * n - 6 - n, 1)
    scale = float((e * e).sum()) / dof
    try:
        cov = np.linalg.inv(S) * scale
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), math.nan)
    shift = theta[0:3] * dt + (_rotation(theta[3:6] * dt) - np.eye(3)) @ o
    with np.errstate(divide="ignore"):
        noise = np.where(info > 0, 1.0 / np.sqrt(info), np.inf)
    return TwoViewFit(theta.copy(), h.copy(), res_px, cov, steps, shift, noise)


def heights_given_motion(
    rays0: np.ndarray,
    rays1: np.ndarray,
    dt: float,
    T_body_cam: np.ndarray,
    ground_plane: tuple[float, float, float],
    motion: np.ndarray,
    *,
    px_per_rad: float,
    scale: float = 1.0,
    iterations: int = 6,
) -> tuple[np.ndarray, np.ndarray]:
    """Each point's height off the plane, the body's motion given: (heights (n,) [m], residuals (n,) [px]).

    The points of :func:`two_view_motion`'s model, each found on its first ray (Gauss-Newton on
    its two angular residuals in the second frame, in the inverse of its distance along the ray,
    which stays finite however far the point) with the motion held, in the motion's own scale.

    Args:
        rays0: (n, 3) unit rays of the points in the first frame, camera frame.
        rays1: (n, 3) ... and in the second.
        dt: Time between the frames [s].
        T_body_cam: (4, 4) the camera in the body frame.
        ground_plane: (a, b, c) of the ground under the first frame, body frame [-, -, m].
        motion: (v_x, v_y, v_z, omega_x, omega_y, omega_z) of the body over the pair, first
            frame's body frame [m/s, rad/s] (:attr:`TwoViewFit.motion`).
        px_per_rad: The image scale [px/rad] of the residuals.
        scale: The true scale over the motion's (the points start on the plane at that scale:
            a fit that reads a third of the move puts the ground a third as far).
        iterations: Gauss-Newton steps.

    Returns:
        Heights (n,) off the plane along its normal's vertical in the motion's scale [m] (NaN
        where the ray misses the plane or the point ends behind the camera), and each point's
        residual [px].
    """
    r0 = np.asarray(rays0, dtype=np.float64).reshape(-1, 3)
    r1 = np.asarray(rays1, dtype=np.float64).reshape(-1, 3)
    a, b, c = (float(v) for v in ground_plane)
    R_bc, o = T_body_cam[:3, :3], T_body_cam[:3, 3]
    d = r0 @ R_bc.T
    den = d[:, 2] - a * d[:, 0] - b * d[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = (c + a * o[0] + b * o[1] - o[2]) / den  # the plane along the ray
    ok = np.isfinite(s0) & (s0 > 0.0)
    m = np.asarray(motion, dtype=np.float64).reshape(6)
    A = R_bc.T @ _rotation(m[3:6] * dt).T
    P = A @ (o - m[0:3] * dt) - R_bc.T @ o  # Xc = P + Q / rho
    Q = d @ A.T
    U = _tangent_basis(r1)
    rho = np.where(ok, max(scale, 1e-3) / np.where(ok, s0, 1.0), 1.0)  # on the plane, in the fit's scale

    def residual(rho: np.ndarray):
        Xc = P + Q / rho[:, None]
        norm = np.sqrt(np.einsum("ij,ij->i", Xc, Xc))
        bp = Xc / norm[:, None]
        return np.einsum("nij,ni->nj", U, bp), Xc, norm, bp

    for _ in range(iterations):
        e, Xc, norm, bp = residual(rho)
        dX = -Q / (rho * rho)[:, None]
        dbp = (dX - np.einsum("ij,ij->i", dX, bp)[:, None] * bp) / norm[:, None]
        J = np.einsum("nij,ni->nj", U, dbp)
        jj = np.einsum("ij,ij->i", J, J)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.where(jj > 0, np.einsum("ij,ij->i", J, e) / jj, 0.0)
        rho = np.clip(rho - step, 1e-3, None)  # (no farther than 1 km)
    e, _, _, bp = residual(rho)
    h = (1.0 / rho - s0) * den
    bad = ~ok | (np.einsum("ij,ij->i", bp, r1) <= 0.0)  # seen behind the second camera
    h[bad] = np.nan
    return h, np.where(bad, np.inf, np.linalg.norm(e, axis=1) * px_per_rad)


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
        ValueError: A mask whose size is not the camera's, a ground plane that is not finite or
            that the fisheye cannot see, or a polynomial that does not fit the camera's image
            (:meth:`~perception.models.cameras.OmniCamera.model_error`).
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
        problem = camera.model_error()
        if problem:
            raise ValueError(problem)
        w, h = camera.image_size
        self.ground_plane = None if ground_plane is None else _plane(ground_plane)
        if self.ground_plane is not None:
            problem = camera.ground_view_error(self.ground_plane, self.cfg.max_range)
            if problem:
                raise ValueError(f"ground_plane: {problem}")
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
            if not np.any(m != 0):
                raise ValueError(
                    "mask: zero everywhere, so no ground is left to track; it must be True (non-zero) "
                    "where the ground may be seen and False only on the rover's parts"
                )
            self._mask = np.where(m != 0, 255, 0).astype(np.uint8)
        else:
            self._mask = np.full((h, w), 255, np.uint8)
        # the rays' own limit: pixels inside the field of view whose rays point down enough to
        # meet the ground (within view_limit_deg of the body's -z)
        yy, xx = np.mgrid[0:h, 0:w]
        rays = camera.cam2world(np.column_stack([xx.ravel(), yy.ravel()]).astype(np.float64))
        down = -(rays @ camera.T_body_cam[:3, :3].T)[:, 2]
        limit = self.cfg.view_limit_deg
        limit = min(95.0 - self.cfg.min_depression_deg, 90.0) if limit is None else limit
        with np.errstate(invalid="ignore"):
            usable = down >= math.cos(math.radians(limit))
        parts = self._mask.copy()
        self._mask[~usable.reshape(h, w)] = 0
        # the ring beyond it where features only find the wheels' tracks (track_view_deg)
        self._ring: np.ndarray | None = None
        if self.cfg.track_view_deg is not None and self.cfg.track_view_deg > limit:
            with np.errstate(invalid="ignore"):
                outer = down >= math.cos(math.radians(self.cfg.track_view_deg))
            self._ring = np.where((outer & ~usable).reshape(h, w), parts, 0).astype(np.uint8)
        ys, xs = np.nonzero(self._mask if self._ring is None else self._mask | self._ring)
        grow = int(math.ceil(self.cfg.max_disp + self.cfg.window))  # a feature's motion and window
        if len(xs):
            self._box = (
                max(int(xs.min()) - grow, 0),
                max(int(ys.min()) - grow, 0),
                min(int(xs.max()) + grow + 1, w),
                min(int(ys.max()) + grow + 1, h),
            )
        else:
            self._box = (0, 0, w, h)
        self._view: np.ndarray | None = None  # the mask at the shadow's pyramid level
        # the image scale [px/rad] at 45 degrees off the axis, or inside a narrower field of view
        # (an equidistant fisheye's is uniform)
        off = min(math.pi / 4, camera.max_fov / 4)
        px = camera.world2cam(np.array([[math.sin(off), 0.0, math.cos(off)]]))[0]
        self._px_per_rad = math.hypot(px[0] - camera.center[0], px[1] - camera.center[1]) / off
        cell = self.cfg.static_cell
        self._hits = np.zeros((-(-h // cell), -(-w // cell)), np.int32)
        self.reset()

    @property
    def config(self) -> FisheyeOdometryConfig:
        """The settings (as :attr:`perception.odometry.flow.FlowOdometry.config`)."""
        return self.cfg

    def reset(self) -> None:
        """Forget the last frame, the learned rover's parts, the wheels' tracks and the roughness."""
        self._prev: np.ndarray | None = None
        self._last: np.ndarray | None = None  # the last valid twist, for the features' prediction
        self._ratios: collections.deque[tuple[float, float]] = collections.deque()  # (dt, plane-test ratio)
        self._span = 0.0  # the time the ratios span [s]
        self._t_prev: float | None = None
        self._prev_plane: tuple[float, float, float] | None = None
        self._hits[:] = 0
        self._allowed: np.ndarray | None = None  # the selection mask, until a cell is learned
        self._ring_ok: np.ndarray | None = None  # ... and the ring's
        self.tracks = WheelTracks(self.cfg.track_half_width)
        #: What set the last estimate's scale: ``"tracks"`` (with the plane's), ``"plane"``, or ``""``.
        self.last_scale_source = ""
        self._moved: tuple[np.ndarray, np.ndarray] | None = None  # the last pair's (R, D), body frame

    @property
    def learned_mask(self) -> np.ndarray:
        """(H, W) bool: where features are still selected (the given mask less the learned cells)."""
        return self._selection_mask() > 0

    def _ring_allowed(self) -> np.ndarray:
        """The ring's selection mask less the cells learned as the rover's (kept until one is learned)."""
        assert self._ring is not None
        if self._ring_ok is None:
            self._ring_ok = self._less_learned(self._ring)
        return self._ring_ok

    def _selection_mask(self) -> np.ndarray:
        if self._allowed is None:
            self._allowed = self._less_learned(self._mask)
        return self._allowed

    def _less_learned(self, mask: np.ndarray) -> np.ndarray:
        """``mask`` (uint8) with the cells learned as the rover's zeroed, read-only."""
        cell = self.cfg.static_cell
        h, w = mask.shape
        bad = np.kron(self._hits >= self.cfg.static_hits, np.ones((cell, cell), bool))[:h, :w]
        out = np.where(bad, 0, mask).astype(np.uint8)
        out.setflags(write=False)
        return out

    def update(
        self, image: np.ndarray, t: float, ground_plane=None, rate_xy=None, contacts=None
    ) -> OdometryEstimate | None:
        """Add a frame taken at ``t`` [s]; the estimate over the interval since the last, or None.

        Args:
            image: (H, W) or (H, W, 3) uint8 fisheye image of the camera's size.
            t: Its time [s], increasing.
            ground_plane: The ground z = a x + b y + c (body frame) [-, -, m] now (default the
                constructor's).
            rate_xy: The body's mean roll and pitch rates since the last frame (a gyro) [rad/s],
                or None.
            contacts: (n, 3) where the wheels touch the ground now, body frame [m]
                (:func:`perception.odometry.wheel_tracks.wheel_contacts` of the kinematics), or None. The
                tracks they leave, carried with the body's motion, give the ground's height
                where the camera sees them again: the scale rests on it (``track_*``).

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
            if not (dt > 0.0 and math.isfinite(dt)):
                raise ValueError(f"t: {t!r} s is not a finite time after the last frame's {self._t_prev!r} s")
            self._moved = None
            self.last_scale_source = ""
            est = self.estimate(
                self._prev,
                gray,
                dt,
                plane,
                t=t,
                prev_plane=self._prev_plane,
                rate_xy=rate_xy,
                predict=self._last if dt <= MAX_PREDICTION_S else None,
                t0=self._t_prev,
            )
            self._last = est.twist.copy() if est.valid else None
            if self._moved is None:  # the body's motion is not known: the tracks cannot follow
                self.tracks.clear()
            else:
                self.tracks.move(*self._moved)
        if contacts is not None:
            self.tracks.add(float(t), contacts)
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
        rate_xy=None,
        predict=None,
        t0: float | None = None,
    ) -> OdometryEstimate:
        """The twist between two grey frames ``dt`` [s] apart over the ground plane (body frame).

        ``ground_plane`` is the ground under ``curr``; ``prev_plane`` under ``prev`` (default the
        same). With two planes each frame's points lie on its own, and the rigid fit is of the
        full motion (the body's roll and pitch between the frames, which a camera this close
        to the ground sees as much as its travel, are told apart from its planar motion).
        ``rate_xy``: the gyro's roll and pitch rates over the pair [rad/s], or None. ``predict``:
        a twist (v_x, v_y, omega) [m/s, rad/s] that the features are tracked from (their ground
        points moved by it; :meth:`update` gives the last valid estimate's), or None. ``t0``: the
        time of ``prev`` [s], at which the wheels' tracks (:attr:`tracks`, kept by :meth:`update`)
        are looked up; None: not.

        Steps: corners on ``prev`` (outside the mask, the learned cells and the shadow's edges)
        tracked into ``curr`` and back; their rays met with the planes; RANSAC on the rigid
        motion of the ground points; then, with ``two_view``, :func:`two_view_motion` on the
        inliers' rays gives the rotation and the translation's direction, and the rigid fit of
        the points whose heights are not outliers, weighted toward the wheels, its length.
        """
        c = self.cfg
        prev = to_gray(prev, self.camera.image_size)
        curr = to_gray(curr, self.camera.image_size)
        plane = _plane(ground_plane)
        plane0 = plane if prev_plane is None else _plane(prev_plane)
        rates = None if rate_xy is None else np.asarray(rate_xy, dtype=np.float64).reshape(2)
        if rates is not None and not np.all(np.isfinite(rates)):
            raise ValueError(f"rate_xy: {rate_xy!r}; give finite roll and pitch rates [rad/s] or None")

        def invalid(reason: str, **kw) -> OdometryEstimate:
            base = dict(n_features=0, n_tracked=0, n_inliers=0, inlier_ratio=0.0, residual=math.nan)
            return OdometryEstimate(
                math.nan, math.nan, math.nan, False, reason, 0.0, dt=dt, t=t, **(base | kw)
            )

        for which, pl in (("this", plane), ("the last", plane0)):
            problem = self.camera.ground_view_error(pl, c.max_range)
            if problem:
                return invalid(f"the ground is not in view in {which} frame: {problem}")
        allowed = self._selection_mask()
        edges = None
        if c.shadow_mask:
            edges = self._shadow_edges(prev)
            if edges.any():
                allowed = np.where(edges, 0, allowed).astype(np.uint8)
        # the work is done on the box that holds the usable ground (and the motion's margin)
        x0, y0, x1, y1 = self._box
        pts = cv2.goodFeaturesToTrack(
            np.ascontiguousarray(prev[y0:y1, x0:x1]),
            c.max_features if predict is None else 2 * c.max_features,  # those that stay, below
            c.quality_level,
            c.min_distance,
            mask=np.ascontiguousarray(allowed[y0:y1, x0:x1]),
            blockSize=5,
        )
        if pts is None or len(pts) < c.min_inliers:
            return invalid("too few features", n_features=0 if pts is None else len(pts))
        p0 = pts.reshape(-1, 2).astype(np.float32)
        n_feat = len(p0)
        win, crit = (c.window, c.window), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        lk = {"winSize": win, "maxLevel": c.levels, "criteria": crit}
        box0 = np.ascontiguousarray(prev[y0:y1, x0:x1])
        box1 = np.ascontiguousarray(curr[y0:y1, x0:x1])
        guess = None
        shift = np.array([x0, y0], np.float64)
        rays0 = self.camera.cam2world(p0.astype(np.float64) + shift)  # (computed once, used below)
        if predict is not None:
            guess = self._predicted(p0 + np.array([x0, y0], np.float32), rays0, dt, (plane0, plane), predict)
        if guess is not None:  # from where the given twist puts them
            # the strongest corners whose ground stays in view (fast, the view's trailing part leaves it)
            gx, gy = np.rint(guess[:, 0]).astype(int), np.rint(guess[:, 1]).astype(int)
            h, w = self._mask.shape
            inside = (gx >= 0) & (gx < w) & (gy >= 0) & (gy < h)
            inside[inside] = self._mask[gy[inside], gx[inside]] > 0
            keep = np.flatnonzero(inside)[: c.max_features]
            if len(keep) < c.min_inliers:
                return invalid("too few features staying in view", n_features=len(keep))
            p0, guess, rays0 = p0[keep], guess[keep], rays0[keep]
            n_feat = len(p0)
            guess -= np.array([x0, y0], np.float32)
        # the ring's corners on the wheels' tracks, tracked with the others (their own fit below)
        n_main = len(p0)
        if c.two_view and self._ring is not None and t0 is not None and len(self.tracks) >= 2:
            pr = self._ring_select(prev, shift, edges, t0)
            if pr is not None:
                rays_r = self.camera.cam2world(pr.astype(np.float64) + shift)
                if guess is not None:
                    gr = self._predicted(pr + shift.astype(np.float32), rays_r, dt, (plane0, plane), predict)
                    assert gr is not None
                    guess = np.vstack([guess, gr - shift.astype(np.float32)])
                p0, rays0 = np.vstack([p0, pr]), np.vstack([rays0, rays_r])
        if guess is not None:
            lk_p = lk | {"maxLevel": c.predict_levels, "flags": cv2.OPTFLOW_USE_INITIAL_FLOW}
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(box0, box1, p0, guess, **lk_p)  # type: ignore[call-overload]
            back = (p1 - (guess - p0)).astype(np.float32)  # the same prediction, backwards
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(box1, box0, p1, back, **lk_p)  # type: ignore[call-overload]
        else:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(box0, box1, p0, None, **lk)  # type: ignore[call-overload]
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(box1, box0, p1, None, **lk)  # type: ignore[call-overload]
        fb = np.linalg.norm(p0 - p0b, axis=1)
        ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < c.fb_max)
        ring = None
        if len(p0) > n_main:  # the ring's tracked corners: their rays in both frames
            okr = ok[n_main:]
            if okr.sum() >= c.track_min_points:
                ring = (
                    rays0[n_main:][okr],
                    self.camera.cam2world(p1[n_main:][okr].astype(np.float64) + shift),
                )
            p0, p1, ok, rays0 = p0[:n_main], p1[:n_main], ok[:n_main], rays0[:n_main]
        P0, P1 = p0[ok].astype(np.float64) + shift, p1[ok].astype(np.float64) + shift
        rays0, rays1 = rays0[ok], self.camera.cam2world(P1)
        T_bc = self.camera.T_body_cam
        G0 = _rays_to_ground(T_bc, rays0, plane0, c.min_depression_deg)
        G1 = _rays_to_ground(T_bc, rays1, plane, c.min_depression_deg)
        o = self.camera.T_body_cam[:3, 3]
        r0 = np.hypot(G0[:, 0] - o[0], G0[:, 1] - o[1])
        near = (
            np.isfinite(G0[:, 0])
            & np.isfinite(G1[:, 0])
            & (r0 <= c.max_range)
            & (np.hypot(G1[:, 0] - o[0], G1[:, 1] - o[1]) <= c.max_range)
        )
        P0, P1, G0, G1, r0 = P0[near], P1[near], G0[near], G1[near], r0[near]
        rays0, rays1 = rays0[near], rays1[near]
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
        fit_rates = rates if dims == 3 else None
        vel, rms, cov = velocity_from_points(
            G0[inl, :dims], G1[inl, :dims], dt, return_cov=True, rate_xy=fit_rates
        )
        self._learn_static(P0, P1, inl)
        if c.two_view:
            refined = self._two_view(rays0, rays1, G0, G1, r0, inl, dt, plane0, dims, vel, rates, t0, ring)
            if refined is not None:
                vel, cov, rms = refined
            else:  # the plane's fit, with the scale's error of the ground lately seen
                cov = _with_speed_error(cov, vel[:2], self._scale_rel(math.nan))
        if self._moved is None:  # the plane's fit carries the tracks: a turn about z, a level move
            half = 0.5 * float(vel[2]) * dt
            ch, sh = math.cos(half), math.sin(half)
            chord = np.array([ch * vel[0] - sh * vel[1], sh * vel[0] + ch * vel[1], 0.0]) * dt
            self._moved = (_rotation(np.array([0.0, 0.0, float(vel[2]) * dt])), chord)
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

    def _predicted(self, px: np.ndarray, rays: np.ndarray, dt: float, plane, twist) -> np.ndarray | None:
        """(n, 2) float32 where ``twist`` (mid-pair) moves the ground seen at ``px`` in ``dt``, or None.

        ``rays``: (n, 3) the pixels' camera-frame rays; ``plane`` the ground (body frame) of the
        first frame and of the next.
        """
        tw = np.asarray(twist, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(tw)):
            return None
        G = _rays_to_ground(self.camera.T_body_cam, rays, plane[0])
        w = float(tw[2])
        a = w * dt
        c, s = math.cos(a), math.sin(a)
        h = 0.5 * a  # the chord is the mid-pair velocity turned by omega dt / 2
        vx = math.cos(h) * tw[0] - math.sin(h) * tw[1]
        vy = math.sin(h) * tw[0] + math.cos(h) * tw[1]
        x, y = G[:, 0] - vx * dt, G[:, 1] - vy * dt  # the body moved, then turned by a
        moved = np.column_stack([c * x + s * y, -s * x + c * y, G[:, 2]])
        A, B, C = plane[1]
        moved[:, 2] = A * moved[:, 0] + B * moved[:, 1] + C  # on the next frame's plane
        T = np.linalg.inv(self.camera.T_body_cam)
        pc = moved @ T[:3, :3].T + T[:3, 3]
        out = self.camera.world2cam(pc, refine=False).astype(np.float32)
        bad = ~np.all(np.isfinite(out), axis=1)
        out[bad] = px[bad]  # no guess: where they were
        return out

    def _ring_select(self, prev, shift, edges, t0) -> np.ndarray | None:
        """Corners of the ring (beyond the motion's view) on the wheels' tracks: (n, 2) box pixels, or None.

        Looked for in small windows about the tracks' images (the ring is wide; the tracks cross
        it in two short strips).
        """
        c = self.cfg
        assert self._ring is not None
        x0, y0, x1, y1 = self._box
        T = np.linalg.inv(self.camera.T_body_cam)
        pad = c.window + 8
        boxes = []
        for track in self.tracks.tracks(t0):
            if len(track) == 0:
                continue
            px = self.camera.world2cam(track @ T[:3, :3].T + T[:3, 3], refine=False)
            px = px[np.all(np.isfinite(px), axis=1)]
            if len(px) == 0:
                continue
            ix, iy = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
            h, w = self._ring.shape
            inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
            inside[inside] = self._ring[iy[inside], ix[inside]] > 0
            if not inside.any():
                continue
            bx0, by0 = max(int(ix[inside].min()) - pad, x0), max(int(iy[inside].min()) - pad, y0)
            bx1, by1 = min(int(ix[inside].max()) + pad + 1, x1), min(int(iy[inside].max()) + pad + 1, y1)
            boxes.append([bx0, by0, bx1, by1])
        merged: list[list[int]] = []  # overlapping windows joined (a rear wheel on a front wheel's track)
        for b in sorted(boxes):
            if merged and b[0] <= merged[-1][2] and b[1] <= merged[-1][3] and b[3] >= merged[-1][1]:
                m = merged[-1]
                m[:] = [min(m[0], b[0]), min(m[1], b[1]), max(m[2], b[2]), max(m[3], b[3])]
            else:
                merged.append(b)
        found = []
        ring = self._ring_allowed()
        for bx0, by0, bx1, by1 in merged:
            mask = ring[by0:by1, bx0:bx1]
            if edges is not None:
                mask = np.where(edges[by0:by1, bx0:bx1], 0, mask).astype(np.uint8)
            pts = cv2.goodFeaturesToTrack(
                np.ascontiguousarray(prev[by0:by1, bx0:bx1]),
                max(c.track_features // len(merged), 1),
                c.quality_level,
                c.min_distance,
                mask=np.ascontiguousarray(mask),
                blockSize=5,
            )
            if pts is not None:
                found.append(pts.reshape(-1, 2) + np.array([bx0 - x0, by0 - y0], np.float32))
        if not found:
            return None
        return np.vstack(found).astype(np.float32)

    def _two_view(self, rays0, rays1, G0, G1, r0, inl, dt, plane0, dims, vel, rates, t0=None, ring=None):
        """The two-view refinement of :meth:`estimate`: (twist, its covariance, RMS) or None (kept planar)."""
        c = self.cfg
        cam = self.camera
        b0, b1 = rays0[inl], rays1[inl]
        init = np.array([vel[0], vel[1], 0.0, 0.0, 0.0, vel[2]])
        if rates is not None:
            init[3:5] = rates
        kw = dict(
            px_per_rad=self._px_per_rad,
            pixel_std=c.pixel_std,
            height_std=c.height_std,
            rate_xy=rates,
            rate_std=c.rate_std if rates is None else c.gyro_rate_std,
        )
        use = np.ones(len(b0), bool)
        for attempt in range(2):
            fit = two_view_motion(b0[use], b1[use], dt, cam.T_body_cam, plane0, init, **kw)
            if fit is None or not (np.all(np.isfinite(fit.motion)) and np.all(np.isfinite(fit.cov))):
                return None
            fitted = use.copy()  # the points of this fit
            bad = fit.residual_px > c.outlier_px
            if attempt == 1 or not bad.any() or int(use.sum() - bad.sum()) < c.min_inliers:
                break
            use[np.flatnonzero(use)[bad]] = False
            init = fit.motion
        ratio = math.inf  # the held fit's mean squared residual over the free fit's
        if c.plane_test > 0.0:  # is the plane enough? fit again with the heights held near it
            good = ~bad
            idx = np.flatnonzero(fitted)[good]
            kw2 = kw | {"height_std": c.min_height_std}
            tight = two_view_motion(b0[idx], b1[idx], dt, cam.T_body_cam, plane0, fit.motion, **kw2)
            if tight is not None and np.all(np.isfinite(tight.motion)) and np.all(np.isfinite(tight.cov)):
                free_ms = float(np.mean(fit.residual_px[good] ** 2))
                # (residuals below 0.1 px are as good as none: a noise-free image holds either fit)
                ratio = max(float(np.mean(tight.residual_px**2)), 0.01) / max(free_ms, 0.01)
                if ratio <= c.plane_test:
                    fit, fitted = tight, np.zeros_like(fitted)
                    fitted[idx] = True
                    bad = tight.residual_px > c.outlier_px
        # the scale: the rigid fit on the plane of the points whose residuals and heights are not outliers
        h = fit.heights
        hk = h[~bad] if np.any(~bad) else h
        med = float(np.median(hk))
        mad = 1.4826 * float(np.median(np.abs(hk - med))) + 1e-4
        good = (~bad) & (np.abs(h - med) <= c.height_cut * mad)
        keep = np.flatnonzero(inl)[np.flatnonzero(fitted)[good]]
        if len(keep) < c.min_inliers:
            return None
        weights = np.maximum(r0[keep], 0.01) ** c.scale_weight_power
        # (without the gyro's roll and pitch rates: the fit's own take up the tilt of the ground in
        # view against the wheels' plane, which would otherwise go into the speed)
        vp, rms, cov_p = velocity_from_points(
            G0[keep, :dims], G1[keep, :dims], dt, return_cov=True, weights=weights
        )
        # the rays fix the camera's displacement up to scale: scale it, then back to the body origin
        m = fit.motion
        lever = (fit.camera_shift[:2] - m[0:2] * dt) / dt  # the camera's velocity less the body's
        vb = m[0:2] + lever  # the camera's velocity (horizontal)
        vc = vp[:2] + lever  # ... as the plane fit puts it
        eps2 = _SCALE_EPS**2
        scale = (float(vc @ vb) + eps2) / (float(vb @ vb) + eps2)
        # (the rays leave the scale free: a fit whose heights all drifted toward the camera reads
        # a shorter move, which the scale makes up; only a move in another direction disagrees)
        nb, nc = math.hypot(vb[0], vb[1]), math.hypot(vc[0], vc[1])
        turned = min(nb, nc) > _DIRECTION_SPEED and float(vc @ vb) < math.cos(_MAX_TURN) * nb * nc
        if turned or not (_SCALE_RANGE[0] <= scale <= _SCALE_RANGE[1]):
            return None  # the plane and the rays disagree: keep the plane's fit
        # the ground's roughness: this pair's ratio, or the median of the last ROUGHNESS_S if rougher
        # (a patch that is a plane but lies off the wheels' passes the test and still errs)
        if math.isfinite(ratio):
            self._ratios.append((dt, ratio))
            self._span += dt
            while self._span > ROUGHNESS_S and len(self._ratios) > 1:
                self._span -= self._ratios.popleft()[0]
        rel = self._scale_rel(ratio)
        speed = math.hypot(vb[0], vb[1])
        u = vb / speed if speed > _SCALE_EPS else np.array([1.0, 0.0])
        speed_var = float(u @ cov_p[:2, :2] @ u) + (rel * scale * speed) ** 2
        # the wheels' tracks in view: the ground's height known there
        anchor = None
        if t0 is not None:
            ar, ah = b0[fitted][good], h[good]
            if ring is not None:  # the ring's points, their heights with the motion held
                hr, res = heights_given_motion(
                    ring[0], ring[1], dt, cam.T_body_cam, plane0, m, px_per_rad=self._px_per_rad, scale=scale
                )
                fine = np.isfinite(hr) & (res <= c.outlier_px)
                ar, ah = np.vstack([ar, ring[0][fine]]), np.concatenate([ah, hr[fine]])
            anchor = self._track_scale(ar, ah, plane0, scale, t0)
        self.last_scale_source = "plane"
        if anchor is not None:
            self.last_scale_source = "tracks"
            k_a, rel_a = anchor
            var_p = speed_var / max(scale * speed, _SCALE_EPS) ** 2  # the plane's, relative
            # weighed against the plane's error from the relief of the ground lately seen (the
            # fit's own deviation, or one pair's plane test, says little of it: on flat ground
            # they handed the tracks half the weight, or all of it, and the speed erred by 1.4
            # times as much)
            rel_lately = self._scale_rel(math.nan)
            w_a = rel_lately**2 / (rel_lately**2 + rel_a**2)
            scale = (1.0 - w_a) * scale + w_a * k_a
            speed_var = (scale * speed) ** 2 * ((1.0 - w_a) ** 2 * var_p + (w_a * rel_a) ** 2)
        # the body's move over the pair, to carry the tracks
        Rm = _rotation(m[3:6] * dt)
        self._moved = (Rm, scale * fit.camera_shift - (Rm - np.eye(3)) @ cam.T_body_cam[:3, 3])
        # the fit's v is the chord over the pair in the first frame's axes; the rigid fits' (and
        # the truth's) the velocity at mid-pair, turned by omega dt / 2 from it
        half = -0.5 * m[5] * dt
        rot = np.array([[math.cos(half), -math.sin(half)], [math.sin(half), math.cos(half)]])
        chord = np.array([scale * vb[0] - lever[0], scale * vb[1] - lever[1]])
        twist = np.array([*(rot @ chord), m[5]])
        # covariance: the speed along the motion from the scale, the rest from the two-view fit
        perp = np.eye(2) - np.outer(u, u)
        cb = fit.cov[np.ix_([0, 1, 5], [0, 1, 5])]
        cov = np.zeros((3, 3))
        cov[:2, :2] = speed_var * np.outer(u, u) + scale**2 * perp @ cb[:2, :2] @ perp
        cov[:2, 2] = cov[2, :2] = scale * perp @ cb[:2, 2]
        cov[2, 2] = cb[2, 2]
        J = np.eye(3)
        J[:2, :2] = rot
        return twist, J @ cov @ J.T, rms

    def _track_scale(self, rays, heights, plane, scale: float, t0: float) -> tuple[float, float] | None:
        """The scale from the points on the wheels' tracks, and its relative deviation, or None.

        ``rays`` (n, 3) camera-frame rays of the first frame's points and ``heights`` (n,) their
        heights off ``plane`` in the two-view fit's own scale; ``scale`` the plane's (where to
        look for the tracks first); ``t0`` the first frame's time [s]. A point at height h in
        the fit's scale lies at k h + (1 - k) H in the true one (H: the camera's height above
        the plane; the rays leave the scale k free), so a point on a track of known height
        gives k: each point's, their median.
        """
        c = self.cfg
        if len(self.tracks) < 2 or len(rays) < c.track_min_points:
            return None
        a, b, cc = plane
        T = self.camera.T_body_cam
        o = T[:3, 3]
        H = float(o[2] - (a * o[0] + b * o[1] + cc))
        d = rays @ T[:3, :3].T
        den = d[:, 2] - a * d[:, 0] - b * d[:, 1]
        s = (-H + heights) / den  # the distance along the ray in the fit's scale
        k = scale
        for _ in range(2):  # the tracks under the points at this scale, then at the tracks' scale
            X = o + (k * s)[:, None] * d
            z, on, travel = self.tracks.heights_at(X[:, :2], t0)
            if on.sum() < c.track_min_points:
                return None
            true = z[on] - (a * X[on, 0] + b * X[on, 1] + cc)
            ks = (H - true) / (H - heights[on])
            k = float(np.median(ks))
        if not (_SCALE_RANGE[0] <= k <= _SCALE_RANGE[1]):
            return None
        spread = 1.4826 * float(np.median(np.abs(ks - k))) / math.sqrt(len(ks))
        z_std = c.track_std + c.track_std_per_m * float(np.median(travel[on]))
        return k, math.hypot(z_std / H, spread / k)

    def _scale_rel(self, ratio: float) -> float:
        """The speed's relative error from the scale, given this pair's plane-test ratio (NaN: none).

        ``scale_std`` where the plane holds, growing with the roughness: this pair's ratio or
        the median over the last ``ROUGHNESS_S`` if larger (``FisheyeOdometryConfig.scale_std``).
        """
        c = self.cfg
        if c.plane_test <= 0:
            return 0.05
        lately = float(np.median([r for _, r in self._ratios])) if self._ratios else 0.0
        rough = max(ratio if math.isfinite(ratio) else 0.0, lately)
        return min(c.scale_std + c.scale_std_relief * math.sqrt(max(rough - 1.3, 0.0)), 0.3)

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
        self._allowed = self._ring_ok = None  # built again at the next selection

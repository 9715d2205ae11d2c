"""Camera models shared by the simulator and the estimators: pinhole and omnidirectional.

Frames (docs/environment.md): the camera optical frame has z along the optical axis, x right and y down
in the image; pixel coordinates are (x = column, y = row) with the centre of the top-left pixel at
(0, 0). ``T_body_cam`` maps camera-frame coordinates into the body frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from perception.models.calib_io import (
    CalibrationError,
    as_array,
    check_distortion,
    check_image_size,
    check_rigid,
    read_mapping,
    write_mapping,
)

__all__ = ["CalibrationError", "OmniCamera", "PinholeCamera"]


def _points(a, n_cols: int, name: str) -> tuple[np.ndarray, tuple[int, ...]]:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[-1:] != (n_cols,):
        raise ValueError(f"{name}: expected shape (..., {n_cols}), got {arr.shape}")
    return arr.reshape(-1, n_cols), arr.shape[:-1]


# ---------------------------------------------------------------------------------------- pinhole
#: What to do when a downward calibration has no ground plane (the odometry's scale rests on it).
GROUND_PLANE_MISSING = (
    "ground_plane: not set. The odometry's scale is the camera's height over the ground: add "
    "ground_plane: [0, 0, -h] to the calibration, h the height of the body frame's origin above flat "
    "ground [m] (measure the lens's height above the ground with the rover on level ground and "
    "subtract T_body_cam's z), or [a, b, c] for a ground z = a x + b y + c in the body frame"
)


#: The most the ground plane may be tilted in the body frame [deg]: the ground under a rover's
#: wheels is never steeper against its body (its suspension's travel and roll are far less);
#: beyond it, a "ground" is a wall, or the plane's slopes are in another unit.
MAX_GROUND_TILT_DEG = 45.0


def _above_plane(T_body_cam: np.ndarray, plane) -> tuple[str, float, np.ndarray]:
    """Why the camera is not above ``plane`` ("" if it is), its height over it [m], the upward normal.

    ``plane``: (a, b, c) of z = a x + b y + c in the body frame [-, -, m], or None (not given).
    A plane tilted more than :data:`MAX_GROUND_TILT_DEG` from the body's x-y plane is refused.
    """
    up = np.array([0.0, 0.0, 1.0])
    if plane is None:
        return GROUND_PLANE_MISSING, math.nan, up
    a, b, c = (float(v) for v in plane)
    if not all(math.isfinite(v) for v in (a, b, c)):
        return f"ground_plane: {plane!r} is not finite", math.nan, up
    tilt = math.degrees(math.atan(math.hypot(a, b)))
    if tilt > MAX_GROUND_TILT_DEG:
        return (
            f"ground_plane: z = {a:g} x + {b:g} y + {c:g} is tilted {tilt:.1f} deg from the body's "
            f"x-y plane, more than the {MAX_GROUND_TILT_DEG:g} deg a rover's ground can be under a "
            "downward camera; a and b are slopes (dz/dx, dz/dy), not angles",
            math.nan,
            up,
        )
    n = np.array([-a, -b, 1.0]) / math.sqrt(1.0 + a * a + b * b)
    centre = T_body_cam[:3, 3]
    height = float(n @ (centre - np.array([0.0, 0.0, c])))
    if height <= 0:
        return (
            f"the camera (at z = {centre[2]:.3f} m in the body frame) is {-height:.3f} m below the "
            f"ground plane z = {a:g} x + {b:g} y + {c:g}: check ground_plane's sign (c is minus the "
            "body origin's height above the ground, [m]) and T_body_cam",
            height,
            n,
        )
    return "", height, n


@dataclass(frozen=True, eq=False)
class PinholeCamera:
    """Pinhole camera with OpenCV's radial-tangential distortion, plain or rational.

    The distortion is ROS's ``plumb_bob`` (k1, k2, p1, p2[, k3]) or ``rational_polynomial``
    (k1, k2, p1, p2, k3, k4, k5, k6), OpenCV's 5- and 8-coefficient models: radial factor
    (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6).

    Attributes:
        K: 3x3 intrinsic matrix [px].
        distortion: (k1, k2, p1, p2, k3) or (k1, k2, p1, p2, k3, k4, k5, k6); 4 given are
            padded with k3 = 0.
        image_size: (W, H) [px].
        T_body_cam: 4x4 transform from the camera optical frame to the body frame [m].
        ground_plane: (a, b, c): the ground is z = a x + b y + c in the body frame [m]; None
            means "not given" (callers use flat ground under the wheels).
    """

    K: np.ndarray
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))
    image_size: tuple[int, int] = (640, 480)
    T_body_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    ground_plane: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        K = as_array(self.K, (3, 3), "K")
        w, h = check_image_size(self.image_size)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(f"K: focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if not (0 <= K[0, 2] <= w and 0 <= K[1, 2] <= h):
            raise CalibrationError(
                f"K: principal point ({K[0, 2]}, {K[1, 2]}) lies outside the {w}x{h} image"
            )
        if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise CalibrationError("K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        dist = check_distortion(self.distortion)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "distortion", dist)
        object.__setattr__(self, "image_size", (w, h))
        object.__setattr__(self, "T_body_cam", check_rigid(self.T_body_cam, "T_body_cam"))
        if self.ground_plane is not None:
            gp = as_array(self.ground_plane, (3,), "ground_plane")
            object.__setattr__(self, "ground_plane", tuple(float(v) for v in gp))
            problem = self.ground_view_error()
            if problem:
                raise CalibrationError(problem)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_fov(
        cls,
        image_size: tuple[int, int],
        hfov: float,
        vfov: float | None = None,
        T_body_cam: np.ndarray | None = None,
        ground_plane: tuple[float, float, float] | None = None,
    ) -> PinholeCamera:
        """Distortion-free camera with the principal point at the image centre.

        Args:
            image_size: (W, H) [px].
            hfov: Horizontal field of view [rad], in (0, pi).
            vfov: Vertical field of view [rad]; default gives square pixels.
            T_body_cam: Camera-to-body transform (default identity).
            ground_plane: See the class attributes.
        """
        w, h = check_image_size(image_size)
        for name, v in (("hfov", hfov), ("vfov", vfov)):
            if v is not None and not (0.0 < v < math.pi):
                raise CalibrationError(f"{name}: {v!r} rad is impossible for a pinhole; use (0, pi)")
        fx = (w / 2.0) / math.tan(hfov / 2.0)
        fy = fx if vfov is None else (h / 2.0) / math.tan(vfov / 2.0)
        # pixel centres at integer coordinates: the image spans [-0.5, W - 0.5]
        K = np.array([[fx, 0.0, (w - 1) / 2.0], [0.0, fy, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(
            K=K,
            image_size=(w, h),
            T_body_cam=np.eye(4) if T_body_cam is None else T_body_cam,
            ground_plane=ground_plane,
        )

    # ------------------------------------------------------------------ geometry
    @property
    def fov(self) -> tuple[float, float]:
        """Horizontal and vertical field of view of the undistorted model [rad]."""
        w, h = self.image_size
        return 2 * math.atan(w / 2 / self.K[0, 0]), 2 * math.atan(h / 2 / self.K[1, 1])

    def project(self, points_cam) -> np.ndarray:
        """Project camera-frame points (..., 3) [m] to distorted pixels (..., 2).

        Points at or behind the camera (z <= 0) give NaN.
        """
        p, lead = _points(points_cam, 3, "points_cam")
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(z > 0, p[:, 0] / z, np.nan)
            y = np.where(z > 0, p[:, 1] / z, np.nan)
        xd, yd = self._distort(x, y)
        K = self.K
        u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        v = K[1, 1] * yd + K[1, 2]
        return np.stack([u, v], -1).reshape(*lead, 2)

    def _radial(self, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The radial factor at r^2 and its derivative with respect to r^2."""
        k1, k2, _, _, k3, k4, k5, k6 = np.r_[self.distortion, np.zeros(8 - len(self.distortion))]
        num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dnum = k1 + r2 * (2 * k2 + 3 * r2 * k3)
        dden = k4 + r2 * (2 * k5 + 3 * r2 * k6)
        return num / den, (dnum * den - num * dden) / (den * den)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p1, p2 = self.distortion[2], self.distortion[3]
        r2 = x * x + y * y
        radial, _ = self._radial(r2)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return xd, yd

    def normalized(self, pixels) -> np.ndarray:
        """Undistorted normalized image coordinates (x/z, y/z) of pixels (..., 2)."""
        p, lead = _points(pixels, 2, "pixels")
        if not np.any(self.distortion):
            K = self.K
            y = (p[:, 1] - K[1, 2]) / K[1, 1]
            x = (p[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
            return np.stack([x, y], -1).reshape(*lead, 2)
        K = self.K
        yd = (p[:, 1] - K[1, 2]) / K[1, 1]
        xd = (p[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        x, y = self._undistort_guess(p, xd, yd)
        # Gauss-Newton on distort(x, y) = (xd, yd) with the analytic 2x2 Jacobian (from OpenCV's
        # fixed-point solution it is usually met at once)
        p1, p2 = self.distortion[2], self.distortion[3]
        for _ in range(20):
            fx, fy = self._distort(x, y)
            ex, ey = fx - xd, fy - yd
            if not np.nanmax(np.abs(ex) + np.abs(ey), initial=0.0) >= 1e-12:  # ~1e-10 px
                break
            radial, dr2 = self._radial(x * x + y * y)
            drad = 2 * dr2  # d(radial)/d(r2) * 2
            jxx = radial + x * x * drad + 2 * p1 * y + 6 * p2 * x
            jxy = x * y * drad + 2 * p1 * x + 2 * p2 * y
            jyx = x * y * drad + 2 * p1 * x + 2 * p2 * y
            jyy = radial + y * y * drad + 6 * p1 * y + 2 * p2 * x
            det = jxx * jyy - jxy * jyx
            x = x - (jyy * ex - jxy * ey) / det
            y = y - (-jyx * ex + jxx * ey) / det
        return np.stack([x, y], -1).reshape(*lead, 2)

    def _undistort_guess(self, p: np.ndarray, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, ...]:
        """A start for :meth:`normalized`'s Newton steps: OpenCV's iterative undistortion where it applies.

        OpenCV's model is this one without skew; elsewhere the start is the distorted point.
        """
        if self.K[0, 1] != 0.0 or len(p) < 8 or len(self.distortion) not in (4, 5, 8):
            return xd.copy(), yd.copy()
        # to 1e-11 px (OpenCV's reprojection error): the Newton steps then only check it
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-11)
        und = cv2.undistortPoints(p.reshape(-1, 1, 2), self.K, self.distortion, criteria=crit).reshape(-1, 2)
        ok = np.all(np.isfinite(und), axis=1)
        return np.where(ok, und[:, 0], xd), np.where(ok, und[:, 1], yd)

    def unproject(self, pixels) -> np.ndarray:
        """Unit rays (..., 3) in the camera frame through pixels (..., 2)."""
        n = self.normalized(pixels)
        rays = np.concatenate([n, np.ones(n.shape[:-1] + (1,))], -1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    def undistort_points(self, pixels) -> np.ndarray:
        """Pixels (..., 2) as an ideal (distortion-free) camera with the same K would see them."""
        n = self.normalized(pixels)
        K = self.K
        u = K[0, 0] * n[..., 0] + K[0, 1] * n[..., 1] + K[0, 2]
        v = K[1, 1] * n[..., 1] + K[1, 2]
        return np.stack([u, v], -1)

    # ------------------------------------------------------------------ ground homography
    def ground_homography(self, ground_plane: tuple[float, float, float] | None = None) -> np.ndarray:
        """H = K M* of the odometry paper: body-frame ground (x, y, 1) -> undistorted pixels.

        With M = [R | t] the body frame expressed in the camera frame and the ground
        z = a x + b y + c (body frame), M* = [r1 + a r3, r2 + b r3, t + c r3] (paper eq. 6-8).

        Args:
            ground_plane: (a, b, c) [-, -, m]; default :attr:`ground_plane`.
        """
        plane = ground_plane if ground_plane is not None else self.ground_plane
        if plane is None:
            raise CalibrationError(GROUND_PLANE_MISSING)
        a, b, c = plane
        T_cam_body = np.linalg.inv(self.T_body_cam)
        R, t = T_cam_body[:3, :3], T_cam_body[:3, 3]
        m_star = np.column_stack([R[:, 0] + a * R[:, 2], R[:, 1] + b * R[:, 2], t + c * R[:, 2]])
        return self.K @ m_star

    def ground_view_error(self, ground_plane: tuple[float, float, float] | None = None) -> str:
        """Why this camera cannot see the ground plane, or "" if it can.

        The camera must stand above the plane z = a x + b y + c (body frame) and the ray through
        the principal point must meet it in front of the camera, at most 100 m away; otherwise
        every pixel maps to a point behind the camera or beyond the horizon and an estimate
        would be valid in form but wrong.

        Args:
            ground_plane: (a, b, c) [-, -, m]; default :attr:`ground_plane`.
        """
        problem, height, n = _above_plane(
            self.T_body_cam, ground_plane if ground_plane is not None else self.ground_plane
        )
        if problem:
            return problem
        axis = self.T_body_cam[:3, :3] @ np.array([0.0, 0.0, 1.0])  # optical axis, body frame
        down = -float(n @ axis)
        if down <= height / 100.0:
            return (
                "T_body_cam: the camera's optical axis does not meet the ground plane in front of it "
                f"(it points {'away from' if down <= 0 else 'along'} the ground); a downward camera's "
                "z axis points down"
            )
        return ""

    def pixels_to_ground(self, pixels, ground_plane: tuple[float, float, float] | None = None) -> np.ndarray:
        """Body-frame ground coordinates (x, y) [m] of distorted pixels (..., 2), via H^-1."""
        p, lead = _points(pixels, 2, "pixels")
        und = self.undistort_points(p)
        h_inv = np.linalg.inv(self.ground_homography(ground_plane))
        q = np.column_stack([und, np.ones(len(und))]) @ h_inv.T
        return (q[:, :2] / q[:, 2:3]).reshape(*lead, 2)

    # ------------------------------------------------------------------ YAML
    _REQUIRED = frozenset({"image_size", "K", "distortion", "T_body_cam"})
    _OPTIONAL = frozenset({"ground_plane"})

    @classmethod
    def load(cls, path: str | Path) -> PinholeCamera:
        """Read a downward-camera calibration YAML (docs/odometry.md).

        Keys: ``image_size: [W, H]``, ``K`` (3x3), ``distortion: [k1, k2, p1, p2, k3]`` (or the
        8 coefficients of the rational model, ``[k1, k2, p1, p2, k3, k4, k5, k6]``),
        ``T_body_cam`` (4x4, camera optical frame to body frame), optional ``ground_plane: [a, b, c]``.

        Raises:
            CalibrationError: Missing file, missing or unknown key, wrong shape or impossible value;
                the message names the file and the key.
        """
        d = read_mapping(path, set(cls._REQUIRED), set(cls._OPTIONAL))
        try:
            return cls(
                K=as_array(d["K"], (3, 3), "K"),
                distortion=check_distortion(d["distortion"]),
                image_size=check_image_size(d["image_size"]),
                T_body_cam=as_array(d["T_body_cam"], (4, 4), "T_body_cam"),
                ground_plane=d.get("ground_plane"),
            )
        except CalibrationError as exc:
            raise CalibrationError(f"{path}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        """Write this calibration in the format :meth:`load` reads."""
        data = {
            "image_size": list(self.image_size),
            "K": self.K,
            "distortion": self.distortion,
            "T_body_cam": self.T_body_cam,
        }
        if self.ground_plane is not None:
            data["ground_plane"] = list(self.ground_plane)
        return write_mapping(path, data)


# ---------------------------------------------------------------------------------------- omni
@dataclass(frozen=True, eq=False)
class OmniCamera:
    """Scaramuzza's omnidirectional camera model (the fisheye paper's calibration model).

    A pixel p = (x, y) maps to sensor coordinates (u, v) through the affine stretch
    ``p - center = [[c, d], [e, 1]] (u, v)``; the viewing ray is (u, v, f(rho)) with
    rho = sqrt(u^2 + v^2) and f(rho) = a0 + a1 rho + ... + aN rho^N, normalised to the unit sphere.

    Sign convention: rays are in the OpenCV optical frame (z along the optical axis), so a0 > 0.
    OCamCalib's files use a0 < 0 with the camera looking along -z and (row, column) pixel order:
    negate the polynomial and swap the centre's coordinates to convert.

    Attributes:
        image_size: (W, H) [px].
        center: (cx, cy) distortion centre [px].
        affine: (c, d, e) of the stretch matrix.
        poly: (a0, ..., aN), N >= 2 [px^(1-k)].
        max_fov: Full field of view [rad] (rays further than max_fov / 2 from the axis are invalid).
        T_body_cam: 4x4 transform from the camera optical frame to the body frame [m].
        ground_plane: (a, b, c): the ground z = a x + b y + c in the body frame [-, -, m] for the
            fisheye's own odometry (:class:`perception.odometry.fisheye.FisheyeOdometry`); None:
            not given (the kinematics does not need it).
        mask_file: An image of the camera's size, non-zero where the ground may be seen and zero
            on the rover's own parts, for the fisheye's odometry (None: none; the parts are then
            learned). A relative path in a calibration file is relative to the file.
    """

    image_size: tuple[int, int]
    center: tuple[float, float]
    affine: tuple[float, float, float]
    poly: tuple[float, ...]
    max_fov: float
    T_body_cam: np.ndarray = field(default_factory=lambda: np.eye(4))
    ground_plane: tuple[float, float, float] | None = None
    mask_file: Path | None = None
    _inv: np.ndarray = field(init=False, repr=False, compare=False)
    _dpoly: np.ndarray = field(init=False, repr=False, compare=False)
    _rho_max: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        w, h = check_image_size(self.image_size)
        center = as_array(self.center, (2,), "center")
        affine = as_array(self.affine, (3,), "affine")
        poly = as_array(self.poly, (-1,), "poly")
        if len(poly) < 3:
            raise CalibrationError(f"poly: need at least a0, a1, a2, got {len(poly)} coefficients")
        if poly[0] <= 0:
            raise CalibrationError(f"poly: a0 must be positive in this convention (got {poly[0]})")
        det = affine[0] - affine[1] * affine[2]
        if not (0.5 < det < 2.0):
            raise CalibrationError(
                f"affine: stretch [[c, d], [e, 1]] has determinant {det:.3g}; expected near 1"
            )
        if not (0 < center[0] < w and 0 < center[1] < h):
            raise CalibrationError(f"center: ({center[0]}, {center[1]}) lies outside the {w}x{h} image")
        if not (0.0 < self.max_fov < 2 * math.pi):
            raise CalibrationError(
                f"max_fov_deg: {math.degrees(self.max_fov):g} deg is impossible; use (0, 360) (max_fov: "
                "(0, 2 pi) rad)"
            )
        object.__setattr__(self, "image_size", (w, h))
        object.__setattr__(self, "center", (float(center[0]), float(center[1])))
        object.__setattr__(self, "affine", tuple(float(v) for v in affine))
        object.__setattr__(self, "poly", tuple(float(v) for v in poly))
        object.__setattr__(self, "T_body_cam", check_rigid(self.T_body_cam, "T_body_cam"))
        if self.ground_plane is not None:
            gp = as_array(self.ground_plane, (3,), "ground_plane")
            object.__setattr__(self, "ground_plane", tuple(float(v) for v in gp))
            problem = self.ground_view_error()
            if problem:
                raise CalibrationError(problem)
        if self.mask_file is not None:
            object.__setattr__(self, "mask_file", Path(self.mask_file))
        # f'(rho), highest power first (np.polyval)
        object.__setattr__(self, "_dpoly", (np.arange(1, len(poly)) * poly[1:])[::-1].copy())
        # f(rho) must fall monotonically relative to rho up to the edge of the field of view
        rho_max = self._rho_limit()
        if rho_max is None:
            raise CalibrationError(
                f"poly: the model does not reach the field of view {math.degrees(self.max_fov):.1f} deg "
                "with a one-to-one mapping; check the coefficients or lower max_fov"
            )
        object.__setattr__(self, "_inv", self._fit_inverse(rho_max))
        object.__setattr__(self, "_rho_max", rho_max)

    def model_error(self) -> str:
        """Why this polynomial does not fit a fisheye of this image, or "" if it does.

        A downward fisheye's field of view ends near the image's border (its image circle), and
        the angle of a ray grows about evenly with its radius there (an equidistant lens: half
        the field of view at half the circle's radius; equisolid and stereographic lenses 45-60
        %). A polynomial scaled by mistake, or fitted to another resolution, puts the circle off
        the image or crowds the angles at its edge.
        """
        w, h = self.image_size
        cx, cy = self.center
        reach = max(math.hypot(x - cx, y - cy) for x in (0, w) for y in (0, h))  # to the farthest corner
        circle = self._rho_max  # the field of view's edge [px from the centre]
        fov = math.degrees(self.max_fov)
        if circle > 1.5 * reach:
            return (
                f"poly: the model's {fov:.0f} deg field of view ends {circle:.0f} px from the centre, "
                f"beyond the {w}x{h} image (its corners are at most {reach:.0f} px away): the "
                "polynomial does not fit this image (scaled, or fitted at another resolution)"
            )
        if circle < 0.1 * min(w, h):
            return (
                f"poly: the model's {fov:.0f} deg field of view fits in a circle of {circle:.1f} px in "
                f"the {w}x{h} image: the polynomial does not fit this image (scaled, or fitted at "
                "another resolution)"
            )
        half = math.degrees(float(np.arctan2(circle / 2, self._f(np.array(circle / 2)))))
        share = half / (fov / 2)
        if not 0.2 <= share <= 0.8:
            return (
                f"poly: half way to the image circle's edge ({circle / 2:.0f} px) the model's ray is "
                f"{half:.1f} deg off the axis, {100 * share:.0f} % of the {fov / 2:.0f} deg at the edge; a "
                "fisheye's angle grows about evenly with the radius (an equidistant lens: 50 %): the "
                "polynomial is scaled or wrong"
            )
        return ""

    def ground_view_error(
        self, ground_plane: tuple[float, float, float] | None = None, max_height: float | None = None
    ) -> str:
        """Why this fisheye cannot see the ground plane under it, or "" if it can.

        The camera must stand above the plane z = a x + b y + c (body frame), and the point of
        the plane straight below it (along the plane's normal) must lie inside the field of view;
        otherwise every ground point of the odometry lies behind the camera or off its image.

        Args:
            ground_plane: (a, b, c) [-, -, m]; default :attr:`ground_plane`.
            max_height: The most the camera may stand above the plane [m] (the odometry's
                ``max_range``: higher, no ground it uses is in view; a plane given in millimetres
                puts it there), or None: no limit.
        """
        plane = ground_plane if ground_plane is not None else self.ground_plane
        problem, height, n = _above_plane(self.T_body_cam, plane)
        if problem:
            return problem
        if max_height is not None and height > max_height:
            a, b, c = (float(v) for v in plane)  # type: ignore[union-attr]
            return (
                f"the camera stands {height:g} m above the ground plane z = {a:g} x + {b:g} y + {c:g}, "
                f"more than the {max_height:g} m of ground the odometry uses about it: give the plane "
                "in metres (c is minus the body origin's height above the ground)"
            )
        down = -(self.T_body_cam[:3, :3].T @ n)  # straight down, in the camera frame
        off = math.degrees(math.acos(max(-1.0, min(1.0, float(down[2])))))
        if off >= math.degrees(self.max_fov) / 2.0:
            return (
                f"T_body_cam: the ground straight below the camera is {off:.0f} deg off its optical axis, "
                f"outside its {math.degrees(self.max_fov):.0f} deg field of view; a downward fisheye's z "
                "axis points down"
            )
        return ""

    # ------------------------------------------------------------------ construction
    @classmethod
    def equidistant(
        cls,
        image_size: tuple[int, int],
        fov: float,
        radius: float,
        degree: int = 4,
        T_body_cam: np.ndarray | None = None,
    ) -> OmniCamera:
        """Fit the polynomial model to an ideal equidistant fisheye (rho = k * angle from axis).

        Args:
            image_size: (W, H) [px], centre at the image centre, no stretch.
            fov: Full field of view [rad] that maps to ``radius``.
            radius: Image-circle radius at fov / 2 [px].
            degree: Polynomial degree (4 as in the paper).
            T_body_cam: Camera-to-body transform.
        """
        w, h = check_image_size(image_size)
        if not (0.0 < fov < 2 * math.pi):
            raise CalibrationError(f"fov: {fov!r} rad is impossible; use (0, 2 pi)")
        k = radius / (fov / 2.0)
        rho = np.linspace(1e-3, radius * 1.02, 400)
        alpha = rho / k  # angle from the optical axis
        f = rho / np.tan(np.where(np.abs(alpha - math.pi / 2) < 1e-9, math.pi / 2 + 1e-9, alpha))
        # f = rho * cot(alpha); least squares with a1 free
        A = np.vander(rho, degree + 1, increasing=True)
        coef = np.linalg.lstsq(A, f, rcond=None)[0]
        return cls(
            image_size=(w, h),
            center=((w - 1) / 2.0, (h - 1) / 2.0),
            affine=(1.0, 0.0, 0.0),
            poly=tuple(coef),
            max_fov=fov,
            T_body_cam=np.eye(4) if T_body_cam is None else T_body_cam,
        )

    # ------------------------------------------------------------------ model
    def _f(self, rho: np.ndarray) -> np.ndarray:
        return np.polyval(self.poly[::-1], rho)

    def _df(self, rho: np.ndarray) -> np.ndarray:
        return np.polyval(self._dpoly, rho)

    def _rho_limit(self) -> float | None:
        """Sensor radius at the edge of the field of view, or None if never reached one-to-one."""
        half = self.max_fov / 2.0
        rho = np.linspace(0.0, 4.0 * max(self.image_size), 20001)
        alpha = np.arctan2(rho, self._f(rho))  # angle from the optical axis
        rising = np.diff(alpha) > 0
        if not rising[0]:
            return None
        stop = int(np.argmin(rising)) if not rising.all() else len(rising)
        alpha, rho = alpha[: stop + 1], rho[: stop + 1]
        if alpha[-1] < half:
            return None
        return float(np.interp(half, alpha, rho))

    def _fit_inverse(self, rho_max: float) -> np.ndarray:
        """Chebyshev fit of rho(alpha) over the field of view (Newton's start in world2cam)."""
        rho = np.linspace(0.0, rho_max * 1.02, 2000)
        alpha = np.arctan2(rho, self._f(rho))
        return np.polynomial.chebyshev.chebfit(alpha, rho, 12)

    def cam2world(self, pixels) -> np.ndarray:
        """Unit rays (..., 3) in the camera frame through pixels (..., 2).

        Pixels outside the field of view give NaN rays.
        """
        p, lead = _points(pixels, 2, "pixels")
        c, d, e = self.affine
        det = c - d * e
        dx = p[:, 0] - self.center[0]
        dy = p[:, 1] - self.center[1]
        u = (dx - d * dy) / det
        v = (-e * dx + c * dy) / det
        rho = np.hypot(u, v)
        z = self._f(rho)
        rays = np.stack([u, v, z], -1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        outside = np.arccos(np.clip(rays[:, 2], -1, 1)) > self.max_fov / 2 + 1e-12
        rays[outside] = np.nan
        return rays.reshape(*lead, 3)

    @functools.cached_property
    def _rho_table(self) -> tuple[np.ndarray, np.ndarray]:
        """(alpha, rho) of the inverse polynomial on a grid fine enough for 1e-5 px by interpolation."""
        alpha = np.linspace(0.0, self.max_fov / 2 + 1e-9, 8193)
        return alpha, np.polynomial.chebyshev.chebval(alpha, self._inv)

    def project_xyz(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (u, v) of camera-frame points given as coordinate arrays of one shape [m -> px].

        The fast form of :meth:`world2cam` without ``refine`` (rho from a dense table of the
        inverse polynomial, within ~1e-5 px), for many points; NaN outside the field of view.
        """
        r = np.hypot(x, y)
        alpha, table = self._rho_table
        # linear interpolation in the uniform table (NaN beyond the view)
        pos = np.arctan2(r, z) * ((len(table) - 1) / alpha[-1])
        inside = pos <= len(table) - 1  # False for NaN
        pos = np.where(inside, pos, 0.0)
        i = np.minimum(pos.astype(np.intp), len(table) - 2)  # alpha >= 0
        rho = np.where(inside, table[i] + (pos - i) * (table[i + 1] - table[i]), np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(r > 0, rho / r, rho * 0.0)  # on the axis: 0, or NaN straight behind
        ux, vy = x * s, y * s
        c, d, e = self.affine
        return c * ux + d * vy + self.center[0], e * ux + vy + self.center[1]

    def world2cam(self, points_cam, refine: bool = True) -> np.ndarray:
        """Pixels (..., 2) of camera-frame points or rays (..., 3); NaN outside the field of view.

        rho starts from the inverse polynomial (within ~1e-5 px; without ``refine`` from a table
        of it) and, with ``refine``, is refined by Newton's method on r f(rho) - z rho = 0
        (r = sqrt(x^2 + y^2)), so that the round trip is exact to ~1e-12 rad.
        """
        p, lead = _points(points_cam, 3, "points_cam")
        r = np.hypot(p[:, 0], p[:, 1])
        alpha = np.arctan2(r, p[:, 2])
        if not refine:
            out = np.empty((len(p), 2))
            out[:, 0], out[:, 1] = self.project_xyz(p[:, 0], p[:, 1], p[:, 2])
            return out.reshape(*lead, 2)
        valid = (alpha <= self.max_fov / 2 + 1e-12) & np.isfinite(alpha)
        rho = np.polynomial.chebyshev.chebval(alpha, self._inv)
        for _ in range(8):  # the Chebyshev start is usually within 1e-5 px already
            g = r * self._f(rho) - p[:, 2] * rho
            dg = r * self._df(rho) - p[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(np.abs(dg) > 0, g / dg, 0.0)
            rho = rho - step
            if not np.nanmax(np.abs(step), initial=0.0) > 1e-7:  # [px]; quadratic: the next is ~1e-14
                break
        with np.errstate(divide="ignore", invalid="ignore"):
            ux = np.where(r > 0, p[:, 0] / r, 0.0) * rho
            vy = np.where(r > 0, p[:, 1] / r, 0.0) * rho
        c, d, e = self.affine
        x = c * ux + d * vy + self.center[0]
        y = e * ux + vy + self.center[1]
        out = np.stack([x, y], -1)
        out[~valid] = np.nan
        return out.reshape(*lead, 2)

    # aliases with the names of the rest of the package
    project = world2cam
    unproject = cam2world

    # ------------------------------------------------------------------ YAML
    _REQUIRED = frozenset({"model", "image_size", "center", "affine", "poly", "max_fov_deg", "T_body_cam"})
    _OPTIONAL = frozenset({"ground_plane", "mask"})

    @classmethod
    def load(cls, path: str | Path) -> OmniCamera:
        """Read an omnidirectional calibration YAML (see :meth:`save` for the keys).

        Optional keys, for the fisheye's own odometry: ``ground_plane: [a, b, c]`` (as the
        downward camera's) and ``mask: FILE`` (an image of the rover's parts, zero on them;
        relative to the YAML's folder).

        Raises:
            CalibrationError: Missing file, missing or unknown key, or an impossible value.
        """
        d = read_mapping(path, set(cls._REQUIRED), set(cls._OPTIONAL))
        mask = d.get("mask")
        if mask is not None:
            if not isinstance(mask, str) or not mask.strip():
                raise CalibrationError(
                    f"{path}: mask: {mask!r}; give the path of a mask image, or leave it out"
                )
            mask = Path(mask) if Path(mask).is_absolute() else Path(path).parent / mask
        if d["model"] != "scaramuzza":
            raise CalibrationError(f"{path}: model: expected 'scaramuzza', got {d['model']!r}")
        try:
            fov = float(as_array(d["max_fov_deg"], (), "max_fov_deg"))
            return cls(
                image_size=check_image_size(d["image_size"]),
                center=tuple(as_array(d["center"], (2,), "center")),
                affine=tuple(as_array(d["affine"], (3,), "affine")),
                poly=tuple(as_array(d["poly"], (-1,), "poly")),
                max_fov=math.radians(fov),
                T_body_cam=as_array(d["T_body_cam"], (4, 4), "T_body_cam"),
                ground_plane=d.get("ground_plane"),
                mask_file=mask,
            )
        except CalibrationError as exc:
            raise CalibrationError(f"{path}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        """Write ``model, image_size, center, affine (c, d, e), poly (a0..aN), max_fov_deg, T_body_cam``.

        And ``ground_plane`` and ``mask`` (the mask file's absolute path) when set.
        """
        data = {
            "model": "scaramuzza",
            "image_size": list(self.image_size),
            "center": list(self.center),
            "affine": list(self.affine),
            "poly": list(self.poly),
            "max_fov_deg": math.degrees(self.max_fov),
            "T_body_cam": self.T_body_cam,
        }
        if self.ground_plane is not None:
            data["ground_plane"] = list(self.ground_plane)
        if self.mask_file is not None:
            data["mask"] = str(Path(self.mask_file).resolve())
        return write_mapping(path, data)

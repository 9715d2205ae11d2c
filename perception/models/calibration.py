"""Calibration of the omnidirectional model and of the downward camera's pose on the body.

The downward camera's 6-DOF pose minimises the reprojection error of ground points known in the
body frame (odometry paper, eq. 9): :func:`calibrate_ground_camera`.

The fisheye paper calibrates with Scaramuzza's toolbox. Here the model is fitted to pixels whose
viewing directions are known in the camera frame (corners of a board at a known pose, such as
the checkerboard ground of the calibration scenario seen from a rover parked at a known pose):

1. Linear start: with the centre at the image centre and no stretch, every corner gives one
   linear equation in the polynomial, f(rho) = rho z / sqrt(x^2 + y^2) (the ray (u, v, f(rho)) is
   parallel to the corner's direction (x, y, z)).
2. Refinement: centre, affine stretch and polynomial by nonlinear least squares on the angle
   between each pixel's model ray and the corner's direction, scaled to pixels by the local
   angular resolution.

The reported error is the reprojection error through :meth:`OmniCamera.world2cam`, in pixels.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares

from perception.models.calib_io import CalibrationError
from perception.models.cameras import OmniCamera, PinholeCamera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OmniFit:
    """Result of :func:`fit_omni_camera`.

    Attributes:
        camera: The fitted model.
        rms_px: Root-mean-square reprojection error over the corners [px].
        max_px: Largest reprojection error of the inliers [px].
        residuals_px: (N,) reprojection error of each corner [px].
        inliers: (N,) bool, the corners the final fit used.
    """

    camera: OmniCamera
    rms_px: float
    max_px: float
    residuals_px: np.ndarray
    inliers: np.ndarray


def _rays(params: np.ndarray, pixels: np.ndarray, degree: int) -> np.ndarray:
    cx, cy, c, d, e = params[:5]
    poly = params[5 : 6 + degree]
    det = c - d * e
    dx, dy = pixels[:, 0] - cx, pixels[:, 1] - cy
    u = (dx - d * dy) / det
    v = (-e * dx + c * dy) / det
    rho = np.hypot(u, v)
    z = np.polynomial.polynomial.polyval(rho, poly)
    r = np.stack([u, v, z], 1)
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def fit_omni_camera(
    pixels,
    directions_cam,
    image_size: tuple[int, int],
    max_fov: float,
    degree: int = 4,
    T_body_cam: np.ndarray | None = None,
    fit_center: bool = True,
    fit_affine: bool = True,
    reject_sigma: float = 4.0,
) -> OmniFit:
    """Fit an :class:`OmniCamera` to pixels and the directions they see, rejecting bad corners.

    Corners whose reprojection error exceeds ``reject_sigma`` robust standard deviations
    (1.4826 x the median absolute error, and at least 0.5 px) are dropped and the model is
    refitted, up to three times: a corner detector that locked onto an aliased or occluded
    corner must not bend the model.

    Args:
        pixels: (N, 2) measured pixel positions [px].
        directions_cam: (N, 3) the corresponding points or directions in the camera optical frame
            (only their direction is used).
        image_size: (W, H) [px].
        max_fov: Full field of view of the fitted model [rad].
        degree: Polynomial degree (4 in the fisheye paper).
        T_body_cam: Camera-to-body transform to store in the model.
        fit_center: Estimate the distortion centre (otherwise the image centre).
        fit_affine: Estimate the affine stretch (otherwise none).
        reject_sigma: Outlier threshold; ``inf`` keeps every corner.

    Raises:
        CalibrationError: Too few or degenerate correspondences, or a model that is not
            one-to-one over ``max_fov``.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    dirs = np.asarray(directions_cam, dtype=np.float64).reshape(-1, 3)
    if len(px) != len(dirs):
        raise CalibrationError(f"pixels ({len(px)}) and directions ({len(dirs)}) differ in number")
    inliers = np.logical_and(np.isfinite(px).all(axis=1), np.isfinite(dirs).all(axis=1))
    args = (image_size, max_fov, degree, T_body_cam, fit_center, fit_affine)
    for _ in range(4):
        camera = _fit_once(px[inliers], dirs[inliers], *args)
        reproj = camera.world2cam(dirs)
        err = np.hypot(reproj[:, 0] - px[:, 0], reproj[:, 1] - px[:, 1])
        err[~np.isfinite(err)] = np.inf
        limit = max(0.5, reject_sigma * 1.4826 * float(np.median(err[inliers])))
        keep = inliers & (err <= limit)
        if keep.sum() == inliers.sum():
            break
        inliers = keep
    if not np.isfinite(err[inliers]).all():
        raise CalibrationError("some corners lie outside the fitted field of view; raise max_fov")
    rms = float(math.sqrt(np.mean(err[inliers] ** 2)))
    log.info(
        "omni fit: %d of %d corners, RMS %.3f px, max %.3f px",
        inliers.sum(),
        len(px),
        rms,
        err[inliers].max(),
    )
    return OmniFit(
        camera=camera, rms_px=rms, max_px=float(err[inliers].max()), residuals_px=err, inliers=inliers
    )


def _fit_once(px, dirs, image_size, max_fov, degree, T_body_cam, fit_center, fit_affine) -> OmniCamera:
    n_params = (2 if fit_center else 0) + (3 if fit_affine else 0) + degree + 1
    if len(px) < 3 * n_params:
        raise CalibrationError(
            f"{len(px)} usable corners for {n_params} parameters; give at least {3 * n_params}"
        )
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    w, h = image_size
    centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])

    # 1. linear start: f(rho) = rho z / r with the centre at the image centre
    rho = np.hypot(px[:, 0] - centre[0], px[:, 1] - centre[1])
    r = np.hypot(dirs[:, 0], dirs[:, 1])
    use = (rho > 5.0) & (r > 1e-6)
    A = np.vander(rho[use], degree + 1, increasing=True)
    b = rho[use] * dirs[use, 2] / r[use]
    # rows in angle units: d(alpha)/d(f) = -rho / (rho^2 + f^2)
    weights = rho[use] / (rho[use] ** 2 + b**2)
    poly0 = np.linalg.lstsq(A * weights[:, None], b * weights, rcond=None)[0]

    # 2. refinement on angles, scaled to pixels by the mean angular resolution
    alpha = np.arccos(np.clip(dirs[:, 2], -1.0, 1.0))
    k = float(np.median(rho[use] / np.maximum(alpha[use], 1e-6)))
    scale = np.concatenate([[1.0, 1.0, 1.0, 1.0, 1.0], np.abs(poly0) + 1e-12])
    x0 = np.concatenate([centre, [1.0, 0.0, 0.0], poly0])
    free = np.ones_like(x0, dtype=bool)
    free[:2] = fit_center
    free[2:5] = fit_affine

    def residual(z: np.ndarray) -> np.ndarray:
        params = x0.copy()
        params[free] = z * scale[free]
        return (k * (_rays(params, px, degree) - dirs)).ravel()

    sol = least_squares(residual, x0[free] / scale[free], method="lm", x_scale="jac")
    params = x0.copy()
    params[free] = sol.x * scale[free]
    try:
        camera = OmniCamera(
            image_size=(w, h),
            center=(params[0], params[1]),
            affine=(params[2], params[3], params[4]),
            poly=tuple(params[5:]),
            max_fov=max_fov,
            T_body_cam=np.eye(4) if T_body_cam is None else T_body_cam,
        )
    except CalibrationError as exc:
        raise CalibrationError(f"the fitted model is unusable ({exc}); add corners near the rim") from exc
    return camera


@dataclass(frozen=True)
class ExtrinsicFit:
    """Result of :func:`calibrate_ground_camera`.

    Attributes:
        camera: The camera with the fitted ``T_body_cam`` and the ground plane fitted to the
            body-frame points (when they are coplanar).
        rms_px: Root-mean-square reprojection error of the inliers [px].
        residuals_px: (N,) reprojection error of each correspondence [px].
        inliers: (N,) bool, the correspondences the final fit used.
    """

    camera: PinholeCamera
    rms_px: float
    residuals_px: np.ndarray
    inliers: np.ndarray


def calibrate_ground_camera(
    camera: PinholeCamera,
    pixels,
    points_body,
    T_body_cam_init: np.ndarray | None = None,
    fit_plane: bool = True,
    reject_sigma: float = 4.0,
) -> ExtrinsicFit:
    """The camera's 6-DOF pose on the body by least squares on reprojection error (odometry paper eq. 9).

    Correspondences whose error exceeds ``reject_sigma`` robust standard deviations (at least
    0.5 px) are dropped and the pose refitted, up to three times.

    Args:
        camera: Intrinsics and distortion (its ``T_body_cam`` is the default start).
        pixels: (N, 2) measured (distorted) pixel positions [px].
        points_body: (N, 3) the same points in the body frame [m], e.g. checkerboard corners on
            the ground with the rover parked at a known pose.
        T_body_cam_init: Start of the search (default ``camera.T_body_cam``; if that is the
            identity, a PnP solution).
        fit_plane: Also fit the ground plane z = a x + b y + c through ``points_body``.
        reject_sigma: Outlier threshold; ``inf`` keeps every correspondence.

    Raises:
        CalibrationError: Fewer than 6 correspondences, mismatched arrays, or a degenerate fit.
    """
    px = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    P = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    if len(px) != len(P):
        raise CalibrationError(f"pixels ({len(px)}) and points_body ({len(P)}) differ in number")
    if len(px) < 6:
        raise CalibrationError(f"{len(px)} correspondences; the 6-DOF pose needs at least 6")
    T0 = camera.T_body_cam if T_body_cam_init is None else np.asarray(T_body_cam_init, dtype=np.float64)
    if np.allclose(T0, np.eye(4)):
        ok, rvec, tvec = cv2.solvePnP(P, px, camera.K, camera.distortion, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise CalibrationError("no initial pose: PnP failed; pass T_body_cam_init")
        x = np.concatenate([rvec.ravel(), tvec.ravel()])
    else:
        T_cb = np.linalg.inv(T0)
        x = np.concatenate([cv2.Rodrigues(T_cb[:3, :3])[0].ravel(), T_cb[:3, 3]])

    def project(x: np.ndarray, pts: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(x[:3])[0]
        return camera.project(pts @ R.T + x[3:])

    inliers = np.ones(len(px), dtype=bool)
    for _ in range(4):
        if inliers.sum() < 6:
            raise CalibrationError("fewer than 6 correspondences agree with one pose; check the matches")
        P_in, px_in = P[inliers], px[inliers]
        x = least_squares(
            lambda z, P_in=P_in, px_in=px_in: (project(z, P_in) - px_in).ravel(), x, method="lm"
        ).x
        err = np.hypot(*(project(x, P) - px).T)
        limit = max(0.5, reject_sigma * 1.4826 * float(np.median(err[inliers])))
        keep = err <= limit
        if np.array_equal(keep, inliers):
            break
        inliers = keep
    T_cb = np.eye(4)
    T_cb[:3, :3], T_cb[:3, 3] = cv2.Rodrigues(x[:3])[0], x[3:]
    plane = camera.ground_plane
    if fit_plane:
        Q = P[inliers]
        A = np.column_stack([Q[:, 0], Q[:, 1], np.ones(len(Q))])
        coef, *_ = np.linalg.lstsq(A, Q[:, 2], rcond=None)
        if np.abs(A @ coef - Q[:, 2]).max() > 0.01:
            raise CalibrationError("points_body are not on one plane (> 1 cm off); pass fit_plane=False")
        plane = (float(coef[0]), float(coef[1]), float(coef[2]))
    fitted = PinholeCamera(
        K=camera.K,
        distortion=camera.distortion,
        image_size=camera.image_size,
        T_body_cam=np.linalg.inv(T_cb),
        ground_plane=plane,
    )
    rms = float(math.sqrt(np.mean(err[inliers] ** 2)))
    log.info("ground camera calibration: %d of %d points, RMS %.3f px", inliers.sum(), len(px), rms)
    return ExtrinsicFit(camera=fitted, rms_px=rms, residuals_px=err, inliers=inliers)

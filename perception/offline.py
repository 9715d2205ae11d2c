"""Odometry on a folder of images from a real (or simulated) downward camera.

``run_folder_odometry`` reads the images in name order, runs :class:`FlowOdometry` in chained mode
at a fixed frame rate, and writes ``odometry.csv`` (one row per frame pair: t, v_x, v_y, omega,
quality, valid, inliers, reason) and ``trajectory.tum`` (the integrated planar pose). With an
IMU CSV beside the images it also reports the gyro's yaw rate per pair (``omega_imu``) and the
path with that yaw (``trajectory_imu.tum``): both yaw sources of the odometry paper's Table I.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from perception.cameras import OmniCamera, PinholeCamera
from perception.fisheye_kinematics import DOF_NAMES, KinematicsConfig, KinematicStateEstimator
from perception.inertial import read_imu_csv
from perception.kinematics import RoverKinematicModel
from perception.markers import SteeringCalibration
from perception.odometry import FlowOdometry, FlowOdometryConfig, integrate_twist
from perception.trajectory import write_planar_tum
from perception.validation import image_file_size

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass(frozen=True)
class FolderOdometryResult:
    """Summary of :func:`run_folder_odometry`.

    Attributes:
        frames: Images found.
        pairs: Frame pairs estimated.
        valid: Pairs with a valid estimate.
        distance: Length of the integrated path [m].
        csv_path: The per-pair CSV.
        tum_path: The integrated trajectory.
        tum_imu_path: The trajectory with the gyro's yaw (None without an IMU log).
        imu_bias: The gyro's body-z bias taken out [rad/s] (None without an IMU log).
    """

    frames: int
    pairs: int
    valid: int
    distance: float
    csv_path: Path
    tum_path: Path
    tum_imu_path: Path | None = None
    imu_bias: float | None = None


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` in name order.

    Raises:
        FileNotFoundError: The folder does not exist or holds no images.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder of images")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FileNotFoundError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def read_frame(
    path: Path, size: tuple[int, int], flags: int = cv2.IMREAD_UNCHANGED
) -> tuple[np.ndarray | None, str]:
    """A log's image and "" , or None and why not; its size is checked from the header first.

    A file whose header is not an image's, or says another size than the calibration's
    ``size`` (width, height) [px], or more pixels than the budget
    (:data:`perception.validation.MAX_IMAGE_PIXELS`), is not decoded.
    """
    try:
        header = image_file_size(path)
    except ValueError as exc:
        return None, str(exc)
    if header is None:
        return None, f"{path.name}: not a readable image"
    if header != tuple(size):
        return (
            None,
            f"{path.name}: {header[0]}x{header[1]} px differs from the calibration's {size[0]}x{size[1]}",
        )
    img = cv2.imread(str(path), flags)
    if img is None:
        return None, f"{path.name}: not a readable image"
    return img, ""


def bit_depth(image: np.ndarray) -> int:
    """Bits per sample of an image: 8, or 10 to 16 for a 16-bit container.

    For a 16-bit container, the smallest of 10, 12, 14 and 16 bits that holds the image's largest value (a
    12-bit sensor never exceeds 4095). One depth serves the whole log, so every frame is scaled
    alike (scaling each frame by its own maximum lets one glint darken it).

    Raises:
        ValueError: A sample type other than 8- or 16-bit unsigned integers.
    """
    if image.dtype == np.uint8:
        return 8
    if image.dtype != np.uint16:
        raise ValueError(f"images of {image.dtype}: use 8- or 16-bit unsigned integer images")
    top = int(image.max())
    return next(b for b in (10, 12, 14, 16) if top < 1 << b)


def _log_bit_depth(files: list[Path], size: tuple[int, int], n: int = 9) -> int:
    """The median :func:`bit_depth` of a log's first ``n`` readable images (not one glint's)."""
    depths = []
    for path in files[:n]:
        img, _ = read_frame(path, size)
        if img is not None:
            depths.append(bit_depth(img))
    return int(np.median(depths)) if depths else 8


def to_8bit(image: np.ndarray, bits: int) -> np.ndarray:
    """``image`` of ``bits`` bits per sample as 8-bit grey levels (values above the depth saturate)."""
    if image.dtype == np.uint8:
        return image
    return cv2.convertScaleAbs(image, alpha=255.0 / ((1 << bits) - 1))


def _open_run(images, out, fps: float, image_size: tuple[int, int]) -> tuple[list[Path], Path]:
    """Checks shared by the folder runs: frame rate, images, the first image's size; makes ``out``."""
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: {fps!r}; give the camera's frame rate in Hz (> 0)")
    files = list_images(images)
    first = image_file_size(files[0])  # from the header: nothing decoded yet
    if first is None:
        raise ValueError(f"{files[0]}: not a readable image")
    if first != tuple(image_size):
        w, h = image_size
        raise ValueError(
            f"{files[0]}: {first[0]}x{first[1]} px, but the calibration is for {w}x{h} px; "
            "use the calibration of this camera and resolution"
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    return files, out


def run_folder_odometry(
    images: str | Path,
    calibration: str | Path | PinholeCamera,
    fps: float,
    out: str | Path,
    config: FlowOdometryConfig | None = None,
    progress: Callable[[float], None] | None = None,
    imu: str | Path | None = None,
    imu_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    imu_still: float = 0.0,
) -> FolderOdometryResult:
    """Chained optical-flow odometry over a folder of downward-camera images.

    Args:
        images: Folder of images (name order is time order).
        calibration: Calibration YAML (docs/odometry.md; with ``ground_plane``) or a camera.
        fps: Frame rate of the images [Hz].
        out: Output folder (created).
        config: Estimator parameters.
        progress: Called with the finished share (0..1).
        imu: An IMU CSV (:func:`perception.inertial.read_imu_csv`; times on the images' clock,
            t = 0 at the first image).
        imu_rpy: The IMU's mount in the body frame, roll-pitch-yaw [rad].
        imu_still: Seconds of standstill at the start of the IMU log: the gyro's bias is their
            mean. With 0 (default) it is the median difference between the gyro's and the
            odometry's yaw rates over the valid pairs.

    Raises:
        FileNotFoundError: Missing folder or no images.
        CalibrationError: Missing or malformed calibration (the message names the key).
        ValueError: A bad frame rate, or a first image whose size differs from the calibration.

    Unreadable images and later images of another size do not stop the run: their rows are
    marked invalid with the reason, and the chain restarts at the next good image.
    """
    camera = calibration if isinstance(calibration, PinholeCamera) else PinholeCamera.load(calibration)
    odo = FlowOdometry(camera, config)
    imu_in = None if imu is None else _open_imu(imu, imu_rpy, imu_still)  # (log, mount z row)
    files, out = _open_run(images, out, fps, camera.image_size)
    bits = _log_bit_depth(files, camera.image_size)
    rows = []
    times, twists = [0.0], [np.zeros(3)]
    for k, path in enumerate(files):
        t = k / fps
        img, reason = read_frame(path, camera.image_size)  # size checked before decoding
        if img is not None and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
        if img is not None and img.dtype != np.uint8:  # 16-bit containers: the log's depth to 8 bits
            img = to_8bit(img, max(bits, 10))
        if reason:
            log.warning("%s; the chain restarts at the next image", reason)
            odo.reset()
            if k > 0:
                rows.append([t, math.nan, math.nan, math.nan, 0.0, 0, 0, reason])
                times.append(t)
                twists.append(np.full(3, math.nan))
            continue
        est = odo.update(img, t)
        if est is not None:
            rows.append(
                [t, est.v_x, est.v_y, est.omega, est.quality, int(est.valid), est.n_inliers, est.reason]
            )
            times.append(t)
            twists.append(est.twist)
        if progress is not None:
            progress((k + 1) / len(files))
    header = ["t", "v_x", "v_y", "omega", "quality", "valid", "inliers", "reason"]
    extra = [[] for _ in rows]
    if imu_in is not None:  # the gyro's yaw rate per pair and its sample count
        w_imu, counts, bias = _imu_yaw_rates(*imu_in, rows, fps, imu_still, imu)
        header += ["omega_imu", "imu_samples"]
        extra = [[f"{wi:.6f}", n] for wi, n in zip(w_imu, counts, strict=True)]
    csv_path = out / "odometry.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r, x in zip(rows, extra, strict=True):
            w.writerow([f"{r[0]:.6f}", *(f"{v:.6f}" for v in r[1:5]), r[5], r[6], r[7], *x])
    poses = integrate_twist(np.array(times), np.array(twists))
    tum_path = write_planar_tum(out / "trajectory.tum", times, poses)
    distance = float(np.sum(np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))))
    n_valid = sum(r[5] for r in rows)
    log.info("odometry: %d frames, %d of %d pairs valid, %.2f m", len(files), n_valid, len(rows), distance)
    result = FolderOdometryResult(len(files), len(rows), n_valid, distance, csv_path, tum_path)
    if imu_in is None:
        return result
    # the same path with the gyro's yaw rate where it has samples (times[0] is the first frame)
    tw = np.array(twists, dtype=np.float64)
    gyro_w = np.concatenate([[math.nan], w_imu])
    tw[:, 2] = np.where(np.isfinite(gyro_w), gyro_w, tw[:, 2])
    tum_imu = write_planar_tum(out / "trajectory_imu.tum", times, integrate_twist(np.array(times), tw))
    return dataclasses.replace(result, tum_imu_path=tum_imu, imu_bias=bias)


def _open_imu(imu, imu_rpy, imu_still: float) -> tuple:
    """The IMU log and the body-z row of its mount, checked before the images are processed."""
    rpy = np.asarray(imu_rpy, dtype=np.float64)
    if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
        raise ValueError(f"imu_rpy: {imu_rpy!r}; give the mount's roll, pitch, yaw [rad]")
    if not (math.isfinite(imu_still) and imu_still >= 0):
        raise ValueError(f"imu_still: {imu_still!r} s; give the standstill's length (>= 0)")
    return read_imu_csv(imu), Rotation.from_euler("xyz", rpy).as_matrix()[2]


def _imu_yaw_rates(imu_log, z_row, rows, fps: float, imu_still: float, name) -> tuple:
    """The gyro's body-z rate over each pair, less its bias: (rates, sample counts, bias) [rad/s]."""
    gyro_z = imu_log.gyro @ z_row
    raw = np.full(len(rows), math.nan)
    counts = np.zeros(len(rows), int)
    for k, r in enumerate(rows):
        # the samples of (t - 1/fps, t]; a microsecond's slack for times written to 6 decimals
        i0, i1 = np.searchsorted(imu_log.t, [r[0] - 1.0 / fps + 1e-6, r[0] + 1e-6], side="right")
        if i1 > i0:
            raw[k], counts[k] = gyro_z[i0:i1].mean(), i1 - i0
    if not np.isfinite(raw).any():
        raise ValueError(f"{name}: no IMU samples between the images' times; check the IMU's clock")
    if imu_still > 0:
        bias = float(gyro_z[imu_log.t <= imu_log.t[0] + imu_still].mean())
    else:
        diff = raw - np.array([r[3] if r[5] else math.nan for r in rows])
        diff = diff[np.isfinite(diff)]
        if not len(diff):
            raise ValueError(f"{name}: no IMU samples during a valid frame pair; give imu_still for the bias")
        bias = float(np.median(diff))
    log.info("imu: %d samples (%d left out), body-z bias %.5f rad/s", len(imu_log.t), imu_log.dropped, bias)
    return raw - bias, counts, bias


@dataclass(frozen=True)
class FolderKinematicsResult:
    """Summary of :func:`run_folder_kinematics`.

    Attributes:
        frames: Images found.
        all_valid: Frames on which all 10 degrees of freedom were measured.
        csv_path: The per-frame CSV.
    """

    frames: int
    all_valid: int
    csv_path: Path


def run_folder_kinematics(
    images: str | Path,
    camera: str | Path | OmniCamera,
    rover: str | Path | RoverKinematicModel,
    fps: float,
    out: str | Path,
    steering: str | Path | SteeringCalibration | None = None,
    config: KinematicsConfig | None = None,
    progress: Callable[[float], None] | None = None,
) -> FolderKinematicsResult:
    """The fisheye kinematics estimator over a folder of fisheye images.

    Args:
        images: Folder of colour images (name order is time order).
        camera: Omnidirectional calibration YAML (:meth:`OmniCamera.save`) or a camera.
        rover: Rover geometry YAML (:meth:`RoverKinematicModel.save`) or a model; its
            ``T_body_cam`` must be the camera's.
        fps: Frame rate of the images [Hz].
        out: Output folder (created); ``kinematics.csv`` gets one row per image: t, the 10
            degrees of freedom (psi_F, psi_R [rad], d_F, d_R [m], lambda_F, lambda_R [rad],
            theta FL..RR [rad]), the four wheel rates [rad/s], quality and a validity flag per
            degree of freedom.
        steering: Optional steering calibration (eq. 5 ratio map) YAML or object.
        config: Estimator parameters.
        progress: Called with the finished share (0..1).

    Raises:
        FileNotFoundError: Missing folder or no images.
        CalibrationError: Missing or malformed calibration files (the message names the key).
        ValueError: A bad frame rate, a first image whose size differs from the calibration, or
            camera and rover files with different mounts.

    Unreadable images and images of another size do not stop the run: the estimator carries its
    state over them with every flag down, and the row says why.
    """
    cam = camera if isinstance(camera, OmniCamera) else OmniCamera.load(camera)
    model = rover if isinstance(rover, RoverKinematicModel) else RoverKinematicModel.load(rover)
    cal = steering if steering is None or isinstance(steering, SteeringCalibration) else None
    if steering is not None and cal is None:
        cal = SteeringCalibration.load(steering)
    est = KinematicStateEstimator(cam, model, config, cal)
    files, out = _open_run(images, out, fps, cam.image_size)
    csv_path = out / "kinematics.csv"
    n_all = 0
    with open(csv_path, "w", newline="") as fh:
        wr = csv.writer(fh)
        wr.writerow(
            ["t", *DOF_NAMES, "rate_FL", "rate_FR", "rate_RL", "rate_RR", "quality"]
            + [f"valid_{d}" for d in DOF_NAMES]
            + ["note"]
        )
        for k, path in enumerate(files):
            t = k / fps
            bgr, note = read_frame(path, cam.image_size, cv2.IMREAD_COLOR)
            if bgr is None:
                rgb = np.zeros((0, 0, 3), np.uint8)  # the estimator flags it and carries on
            else:
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            if note:
                log.warning("%s; the state is carried over it", note)
            s = est.update(rgb, t)
            n_all += int(all(s.valid.values()))
            dof = np.r_[s.psi, s.depth, s.lam, s.theta]
            wr.writerow(
                [
                    f"{t:.6f}",
                    *(f"{v:.6f}" for v in dof),
                    *(f"{v:.5f}" for v in s.theta_dot),
                    f"{s.quality:.2f}",
                ]
                + [int(s.valid[d]) for d in DOF_NAMES]
                + [note]
            )
            if progress is not None:
                progress((k + 1) / len(files))
    log.info("kinematics: %d frames, all 10 DOF on %d", len(files), n_all)
    return FolderKinematicsResult(len(files), n_all, csv_path)

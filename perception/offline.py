"""Odometry on a folder of images from a real (or simulated) downward camera.

``run_folder_odometry`` reads the images in name order, runs :class:`FlowOdometry` in chained mode
at a fixed frame rate, and writes ``odometry.csv`` (one row per frame pair: t, v_x, v_y, omega,
quality, valid, inliers, reason) and ``trajectory.tum`` (the integrated planar pose). With an
IMU CSV beside the images it also reports the gyro's yaw rate per pair (``omega_imu``) and the
path with that yaw (``trajectory_imu.tum``): both yaw sources of the odometry paper's Table I.
"""

from __future__ import annotations

import contextlib
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
        mcap_path: ``odometry.mcap`` (None when not written).
    """

    frames: int
    pairs: int
    valid: int
    distance: float
    csv_path: Path
    tum_path: Path
    tum_imu_path: Path | None = None
    imu_bias: float | None = None
    mcap_path: Path | None = None


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


def _open_run(images, fps: float | None, image_size: tuple[int, int]) -> list[Path]:
    """Checks shared by the folder runs: frame rate, images, the first image's size."""
    if fps is None or not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: {fps!r}; give the camera's frame rate in Hz (> 0) for a folder of images")
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
    return files


def run_folder_odometry(
    images: str | Path,
    calibration: str | Path | PinholeCamera,
    fps: float | None,
    out: str | Path,
    config: FlowOdometryConfig | None = None,
    progress: Callable[[float], None] | None = None,
    imu: str | Path | None = None,
    imu_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    imu_still: float = 0.0,
    topic: str | None = None,
    imu_topic: str | None = None,
    mcap: bool = True,
) -> FolderOdometryResult:
    """Chained optical-flow odometry over a folder of downward-camera images or a robot log.

    Args:
        images: Folder of images (name order is time order), or a ROS 1 bag, ROS 2 bag folder
            or MCAP file (:mod:`perception.bags`; times from the messages' stamps).
        calibration: Calibration YAML (docs/odometry.md; with ``ground_plane``) or a camera. For
            a log with a ``CameraInfo`` beside the images, the YAML's intrinsics (``image_size``,
            ``K``, ``distortion``) may be left out: the log's fill them.
        fps: Frame rate of the images [Hz] (image folders only; ignored for logs).
        out: Output folder (created): ``odometry.csv``, ``trajectory.tum`` and, with ``mcap``,
            ``odometry.mcap`` (one ``nav_msgs/Odometry`` per estimate).
        config: Estimator parameters.
        progress: Called with the finished share (0..1).
        imu: An IMU CSV (:func:`perception.inertial.read_imu_csv`; times on the images' clock,
            t = 0 at the first image of a folder).
        imu_rpy: The IMU's mount in the body frame, roll-pitch-yaw [rad].
        imu_still: Seconds of standstill at the start of the IMU log: the gyro's bias is their
            mean. With 0 (default) it is the median difference between the gyro's and the
            odometry's yaw rates over the valid pairs.
        topic: The log's image topic (default: its only image topic).
        imu_topic: Read the IMU from this topic of the log instead of a CSV.
        mcap: Also write ``odometry.mcap``.

    Raises:
        FileNotFoundError: Missing folder or log, or no images.
        CalibrationError: Missing or malformed calibration (the message names the key).
        ValueError: A bad frame rate, a first image whose size differs from the calibration, or
            a log without the topic.

    Unreadable images, later images of another size and frames whose time does not follow the
    last one's do not stop the run: their rows are marked invalid with the reason, and the chain
    restarts at the next good image.
    """
    from perception import bags

    is_log = bags.is_log(images)
    if is_log:
        source = bags.log_images(images, topic)
        camera = _log_camera(calibration, source)
        n_frames = source.count
        frames = source.frames()
    else:
        camera = calibration if isinstance(calibration, PinholeCamera) else PinholeCamera.load(calibration)
        files = _open_run(images, fps, camera.image_size)
        n_frames = len(files)
        frames = _folder_frames(files, fps, camera.image_size)
    odo = FlowOdometry(camera, config)
    if imu_topic is not None:
        if not is_log:
            raise ValueError("imu_topic: an IMU topic needs a log (bag or MCAP) as the image source")
        data, _ = bags.log_imu(images, imu_topic)
        imu_in = _imu_rows(data, imu_rpy, imu_still, f"{images}:{imu_topic}")
    else:
        imu_in = None if imu is None else _open_imu(imu, imu_rpy, imu_still)  # (log, mount z row)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, pair_start = [], []
    times, twists, covs = [], [], []
    t_last = -math.inf
    depth = None
    for k, (t, img, reason) in enumerate(frames):
        if img is not None and not reason and (img.shape[1], img.shape[0]) != camera.image_size:
            reason = f"frame {k}: {img.shape[1]}x{img.shape[0]} px differs from the calibration"
        if not reason and not t > t_last:
            reason = f"frame {k}: time {t!r} s does not follow the last frame's {t_last!r} s"
        if img is not None and not reason:
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
            if img.dtype != np.uint8:  # 16-bit containers: the log's depth (its first such frame's)
                depth = depth or max(bit_depth(img), 10)
                img = to_8bit(img, depth)
        if reason or img is None:
            reason = reason or f"frame {k}: no image"
            log.warning("%s; the chain restarts at the next image", reason)
            odo.reset()
            if times and math.isfinite(t) and t > t_last:
                rows.append([t, math.nan, math.nan, math.nan, 0.0, 0, 0, reason])
                pair_start.append(t_last)
                times.append(t)
                twists.append(np.full(3, math.nan))
                covs.append(None)
                t_last = t
            continue
        est = odo.update(img, t)
        if est is not None:
            rows.append(
                [t, est.v_x, est.v_y, est.omega, est.quality, int(est.valid), est.n_inliers, est.reason]
            )
            pair_start.append(t_last)
            times.append(t)
            twists.append(est.twist)
            covs.append(est.twist_cov if est.valid else None)
        else:  # the first frame of a chain
            if not times:
                times.append(t)
                twists.append(np.zeros(3))
                covs.append(None)
        t_last = t
        if progress is not None:
            progress(min(1.0, (k + 1) / max(n_frames, 1)))
    if not times:
        raise ValueError(f"{images}: no readable image of the calibration's size")
    header = ["t", "v_x", "v_y", "omega", "quality", "valid", "inliers", "reason"]
    extra = [[] for _ in rows]
    if imu_in is not None:  # the gyro's yaw rate per pair and its sample count
        w_imu, counts, bias = _imu_yaw_rates(*imu_in, rows, pair_start, imu_still, imu or imu_topic)
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
    if mcap:
        with bags.McapWriter(out / "odometry.mcap") as mw:
            for t, pose, tw, cov in zip(times[1:], poses[1:], twists[1:], covs[1:], strict=True):
                mw.odometry(t, pose, tw, cov)
    distance = float(np.sum(np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))))
    n_valid = sum(r[5] for r in rows)
    log.info("odometry: %d frames, %d of %d pairs valid, %.2f m", n_frames, n_valid, len(rows), distance)
    result = FolderOdometryResult(n_frames, len(rows), n_valid, distance, csv_path, tum_path)
    if mcap:
        result = dataclasses.replace(result, mcap_path=out / "odometry.mcap")
    if imu_in is None:
        return result
    # the same path with the gyro's yaw rate where it has samples (times[0] is the first frame)
    tw = np.array(twists, dtype=np.float64)
    gyro_w = np.concatenate([[math.nan], w_imu])
    tw[:, 2] = np.where(np.isfinite(gyro_w), gyro_w, tw[:, 2])
    tum_imu = write_planar_tum(out / "trajectory_imu.tum", times, integrate_twist(np.array(times), tw))
    return dataclasses.replace(result, tum_imu_path=tum_imu, imu_bias=bias)


def _folder_frames(files: list[Path], fps: float, size: tuple[int, int]):
    """(t [s], image or None, why not) of each file of an image folder at ``fps``."""
    bits = _log_bit_depth(files, size)
    for k, path in enumerate(files):
        img, reason = read_frame(path, size)  # size checked before decoding
        if img is not None and img.dtype != np.uint8:
            img = to_8bit(img, max(bits, 10))
        yield k / fps, img, reason


def _log_camera(calibration, source) -> PinholeCamera:
    """The downward camera for a log: the calibration, its missing intrinsics from the log's CameraInfo."""
    from perception import bags
    from perception.calib_io import CalibrationError, read_mapping

    if isinstance(calibration, PinholeCamera):
        return calibration
    intrinsics = {"image_size", "K", "distortion"}
    data = read_mapping(calibration, {"T_body_cam"}, intrinsics | {"ground_plane"})
    info = bags.camera_info(source.path, source.topic)
    if intrinsics <= data.keys():
        cam = PinholeCamera.load(calibration)
        if info is not None and tuple(info["image_size"]) != cam.image_size:
            log.warning("%s: CameraInfo says %s px, the calibration %s px; using the calibration",
                        info["topic"], info["image_size"], cam.image_size)  # fmt: skip
        return cam
    if info is None:
        missing = sorted(intrinsics - data.keys())
        raise CalibrationError(
            f"{calibration}: missing {', '.join(missing)}, and {source.path} has no CameraInfo beside "
            f"{source.topic} to fill them; add them to the calibration"
        )
    log.info("intrinsics from %s (CameraInfo)", info["topic"])
    merged = {k: data.get(k, info[k]) for k in ("image_size", "K", "distortion")}
    try:
        return PinholeCamera(
            image_size=tuple(int(v) for v in merged["image_size"]),
            K=np.asarray(merged["K"], dtype=np.float64),
            distortion=np.asarray(merged["distortion"], dtype=np.float64),
            T_body_cam=np.asarray(data["T_body_cam"], dtype=np.float64),
            ground_plane=data.get("ground_plane"),
        )
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{calibration}: {exc}") from None


def _mount_z_row(imu_rpy, imu_still: float) -> np.ndarray:
    """The body-z row of the IMU's mount (roll-pitch-yaw [rad]), with both inputs checked."""
    rpy = np.asarray(imu_rpy, dtype=np.float64)
    if rpy.shape != (3,) or not np.all(np.isfinite(rpy)):
        raise ValueError(f"imu_rpy: {imu_rpy!r}; give the mount's roll, pitch, yaw [rad]")
    if not (math.isfinite(imu_still) and imu_still >= 0):
        raise ValueError(f"imu_still: {imu_still!r} s; give the standstill's length (>= 0)")
    return Rotation.from_euler("xyz", rpy).as_matrix()[2]


def _open_imu(imu, imu_rpy, imu_still: float) -> tuple:
    """The IMU CSV's log and the body-z row of its mount, checked before the images are processed."""
    z_row = _mount_z_row(imu_rpy, imu_still)
    return read_imu_csv(imu), z_row


def _imu_rows(data: np.ndarray, imu_rpy, imu_still: float, name: str) -> tuple:
    """An IMU topic's (N, 7) samples as the IMU log and the body-z row of its mount."""
    from perception.inertial import ImuLog

    if len(data) < 2:
        raise ValueError(f"{name}: fewer than two IMU samples")
    keep = np.r_[True, np.diff(data[:, 0]) > 0]  # repeated stamps: the first of each
    dropped = int((~keep).sum())
    if dropped:
        log.warning("%s: %d IMU samples with a repeated time left out", name, dropped)
    imu_log = ImuLog(data[keep, 0], data[keep, 1:4], data[keep, 4:7], dropped)
    return imu_log, _mount_z_row(imu_rpy, imu_still)


def _imu_yaw_rates(imu_log, z_row, rows, pair_start, imu_still: float, name) -> tuple:
    """The gyro's body-z rate over each pair, less its bias: (rates, sample counts, bias) [rad/s]."""
    gyro_z = imu_log.gyro @ z_row
    raw = np.full(len(rows), math.nan)
    counts = np.zeros(len(rows), int)
    for k, (r, t0) in enumerate(zip(rows, pair_start, strict=True)):
        # the samples of (t0, t]; a microsecond's slack for times written to 6 decimals
        i0, i1 = np.searchsorted(imu_log.t, [t0 + 1e-6, r[0] + 1e-6], side="right")
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
    mcap_path: Path | None = None


def run_folder_kinematics(
    images: str | Path,
    camera: str | Path | OmniCamera,
    rover: str | Path | RoverKinematicModel,
    fps: float | None,
    out: str | Path,
    steering: str | Path | SteeringCalibration | None = None,
    config: KinematicsConfig | None = None,
    progress: Callable[[float], None] | None = None,
    topic: str | None = None,
    mcap: bool = True,
) -> FolderKinematicsResult:
    """The fisheye kinematics estimator over a folder of fisheye images or a robot log.

    Args:
        images: Folder of colour images (name order is time order), or a ROS 1 bag, ROS 2 bag
            folder or MCAP file (:mod:`perception.bags`; times from the messages' stamps).
        camera: Omnidirectional calibration YAML (:meth:`OmniCamera.save`) or a camera.
        rover: Rover geometry YAML (:meth:`RoverKinematicModel.save`) or a model; its
            ``T_body_cam`` must be the camera's.
        fps: Frame rate of the images [Hz] (image folders only; ignored for logs).
        out: Output folder (created); ``kinematics.csv`` gets one row per image: t, the 10
            degrees of freedom (psi_F, psi_R [rad], d_F, d_R [m], lambda_F, lambda_R [rad],
            theta FL..RR [rad]), the four wheel rates [rad/s], quality and a validity flag per
            degree of freedom. With ``mcap``, ``kinematics.mcap`` holds one
            ``sensor_msgs/JointState`` per image (NaN where a joint was not measured).
        steering: Optional steering calibration (eq. 5 ratio map) YAML or object.
        config: Estimator parameters.
        progress: Called with the finished share (0..1).
        topic: The log's image topic (default: its only image topic).
        mcap: Also write ``kinematics.mcap``.

    Raises:
        FileNotFoundError: Missing folder or log, or no images.
        CalibrationError: Missing or malformed calibration files (the message names the key).
        ValueError: A bad frame rate, a first image whose size differs from the calibration, a
            log without the topic, or camera and rover files with different mounts.

    Unreadable images, images of another size and frames whose time does not follow the last
    one's do not stop the run: the estimator carries its state over them with every flag down,
    and the row says why.
    """
    from perception import bags

    cam = camera if isinstance(camera, OmniCamera) else OmniCamera.load(camera)
    model = rover if isinstance(rover, RoverKinematicModel) else RoverKinematicModel.load(rover)
    cal = steering if steering is None or isinstance(steering, SteeringCalibration) else None
    if steering is not None and cal is None:
        cal = SteeringCalibration.load(steering)
    est = KinematicStateEstimator(cam, model, config, cal)
    if bags.is_log(images):
        source = bags.log_images(images, topic)
        n_frames, frames = source.count, source.frames()
    else:
        files = _open_run(images, fps, cam.image_size)
        n_frames = len(files)
        frames = (
            (k / fps, *read_frame(path, cam.image_size, cv2.IMREAD_COLOR)) for k, path in enumerate(files)
        )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "kinematics.csv"
    n_all = n_rows = 0
    t_last = -math.inf
    mw = bags.McapWriter(out / "kinematics.mcap") if mcap else None
    names = [*DOF_NAMES, *(f"wheel_{w}" for w in ("FL", "FR", "RL", "RR"))]
    with open(csv_path, "w", newline="") as fh, mw if mw is not None else contextlib.nullcontext():
        wr = csv.writer(fh)
        wr.writerow(
            ["t", *DOF_NAMES, "rate_FL", "rate_FR", "rate_RL", "rate_RR", "quality"]
            + [f"valid_{d}" for d in DOF_NAMES]
            + ["note"]
        )
        for k, (t, bgr, note) in enumerate(frames):
            if not note and bgr is not None and (bgr.shape[1], bgr.shape[0]) != cam.image_size:
                note = f"frame {k}: {bgr.shape[1]}x{bgr.shape[0]} px differs from the calibration"
            if not (math.isfinite(t) and t > t_last):
                log.warning("frame %d: time %r s does not follow the last frame's; left out", k, t)
                continue
            t_last = t
            if bgr is None or note:
                rgb = np.zeros((0, 0, 3), np.uint8)  # the estimator flags it and carries on
            elif bgr.ndim == 2 or bgr.dtype != np.uint8:
                note = f"frame {k}: a colour 8-bit image is needed (got {bgr.dtype}, {bgr.ndim} axes)"
                rgb = np.zeros((0, 0, 3), np.uint8)
            else:
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            if note:
                log.warning("%s; the state is carried over it", note)
            s = est.update(rgb, t)
            n_rows += 1
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
            if mw is not None:
                pos = np.where([s.valid[d] for d in DOF_NAMES], dof, math.nan)
                vel = np.r_[np.full(len(DOF_NAMES), math.nan), s.theta_dot]
                mw.joints(t, names, np.r_[pos, np.full(4, math.nan)], vel)
            if progress is not None:
                progress(min(1.0, (k + 1) / max(n_frames, 1)))
    log.info("kinematics: %d frames, all 10 DOF on %d", n_rows, n_all)
    result = FolderKinematicsResult(n_rows, n_all, csv_path)
    return dataclasses.replace(result, mcap_path=out / "kinematics.mcap") if mcap else result

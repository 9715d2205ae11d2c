"""Odometry and kinematics on robot logs: folders of images, ROS 1 and 2 bags, MCAP files.

``run_folder_odometry`` runs :class:`FlowOdometry` in chained mode over a downward camera's
frames and writes ``odometry.csv`` (one row per frame after the first: t, v_x, v_y, omega,
quality, valid, inliers, reason), ``trajectory.tum`` (the integrated planar pose) and
``odometry.mcap``. With an IMU it also reports the gyro's yaw rate per pair (``omega_imu``)
and the path with that yaw (``trajectory_imu.tum``): both yaw sources of the odometry paper's
Table I. ``run_folder_kinematics`` runs the fisheye kinematics estimator and writes
``kinematics.csv`` and ``kinematics.mcap``.

Both treat a log as a stream that can be damaged or glitched (docs/logs.md): frame times come
from the header stamps checked against the receive times (:mod:`perception.logs.log_time`); a bad
frame becomes an invalid row with the reason and the frames after it are kept; outputs
go through :class:`perception.logs.outputs.OutputFolder` (staged files, one commit, nothing of the
user's removed).
"""

from __future__ import annotations

import collections
import contextlib
import csv
import dataclasses
import itertools
import logging
import math
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from perception.fusion.inertial import ImuLog, check_gyro_against_odometry, check_imu_units, read_imu_csv
from perception.kinematics.fisheye import DOF_NAMES, KinematicsConfig, KinematicStateEstimator
from perception.kinematics.markers import SteeringCalibration
from perception.kinematics.sinkage import SinkageEstimator, SinkageTrack
from perception.logs.bags import LogFrame
from perception.logs.log_time import Placed, in_stamp_order, place
from perception.logs.outputs import OutputFolder
from perception.models.cameras import OmniCamera, PinholeCamera
from perception.models.drive_geometry import WHEELS
from perception.models.rover import RoverKinematicModel
from perception.models.validation import image_file_size
from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig
from perception.odometry.flow import FlowOdometry, FlowOdometryConfig, integrate_twist
from perception.odometry.trajectory import format_planar_tum

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")
ODOMETRY_PRODUCTS = ("odometry.csv", "trajectory.tum", "trajectory_imu.tum", "odometry.mcap")
KINEMATICS_PRODUCTS = ("kinematics.csv", "kinematics.mcap")
#: Longest time the integrated path holds the last valid twist over invalid pairs [s]: a few
#: lost pairs are bridged, a camera drop-out is not filled with made-up motion.
MAX_HOLD = 0.5


class NothingValidError(ValueError):
    """A run read its input but produced no valid estimate; its files say why, row by row."""


@dataclass(frozen=True)
class FolderOdometryResult:
    """Summary of :func:`run_folder_odometry`.

    Attributes:
        frames: Frames read.
        pairs: Rows written (one per frame after the first that could be placed in time).
        valid: Pairs with a valid estimate.
        distance: Length of the integrated path [m].
        csv_path: The per-pair CSV.
        tum_path: The integrated trajectory.
        tum_imu_path: The trajectory with the gyro's yaw (None without an IMU log).
        imu_bias: The gyro's body-z bias taken out [rad/s] (None without an IMU log).
        mcap_path: ``odometry.mcap`` (None when not written).
        reasons: {reason: count} of the invalid rows (frame numbers left out).
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
    reasons: dict = dataclasses.field(default_factory=dict)


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
    (:data:`perception.models.validation.MAX_IMAGE_PIXELS`), is not decoded.
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
    """Checks shared by the folder runs: frame rate, images, and that some image has the calibration's size.

    A folder of which no image has the calibration's size (the wrong calibration) is refused;
    an odd image among good ones, the first included, is an invalid row of the run.
    """
    if fps is None or not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps: {fps!r}; give the camera's frame rate in Hz (> 0) for a folder of images")
    files = list_images(images)
    first: tuple[Path, tuple[int, int]] | None = None  # the first readable image and its size
    for path in files:  # from the headers, until one fits: nothing decoded yet
        size = image_file_size(path)
        if size == tuple(image_size):
            return files
        if size is not None and first is None:
            first = (path, size)
    if first is None:
        raise ValueError(f"{images}: none of its {len(files)} images is readable")
    w, h = image_size
    (fw, fh) = first[1]
    raise ValueError(
        f"{first[0]}: {fw}x{fh} px, and no image of {images} has the calibration's {w}x{h} px; use the "
        "calibration of this camera and resolution"
    )


def _cell(text: str) -> str:
    """A reason as one CSV cell that naive comma splitting reads too (no commas, one line)."""
    return " ".join(str(text).replace(",", ";").split())


def _most(reasons: dict[str, int]) -> str:
    """The most common kind of reason of a result's ``reasons``, and how often."""
    if not reasons:
        return "no frame pair"
    text, n = max(reasons.items(), key=lambda kv: kv[1])
    return f"{text} ({n} alike)"


class _Reasons:
    """Why rows were invalid: alike reasons (the same but for their numbers) counted together."""

    def __init__(self) -> None:
        self.counts: collections.Counter = collections.Counter()
        self.example: dict[str, str] = {}

    def add(self, reason: str) -> None:
        text = re.sub(r"^frame \d+: ", "", reason)
        key = re.sub(r"\d+(\.\d+)?", "#", text)
        self.counts[key] += 1
        self.example.setdefault(key, text)

    def as_dict(self) -> dict[str, int]:
        """{the first of each kind of reason: how many rows had a reason of that kind}."""
        return {self.example[k]: n for k, n in self.counts.most_common()}

    def summary(self) -> str:
        """The most common kind of reason, and how often."""
        if not self.counts:
            return "no frame pair"
        key, n = self.counts.most_common(1)[0]
        return f"{self.example[key]} ({n} alike)"


@dataclass
class _Source:
    """A run's frames placed on the time line (by :func:`place` for a log), and what is known."""

    placed: Iterator[Placed]
    count: int | None
    span: tuple[float, float] | None  # the images' time span, where known [s]
    depth: int | None = None  # bits of a log's 16-bit images (the median of its first ones)
    times: tuple[float, ...] = ()  # a log's usable frames' times, in order [s]


def _log_source(src, images) -> _Source:
    """The frames of a log's image topic in stamp order, placed on the time line (:func:`place`).

    The stamps of the whole topic are read first (no image decoded), so that every frame's time
    is judged with the frames before and after it; then the frames are read and given theirs.
    """
    order = in_stamp_order(src.stamps(), same=lambda a, b: a.digest == b.digest)
    if not order:
        raise ValueError(f"{images}: no readable message on {src.topic}")
    placed = place(order, name=f"{images}: {src.topic}")
    times = [p.t for p in placed if not p.why and math.isfinite(p.t)]
    span = (min(times), max(times)) if times else None
    frames = src.frames()
    first = list(itertools.islice(frames, 9))  # a look at the log's start: its bit depth
    deep = [bit_depth(f.image) for f in first if f.image is not None and f.image.dtype == np.uint16]
    depth = max(int(np.median(deep)), 10) if deep else None
    return _Source(
        _placed_frames(itertools.chain(first, frames), placed), len(placed), span, depth, tuple(sorted(times))
    )


def _placed_frames(frames: Iterator[LogFrame], placed: list[Placed]) -> Iterator[Placed]:
    """``frames`` (in the log's order) given their placements, in the placements' order."""
    at = {p.item.index: p for p in placed}
    waiting: dict[int, LogFrame] = {}
    nxt = 0
    for frame in frames:
        if frame.index not in at:
            continue  # a second recording of a message
        waiting[frame.index] = frame
        while nxt < len(placed) and (placed[nxt].item.index in waiting or len(waiting) > 64):
            p = placed[nxt]
            nxt += 1
            if p.item.index in waiting:  # (one that never came is passed over)
                yield Placed(waiting.pop(p.item.index), p.t, p.why, p.anchor)
    for p in placed[nxt:]:
        if p.item.index in waiting:
            yield Placed(waiting.pop(p.item.index), p.t, p.why, p.anchor)


def _folder_source(images, fps, size: tuple[int, int], colour: bool = False) -> _Source:
    """The frames of an image folder at ``fps`` (``colour``: 8-bit BGR, for the fisheye)."""
    files = _open_run(images, fps, size)
    span = (0.0, (len(files) - 1) / fps)
    placed = (Placed(f, f.stamp) for f in _folder_frames(files, fps, size, colour))
    return _Source(placed, len(files), span)


def _folder_frames(files: list[Path], fps: float, size: tuple[int, int], colour: bool) -> Iterator[LogFrame]:
    """The frames of an image folder at ``fps``: frame k at k / fps [s]."""
    if colour:
        for k, path in enumerate(files):
            yield LogFrame(k, k / fps, math.nan, *read_frame(path, size, cv2.IMREAD_COLOR))
        return
    bits = _log_bit_depth(files, size)
    for k, path in enumerate(files):
        img, reason = read_frame(path, size)  # size checked before decoding
        if img is not None and img.dtype != np.uint8:
            img = to_8bit(img, max(bits, 10))
        yield LogFrame(k, k / fps, math.nan, img, reason)


def _grey8(img: np.ndarray, depth: int | None) -> tuple[np.ndarray | None, str]:
    """A frame as 8-bit grey (16-bit scaled by the log's ``depth``), or None and why not."""
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    if img.dtype == np.uint16:
        return to_8bit(img, depth or max(bit_depth(img), 10)), ""
    if img.dtype != np.uint8:
        return None, f"an image of {img.dtype}: use 8- or 16-bit images"
    return img, ""


def load_odometry_camera(path: str | Path) -> PinholeCamera | OmniCamera:
    """The camera of an odometry calibration YAML: omnidirectional (``model: scaramuzza``) or pinhole."""
    return OmniCamera.load(path) if is_omni(path) else PinholeCamera.load(path)


def is_omni(calibration) -> bool:
    """Whether ``calibration`` (a camera or a YAML path) is omnidirectional (``model: scaramuzza``)."""
    if isinstance(calibration, OmniCamera | PinholeCamera):
        return isinstance(calibration, OmniCamera)
    from perception.models.calib_io import CalibrationError, read_yaml

    d = read_yaml(Path(calibration), CalibrationError, "calibration file")
    return isinstance(d, dict) and d.get("model") == "scaramuzza"


def _path(calibration) -> str | Path:
    """``calibration`` as a path (TypeError if it is a camera of the other kind)."""
    if isinstance(calibration, str | Path):
        return calibration
    raise TypeError(
        f"calibration: a {type(calibration).__name__} where a YAML path or the other camera was due"
    )


def _need_ground_plane(camera, name: str, config=None) -> None:
    """The odometry's scale: a camera without a ground plane it can see is refused before any frame."""
    from perception.models.calib_io import CalibrationError

    if camera.ground_plane is None:
        from perception.models.cameras import GROUND_PLANE_MISSING

        raise CalibrationError(f"{name}: {GROUND_PLANE_MISSING}")
    if isinstance(camera, OmniCamera):
        reach = (config if isinstance(config, FisheyeOdometryConfig) else FisheyeOdometryConfig()).max_range
        problem = camera.model_error() or camera.ground_view_error(max_height=reach)
    else:
        problem = camera.ground_view_error()
    if problem:
        raise CalibrationError(f"{name}: {problem}")


def run_folder_odometry(
    images: str | Path,
    calibration: str | Path | PinholeCamera | OmniCamera,
    fps: float | None,
    out: str | Path,
    config: FlowOdometryConfig | FisheyeOdometryConfig | None = None,
    progress: Callable[[float], None] | None = None,
    imu: str | Path | None = None,
    imu_rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    imu_still: float = 0.0,
    topic: str | None = None,
    imu_topic: str | None = None,
    mcap: bool = True,
    overwrite: bool = False,
) -> FolderOdometryResult:
    """Chained visual odometry over a folder of downward-camera or fisheye images or a robot log.

    Args:
        images: Folder of images (name order is time order), or a ROS 1 bag, ROS 2 bag folder
            or MCAP file (:mod:`perception.logs.bags`; times from the messages' stamps).
        calibration: Calibration YAML (docs/odometry.md; with ``ground_plane``) or a camera. A
            pinhole camera runs :class:`FlowOdometry`; for a log with a ``CameraInfo`` beside the
            images, the YAML's intrinsics (``image_size``, ``K``, ``distortion``) may be left out:
            the log's fill them. An omnidirectional calibration (``model: scaramuzza``, its
            ``ground_plane`` and optional ``mask`` of the rover's parts) runs
            :class:`perception.odometry.fisheye.FisheyeOdometry` on fisheye images.
        fps: Frame rate of the images [Hz] (image folders only; ignored for logs).
        out: Output folder (:class:`perception.logs.outputs.OutputFolder`): ``odometry.csv``,
            ``trajectory.tum`` and, with ``mcap``, ``odometry.mcap`` (one ``nav_msgs/Odometry``
            per estimate). Written only when the run succeeds; a user's files there stay.
        config: Estimator parameters (:class:`FlowOdometryConfig` for a pinhole camera,
            :class:`~perception.odometry.fisheye.FisheyeOdometryConfig` for a fisheye).
        progress: Called with the finished share (0..1).
        imu: An IMU CSV (:func:`perception.fusion.inertial.read_imu_csv`; times on the images' clock,
            t = 0 at the first image of a folder).
        imu_rpy: The IMU's mount in the body frame, roll-pitch-yaw [rad].
        imu_still: Seconds of standstill at the start of the IMU log: the gyro's bias is their
            mean. With 0 (default) it is the median difference between the gyro's and the
            odometry's yaw rates over the valid pairs.
        topic: The log's image topic (default: its only image topic).
        imu_topic: Read the IMU from this topic of the log instead of a CSV.
        mcap: Also write ``odometry.mcap``.
        overwrite: Replace the results of an earlier run in ``out``.

    Raises:
        FileNotFoundError: Missing folder or log, or no images.
        CalibrationError: Missing or malformed calibration (the message names the key).
        ValueError: A bad frame rate, a first image whose size differs from the calibration, a
            log without the topic, IMU data in other units or on another clock, an ``out``
            that holds the input or earlier results (without ``overwrite``).
        NothingValidError: No pair gave a valid estimate (the files are written; their rows
            say why).

    Unreadable images, images of another size and frames whose stamp is flagged
    (:func:`perception.logs.log_time.place`) do not stop the run: each is an invalid row with
    the reason, and the next good frame pairs with the last good one across it. Where the
    header clock jumps, the pair across the jump is the invalid row and the chain starts again.
    """
    from perception.logs import bags

    bags.new_run()
    is_log = bags.is_log(images)
    name = "camera" if isinstance(calibration, PinholeCamera | OmniCamera) else str(calibration)
    camera: PinholeCamera | OmniCamera
    if is_omni(calibration):  # the fisheye's odometry
        camera = calibration if isinstance(calibration, OmniCamera) else OmniCamera.load(_path(calibration))
        _need_ground_plane(camera, name, config)
        source = _log_source(bags.log_images(images, topic), images) if is_log else None
    elif is_log:
        src = bags.log_images(images, topic)
        camera = _log_camera(calibration, src)
        source = _log_source(src, images)
    else:
        camera = (
            calibration if isinstance(calibration, PinholeCamera) else PinholeCamera.load(_path(calibration))
        )
        source = None
    _need_ground_plane(camera, name, config)
    if source is None:
        source = _folder_source(images, fps, camera.image_size)
    _check_config(camera, config)
    mask = None
    if isinstance(camera, OmniCamera) and camera.mask_file is not None:
        from perception.odometry.fisheye import read_mask

        try:
            mask = read_mask(camera.mask_file)
            FisheyeOdometry(camera, mask=mask)  # its size, checked before any frame
        except (ValueError, OSError) as exc:
            from perception.models.calib_io import CalibrationError

            raise CalibrationError(f"{name}: {exc}") from exc
    imu_in = _read_imu(images, is_log, imu, imu_topic, imu_rpy, imu_still, source.span)
    with OutputFolder(out, ODOMETRY_PRODUCTS, overwrite, inputs=(images,)) as folder:
        res = _odometry(
            source,
            camera,
            config,
            progress,
            imu_in,
            imu_still,
            imu or imu_topic,
            mcap,
            folder,
            str(images),
            mask,
        )
    if not res.valid:
        raise NothingValidError(
            f"{images}: no valid estimate in {res.pairs} pairs of {res.frames} frames; most often: "
            f"{_most(res.reasons)}. {res.csv_path} says why, row by row"
        )
    return res


def _read_imu(images, is_log, imu, imu_topic, imu_rpy, imu_still, span) -> tuple | None:
    """The IMU's log and mount row, checked (units, clock) before any image is processed."""
    if imu is not None and imu_topic is not None:
        raise ValueError("imu and imu_topic: give one IMU source")
    if imu_topic is not None:
        from perception.logs import bags

        if not is_log:
            raise ValueError("imu_topic: an IMU topic needs a log (bag or MCAP) as the image source")
        data, _ = bags.log_imu(images, imu_topic)
        imu_in = _imu_rows(data, imu_rpy, imu_still, f"{images}:{imu_topic}")
        name = f"{images}:{imu_topic}"
    elif imu is not None:
        imu_in = _open_imu(imu, imu_rpy, imu_still)
        name = str(imu)
    else:
        return None
    imu_log = imu_in[0]
    check_imu_units(imu_log, name, imu_still)
    if span is not None:
        a, b = float(imu_log.t[0]), float(imu_log.t[-1])
        if b < span[0] or a > span[1]:
            raise ValueError(
                f"{name}: the IMU's samples span {a:.3f} to {b:.3f} s, the images {span[0]:.3f} to "
                f"{span[1]:.3f} s: no overlap; put the IMU's times on the images' clock"
                + (" (t = 0 at the first image of a folder)" if not is_log else "")
            )
    return imu_in


def _check_config(camera, config) -> None:
    """A configuration of the camera's odometry, or TypeError naming the one to give."""
    if config is None:
        return
    want = FisheyeOdometryConfig if isinstance(camera, OmniCamera) else FlowOdometryConfig
    if not isinstance(config, want):
        raise TypeError(
            f"config: {type(config).__name__} for a {type(camera).__name__}; give a {want.__name__}"
        )


def _odometry(source, camera, config, progress, imu_in, imu_still, imu_name, mcap, folder, name, mask=None):
    """The odometry loop and its files (staged in ``folder``, committed at the end)."""
    odo: FlowOdometry | FisheyeOdometry
    if isinstance(camera, OmniCamera):
        odo = FisheyeOdometry(camera, config, ground_plane=camera.ground_plane, mask=mask)
    else:
        odo = FlowOdometry(camera, config)
    rows, pair_start = [], []
    times, twists, covs = [], [], []
    reasons = _Reasons()
    t_row = t_fed = -math.inf  # the last row's time; the last frame given to the odometry
    chain = False  # the odometry holds a frame to pair the next one with
    n = 0

    def invalid(t: float, reason: str) -> None:
        nonlocal t_row
        rows.append([t, math.nan, math.nan, math.nan, 0.0, 0, 0, reason])
        pair_start.append(t_row)
        times.append(t)
        twists.append(np.full(3, math.nan))
        covs.append(None)
        reasons.add(reason)
        t_row = t

    for n, p in enumerate(source.placed, start=1):
        frame, t = p.item, p.t
        k = frame.index
        reason = f"frame {k}: {p.why}" if p.why else (f"frame {k}: {frame.why}" if frame.why else "")
        img = frame.image
        if not reason and img is None:
            reason = f"frame {k}: no image"
        if not reason and (img.shape[1], img.shape[0]) != camera.image_size:
            reason = f"frame {k}: {img.shape[1]}x{img.shape[0]} px differs from the calibration"
        if not reason:
            img, why = _grey8(img, source.depth)
            reason = f"frame {k}: {why}" if why else ""
        if p.anchor:  # a new clock: the pair across the jump is unknown; the chain starts again here
            odo.reset()
            chain = False
        if reason:
            log.warning(
                "%s; %s", reason, "the next pair starts here" if p.anchor else "the frame is left out"
            )
            if times and math.isfinite(t) and t > t_row:
                invalid(t, reason)
            elif not times:
                reasons.add(reason)
            if p.anchor and img is not None and frame.why == "":
                img2, _ = _grey8(frame.image, source.depth)
                if img2 is not None and (img2.shape[1], img2.shape[0]) == camera.image_size:
                    odo.update(img2, t)  # the first frame of the new chain
                    chain, t_fed = True, t
            continue
        est = odo.update(img, t)
        if est is not None:
            rows.append(
                [t, est.v_x, est.v_y, est.omega, est.quality, int(est.valid), est.n_inliers, est.reason]
            )
            pair_start.append(t_fed)
            times.append(t)
            twists.append(est.twist)
            covs.append(est.twist_cov if est.valid else None)
            if not est.valid:
                reasons.add(est.reason)
            t_row = t
        elif not times:  # the very first frame: the path's origin
            times.append(t)
            twists.append(np.zeros(3))
            covs.append(None)
            t_row = t
        elif not chain and t > t_row:  # the first frame after a clock jump whose frame was unusable
            invalid(t, f"frame {k}: starts a new chain after the clock jump")
        chain, t_fed = True, t
        if progress is not None and source.count:
            progress(min(1.0, n / source.count))
    if not times:
        raise ValueError(
            f"{name}: no usable frame in {n} frames; most often: {reasons.summary()}"
            if n
            else f"{name}: no frames to read"
        )
    header = ["t", "v_x", "v_y", "omega", "quality", "valid", "inliers", "reason"]
    extra: list[list] = [[] for _ in rows]
    imu_error = None
    w_imu = bias = None
    if imu_in is not None:  # the gyro's yaw rate per pair and its sample count
        try:
            w_imu, counts, bias = _imu_yaw_rates(*imu_in, rows, pair_start, imu_still, imu_name)
            header += ["omega_imu", "imu_samples"]
            extra = [[f"{wi:.6f}", c] for wi, c in zip(w_imu, counts, strict=True)]
        except ValueError as exc:  # the odometry's own files are still written
            imu_error = exc
    n_valid = sum(r[5] for r in rows)
    with folder.open("odometry.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for r, x in zip(rows, extra, strict=True):
            w.writerow([f"{r[0]:.6f}", *(f"{v:.6f}" for v in r[1:5]), r[5], r[6], _cell(r[7]), *x])
    t_arr = np.array(times)
    poses = integrate_twist(t_arr, np.array(twists), max_hold=MAX_HOLD)
    folder.write_text("trajectory.tum", format_planar_tum(t_arr, poses))
    if mcap:
        from perception.logs import bags

        with folder.writing("odometry.mcap") as tmp, bags.McapWriter(tmp) as mw:
            for t, pose, tw, cov in zip(times[1:], poses[1:], twists[1:], covs[1:], strict=True):
                mw.odometry(t, pose, tw, cov)
    tum_imu = None
    if w_imu is not None:  # the same path with the gyro's yaw rate where it has samples
        tw = np.array(twists, dtype=np.float64)
        gyro_w = np.concatenate([[math.nan], w_imu])
        tw[:, 2] = np.where(np.isfinite(gyro_w), gyro_w, tw[:, 2])
        tum_imu = folder.write_text(
            "trajectory_imu.tum", format_planar_tum(t_arr, integrate_twist(t_arr, tw, max_hold=MAX_HOLD))
        )
    folder.commit()
    out = folder.path
    distance = float(np.sum(np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))))
    log.info("odometry: %d frames, %d of %d pairs valid, %.2f m", n, n_valid, len(rows), distance)
    if imu_error is not None:
        raise ValueError(
            f"{imu_error}. The odometry without the IMU is in {out} (odometry.csv, trajectory.tum"
            f"{', odometry.mcap' if mcap else ''})"
        )
    return FolderOdometryResult(
        n, len(rows), n_valid, distance, out / "odometry.csv", out / "trajectory.tum",
        tum_imu_path=tum_imu, imu_bias=bias, mcap_path=out / "odometry.mcap" if mcap else None,
        reasons=reasons.as_dict(),
    )  # fmt: skip


def _log_camera(calibration, source) -> PinholeCamera:
    """The downward camera for a log: the calibration, its missing intrinsics from the log's CameraInfo.

    A CameraInfo the camera cannot use is blamed on the log and its topic, not the calibration.
    """
    from perception.logs import bags
    from perception.models.calib_io import CalibrationError, read_mapping

    if isinstance(calibration, PinholeCamera):
        return calibration
    intrinsics = {"image_size", "K", "distortion"}
    data = read_mapping(calibration, {"T_body_cam"}, intrinsics | {"ground_plane"})
    if intrinsics <= data.keys():
        cam = PinholeCamera.load(calibration)
        try:
            info = bags.camera_info(source.path, source.topic)
        except ValueError as exc:  # not needed: the calibration has every intrinsic
            log.warning("%s; the calibration's intrinsics are used", exc)
            info = None
        if info is not None and tuple(info["image_size"]) != cam.image_size:
            log.warning("%s: CameraInfo says %s px, the calibration %s px; using the calibration",
                        info["topic"], info["image_size"], cam.image_size)  # fmt: skip
        return cam
    info = bags.camera_info(source.path, source.topic)
    if info is None:
        missing = sorted(intrinsics - data.keys())
        raise CalibrationError(
            f"{calibration}: missing {', '.join(missing)}, and {source.path} has no readable CameraInfo "
            f"beside {source.topic} to fill them; add them to the calibration"
        )
    try:  # the log's intrinsics on their own: their faults are the log's
        PinholeCamera(image_size=info["image_size"], K=info["K"], distortion=info["distortion"])
    except (CalibrationError, TypeError, ValueError) as exc:
        raise ValueError(f"{info['where']}: the CameraInfo's intrinsics are not usable ({exc})") from None
    log.info("intrinsics from %s (CameraInfo)", info["topic"])
    merged = {k: data.get(k, info[k]) for k in ("image_size", "K", "distortion")}
    try:
        return PinholeCamera(
            image_size=merged["image_size"],
            K=merged["K"],
            distortion=merged["distortion"],
            T_body_cam=data["T_body_cam"],
            ground_plane=data.get("ground_plane"),
        )
    except (CalibrationError, TypeError, ValueError) as exc:
        raise CalibrationError(f"{calibration} (with {info['topic']}'s intrinsics): {exc}") from None


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
    from perception.fusion.inertial import GYRO_BIAS_MAX

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
    odo_w = np.array([r[3] if r[5] else math.nan for r in rows])
    check_gyro_against_odometry(raw, odo_w, str(name))
    if imu_still > 0:
        bias = float(gyro_z[imu_log.t <= imu_log.t[0] + imu_still].mean())
    else:
        diff = raw - odo_w
        diff = diff[np.isfinite(diff)]
        if not len(diff):
            raise ValueError(f"{name}: no IMU samples during a valid frame pair; give imu_still for the bias")
        bias = float(np.median(diff))
        if abs(bias) > GYRO_BIAS_MAX:
            raise ValueError(
                f"{name}: the gyro's yaw rate differs from the odometry's by {bias:.4g} rad/s, beyond any "
                f"data sheet's bias ({GYRO_BIAS_MAX:.2f} rad/s = 20 deg/s); check its units (rad/s), its "
                "clock and its mount (imu_rpy)"
            )
    log.info("imu: %d samples (%d left out), body-z bias %.5f rad/s", len(imu_log.t), imu_log.dropped, bias)
    return raw - bias, counts, bias


@dataclass(frozen=True)
class FolderKinematicsResult:
    """Summary of :func:`run_folder_kinematics`.

    Attributes:
        frames: Rows written (frames that could be placed in time).
        all_valid: Frames on which all 10 degrees of freedom were measured.
        csv_path: The per-frame CSV.
        mcap_path: ``kinematics.mcap`` (None when not written).
        any_valid: Frames on which at least one degree of freedom was measured.
        reasons: {note: count} of the frames with a note (frame numbers left out).
    """

    frames: int
    all_valid: int
    csv_path: Path
    mcap_path: Path | None = None
    any_valid: int = 0
    reasons: dict = dataclasses.field(default_factory=dict)


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
    overwrite: bool = False,
) -> FolderKinematicsResult:
    """The fisheye kinematics estimator over a folder of fisheye images or a robot log.

    Args:
        images: Folder of colour images (name order is time order), or a ROS 1 bag, ROS 2 bag
            folder or MCAP file (:mod:`perception.logs.bags`; times from the messages' stamps).
        camera: Omnidirectional calibration YAML (:meth:`OmniCamera.save`) or a camera.
        rover: Rover geometry YAML (:meth:`RoverKinematicModel.save`) or a model; its
            ``T_body_cam`` must be the camera's.
        fps: Frame rate of the images [Hz] (image folders only; ignored for logs).
        out: Output folder (:class:`perception.logs.outputs.OutputFolder`); ``kinematics.csv`` gets
            one row per image: t, the 10 degrees of freedom (psi_F, psi_R [rad], d_F, d_R [m],
            lambda_F, lambda_R [rad], theta FL..RR [rad]), the four wheel rates [rad/s],
            quality, a validity flag per degree of freedom, each wheel's sinkage [m]
            (:class:`perception.kinematics.sinkage.SinkageTrack` over the frames measured, as the
            built-in estimator gives it; empty where too few frames of the last 0.8 s measured
            it) and their quality, and a note. With ``mcap``,
            ``kinematics.mcap`` holds one ``sensor_msgs/JointState`` per image (NaN where a
            joint was not measured).
        steering: Optional steering calibration (eq. 5 ratio map) YAML or object.
        config: Estimator parameters.
        progress: Called with the finished share (0..1).
        topic: The log's image topic (default: its only image topic).
        mcap: Also write ``kinematics.mcap``.
        overwrite: Replace the results of an earlier run in ``out``.

    Raises:
        FileNotFoundError: Missing folder or log, or no images.
        CalibrationError: Missing or malformed calibration files (the message names the key).
        ValueError: A bad frame rate, a first image whose size differs from the calibration, a
            log without the topic, camera and rover files with different mounts, or an ``out``
            that holds the input or earlier results (without ``overwrite``).
        NothingValidError: No frame gave any degree of freedom (the files are written; their
            notes say why).

    Unreadable images, images of another size and frames whose stamp is flagged do not stop
    the run: the estimator carries its state over them with every flag down, and the row says
    why.
    """
    from perception.logs import bags

    cam = camera if isinstance(camera, OmniCamera) else OmniCamera.load(camera)
    model = rover if isinstance(rover, RoverKinematicModel) else RoverKinematicModel.load(rover)
    if steering is None or isinstance(steering, SteeringCalibration):
        cal = steering
    else:
        cal = SteeringCalibration.load(steering)
    est = KinematicStateEstimator(cam, model, config, cal)
    bags.new_run()
    if bags.is_log(images):
        source = _log_source(bags.log_images(images, topic), images)
    else:
        source = _folder_source(images, fps, cam.image_size, colour=True)
    with OutputFolder(out, KINEMATICS_PRODUCTS, overwrite, inputs=(images,)) as folder:
        sink = SinkageEstimator(cam, model)
        res = _kinematics(source, cam, est, sink, progress, mcap, folder, str(images))
    if not res.any_valid:
        raise NothingValidError(
            f"{images}: no degree of freedom measured on any of {res.frames} frames; most often: "
            f"{_most(res.reasons)}. {res.csv_path} says why, row by row"
        )
    return res


def _kinematics(source, cam, est, sink, progress, mcap, folder, name) -> FolderKinematicsResult:
    from perception.logs import bags

    n_all = n_any = n_rows = 0
    reasons = _Reasons()
    names = [*DOF_NAMES, *(f"wheel_{w}" for w in WHEELS)]
    with contextlib.ExitStack() as stack:
        fh = stack.enter_context(folder.open("kinematics.csv", "w", newline=""))
        mw = None
        if mcap:
            tmp = stack.enter_context(folder.writing("kinematics.mcap"))
            mw = stack.enter_context(bags.McapWriter(tmp))
        wr = csv.writer(fh)
        wr.writerow(
            ["t", *DOF_NAMES, "rate_FL", "rate_FR", "rate_RL", "rate_RR", "quality"]
            + [f"valid_{d}" for d in DOF_NAMES]
            + [f"sinkage_{w}" for w in WHEELS]
            + ["sinkage_quality", "note"]
        )
        t_row = -math.inf
        track = SinkageTrack()
        for n, p in enumerate(source.placed, start=1):
            frame, t = p.item, p.t
            k = frame.index
            note = f"frame {k}: {p.why}" if p.why else (f"frame {k}: {frame.why}" if frame.why else "")
            bgr = frame.image
            if not note and bgr is not None and (bgr.shape[1], bgr.shape[0]) != cam.image_size:
                note = f"frame {k}: {bgr.shape[1]}x{bgr.shape[0]} px differs from the calibration"
            if not (math.isfinite(t) and t > t_row):
                log.warning("%s; no row: it cannot be placed in time", note)
                reasons.add(note)
                continue
            t_row = t
            rgb = np.zeros((0, 0, 3), np.uint8)  # the estimator flags it and carries on
            if not note and bgr is None:
                note = f"frame {k}: no image"
            elif not note and (bgr.ndim == 2 or bgr.dtype != np.uint8):
                kind = "a grey" if bgr.ndim == 2 else f"a {bgr.dtype}"
                note = f"frame {k}: {kind} image; the markers are found by colour: give 8-bit colour images"
            elif not note:
                rgb = cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            if note:
                log.warning("%s; the state is carried over it", note)
                reasons.add(note)
            s = est.update(rgb, t)
            n_rows += 1
            n_all += int(all(s.valid.values()))
            n_any += int(any(s.valid.values()))
            dof = np.r_[s.psi, s.depth, s.lam, s.theta]
            measured = None
            if rgb.size and s.axles_valid:  # where the wheels stand
                measured = sink.measure(rgb, s.psi, s.depth + est.depth_zero, s.delta)
            z, q_z = track.update(t, measured).reported()
            wr.writerow(
                [
                    f"{t:.6f}",
                    *(f"{v:.6f}" for v in dof),
                    *(f"{v:.5f}" for v in s.theta_dot),
                    f"{s.quality:.2f}",
                ]
                + [int(s.valid[d]) for d in DOF_NAMES]
                + [f"{v:.4f}" if math.isfinite(v) else "" for v in z]
                + [f"{q_z:.2f}", _cell(note)]
            )
            if mw is not None:
                pos = np.where([s.valid[d] for d in DOF_NAMES], dof, math.nan)
                vel = np.r_[np.full(len(DOF_NAMES), math.nan), s.theta_dot]
                mw.joints(t, names, np.r_[pos, np.full(4, math.nan)], vel)
            if progress is not None and source.count:
                progress(min(1.0, n / source.count))
    if not n_rows:
        raise ValueError(f"{name}: no usable frame; most often: {reasons.summary()}")
    folder.commit()
    log.info("kinematics: %d frames, all 10 DOF on %d", n_rows, n_all)
    out = folder.path
    return FolderKinematicsResult(
        n_rows,
        n_all,
        out / "kinematics.csv",
        out / "kinematics.mcap" if mcap else None,
        n_any,
        reasons.as_dict(),
    )

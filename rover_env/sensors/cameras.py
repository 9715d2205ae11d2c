"""Simulated cameras on the rover: the downward mast camera and the fisheye under the body.

A camera turns the simulator state into timestamped images and nothing else; the estimators get
the images and the camera model (:class:`perception.PinholeCamera`), never the simulator.
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from perception.models.cameras import PinholeCamera
from perception.models.rover_parts import kinematics_roi
from rover_env.config.cameras import DownwardCameraConfig, FisheyeCameraConfig
from rover_env.config.io import ConfigError
from rover_env.rendering import focus_on_rover, renderer_for
from rover_env.rendering.base import FisheyeView, Lighting, MotionSpec, RenderedView
from rover_env.rendering.cubemap import CubemapRemap
from rover_env.sensors.image_sensor import ImageSensor
from rover_env.sensors.motion_blur import MotionField, blur, remap_image
from rover_env.sim.geometry import RoverGeometry
from rover_env.sim.simulation import RoverSim

# image right = body forward, image down = body right, optical axis = body down
R_BODY_FISHEYE = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
# image up = body forward, image right = body right, optical axis = body down
R_BODY_DOWNCAM = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def blackout_windows(value, name: str = "blackout") -> list[tuple[float, float]]:
    """``value`` as a list of (t0, t1) time windows [s], t0 < t1, both finite; ValueError naming ``name``."""
    how = "give a list of (t0, t1) windows of time [s] with t0 < t1, e.g. [(2.0, 3.5)]"
    if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__iter__"):
        raise ValueError(f"{name}={value!r}: {how}")
    out = []
    for w in value:
        try:
            t0, t1 = (float(v) for v in w)
        except (TypeError, ValueError):
            raise ValueError(f"{name}: window {w!r}: {how}") from None
        if not (math.isfinite(t0) and math.isfinite(t1) and t1 > t0):
            raise ValueError(f"{name}: window {w!r}: {how}")
        out.append((t0, t1))
    return out


def _lens_footprint(xs: np.ndarray, ys: np.ndarray, size: tuple[int, int], reach: int) -> np.ndarray:
    """The pixels (H, W) bool of a (W, H) = ``size`` view that a bilinear remap at ``xs``, ``ys`` reads.

    ``xs``, ``ys``: the remap's positions [px]; the pixels they read are grown by ``reach`` [px]:
    a path of at most ``reach`` pixels along each axis from any remap position stays in it
    (:func:`rover_env.sensors.motion_blur.blur` with ``maps``).
    """
    w, h = size
    read = np.zeros((h, w), np.uint8)
    x0 = np.clip(np.floor(xs).astype(np.int64), 0, w - 1)
    y0 = np.clip(np.floor(ys).astype(np.int64), 0, h - 1)
    for dy in (0, 1):
        for dx in (0, 1):
            read[np.minimum(y0 + dy, h - 1), np.minimum(x0 + dx, w - 1)] = 1
    if reach > 0:
        return cv2.dilate(read, np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)
    return read.astype(bool)


@dataclass(frozen=True)
class Frame:
    """A timestamped image.

    Attributes:
        image: (H, W, 3) uint8 RGB.
        t: Simulation time of the exposure [s].
        shadow: (H, W) bool, where the sun was blocked (simulator knowledge, for evaluation only);
            None for fisheye frames.
    """

    image: np.ndarray
    t: float
    shadow: np.ndarray | None = None


def _pixels(w: int, h: int) -> np.ndarray:
    """(H, W, 2) the (x, y) coordinates of every pixel of a W x H image [px]."""
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    return np.stack([xs, ys], -1)


class _RoverCamera(ABC):
    """A camera fixed to the rover body: pose, sun lighting, frames and frame pairs."""

    def __init__(self, sim: RoverSim, config, T_body_cam: np.ndarray) -> None:
        self.sim = sim
        self.config = config
        self.T_body_cam = T_body_cam
        steps = self.period / sim.dt
        if abs(steps - round(steps)) > 1e-6:
            raise ConfigError(
                f"rate_hz: {config.rate_hz:g} Hz does not divide the physics rate {1 / sim.dt:g} Hz; "
                "frame pairs must be whole physics steps apart (e.g. 30, 60, 80, 120 Hz at 240 Hz)"
            )
        self._last: Frame | None = None
        #: The image sensor between the renderer and the estimator (``camera_effects="field"``),
        #: or None: the rendered image is delivered as it is.
        self.image_sensor: ImageSensor | None = None
        #: The image sensor's figures on this camera: the configured ones, a preset's longest
        #: exposure capped at a faster camera's frame period
        #: (:meth:`~rover_env.config.image_sensor.ImageSensorConfig.for_frame_period`).
        self.sensor_config = config.sensor.for_frame_period(self.period)
        self._motion: MotionField | None = None
        #: (t0, t1) windows of simulation time [s] in which :meth:`sample` delivers black frames
        #: (a camera fault: the estimator sees only the images).
        self.blackout: list[tuple[float, float]] = []
        #: (4, 4) the mount's error: the camera sits at ``T_body_cam @ mount_error`` while its
        #: calibration (:attr:`T_body_cam`, the rig's mount) stays nominal.
        self.mount_error = np.eye(4)

    @property
    def period(self) -> float:
        """Time between frames [s]."""
        return 1.0 / self.config.rate_hz

    @property
    def lighting(self) -> Lighting:
        """Sun lighting from the scenario."""
        sim = self.sim
        sun = sim.scenario.sun
        sx, sy, sz = (float(v) for v in sun.direction(sim.t))
        return Lighting(
            (sx, sy, sz),
            ambient=self.config.ambient if sim.ambient is None else sim.ambient,
            diffuse=sun.transmission(sim.t) * sim.haze,
            shadows=self.config.shadows,
            clouds=sun.cloud_bands(sim.t),
        )

    def set_mount_error(self, error: np.ndarray | None) -> None:
        """Mount the camera off its nominal pose by ``error`` (see :attr:`mount_error`; None: none).

        ``error``: (6,) rotation vector [rad] and offset [m] in the camera's frame, or (4, 4).
        """
        if error is None:
            self.mount_error = np.eye(4)
            return
        e = np.asarray(error, dtype=np.float64)
        if e.shape == (4, 4):
            self.mount_error = e.copy()
            return
        if e.shape != (6,) or not np.all(np.isfinite(e)):
            raise ValueError(f"error: {error!r}; give (rx, ry, rz [rad], dx, dy, dz [m]) or a (4, 4) pose")
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(e[:3])[0]
        T[:3, 3] = e[3:]
        self.mount_error = T

    def T_world_cam(self) -> np.ndarray:
        """Pose of the camera optical frame in the world now (its true mount) [m]."""
        return self.sim.base_matrix() @ self.T_body_cam @ self.mount_error

    def render_view(self):
        """Render now, with per-pixel ground truth (for tests and evaluation)."""
        focus_on_rover(self.sim, self.config.ground_range)
        return self._render(labels=True)

    @abstractmethod
    def _render(self, labels: bool, parts: np.ndarray | None = None, motion: MotionSpec | None = None):
        """Render the view now; the per-pixel labels only if ``labels``.

        ``parts``: a fisheye's windows; ``motion``: with the renderer's velocity buffer.
        """

    @abstractmethod
    def _rays_and_model(self) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
        """(H, W, 3) unit ray of each pixel in the optical frame, and the model's projection."""

    @abstractmethod
    def _points_cam(self, view) -> np.ndarray:
        """(H, W, 3) each pixel's surface point in the optical frame of a labelled view [m]."""

    def capture(self) -> Frame:
        """Render one frame at the current simulation time."""
        focus_on_rover(self.sim, self.config.ground_range)
        return self._keep(self._render(labels=False))

    def set_effects(self, on: bool, seed: int | None = None) -> None:
        """Deliver images through the configured image sensor (``on``) or as rendered.

        Raises:
            ConfigError: The sensor's figures do not fit this camera (an exposure longer than
                its frame period, an odd image size).
        """
        if not on:
            self.image_sensor = None
            return
        size = (self.config.width, self.config.height)
        if size[0] % 2 or size[1] % 2:
            raise ConfigError(
                f"width, height: {size}; an image sensor with a Bayer pattern needs even sizes "
                "(or camera_effects='ideal')"
            )
        try:
            self.image_sensor = ImageSensor(self.sensor_config, size, self.period, seed, self._readout())
        except ConfigError as exc:
            raise ConfigError(f"sensor.{exc}") from None
        s = self.config.sensor
        if s.blur_samples > 1 or s.rolling_shutter_s > 0:
            self._motion = MotionField(*self._rays_and_model())
        else:
            self._motion = None

    def _readout(self) -> np.ndarray | None:
        """(H, W) bool the pixels the image sensor reads (its region of interest); None: all."""
        return None

    def reset_effects(self, seed: int | None, sensor=None) -> None:
        """A new episode of the image sensor (its fixed pattern, noise and exposure), if it has one.

        ``sensor``: this episode's :class:`~rover_env.config.image_sensor.ImageSensorConfig`
        (domain randomisation); None: the configured one.
        """
        if self.image_sensor is not None:
            self.image_sensor.reset(seed, self.sensor_config if sensor is None else sensor)

    def _field_frame(self, parts: np.ndarray | None = None) -> np.ndarray:
        """A frame through the image sensor: rendered, blurred along each pixel's motion, exposed."""
        sensor = self.image_sensor
        assert sensor is not None
        renderer = focus_on_rover(self.sim, self.config.ground_range)
        motion = self._motion
        if motion is not None and renderer.draws_motion:
            # the renderer draws each pixel's velocity in the colour pass (a velocity buffer)
            T = self.T_world_cam()
            links = self.sim.link_motion()
            com, v_l, w_l = links[-1]
            r = T[:3, 3] - com
            v_cam = v_l + (
                w_l[1] * r[2] - w_l[2] * r[1],
                w_l[2] * r[0] - w_l[0] * r[2],
                w_l[0] * r[1] - w_l[1] * r[0],
            )
            expose = self._expose_drawn()
            view = self._render(
                labels=False,
                parts=parts,
                motion=MotionSpec(self.sim.rover.body_id, links, v_cam, w_l, expose),
            )
            image = self._lens(view.rgb) if expose is not None else self._exposed(view.rgb, view.motion)
        elif motion is not None:  # from a labelled render: each pixel's point and body
            view = self._render(labels=True, parts=parts)
            velocity = motion.velocity(
                self._points_cam(view),
                view.segmentation,
                self.T_world_cam(),
                self.sim.link_motion(),
                self.sim.rover.body_id,
            )
            image = self._exposed(view.rgb, velocity)
        else:
            view = self._render(labels=False, parts=parts)
            image = self._lens(view.rgb)
        return sensor.capture(image, meter="rendered")

    def _exposed(self, image: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        """The rendered ``image`` integrated over the exposure along ``velocity`` [px/s], through the lens."""
        sensor, s = self.image_sensor, self.config.sensor
        assert sensor is not None
        return self._lens(blur(image, velocity, sensor.exposure_s, s.blur_samples, s.rolling_shutter_s))

    def _expose_drawn(self) -> Callable | None:
        """The exposure the renderer applies to each view it draws (:attr:`MotionSpec.expose`).

        None: the camera exposes the whole drawn image with its velocity buffer (:meth:`_exposed`).
        """
        return None

    def _lens(self, image: np.ndarray) -> np.ndarray:
        """The rendered (ideal) image as the lens forms it on the sensor (a fisheye's model has its lens)."""
        return image

    def set_blackout(self, windows) -> None:
        """Deliver black frames from :meth:`sample` within each (t0, t1) window [s] of simulation time.

        Raises:
            ValueError: ``windows`` is not a list of two finite times with t0 < t1.
        """
        self.blackout = blackout_windows(windows)

    def _dark(self) -> bool:
        t = self.sim.t
        return any(t0 <= t < t1 for t0, t1 in self.blackout)

    def _black(self) -> np.ndarray:
        return np.zeros((self.config.height, self.config.width, 3), dtype=np.uint8)

    def sample(self) -> np.ndarray:
        """The image the camera delivers now, (H, W, 3) uint8 RGB, as a sensor of the simulation.

        A rendered frame, or a black one inside a :attr:`blackout` window.
        """
        if self._dark():
            return self._black()
        if self.image_sensor is not None:
            return self._field_frame()
        return self.capture().image

    @property
    def last_frame(self) -> Frame | None:
        """The last frame :meth:`capture` returned (None before the first)."""
        return self._last

    def _keep(self, view) -> Frame:
        frame = Frame(image=view.rgb, t=self.sim.t, shadow=view.shadow)
        self._last = frame
        return frame


class DownwardCamera(_RoverCamera):
    """The mast camera of ``sim``'s rover: renders frames and frame pairs.

    Args:
        sim: The simulation (its rover and sun).
        config: Camera configuration.
        T_body_cam: (4, 4) pose of its optical frame in the body frame [m]; None: on the mast
            (:meth:`standard_mount`).
    """

    #: With a distorting lens, the ideal view is drawn only within this reach [px] of the pixels
    #: the lens reads; a frame whose motion blur reaches farther is drawn in full.
    BLUR_REACH_PX = 2

    @staticmethod
    def standard_mount(g: RoverGeometry) -> np.ndarray:
        """(4, 4) body-from-camera pose on the mast, looking straight down, image up = forward."""
        T = np.eye(4)
        T[:3, :3] = R_BODY_DOWNCAM
        T[:3, 3] = g.mast_camera_position
        return T

    def __init__(
        self, sim: RoverSim, config: DownwardCameraConfig | None = None, T_body_cam: np.ndarray | None = None
    ) -> None:
        cfg = config or DownwardCameraConfig()
        g = sim.geometry
        T = self.standard_mount(g) if T_body_cam is None else np.asarray(T_body_cam, dtype=np.float64)
        super().__init__(sim, cfg, T)
        nominal_height = g.wheel_radius - g.axle_z  # body origin above flat ground at rest [m]
        #: The camera's calibration: its intrinsics, distortion (with a field lens) and mount.
        self.model = PinholeCamera.from_fov(
            (cfg.width, cfg.height),
            math.radians(cfg.hfov_deg),
            math.radians(cfg.vfov_deg),
            T_body_cam=T,
            ground_plane=(0.0, 0.0, -nominal_height),
        )
        self._ideal = self.model
        # the ideal view that is rendered, and the lens's remap from it (None: no distortion)
        self._render_model = self.model
        self._lens_maps: tuple[np.ndarray, np.ndarray] | None = None
        # the pixels of the ideal view that the lens and a blur of up to BLUR_REACH_PX read
        self._lens_keep: np.ndarray | None = None

    def set_effects(self, on: bool, seed: int | None = None) -> None:
        """As :meth:`_RoverCamera.set_effects`; a field lens also distorts (``sensor.distortion``).

        With distortion, :attr:`model` carries it (the calibration the estimator is given), and
        an ideal view wide enough to hold every distorted pixel's ray is rendered and remapped.
        """
        dist = np.asarray(self.config.sensor.distortion, dtype=np.float64)
        ideal = self._ideal
        if not (on and np.any(dist)):
            self.model, self._render_model, self._lens_maps, self._lens_keep = ideal, ideal, None, None
        else:
            model = PinholeCamera(
                K=ideal.K,
                image_size=ideal.image_size,
                distortion=dist,
                T_body_cam=ideal.T_body_cam,
                ground_plane=ideal.ground_plane,
            )
            w, h = ideal.image_size
            ideal_px = ideal.project(
                np.concatenate([model.normalized(_pixels(w, h)), np.ones((h, w, 1))], -1)
            )
            lo = np.floor(ideal_px.reshape(-1, 2).min(axis=0)) - 2
            hi = np.ceil(ideal_px.reshape(-1, 2).max(axis=0)) + 2
            K = ideal.K.copy()
            K[0, 2] -= lo[0]
            K[1, 2] -= lo[1]
            size = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
            self._render_model = PinholeCamera(K=K, image_size=size, T_body_cam=ideal.T_body_cam)
            self._lens_maps = (
                (ideal_px[..., 0] - lo[0]).astype(np.float32),
                (ideal_px[..., 1] - lo[1]).astype(np.float32),
            )
            self._lens_keep = _lens_footprint(*self._lens_maps, size, self.BLUR_REACH_PX)
            self.model = model
        super().set_effects(on, seed)

    def _exposed(self, image: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        # with a lens, each sensor pixel's path is sampled in the ideal view at once (one
        # resampling, not the blur's and then the lens's)
        if self._lens_maps is None:
            return super()._exposed(image, velocity)
        sensor, s = self.image_sensor, self.config.sensor
        assert sensor is not None
        return blur(
            image, velocity, sensor.exposure_s, s.blur_samples, s.rolling_shutter_s, maps=self._lens_maps
        )

    def _lens(self, image: np.ndarray) -> np.ndarray:
        if self._lens_maps is None:
            return image
        return remap_image(image, *self._lens_maps)

    def render_view(self) -> RenderedView:
        """Render now, with depth and segmentation (for tests and evaluation)."""
        return super().render_view()

    def _rays_and_model(self):
        model = self._render_model
        w, h = model.image_size
        rays = model.unproject(_pixels(w, h))
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        return rays, model.project

    def _points_cam(self, view) -> np.ndarray:
        rays = self._motion.rays if self._motion is not None else self._rays_and_model()[0]
        return rays * (view.depth / rays[..., 2])[..., None]

    def _render(
        self, labels: bool, parts: np.ndarray | None = None, motion: MotionSpec | None = None
    ) -> RenderedView:
        if parts is not None:
            raise ValueError("parts: a pinhole camera renders whole frames")
        lighting = self.lighting
        renderer = renderer_for(self.sim)
        T = self.T_world_cam()
        if motion is None:
            return renderer.render_pinhole(self._render_model, T, lighting, segmentation=labels)
        if self._lens_keep is None:
            return renderer.render_pinhole(self._render_model, T, lighting, segmentation=False, motion=motion)
        # the ideal view's pixels that no sensor pixel reads are left undrawn: exact while no
        # pixel's path over the exposure is longer than BLUR_REACH_PX (else drawn again in full)
        view = renderer.render_pinhole(
            self._render_model, T, lighting, segmentation=False, motion=motion, keep=self._lens_keep
        )
        sensor, s = self.image_sensor, self.config.sensor
        vel = view.motion
        assert sensor is not None and vel is not None
        span = float(max(-vel.min(), vel.max())) if vel.size else 0.0
        if span * (sensor.exposure_s + s.rolling_shutter_s) > self.BLUR_REACH_PX:
            view = renderer.render_pinhole(self._render_model, T, lighting, segmentation=False, motion=motion)
        return view


@functools.lru_cache(maxsize=8)
def _kinematics_roi(
    cfg: FisheyeCameraConfig, g: RoverGeometry, mount: tuple[float, ...]
) -> tuple[np.ndarray, ...]:
    """:func:`kinematics_roi` of this fisheye on this rover (0.6 s to build, so built once).

    With ``roi_ground_deg``, a second region: the ground the fisheye's own odometry tracks (its
    own views, which a readout window takes whole while the kinematics' are windowed).
    """
    T = np.array(mount, dtype=np.float64).reshape(4, 4)
    model = cfg.model(T)
    roi = kinematics_roi(model, g.kinematic_model(T), g.roll_limit, g.travel_limit, g.steer_limit)
    roi.setflags(write=False)
    if cfg.roi_ground_deg <= 0.0:
        return (roi,)
    w, h = model.image_size
    down = -(model.cam2world(_pixels(w, h)) @ T[:3, :3].T)[..., 2]  # (H, W)
    with np.errstate(invalid="ignore"):
        ground = down >= math.cos(math.radians(cfg.roi_ground_deg))
    ground.setflags(write=False)
    return roi, ground


def ground_in_parts(
    cfg: FisheyeCameraConfig, mount: np.ndarray, ground: np.ndarray, disc_deg: float = 30.0
) -> tuple[np.ndarray, ...]:
    """The ground region split into a disc and four sectors beyond it, each a view of its own.

    ``ground`` (H, W) bool: the rays within ``roi_ground_deg`` of the body's -z; ``mount`` the
    (4, 4) body-from-camera pose; ``disc_deg``: the disc's angle off the body's -z [deg]. The
    sectors are centred on the body's +x, +y, -x and -y. Each part's view is aimed at its
    middle, so the views oversample the fisheye less than the cube's faces (57,700 face pixels
    against 71,500 at the train preset, for the same fisheye pixels; ``benchmarks/rig_speed.py
    --floor``).
    """
    model = cfg.model(mount)
    w, h = model.image_size
    d = model.cam2world(_pixels(w, h)) @ mount[:3, :3].T  # body-frame rays
    with np.errstate(invalid="ignore"):
        disc = ground & (-d[..., 2] >= math.cos(math.radians(disc_deg)))
    az = np.degrees(np.arctan2(d[..., 1], d[..., 0]))
    sectors = [ground & ~disc & (((az + 45.0 - a) % 360.0) < 90.0) for a in (0.0, 90.0, 180.0, 270.0)]
    return (disc, *sectors)


class FisheyeCamera(_RoverCamera):
    """The fisheye under ``sim``'s rover body, looking down (kinematics paper).

    Args:
        sim: The simulation (its rover and sun).
        config: Camera configuration.
    """

    @staticmethod
    def standard_mount(g: RoverGeometry) -> np.ndarray:
        """(4, 4) body-from-camera pose under the body, looking down, image x = body forward."""
        T = np.eye(4)
        T[:3, :3] = R_BODY_FISHEYE
        T[:3, 3] = g.fisheye_origin
        return T

    def __init__(
        self, sim: RoverSim, config: FisheyeCameraConfig | None = None, T_body_cam: np.ndarray | None = None
    ) -> None:
        cfg = config or FisheyeCameraConfig()
        g = sim.geometry
        T = self.standard_mount(g) if T_body_cam is None else np.asarray(T_body_cam, dtype=np.float64)
        super().__init__(sim, cfg, T)
        self.model = cfg.model(T)
        roi = _kinematics_roi(cfg, g, tuple(T.ravel().tolist())) if cfg.roi else None
        # the kinematics' region, then the ground's (in one mask or in parts)
        factors = None if roi is None or len(roi) < 2 else (1.0,) + (cfg.ground_oversample,) * (len(roi) - 1)
        self.remapper = CubemapRemap(
            self.model, oversample=cfg.oversample, roi=roi, region_oversample=factors
        )
        self._window: tuple[float, np.ndarray] | None = None
        self._cam_body: tuple[bytes, np.ndarray] | None = None
        #: Frames sampled so far: all, and those rendered in windows.
        self.sampled = {"frames": 0, "windowed": 0}

    def request_window(self, t: float, parts: np.ndarray | None) -> None:
        """Render only the windows holding ``parts`` in the frame sampled at time ``t`` [s].

        A tracker-driven windowed readout: the estimator asks, after each frame, for the parts
        the next one must show (see :meth:`capture`). The request holds for that one frame; a
        frame at any other time is rendered whole.
        """
        self._window = None if parts is None else (float(t), np.asarray(parts, dtype=np.float64))

    def sample(self) -> np.ndarray:
        """The image delivered now (see :meth:`_RoverCamera.sample`), windowed if requested for now."""
        req, self._window = self._window, None
        parts = req[1] if req is not None and abs(req[0] - self.sim.t) < 1e-9 else None
        self.sampled["frames"] += 1
        if self._dark():
            return self._black()
        self.sampled["windowed"] += parts is not None
        if self.image_sensor is not None:
            return self._field_frame(parts)
        return self.capture(parts=parts).image

    def render_view(self, parts: np.ndarray | None = None) -> FisheyeView:
        """Render now, with segmentation, shadow and 3-D points (for tests and evaluation).

        ``parts``: as in :meth:`capture`.
        """
        focus_on_rover(self.sim, self.config.ground_range)
        return self._render(labels=True, parts=parts)

    def capture(self, parts: np.ndarray | None = None) -> Frame:
        """Render one frame at the current simulation time.

        Args:
            parts: (N, 3) body-frame points [m] that the frame must show, such as
                :func:`perception.models.rover_parts.joint_window_parts` about a tracker's last state: each
                view then renders only the rectangle that holds their images (plus
                :attr:`window_margin`), like a sensor's windowed readout, and the rest of the
                image is black. None: the whole image (or region of interest).
        """
        focus_on_rover(self.sim, self.config.ground_range)
        return self._keep(self._render(labels=False, parts=parts))

    @property
    def window_margin(self) -> int:
        """Growth of each window about its parts' images [face px]: 2 % of the image width."""
        return max(2, round(0.02 * self.config.width))

    def windows(self, parts: np.ndarray) -> list[tuple[int, int, int, int]]:
        """The rectangle of each view (:attr:`remapper` faces) that holds the images of ``parts``.

        ``parts``: (N, 3) body-frame points [m]. See :meth:`CubemapRemap.windows`. The views of
        the ground region (``roi_ground_deg``) are whole.
        """
        T = self._T_cam_body
        pts = np.asarray(parts, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        wins = self.remapper.windows(pts, self.window_margin)
        # the ground region (roi_ground_deg) is read whole: the fisheye's own odometry tracks it
        return [
            (0, 0, *fc.size) if region > 0 else win
            for win, fc, region in zip(wins, self.remapper.faces, self.remapper.face_region, strict=True)
        ]

    @property
    def _T_cam_body(self) -> np.ndarray:
        """Camera-from-body pose of the camera as mounted (with its mount error)."""
        key = self.mount_error.tobytes()
        if self._cam_body is None or self._cam_body[0] != key:
            self._cam_body = (key, np.linalg.inv(self.T_body_cam @ self.mount_error))
        return self._cam_body[1]

    def _rays_and_model(self):
        w, h = self.model.image_size
        return self.model.cam2world(_pixels(w, h)), self.model.world2cam

    def _readout(self) -> np.ndarray | None:
        # with a region of interest, the sensor reads it (the rest is not rendered either)
        return self.remapper.rendered if self.config.roi else None

    @functools.cached_property
    def _atlas_row_fraction(self) -> np.ndarray:
        """Each atlas pixel's sensor row fraction (0: first row, 1: last), for a rolling shutter."""
        return self.remapper.atlas_rows / np.float32(max(self.model.image_size[1] - 1, 1))

    def _expose_drawn(self) -> Callable | None:
        # each cube-face window is blurred as drawn, before the remap to the fisheye
        sensor, s = self.image_sensor, self.config.sensor
        assert sensor is not None
        rows = self._atlas_row_fraction if s.rolling_shutter_s > 0 else None

        def expose(image: np.ndarray, velocity: np.ndarray, origin: tuple[int, int]) -> np.ndarray:
            r = None
            if rows is not None:
                (x0, y0), (h, w) = origin, image.shape[:2]
                r = rows[y0 : y0 + h, x0 : x0 + w]
            return blur(image, velocity, sensor.exposure_s, s.blur_samples, s.rolling_shutter_s, r)

        return expose

    def _points_cam(self, view) -> np.ndarray:
        T = (self._T_cam_body @ np.linalg.inv(self.sim.base_matrix())).astype(np.float32)
        return view.points_world @ T[:3, :3].T + T[:3, 3]

    def _render(
        self, labels: bool, parts: np.ndarray | None = None, motion: MotionSpec | None = None
    ) -> FisheyeView:
        lighting = self.lighting
        extra: dict[str, Any] = {} if motion is None else {"motion": motion}
        return renderer_for(self.sim).render_fisheye(
            self.remapper,
            self.T_world_cam(),
            lighting,
            labels=labels,
            windows=None if parts is None else self.windows(parts),
            **extra,
        )

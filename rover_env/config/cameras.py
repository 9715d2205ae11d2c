"""The simulated cameras' configurations and the renderer choices.

One base (:class:`CameraConfig`: image size, rate, shadows, ground range, presets) for the
downward camera and the fisheye.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, TypeVar, cast, get_args

import numpy as np

from perception.models.cameras import OmniCamera
from rover_env.config.image_sensor import ImageSensorConfig
from rover_env.config.io import ConfigError, check_range

#: What draws the cameras' images: ``"gl"`` (OpenGL on headless EGL), ``"tiny"`` (PyBullet's
#: TinyRenderer, on the CPU), or ``"auto"`` (gl where an EGL context can be created, else tiny).
RendererName = Literal["auto", "gl", "tiny"]
RENDERER_NAMES: tuple[str, ...] = get_args(RendererName)


def check_renderer(name: object) -> RendererName:
    """``name`` if it is a renderer choice (:data:`RendererName`).

    Raises:
        ValueError: Unknown name; the message lists the choices.
    """
    if name not in RENDERER_NAMES:
        raise ValueError(
            f"renderer={name!r}: use 'gl' (OpenGL on headless EGL), 'tiny' (PyBullet's TinyRenderer) "
            "or 'auto' (gl where an EGL context can be created, else tiny)"
        )
    return cast(RendererName, name)


#: The renderers draw the exact ground within this distance of the rover [m]; a camera's
#: ``ground_range`` is at most this.
FINE_RADIUS = 2.0

#: Image sizes by preset name: (width, height) [px].
CAMERA_PRESETS: dict[str, tuple[int, int]] = {"full": (640, 480), "half": (320, 240), "train": (160, 120)}

C = TypeVar("C", bound="CameraConfig")


@dataclass(frozen=True)
class CameraConfig:
    """The fields every camera has.

    Attributes:
        width: Image width [px].
        height: Image height [px].
        rate_hz: Frame rate [Hz].
        shadows: Render the sun's cast shadows.
        ambient: Shadowed share of the sunlit brightness at normal incidence (see
            :class:`rover_env.rendering.base.Lighting`).
        ground_range: Draw only the ground within this distance of the rover [m] (at most the
            terrain's exact-detail radius, 2 m), for speed: TinyRenderer spends time on every
            triangle whose projection overlaps a view, even where nearer surfaces hide it. Ground
            seen beyond it is left out (the background shows). None: all ground is drawn.
        sensor: The image sensor and lens between the renderer and the estimator, used with
            ``camera_effects="field"`` (:class:`~rover_env.config.image_sensor.ImageSensorConfig`).
    """

    width: int = 640
    height: int = 480
    rate_hz: float = 30.0
    shadows: bool = True
    ambient: float = 0.25
    ground_range: float | None = None
    sensor: ImageSensorConfig = ImageSensorConfig()

    def __post_init__(self) -> None:
        for key in ("width", "height"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or not 16 <= v <= 4096:
                raise ConfigError(f"{key}: {v!r} px is not a usable image size; use an integer in 16..4096")
        check_range("rate_hz", self.rate_hz, 1.0, 1000.0)
        check_range("ambient", self.ambient, 0.0, 1.0, lo_open=True)
        if self.ground_range is not None:
            check_range("ground_range", self.ground_range, 0.0, FINE_RADIUS, lo_open=True)

    @classmethod
    def preset(cls: type[C], name: str, **overrides) -> C:
        """A resolution preset with ``overrides``.

        :data:`CAMERA_PRESETS`: ``full`` 640x480, ``half`` 320x240, ``train`` 160x120.
        """
        if name not in CAMERA_PRESETS:
            raise ConfigError(f"preset: unknown {name!r}; choose one of {sorted(CAMERA_PRESETS)}")
        w, h = CAMERA_PRESETS[name]
        return cls(width=w, height=h, **overrides)


@dataclass(frozen=True)
class DownwardCameraConfig(CameraConfig):
    """Downward pinhole camera on the mast (the fields of :class:`CameraConfig`, and its view).

    Attributes:
        hfov_deg: Horizontal field of view (across the rover) [deg].
        vfov_deg: Vertical field of view (along the rover) [deg].

    Its default rate is 60 Hz (a frame pair is one period apart).
    """

    rate_hz: float = 60.0
    hfov_deg: float = 77.0
    vfov_deg: float = 57.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range("hfov_deg", self.hfov_deg, 1.0, 170.0)
        check_range("vfov_deg", self.vfov_deg, 1.0, 170.0)


@dataclass(frozen=True)
class FisheyeCameraConfig(CameraConfig):
    """Downward fisheye under the body (kinematics paper): :class:`CameraConfig` and its optics.

    Attributes:
        fov_deg: Full field of view of the image circle [deg] (>= 185).
        radius_frac: Radius of the image circle at fov_deg / 2, as a share of the image width
            (0.47: the circle spans the width and is cut by the top and bottom edges).
        oversample: Cube-face resolution relative to the fisheye's finest angular resolution.
        roi: Render only the region of interest of the kinematics estimator
            (:func:`perception.models.rover_parts.kinematics_roi`: wheels, markers and steering arms
            over the joint range);
            the rest of the image is black. Faster in proportion to the pixels saved.
        roi_ground_deg: With ``roi``, the region also holds the rays within this angle of the
            body's -z [deg]: the ground that the fisheye's own odometry tracks on a one-camera
            rig (75 there, :data:`rover_env.config.rig.FISHEYE_ONLY_GROUND_DEG`; the odometry
            selects features 5 degrees inside it). 0: none.
        ground_oversample: The ground region's cube-face resolution relative to ``oversample``'s
            (its faces are rendered at this factor squared of the pixels).

    Its width runs along the body's x axis, its height across the body.
    """

    fov_deg: float = 190.0
    radius_frac: float = 0.47
    oversample: float = 1.0
    roi: bool = False
    roi_ground_deg: float = 0.0
    ground_oversample: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        check_range("fov_deg", self.fov_deg, 185.0, 250.0)
        check_range("radius_frac", self.radius_frac, 0.1, 1.0)
        check_range("oversample", self.oversample, 0.25, 4.0)
        check_range("ground_oversample", self.ground_oversample, 0.25, 4.0)
        check_range("roi_ground_deg", self.roi_ground_deg, 0.0, 90.0)

    def model(self, T_body_cam: np.ndarray) -> OmniCamera:
        """The ideal (equidistant, 4th-order polynomial) model of this configuration."""
        return OmniCamera.equidistant(
            (self.width, self.height),
            math.radians(self.fov_deg),
            self.radius_frac * self.width,
            degree=4,
            T_body_cam=T_body_cam,
        )

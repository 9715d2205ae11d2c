"""What every simulated camera's configuration has: image size, rate, shadows, ground range, presets."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

from rover_env.config.io import ConfigError, check_range

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
    """

    width: int = 640
    height: int = 480
    rate_hz: float = 30.0
    shadows: bool = True
    ambient: float = 0.25
    ground_range: float | None = None

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

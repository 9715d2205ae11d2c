"""A camera's image sensor and lens: the figures of :class:`rover_env.sensors.image_sensor.ImageSensor`.

The chain from the rendered scene to the 8-bit image a camera delivers:

1. the rendered image is the scene's linear radiance, 1 = a white surface facing the full sun;
   the lens dims it toward the corners (``vignetting``);
2. each pixel of a Bayer colour-filter array (RGGB) collects
   ``sun_e_per_s * exposure * radiance`` photo-electrons with its fixed response error
   (PRNU), plus dark current and its fixed offset (DSNU); photon shot noise and the read
   noise are drawn per frame;
3. the charge clips at the full well, is amplified by the analog gain and digitised above a
   black level at the ADC's bit depth (the photon-transfer slope is ``K = gain *
   (2**adc_bits - 1 - black_level_dn) / full_well_e`` DN per electron);
4. the raw image is demosaiced, mapped through the output gamma to 8 bits, and optionally
   JPEG-compressed;
5. auto-exposure meters each output frame and moves exposure, then gain, toward its target
   with a lag.

Figures are per sensor preset (:data:`IMAGE_SENSOR_PRESETS`). Units: seconds, electrons (e-),
digital numbers (DN), decibels of amplitude gain.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

from rover_env.config.io import ConfigError, check_range, from_dict


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


@dataclass(frozen=True)
class ImageSensorConfig:
    """Figures of an image sensor, its lens and its exposure control.

    Attributes:
        name: Preset name (or "custom").
        full_well_e: Saturation capacity [e-].
        read_noise_e: Temporal dark (read) noise at unity gain [e- RMS].
        dark_current_e_s: Dark current [e-/s].
        dsnu_e: Dark signal non-uniformity: spread of the pixels' fixed offsets [e- RMS].
        prnu: Photo-response non-uniformity: spread of the pixels' fixed gains [share].
        adc_bits: Bit depth of the analog-to-digital converter.
        black_level_dn: Offset added before digitising, so that noise about zero is not clipped [DN].
        gain_max_db: Largest analog gain [dB of amplitude]; the gain runs from 0 dB.
        exposure_min_s: Shortest exposure [s].
        exposure_max_s: Longest exposure auto-exposure uses [s]; at most the frame period.
        exposure_s: The exposure at the start of an episode, and throughout without auto-exposure [s].
        gain_db: The gain at the start, and throughout without auto-exposure [dB].
        sun_e_per_s: Electrons per second a pixel collects from a white surface facing the full
            sun through the lens (its f-number, the filter's transmission and the quantum
            efficiency folded into one figure) [e-/s].
        auto_exposure: Meter each frame and adapt the exposure and gain.
        ae_target: Mean output level auto-exposure aims for, as a share of white (in the 8-bit,
            gamma-encoded output).
        ae_settling_s: Time auto-exposure takes to bring the mean within 5 % of its target after
            the light steps by a factor 4 [s] (the loop's lag; it meters one frame late).
        gamma: Output encoding: the 8-bit value is 255 * x ** (1 / gamma) of the linear level x.
        vignetting: Relative illumination at the image corner (1: none): the lens's falloff
            1 / (1 + a r^2)^2 over the radius r from the centre (1 at the corner).
        distortion: A pinhole camera's lens distortion, Brown-Conrady (k1, k2, p1, p2, k3) as
            OpenCV and ROS's ``plumb_bob`` write it; the estimator is given it with the camera's
            calibration. A fisheye's own model already holds its lens, so it ignores this.
        jpeg_quality: JPEG quality of the delivered frames (1-100), or None: uncompressed.
        rolling_shutter_s: Readout time from the first row to the last [s]; 0: a global shutter.
        blur_samples: Samples along each pixel's motion that integrate the exposure's blur.
    """

    name: str = "imx296"
    full_well_e: float = 10_400.0
    read_noise_e: float = 2.1
    dark_current_e_s: float = 3.0
    dsnu_e: float = 1.0
    prnu: float = 0.005
    adc_bits: int = 10
    black_level_dn: float = 60.0
    gain_max_db: float = 48.0
    exposure_min_s: float = 29e-6
    exposure_max_s: float = 0.010
    exposure_s: float = 0.002
    gain_db: float = 0.0
    sun_e_per_s: float = 4.0e6
    auto_exposure: bool = True
    ae_target: float = 0.45
    ae_settling_s: float = 0.3
    gamma: float = 2.2
    vignetting: float = 0.8
    distortion: tuple[float, float, float, float, float] = (-0.25, 0.07, 0.0, 0.0, 0.0)
    jpeg_quality: int | None = None
    rolling_shutter_s: float = 0.0
    blur_samples: int = 8

    def __post_init__(self) -> None:
        check_range("full_well_e", self.full_well_e, 0.0, 1e7, lo_open=True)
        check_range("read_noise_e", self.read_noise_e, 0.0, 1e4)
        check_range("dark_current_e_s", self.dark_current_e_s, 0.0, 1e7)
        check_range("dsnu_e", self.dsnu_e, 0.0, 1e4)
        check_range("prnu", self.prnu, 0.0, 0.5)
        if not _is_int(self.adc_bits) or not 8 <= self.adc_bits <= 16:
            raise ConfigError(f"adc_bits: {self.adc_bits!r}; use an integer bit depth in 8..16")
        check_range("black_level_dn", self.black_level_dn, 0.0, 0.5 * ((1 << self.adc_bits) - 1))
        check_range("gain_max_db", self.gain_max_db, 0.0, 60.0)
        check_range("exposure_min_s", self.exposure_min_s, 0.0, 1.0, lo_open=True)
        check_range("exposure_max_s", self.exposure_max_s, 0.0, 1.0, lo_open=True)
        if self.exposure_max_s < self.exposure_min_s:
            raise ConfigError(
                f"exposure_max_s: {self.exposure_max_s} s is below exposure_min_s {self.exposure_min_s} s"
            )
        check_range("exposure_s", self.exposure_s, self.exposure_min_s, self.exposure_max_s)
        check_range("gain_db", self.gain_db, 0.0, self.gain_max_db)
        check_range("sun_e_per_s", self.sun_e_per_s, 0.0, 1e12, lo_open=True)
        check_range("ae_target", self.ae_target, 0.0, 1.0, lo_open=True, hi_open=True)
        check_range("ae_settling_s", self.ae_settling_s, 0.0, 60.0, lo_open=True)
        check_range("gamma", self.gamma, 0.0, 5.0, lo_open=True)
        check_range("vignetting", self.vignetting, 0.0, 1.0, lo_open=True)
        if len(self.distortion) != 5:
            raise ConfigError(f"distortion: {self.distortion!r}; give five coefficients (k1, k2, p1, p2, k3)")
        for i, k in enumerate(self.distortion):
            check_range(f"distortion[{i}]", k, -2.0, 2.0)
        if self.jpeg_quality is not None and (
            not _is_int(self.jpeg_quality) or not 1 <= self.jpeg_quality <= 100
        ):
            raise ConfigError(f"jpeg_quality: {self.jpeg_quality!r}; use an integer in 1..100 or None")
        check_range("rolling_shutter_s", self.rolling_shutter_s, 0.0, 1.0)
        if not _is_int(self.blur_samples) or not 1 <= self.blur_samples <= 64:
            raise ConfigError(f"blur_samples: {self.blur_samples!r}; use an integer in 1..64")

    def check_frame_period(self, period: float, key: str = "exposure_max_s") -> None:
        """Raise :class:`ConfigError` unless the longest exposure and readout fit in ``period`` [s]."""
        if self.exposure_max_s > period + 1e-12:
            raise ConfigError(
                f"{key}: {self.exposure_max_s * 1e3:g} ms is longer than the frame period "
                f"{period * 1e3:g} ms; a frame's exposure must end before the next begins"
            )
        if self.rolling_shutter_s > period + 1e-12:
            raise ConfigError(
                f"rolling_shutter_s: {self.rolling_shutter_s * 1e3:g} ms is longer than the frame period "
                f"{period * 1e3:g} ms"
            )

    def for_frame_period(self, period: float) -> ImageSensorConfig:
        """These figures on a camera of frame period ``period`` [s].

        A preset's longest exposure is the preset's choice for its usual rate; on a faster
        camera a preset left as it is gets it capped at the frame period (and the starting
        exposure with it), as an exposure control must. Figures set by hand are kept, for
        :meth:`check_frame_period` to judge.
        """
        if self != IMAGE_SENSOR_PRESETS.get(self.name) or self.exposure_max_s <= period:
            return self
        top = max(float(period), self.exposure_min_s)
        return replace(self, exposure_max_s=top, exposure_s=min(self.exposure_s, top))

    @property
    def dn_max(self) -> int:
        """Largest raw value [DN]."""
        return (1 << self.adc_bits) - 1

    def system_gain(self, gain_db: float | None = None) -> float:
        """Photon-transfer slope K [DN/e-] at ``gain_db`` (None: the starting gain).

        At 0 dB the full well fills the ADC's range above the black level.
        """
        g = self.gain_db if gain_db is None else gain_db
        return 10.0 ** (g / 20.0) * (self.dn_max - self.black_level_dn) / self.full_well_e

    @classmethod
    def preset(cls, name: str, **overrides: Any) -> ImageSensorConfig:
        """A preset of :data:`IMAGE_SENSOR_PRESETS` with ``overrides``."""
        if name not in IMAGE_SENSOR_PRESETS:
            raise ConfigError(f"image sensor preset {name!r}: choose one of {sorted(IMAGE_SENSOR_PRESETS)}")
        return replace(IMAGE_SENSOR_PRESETS[name], **overrides)

    @classmethod
    def from_dict(cls, d: Any) -> ImageSensorConfig:
        """From a scenario mapping: ``preset`` (optional, default ``imx296``) and overrides.

        Unknown keys and values of the wrong type are named (:func:`rover_env.config.io.from_dict`).
        """
        if isinstance(d, str):
            return cls.preset(d)
        if not isinstance(d, dict):
            raise ConfigError(f"sensor: {d!r}; give a preset name or a mapping (preset and figures)")
        d = dict(d)
        name = d.pop("preset", "imx296")
        if not isinstance(name, str) or name not in IMAGE_SENSOR_PRESETS:
            raise ConfigError(f"sensor.preset: {name!r}; choose one of {sorted(IMAGE_SENSOR_PRESETS)}")
        base = asdict(IMAGE_SENSOR_PRESETS[name])
        base.update(d)
        if d:
            base["name"] = d.get("name", f"{name}+custom")
        return from_dict(cls, base, "sensor")

    def settling_tau(self, frame_period: float) -> float:
        """Time constant [s] of auto-exposure's first-order loop, in log exposure.

        The loop settles a 4x step of light to an output mean within 5 % of the target in
        :attr:`ae_settling_s`, one frame of which is the metering delay. The output is the
        linear level to the power 1 / ``gamma``, so within 5 % there is a linear error within
        ``gamma * ln(1.05)``, reached from ``ln(4)``.
        """
        span = max(self.ae_settling_s - frame_period, frame_period)
        return span / math.log(math.log(4.0) / (self.gamma * math.log(1.05)))


#: Sensor presets by name. ``imx296``: Sony's IMX296 global-shutter colour sensor (3.45 um pixels,
#: 10-bit ADC, 0-48 dB gain, exposures from 29 us: Teledyne FLIR Firefly FFY-U3-16S2 spec sheet;
#: black level 60 DN: the Linux imx296 driver's setting). Its EMVA 1288 figures are not
#: published; the full well (10,400 e-) and read noise (2.1 e-) are those of the IMX273, the
#: same 3.45 um Pregius pixel (Allied Vision Alvium 1800 C-158m data sheet). Assumed: dark
#: current, DSNU, PRNU, the lens's throughput (sun_e_per_s) and vignetting, and the
#: auto-exposure's target and settling time. Sources in docs/cameras.md.
IMAGE_SENSOR_PRESETS: dict[str, ImageSensorConfig] = {
    "imx296": ImageSensorConfig(),
}

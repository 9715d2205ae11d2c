"""An image sensor between the renderer and the estimator: light to photo-electrons to an 8-bit image.

:class:`ImageSensor` takes the rendered scene as linear radiance (1 = a white surface facing the
full sun) and delivers what a colour machine-vision camera would: lens vignetting, a Bayer
colour-filter array, photon shot noise, dark current, fixed-pattern noise (DSNU, PRNU), read
noise, the full well's clipping, analog gain, quantisation at the ADC's bit depth, demosaicing,
the output gamma to 8 bits, optional JPEG, and auto-exposure that meters each frame and adapts
with a lag. Its figures are an :class:`rover_env.config.image_sensor.ImageSensorConfig`.

Noise is drawn from the sensor's own generator, seeded per episode (:meth:`ImageSensor.reset`):
the same seed gives the same images. Shot and read noise are one Gaussian draw with the Poisson
variance plus the read variance (exact in mean and variance). The raw values are gamma-encoded
before demosaicing, as a camera's image pipeline does on 8-bit data.
"""

from __future__ import annotations

import collections
import math

import cv2
import numpy as np

from perception.models.photometry import relative_illumination
from rover_env.config.image_sensor import ImageSensorConfig

#: Bayer pattern of the colour-filter array: R at (0, 0), G at (0, 1) and (1, 0), B at (1, 1).
BAYER = "RGGB"
# OpenCV names a Bayer pattern by the second row's second and third pixels: RGGB is its "BG"
_DEMOSAIC = cv2.COLOR_BayerBG2RGB


#: Draws of OpenCV's generator dropped after each seed (its first is biased, see ImageSensor._normal).
_NORMAL_SKIP = 4
#: The RGB channel each pixel of the 2 x 2 RGGB tile samples, by (row, column) parity.
_CFA_CHANNEL = np.array([[0, 1], [1, 2]])


def mosaic(rgb: np.ndarray) -> np.ndarray:
    """The (H, W) Bayer (RGGB) samples of an (H, W, 3) image."""
    out = np.empty(rgb.shape[:2], dtype=rgb.dtype)
    out[0::2, 0::2] = rgb[0::2, 0::2, 0]
    out[0::2, 1::2] = rgb[0::2, 1::2, 1]
    out[1::2, 0::2] = rgb[1::2, 0::2, 1]
    out[1::2, 1::2] = rgb[1::2, 1::2, 2]
    return out


class ImageSensor:
    """One camera's sensor: exposure, noise, quantisation, demosaicing, gamma and auto-exposure.

    Args:
        config: The sensor's figures.
        size: Image (width, height) [px]; both even (a whole Bayer pattern).
        frame_period: Time between frames [s]; the longest exposure must fit in it.
        seed: Seeds the fixed pattern (PRNU, DSNU) and the per-frame noise.
        readout: (H, W) bool the pixels read out (a region-of-interest readout, grown to whole
            2 x 2 Bayer tiles); the others read 0 DN and cost nothing (black, but for the one
            pixel the demosaic's interpolation reaches past the region). None: all.

    Attributes:
        exposure_s: The exposure of the next frame [s].
        gain_db: The analog gain of the next frame [dB].
    """

    def __init__(
        self,
        config: ImageSensorConfig,
        size: tuple[int, int],
        frame_period: float,
        seed: int | None = None,
        readout: np.ndarray | None = None,
    ) -> None:
        w, h = size
        if w % 2 or h % 2:
            raise ValueError(f"size: {size}; a Bayer sensor needs an even width and height")
        # the read pixels (flat indices) and their own colour's index into a flat RGB image
        self._read: np.ndarray | None = None
        if readout is not None:
            mask = np.asarray(readout, dtype=bool)
            if mask.shape != (h, w):
                raise ValueError(f"readout: shape {mask.shape}; this sensor is {w} x {h} px")
            if not mask.any():
                raise ValueError("readout: no pixel is read; give a mask with some True, or None (all)")
            tiles = mask.reshape(h // 2, 2, w // 2, 2).any(axis=(1, 3))
            mask = np.repeat(np.repeat(tiles, 2, axis=0), 2, axis=1)
            self._read = np.flatnonzero(mask)
            ys, xs = np.divmod(self._read, w)
            self._read_rgb = self._read * 3 + _CFA_CHANNEL[ys % 2, xs % 2]
        config.check_frame_period(frame_period)
        self.config = config
        self.size = (int(w), int(h))
        self.frame_period = float(frame_period)
        self._vignetting = relative_illumination(self.size, config.vignetting)
        self._lut = self._gamma_lut()
        self._alpha = 1.0 - math.exp(-frame_period / config.settling_tau(frame_period))
        #: The last frames delivered, each with the Bayer mosaic it was demosaiced from
        #: (:meth:`keep_mosaics`); empty unless asked for.
        self._recent: collections.deque[tuple[np.ndarray, np.ndarray]] = collections.deque(maxlen=1)
        self._keep = 0
        self.reset(seed)

    def keep_mosaics(self, n: int) -> None:
        """Keep the gamma-encoded Bayer mosaics of the last ``n`` frames delivered (0: none, the default).

        A recorder logs a frame as the camera produced it, one colour per pixel
        (:meth:`mosaic_of`): a third of the RGB image's bytes, and demosaiced again into the very
        same image. A frame through JPEG keeps none.
        """
        self._keep = int(n)
        self._recent = collections.deque(maxlen=max(self._keep, 1))

    def mosaic_of(self, image: np.ndarray) -> np.ndarray | None:
        """The (H, W) uint8 Bayer mosaic that ``image`` (a delivered frame itself) was demosaiced from.

        None if it is not among the frames kept (:meth:`keep_mosaics`).
        """
        for rgb, encoded in self._recent:
            if rgb is image:
                return encoded
        return None

    def _gamma_lut(self) -> np.ndarray:
        c = self.config
        x = np.clip((np.arange(c.dn_max + 1) - c.black_level_dn) / (c.dn_max - c.black_level_dn), 0.0, 1.0)
        return np.clip(np.rint(255.0 * x ** (1.0 / c.gamma)), 0, 255).astype(np.uint8)

    def reset(self, seed: int | None = None, config: ImageSensorConfig | None = None) -> None:
        """A new episode: a new fixed pattern and noise from ``seed``; exposure and gain at their start.

        ``config``: this episode's figures (a unit's own, as domain randomisation draws them);
        None: keep the current ones.
        """
        if config is not None and config is not self.config:
            config.check_frame_period(self.frame_period)
            self.config = config
            self._vignetting = relative_illumination(self.size, config.vignetting)
            self._lut = self._gamma_lut()
            self._alpha = 1.0 - math.exp(-self.frame_period / config.settling_tau(self.frame_period))
        c = self.config
        rng = np.random.default_rng(seed)
        w, h = self.size
        # each pixel's response: the lens's vignetting times its fixed gain (PRNU)
        prnu = 1.0 + c.prnu * rng.standard_normal((h, w))
        self._response = (self._vignetting * prnu).astype(np.float32).reshape(-1)
        self._offset_e = (c.dsnu_e * rng.standard_normal((h, w))).astype(np.float32).reshape(-1)
        if self._read is not None:
            self._response = self._response[self._read]
            self._offset_e = self._offset_e[self._read]
        self._rng = rng
        self.exposure_s = c.exposure_s
        self.gain_db = c.gain_db

    # ------------------------------------------------------------------ the chain
    def raw(
        self,
        image: np.ndarray,
        exposure_s: float | None = None,
        gain_db: float | None = None,
        light: float = 1.0,
    ) -> np.ndarray:
        """Raw Bayer values (H, W) uint16 [DN] of one exposure of a rendered image.

        Args:
            image: (H, W, 3) uint8 linear RGB as rendered (255: a white surface facing the full sun).
            exposure_s: Exposure [s]; None: :attr:`exposure_s`.
            gain_db: Analog gain [dB]; None: :attr:`gain_db`.
            light: The scene's brightness relative to the rendered image (a passing cloud: < 1).

        Each pixel's mean charge is its radiance times the lens's vignetting, its fixed gain
        (PRNU) and ``sun_e_per_s * exposure``, plus dark current and its fixed offset (DSNU).
        The charge gets photon shot noise (the Poisson variance: the mean) and read noise in one
        Gaussian draw, clips at the full well, and is digitised: times the system gain, plus the
        black level, rounded and clipped to the ADC's range.
        """
        return self._frame(self._dn(image, exposure_s, gain_db, light), np.uint16)

    def _frame(self, values: np.ndarray, dtype) -> np.ndarray:
        """The (H, W) frame of the read pixels' ``values`` (:meth:`_dn`'s order), 0 elsewhere."""
        w, h = self.size
        if self._read is None:
            return values.astype(dtype, copy=False).reshape(h, w)
        out = np.zeros(h * w, dtype)
        out[self._read] = values
        return out.reshape(h, w)

    def _dn(
        self, image: np.ndarray, exposure_s: float | None, gain_db: float | None, light: float
    ) -> np.ndarray:
        """:meth:`raw`'s values of the read pixels only, flat uint16 [DN]; sets :attr:`_drawn`."""
        c = self.config
        t = self.exposure_s if exposure_s is None else float(exposure_s)
        w, h = self.size
        if image.shape != (h, w, 3):
            raise ValueError(f"image: shape {image.shape}; this sensor is {w} x {h} px (H, W, 3)")
        # each read pixel's sample of its own colour
        bayer = mosaic(image).reshape(-1) if self._read is None else image.reshape(-1)[self._read_rgb]
        scale = np.float32(light * c.sun_e_per_s * t / 255.0)
        # (in place where it can be: the same operations in the same order as written out)
        mean = self._response * scale
        mean *= bayer
        mean += self._offset_e + np.float32(c.dark_current_e_s * t)
        np.maximum(mean, 0.0, out=mean)
        e = mean + np.float32(c.read_noise_e**2)
        np.sqrt(e, out=e)  # the deviation of shot and read noise
        e *= self._normal(mean.shape)
        e += mean
        np.minimum(e, np.float32(c.full_well_e), out=e)
        k = c.system_gain(self.gain_db if gain_db is None else gain_db)
        e *= np.float32(k)
        e += np.float32(c.black_level_dn)
        np.rint(e, out=e)
        dn = np.clip(e, 0, c.dn_max, out=e).astype(np.uint16)
        self._drawn = bayer > 0  # which read pixels the renderer drew (not black)
        return dn

    def _normal(self, shape: tuple[int, ...]) -> np.ndarray:
        """Standard normal draws (float32), from this sensor's seeded generator.

        OpenCV's generator draws them (a quarter of NumPy's time), seeded each frame from the
        sensor's own generator: the same seed repeats the same frames. Its first draws after a
        32-bit seed are biased (the first is positive 99 % of the time), so a few are dropped.
        """
        n = int(np.prod(shape))
        out = np.empty(n + _NORMAL_SKIP, np.float32)
        cv2.setRNGSeed(int(self._rng.integers(1, 2**31)))
        cv2.randn(out, 0.0, 1.0)  # type: ignore[call-overload]  # (OpenCV's type hints take sequences)
        return out[_NORMAL_SKIP:].reshape(shape)

    def develop(self, raw: np.ndarray) -> np.ndarray:
        """The delivered (H, W, 3) uint8 RGB image of raw Bayer values: gamma-encoded, demosaiced, JPEG."""
        return self._develop_encoded(self._lut[raw])

    def _develop_encoded(self, encoded: np.ndarray) -> np.ndarray:
        """:meth:`develop` of the gamma-encoded Bayer values (H, W) uint8."""
        rgb = cv2.cvtColor(encoded, _DEMOSAIC)
        q = self.config.jpeg_quality
        if self._keep and q is None:
            self._recent.append((rgb, encoded))
        if q is not None:
            ok, buf = cv2.imencode(".jpg", rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(q)])
            bgr = cv2.imdecode(buf, cv2.IMREAD_COLOR) if ok else None
            if bgr is None:  # OpenCV encodes and decodes any 8-bit image
                raise RuntimeError("JPEG round trip failed")
            rgb = bgr[..., ::-1].copy()
        return rgb

    def capture(
        self, image: np.ndarray, light: float = 1.0, meter: np.ndarray | str | None = None
    ) -> np.ndarray:
        """One frame of a rendered ``image`` (see :meth:`raw`) at the current settings, as uint8 RGB.

        Auto-exposure then meters the frame and sets the next frame's exposure and gain, over
        ``meter``: an (H, W) bool mask, ``"rendered"`` (the pixels the renderer drew: not black,
        as a region-of-interest readout meters its region), or None (all of it).
        """
        if isinstance(meter, str) and meter != "rendered":
            raise ValueError(f"meter={meter!r}: use a mask, 'rendered' or None")
        # the gamma table on the read pixels only, before a region of interest is placed in the frame
        values = np.take(self._lut, self._dn(image, None, None, light))
        encoded = self._frame(values, np.uint8)
        out = self._develop_encoded(encoded)
        if self.config.auto_exposure:
            if isinstance(meter, str):
                self._meter(values[self._drawn])
            else:
                self._meter(encoded.reshape(-1) if meter is None else encoded[meter])
        return out

    # ------------------------------------------------------------------ auto-exposure
    def _meter(self, values: np.ndarray) -> None:
        """Move exposure, then gain, toward the level at which the output's mean is the target.

        ``values``: the metered pixels' gamma-encoded Bayer values (all colours alike).
        """
        c = self.config
        level = float(values.mean()) / 255.0 if values.size else 0.0
        # the linear change that brings the mean to the target (at most 16x a frame when black or white)
        ratio = (c.ae_target / level) ** c.gamma if level > 1e-3 else 16.0
        ratio = min(max(ratio, 1.0 / 16.0), 16.0)
        total = self.exposure_s * 10.0 ** (self.gain_db / 20.0)
        total *= math.exp(self._alpha * math.log(ratio))
        exposure = min(max(total, c.exposure_min_s), c.exposure_max_s)
        gain = min(max(20.0 * math.log10(total / exposure), 0.0), c.gain_max_db)
        self.exposure_s, self.gain_db = exposure, gain

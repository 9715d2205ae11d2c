"""A camera's photometry as an estimator undoes it: its output gamma, vignetting and colour-filter array.

Estimators that compare light levels (a shadow's ratio, paint against tread) need linear levels:
:func:`linear_gray` undoes the camera's gamma (:attr:`perception.rig.SensorSpec.gamma`).

A lens's vignetting darkens the image towards its corners. The shading is fixed to the sensor, so
a texture tracker reads it as a pattern that does not move, and on faint texture it pulls the
flow towards zero (2 % of the speed on a dim, low-contrast ground at a corner illumination of
0.8). :func:`flat_field_gain` is the gain that undoes it, from the calibrated relative
illumination at the image corner (:attr:`perception.rig.SensorSpec.vignetting`).

A colour camera samples one colour per pixel through its colour-filter array (CFA) and
interpolates the other two (demosaicing). Where the scene is tinted, its colours are read with
different gains, so a grey image made from the demosaiced colours carries the array's 2-pixel
checker, fixed to the sensor, at the scale of fine texture. A texture tracker then finds that
checker at zero motion. :func:`cfa_luminance` takes each pixel's own sample (a bilinear
demosaic keeps it) and scales it by its colour's local level: the checker goes, and every pixel
keeps its own reading.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

#: The colour-filter arrays :func:`cfa_luminance` knows: the colours of the 2 x 2 tile's pixels
#: (0, 0), (0, 1), (1, 0), (1, 1) as RGB channel indices.
CFA_PATTERNS: dict[str, tuple[int, int, int, int]] = {
    "RGGB": (0, 1, 1, 2),
    "BGGR": (2, 1, 1, 0),
    "GRBG": (1, 0, 2, 1),
    "GBRG": (1, 2, 0, 1),
}
_SITES = ((0, 0), (0, 1), (1, 0), (1, 1))


@functools.lru_cache(maxsize=8)
def _linear_lut(gamma: float) -> np.ndarray:
    lut = (255.0 * (np.arange(256) / 255.0) ** gamma).astype(np.float32)
    lut.flags.writeable = False
    return lut


def relative_illumination(size: tuple[int, int], corner: float) -> np.ndarray:
    """A lens's relative illumination (H, W) float32, 1 at the image centre and ``corner`` at its corners.

    The radial model 1 / (1 + a r^2)^2, r the distance from the image centre as a share of the
    half diagonal, ``a`` set by ``corner`` (in (0, 1]); ``size`` is (W, H) [px].
    """
    w, h = int(size[0]), int(size[1])
    if not 0.0 < corner <= 1.0:
        raise ValueError(f"corner: {corner!r}; use a relative illumination in (0, 1]")
    a = 1.0 / math.sqrt(corner) - 1.0
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = ((xs - (w - 1) / 2.0) ** 2 + (ys - (h - 1) / 2.0) ** 2) / ((w / 2.0) ** 2 + (h / 2.0) ** 2)
    return (1.0 / (1.0 + a * r2) ** 2).astype(np.float32)


def flat_field_gain(size: tuple[int, int], corner: float, gamma: float = 1.0) -> np.ndarray | None:
    """The gain (H, W) float32 that undoes vignetting on a camera's encoded 8-bit values, or None.

    An encoded value is ``255 (V L) ** (1 / gamma)`` of the linear level L under the relative
    illumination V (:func:`relative_illumination`), so the gain is ``V ** (-1 / gamma)``: 1 at the
    centre, above 1 towards the corners; None for ``corner`` 1 (no vignetting, or none calibrated).
    """
    if corner == 1.0:
        return None
    if not gamma > 0:
        raise ValueError(f"gamma: {gamma!r}; give the camera's response exponent above 0")
    return (relative_illumination(size, corner) ** np.float32(-1.0 / gamma)).astype(np.float32)


def flat_field(gray: np.ndarray, gain: np.ndarray | None) -> np.ndarray:
    """uint8 ``gray`` times ``gain`` (:func:`flat_field_gain`), rounded, clipped to 0-255 (None: ``gray``)."""
    if gain is None:
        return gray
    return cv2.multiply(gray, gain, dtype=cv2.CV_8U)


def linear_gray(gray: np.ndarray, gamma: float) -> np.ndarray:
    """A gamma-encoded uint8 image (any shape) as relative irradiance, float32 on the same 0-255 scale.

    ``gamma``: the camera's response (:attr:`perception.rig.SensorSpec.gamma`): a value ``v``
    encodes the irradiance ``255 (v / 255) ** gamma``. The treads' band-pass divides by the local
    light level and finds shadow edges by the step of its log, both of which hold only for
    linear levels (gamma 2.2 shrinks a shadow's light ratio of 3 to 1.65).
    """
    img = np.asarray(gray, dtype=np.uint8)
    lut = _linear_lut(float(gamma))
    if img.size and (img.ndim == 2 or (img.ndim == 3 and img.shape[2] <= 4)):
        return cv2.LUT(img, lut).reshape(img.shape)  # the same table in a quarter of the time
    return lut[img]


def cfa_luminance(
    rgb: np.ndarray,
    pattern: str,
    gamma: float = 1.0,
    sigma: float = 1.5,
    rect: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """Linear luminance (H, W) float32 of a demosaiced colour image, from each pixel's own sample.

    Each pixel's sample of its own colour (``pattern``: the camera's CFA, :data:`CFA_PATTERNS`)
    is linearised (``gamma``) and multiplied by the local luminance over the local level of its
    colour (both Gaussian means, ``sigma`` pixels of that colour's quarter-resolution plane):
    locally even colour then gives one level to all four sites, and every pixel keeps its own
    reading of the texture.

    Args:
        rgb: (H, W, 3) uint8 RGB as the camera delivered it (bilinear demosaicing keeps each
            pixel's own sample); H and W even.
        pattern: The CFA, a key of :data:`CFA_PATTERNS`.
        gamma: The camera's output gamma (1: linear images).
        sigma: Width of the local levels [pixels of a colour plane, i.e. 2 image pixels].
        rect: (x0, y0, x1, y1) [px, end exclusive]: only this part of the result, computed from
            the image about it (the Gaussians' reach): the whole image's values, to float
            rounding (about 1e-7 of the range).

    Raises:
        ValueError: An unknown pattern, an image that is not (H, W, 3) uint8 of even size.
    """
    if pattern not in CFA_PATTERNS:
        raise ValueError(f"pattern: {pattern!r}; use one of {sorted(CFA_PATTERNS)}")
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3 or img.shape[0] % 2 or img.shape[1] % 2:
        raise ValueError(f"rgb: {img.dtype} {img.shape}; expected (H, W, 3) uint8 with H and W even")
    if rect is not None:
        h, w = img.shape[:2]
        x0, y0, x1, y1 = (int(v) for v in rect)
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"rect: {rect}; use 0 <= x0 < x1 <= {w}, 0 <= y0 < y1 <= {h}")
        # both Gaussians reach 4 of their sigmas, 8 sigma image pixels (cv2's kernels), and
        # an even origin keeps the colour-filter array's phase
        pad = 2 * math.ceil(4.0 * sigma) + 2
        px0, py0 = max(0, (x0 - pad) & ~1), max(0, (y0 - pad) & ~1)
        px1, py1 = min(w, (x1 + pad + 1) & ~1), min(h, (y1 + pad + 1) & ~1)
        out = cfa_luminance(img[py0:py1, px0:px1], pattern, gamma, sigma)
        return out[y0 - py0 : y1 - py0, x0 - px0 : x1 - px0]
    lin = linear_gray(img, gamma) if gamma != 1.0 else img.astype(np.float32)
    level = cv2.GaussianBlur(cv2.cvtColor(lin, cv2.COLOR_RGB2GRAY), (0, 0), 2.0 * sigma)
    # the four sites' own samples, one colour plane each, blurred in one call (as four channels)
    h, w = img.shape[:2]
    sites = list(zip(_SITES, CFA_PATTERNS[pattern], strict=True))
    planes = np.empty((h // 2, w // 2, 4), np.float32)
    for k, ((dy, dx), c) in enumerate(sites):
        planes[..., k] = lin[dy::2, dx::2, c]
    means = cv2.GaussianBlur(planes, (0, 0), sigma)
    np.maximum(means, np.float32(1e-3), out=means)
    # each pixel's own sample and its colour's level, at full resolution for the arithmetic
    own = np.empty((h, w), np.float32)
    own_mean = np.empty((h, w), np.float32)
    for k, ((dy, dx), _) in enumerate(sites):
        own[dy::2, dx::2] = planes[..., k]
        own_mean[dy::2, dx::2] = means[..., k]
    own *= level
    own /= own_mean
    return own

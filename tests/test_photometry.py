"""A camera's photometry undone: its gamma, and its colour-filter array's checker."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from perception.models.photometry import CFA_PATTERNS, cfa_luminance, linear_gray

# OpenCV names a Bayer pattern by the second row's second and third pixels
_DEMOSAIC = {"RGGB": cv2.COLOR_BayerBG2RGB, "BGGR": cv2.COLOR_BayerRG2RGB, "GRBG": cv2.COLOR_BayerGB2RGB}


def tinted_frame(pattern: str, shift: int = 0, gamma: float = 2.2, tint=(1.0, 0.7, 0.45)):
    """A tinted fine texture through a colour camera: mosaic, gamma, bilinear demosaic (uint8 RGB).

    Returns the delivered image and the true linear luminance (OpenCV's grey of linear colours).
    """
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.random((130, 170)).astype(np.float32), (0, 0), 1.0)
    tex = 0.2 + 0.6 * (tex - tex.min()) / np.ptp(tex)
    tex = tex[:120, shift : shift + 160]
    lin = tex[..., None] * np.asarray(tint, np.float32)[None, None] * 255.0  # linear RGB
    raw = np.empty(tex.shape, np.float32)
    for (dy, dx), c in zip(((0, 0), (0, 1), (1, 0), (1, 1)), CFA_PATTERNS[pattern], strict=True):
        raw[dy::2, dx::2] = lin[dy::2, dx::2, c]
    encoded = np.clip(np.rint(255.0 * (raw / 255.0) ** (1.0 / gamma)), 0, 255).astype(np.uint8)
    rgb = cv2.cvtColor(encoded, _DEMOSAIC[pattern])
    luma = 0.299 * tint[0] + 0.587 * tint[1] + 0.114 * tint[2]  # OpenCV's grey of the colours
    return rgb, tex * 255.0 * luma


def _fine(img: np.ndarray) -> np.ndarray:
    """The fine texture: the image less its 3-pixel Gaussian mean, 8-pixel border left out."""
    img = np.asarray(img, np.float32)
    return (img - cv2.GaussianBlur(img, (0, 0), 3.0))[8:-8, 8:-8]


def _ncc(x: np.ndarray, y: np.ndarray) -> float:
    x, y = x - x.mean(), y - y.mean()
    return float((x * y).sum() / np.sqrt((x * x).sum() * (y * y).sum()))


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG"])
def test_cfa_luminance_keeps_each_pixels_reading_of_the_fine_texture(pattern):
    """A tinted texture through a colour camera: the grey of the demosaiced colours mixes each
    pixel's own sample with its neighbours' (0.978 of the true fine texture); each pixel's own
    sample, levelled by its colour, keeps it (0.9995)."""
    rgb, truth = tinted_frame(pattern)
    naive = linear_gray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), 2.2)
    lum = cfa_luminance(rgb, pattern, gamma=2.2)
    corr = [_ncc(_fine(x), _fine(truth)) for x in (naive, lum)]
    level = float(np.median(lum / truth))
    print(f"{pattern}: fine texture against the truth {corr[0]:.4f} -> {corr[1]:.4f}; level {level:.3f}")
    assert corr[1] > 0.999 and corr[0] < 0.99
    assert level == pytest.approx(1.0, abs=0.03)  # linear, on the truth's scale


def test_a_moving_texture_matches_itself_better_from_each_pixels_own_sample():
    """Two frames of a texture moved by 3 pixels, compared where it moved."""
    (f0, _), (f1, _) = tinted_frame("RGGB", 0), tinted_frame("RGGB", 3)
    out = []
    for gray in (
        lambda f: linear_gray(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), 2.2),
        lambda f: cfa_luminance(f, "RGGB", 2.2),
    ):
        a, b = _fine(gray(f0)), _fine(gray(f1))
        out.append(_ncc(a[:, 3:], b[:, :-3]))
    print(f"NCC at the motion {out[0]:.4f} -> {out[1]:.4f}")
    assert out[1] > 0.998 and out[1] - out[0] > 0.02


def test_bad_patterns_and_images_are_named():
    rgb, _ = tinted_frame("RGGB")
    with pytest.raises(ValueError, match="pattern"):
        cfa_luminance(rgb, "RGBW")
    with pytest.raises(ValueError, match="even"):
        cfa_luminance(rgb[:-1], "RGGB")
    with pytest.raises(ValueError, match="uint8"):
        cfa_luminance(rgb.astype(np.float32), "RGGB")

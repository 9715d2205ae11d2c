"""Procedural, seamlessly tiling ground and tread textures.

Every texture is periodic (it tiles without a visible seam) because its noise is synthesised in
the Fourier domain and its stones are drawn with wrap-around. Textures are plain RGB uint8
arrays; :func:`texture_file` caches them as PNG files for PyBullet, which loads textures from
disk.
"""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from rover_env.config.scenario import CHECKER_SQUARES_PER_TILE

log = logging.getLogger(__name__)


def periodic_noise(
    n: int,
    rng: np.random.Generator,
    beta: float,
    min_period_px: float = 2.0,
    max_period_px: float | None = None,
) -> np.ndarray:
    """Zero-mean, unit-std periodic noise with power spectrum ~ 1/f^beta.

    Args:
        n: Image edge length [px].
        rng: Random generator.
        beta: Spectral exponent (0 white, 2 natural terrain-like, 3 very smooth).
        min_period_px: Shortest spatial period kept [px].
        max_period_px: Longest spatial period kept [px] (default: the tile).

    Returns:
        Array (n, n) float64, periodic in both axes.
    """
    f = np.fft.fftfreq(n)
    fx, fy = np.meshgrid(f, f)
    fr = np.hypot(fx, fy)
    fr[0, 0] = 1.0
    amp = fr ** (-beta / 2.0)
    amp[fr > 1.0 / min_period_px] = 0.0
    if max_period_px is not None:
        amp[fr < 1.0 / max_period_px] = 0.0
    amp[0, 0] = 0.0
    phase = rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))
    img = np.fft.ifft2(amp * phase).real
    std = img.std()
    return img / std if std > 0 else img


def _stamp_stones(
    img: np.ndarray,
    rng: np.random.Generator,
    count: int,
    r_min: float,
    r_max: float,
    shade: tuple[float, float],
    light_dir: tuple[float, float] = (-0.6, -0.6),
) -> None:
    """Draw shaded elliptical stones into the float image ``img`` in place, wrapping around.

    A stone that crosses the border is drawn again at its periodic copies, so the tile stays
    seamless.
    """
    n = img.shape[0]
    pad = int(np.ceil(r_max)) + 2
    size = 2 * pad + 1
    yy, xx = np.mgrid[-pad : pad + 1, -pad : pad + 1]
    lx, ly = light_dir
    for _ in range(count):
        cx, cy = rng.integers(0, n, 2)
        a = rng.uniform(r_min, r_max)
        b = a * rng.uniform(0.55, 1.0)
        mask = np.zeros((size, size), np.uint8)
        cv2.ellipse(
            mask,
            (pad, pad),
            (max(1, round(a)), max(1, round(b))),
            rng.uniform(0, 180),
            0,
            360,
            255,
            -1,
            cv2.LINE_AA,
        )
        m = mask / 255.0
        stone = rng.uniform(*shade) * (1.0 + 0.35 * (-(xx * lx + yy * ly) / max(a, 1.0)).clip(-1.5, 1.5))
        for oy in (-n, 0, n):
            for ox in (-n, 0, n):
                x0, y0 = cx + ox - pad, cy + oy - pad
                xa, ya = max(x0, 0), max(y0, 0)
                xb, yb = min(x0 + size, n), min(y0 + size, n)
                if xa >= xb or ya >= yb:
                    continue
                mm = m[ya - y0 : yb - y0, xa - x0 : xb - x0]
                st = stone[ya - y0 : yb - y0, xa - x0 : xb - x0]
                img[ya:yb, xa:xb] = img[ya:yb, xa:xb] * (1 - mm) + st * mm


def _to_rgb(gray: np.ndarray, tint: tuple[float, float, float]) -> np.ndarray:
    rgb = np.clip(gray[..., None] * np.asarray(tint)[None, None, :], 0, 255)
    return rgb.astype(np.uint8)


def ground_texture(name: str, px: int = 1024, seed: int = 0) -> np.ndarray:
    """A seamlessly tiling ground texture.

    Args:
        name: ``regolith``, ``sand``, ``gravel``, ``concrete`` or ``checkerboard``.
        px: Edge length [px].
        seed: Random seed; the same seed gives the same texture.

    Returns:
        RGB image (px, px, 3) uint8.
    """
    rng = np.random.default_rng(seed)
    s = px / 1024.0  # stone sizes scale with resolution (tile-relative)
    if name == "regolith":
        g = 120 + 22 * periodic_noise(px, rng, 2.2, 4) + 14 * periodic_noise(px, rng, 0.5, 1.5)
        _stamp_stones(g, rng, int(900 * s * s), 2 * s, 9 * s, (80, 170))
        g += 6 * periodic_noise(px, rng, 0.0, 1.5)
        return _to_rgb(g, (1.0, 0.93, 0.85))
    if name == "sand":
        yy, xx = np.mgrid[0:px, 0:px] / px
        warp = 0.06 * periodic_noise(px, rng, 3.0, 8)
        ripples = np.sin(2 * np.pi * (7 * xx + 2 * yy + warp))
        g = 150 + 10 * ripples + 16 * periodic_noise(px, rng, 2.0, 3)
        g += 18 * periodic_noise(px, rng, 0.0, 1.5)
        _stamp_stones(g, rng, int(250 * s * s), 1.5 * s, 4 * s, (110, 190))
        return _to_rgb(g, (1.0, 0.9, 0.72))
    if name == "gravel":
        g = 70 + 12 * periodic_noise(px, rng, 1.0, 2)
        _stamp_stones(g, rng, int(3500 * s * s), 5 * s, 14 * s, (90, 200))
        g += 8 * periodic_noise(px, rng, 0.0, 1.5)
        return _to_rgb(g, (0.98, 0.96, 0.93))
    if name == "concrete":
        g = 165 + 8 * periodic_noise(px, rng, 2.5, 8) + 14 * periodic_noise(px, rng, 0.3, 1.5)
        _stamp_stones(g, rng, int(1800 * s * s), 1.5 * s, 4 * s, (120, 205))
        _stamp_stones(g, rng, int(300 * s * s), 0.8 * s, 1.6 * s, (60, 90))  # pores
        return _to_rgb(g, (0.97, 0.97, 0.95))
    if name == "checkerboard":
        squares = CHECKER_SQUARES_PER_TILE
        yy, xx = np.mgrid[0:px, 0:px] * squares // px
        g = np.where((xx + yy) % 2 == 0, 235.0, 25.0)
        return _to_rgb(g, (1.0, 1.0, 1.0))
    raise ValueError(f"unknown texture preset {name!r}; use regolith, sand, gravel, concrete or checkerboard")


def tread_texture(
    px_u: int = 512, px_v: int = 128, marker_arc: float = 0.28, grousers: int = 16, seed: int = 0
) -> np.ndarray:
    """Wheel texture atlas: tread in rows [0, 0.75), sidewall grey in rows [0.75, 1].

    Texture u runs once around the wheel (u = 0.5 at wheel angle 0, where the white
    correction marker is centred); v runs across the tread width.

    Args:
        px_u: Pixels around the circumference.
        px_v: Pixels across (tread plus sidewall strip).
        marker_arc: Angular width of the white correction marker [rad].
        grousers: Number of grouser bars around the wheel.
        seed: Random seed of the speckle that optical flow tracks.

    Returns:
        RGB image (px_v, px_u, 3) uint8; row index is v, column index is u.
    """
    rng = np.random.default_rng(seed)
    tread_rows = int(round(0.75 * px_v))
    # speckle a few millimetres across (6 to 40 texels of 1.4 mm): resolved by the fisheye at
    # half a metre, so tracking does not feed on aliased detail
    noise = periodic_noise(px_u, rng, 1.0, 6.0, 40.0)[:tread_rows, :]
    g = 100 + 38 * noise
    u = (np.arange(px_u) + 0.5) / px_u
    # grousers at irregular spacing, so that the tread has no period for tracking to lock onto
    edges = (np.arange(grousers) + rng.uniform(-0.3, 0.3, grousers)) / grousers
    width = 0.22 / grousers * rng.uniform(0.8, 1.2, grousers)
    bars = np.zeros(px_u)
    for e, wd in zip(edges, width, strict=True):
        bars[((u - e) % 1.0) < wd] = 1.0
    g = g * (1 - 0.4 * bars[None, :])
    img = _to_rgb(g, (0.95, 0.95, 1.0))
    half = marker_arc / (2 * np.pi) / 2
    cols = np.abs(u - 0.5) <= half
    img[:, cols, :] = 250
    side = np.full((px_v - tread_rows, px_u, 3), 70, np.uint8)
    return np.concatenate([img, side], axis=0)


def cache_dir() -> Path:
    """Folder for generated assets: ``$ROVER_CACHE_DIR`` or ``~/.cache/rover_env``."""
    root = os.environ.get("ROVER_CACHE_DIR") or os.path.join(os.path.expanduser("~"), ".cache", "rover_env")
    path = Path(root)
    path.mkdir(parents=True, exist_ok=True)
    return path


def write_cached(key: str, make: Callable[[], np.ndarray], suffix: str = ".png") -> Path:
    """Write ``make()`` (an RGB image) to the cache under a hash of ``key`` once; return the path.

    The write is atomic (temporary file + rename), so parallel workers never see a partial file.
    """
    digest = hashlib.sha1(key.encode()).hexdigest()[:16]
    path = cache_dir() / f"{digest}{suffix}"
    if path.is_file() and cv2.imread(str(path), cv2.IMREAD_COLOR) is None:
        log.warning("cached texture %s does not decode (truncated or corrupt); rebuilding it", path)
        path.unlink(missing_ok=True)
    if not path.is_file():
        img = make()
        fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=suffix)
        os.close(fd)
        if not cv2.imwrite(tmp, np.ascontiguousarray(img[..., ::-1])):
            os.unlink(tmp)
            raise OSError(f"could not write texture to {tmp}")
        os.replace(tmp, path)
        log.debug("generated %s -> %s", key, path)
    return path


def read_texture(path) -> np.ndarray:
    """The RGB uint8 image (H, W, 3) of a texture file (8-bit; grey and alpha are dropped to RGB).

    Raises:
        ConfigError: The file does not exist or is not a readable image; the message names it.
    """
    from perception.models.validation import ConfigError, image_file_size

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"terrain.texture: {p} does not exist; give an image file or a preset name")
    try:
        image_file_size(p)  # the size from the header, before any decoding
    except ValueError as exc:
        raise ConfigError(f"terrain.texture: {exc}") from None
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise ConfigError(
            f"terrain.texture: {p} is not a readable image (PNG, JPEG, ...); "
            "give an image file or a preset name"
        )
    return np.ascontiguousarray(img[..., ::-1])


def texture_file(name: str, px: int = 1024, seed: int = 0) -> Path:
    """Path of the PNG for ground texture ``name`` (generated and cached on first use)."""
    return write_cached(f"ground:{name}:{px}:{seed}:v1", lambda: ground_texture(name, px, seed))

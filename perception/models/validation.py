"""Checks of configuration values shared by every package: one error type, one range check."""

from __future__ import annotations

import math

import numpy as np


class ConfigError(ValueError):
    """A configuration value or file is invalid. The message names the key and what to do."""


def not_a_number(value: object) -> str:
    """Why ``value`` is not a real number as a configuration value, or "" if it is one.

    Real numbers are Python and NumPy integers and floats. A bool (YAML ``true``), a string
    (YAML reads ``inf`` or ``1e-3`` without a dot before the e as text) or None is not one,
    even where Python would convert it.
    """
    import numbers

    if isinstance(value, bool | np.bool_):
        return f"{value!r} is a true/false value, not a number"
    if isinstance(value, str):
        hint = (
            " (YAML writes infinity as .inf)"
            if value.strip().lower().lstrip("+-") in ("inf", "infinity")
            else ""
        )
        return f"{value!r} is text, not a number{hint}"
    if not isinstance(value, numbers.Real):
        return f"{value!r} is not a number"
    return ""


def real_number(key: str, value: object, allow_inf: bool = False) -> float:
    """``value`` as a float, or :class:`ConfigError` naming ``key`` if it is not a real number.

    Args:
        key: The value's key path, for the message.
        value: The value read from a file or given by a caller.
        allow_inf: Accept +-infinity (NaN never).
    """
    why = not_a_number(value)
    if why:
        raise ConfigError(f"{key}: expected a number, got {why}")
    v = float(value)  # type: ignore[arg-type]
    if math.isnan(v) or (math.isinf(v) and not allow_inf):
        raise ConfigError(f"{key}: must be finite, got {value!r}")
    return v


def check_range(
    key: str,
    value: float,
    lo: float | None = None,
    hi: float | None = None,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
) -> None:
    """Raise :class:`ConfigError` unless ``lo <= value <= hi`` (open bounds on request).

    Args:
        key: The field name used in the message.
        value: The value to check; NaN and infinities are always rejected.
        lo: Lower bound, or None.
        hi: Upper bound, or None.
        lo_open: Exclude ``lo`` itself.
        hi_open: Exclude ``hi`` itself.
    """
    why = not_a_number(value)
    if why:
        raise ConfigError(f"{key}: expected a number, got {why}")
    if not math.isfinite(value):
        raise ConfigError(f"{key}: must be a finite number, got {value!r}")
    bad_lo = lo is not None and (value <= lo if lo_open else value < lo)
    bad_hi = hi is not None and (value >= hi if hi_open else value > hi)
    if bad_lo or bad_hi:
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        lo_s = "-inf" if lo is None else f"{lo:g}"
        hi_s = "inf" if hi is None else f"{hi:g}"
        raise ConfigError(f"{key}: {value!r} is out of range {left}{lo_s}, {hi_s}{right}")


#: Most pixels an image file may hold before it is decoded (a memory budget: 64 Mpx is 192 MB
#: as 8-bit RGB; a 1 kB file can claim 100,000 x 100,000 px).
MAX_IMAGE_PIXELS = 8192 * 8192


def image_file_size(path, max_pixels: int = MAX_IMAGE_PIXELS) -> tuple[int, int] | None:
    """(width, height) [px] of an image file from its header, without decoding it.

    Returns None when the header is not an image's. Raises ValueError (naming the file and the
    numbers) when the image exceeds ``max_pixels``, before any memory is spent on it.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as img:
            w, h = img.size
    except Image.DecompressionBombError as exc:  # Pillow's own limit, beyond ours
        raise ValueError(f"{path}: beyond the {max_pixels:,}-pixel budget for one image ({exc})") from None
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    if w * h > max_pixels:
        raise ValueError(
            f"{path}: {w} x {h} px is beyond the {max_pixels:,}-pixel budget for one image; scale it down"
        )
    return int(w), int(h)


def read_yaml(path, error: type[ConfigError] = ConfigError, what: str = "file"):
    """The YAML document in ``path``: the one reader of every configuration and calibration file.

    Args:
        path: The file.
        error: The :class:`ConfigError` (sub)class to raise.
        what: What the file is, for the message (``"calibration file"``).

    Raises:
        error: The file is missing, unreadable, not UTF-8 (the byte and offset named) or not
            YAML (the line named); every message starts with the file.
    """
    from pathlib import Path

    import yaml

    p = Path(path)
    if p.is_dir():
        raise error(f"{p}: a folder, not a {what}; give the YAML file's path")
    if not p.is_file():
        raise error(f"{p}: {what} not found")
    try:
        return yaml.safe_load(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise error(
            f"{p}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset {exc.start}); save it as UTF-8"
        ) from None
    except yaml.YAMLError as exc:
        raise error(f"{p}: not valid YAML: {' '.join(str(exc).split())}") from None
    except OSError as exc:
        raise error(f"{p}: not readable ({exc.strerror or exc})") from None

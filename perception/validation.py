"""Checks of configuration values shared by every package: one error type, one range check."""

from __future__ import annotations

import math


class ConfigError(ValueError):
    """A configuration value or file is invalid. The message names the key and what to do."""


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

"""Strict reading and writing of camera calibration YAML files.

Every error names the file and the key, and says what was expected, so that a user can fix a
hand-edited calibration without reading the code.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from perception.models.validation import ConfigError, not_a_number, read_yaml


class CalibrationError(ConfigError):
    """A calibration file or value is missing, malformed or physically impossible."""


def read_mapping(
    path: str | Path, required: set[str], optional: set[str], what: str = "calibration file"
) -> dict[str, Any]:
    """Load a YAML mapping and check its keys (``what`` the file is, for the messages).

    Raises:
        CalibrationError: The file is missing or unreadable, is not a mapping, lacks a required
            key or has an unknown one (the message names it and lists the accepted keys).
    """
    p = Path(path)
    data = read_yaml(p, CalibrationError, what)
    if not isinstance(data, dict):
        raise CalibrationError(f"{p}: expected a mapping of keys at the top level")
    missing = sorted(required - data.keys(), key=str)
    if missing:
        raise CalibrationError(f"{p}: missing key {missing[0]!r} (required: {sorted(required)})")
    unknown = sorted(data.keys() - required - optional, key=str)
    if unknown:
        raise CalibrationError(f"{p}: unknown key {unknown[0]!r} (accepted: {sorted(required | optional)})")
    return data


def as_array(value: Any, shape: tuple[int, ...], key: str, where: str = "") -> np.ndarray:
    """Convert ``value`` to a finite float array of ``shape`` or raise naming ``key``.

    A dimension of -1 in ``shape`` accepts any length.
    """
    prefix = f"{where}: " if where else ""
    why = _not_numbers(value)
    if why:
        raise CalibrationError(f"{prefix}{key}: expected numbers, got {value!r} ({why})")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{prefix}{key}: expected numbers, got {value!r}") from exc
    ok = arr.ndim == len(shape) and all(s in (-1, n) for s, n in zip(shape, arr.shape))
    if not ok:
        want = "x".join("N" if s == -1 else str(s) for s in shape)
        raise CalibrationError(f"{prefix}{key}: expected shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{prefix}{key}: contains NaN or infinite values")
    return arr


def _not_numbers(value: Any) -> str:
    """Why ``value`` (a number or nested lists of them) holds something that is not a real number, or ""."""
    if isinstance(value, np.ndarray):
        return "" if value.dtype.kind in "iuf" else f"an array of {value.dtype}"
    if isinstance(value, list | tuple):
        for v in value:
            why = _not_numbers(v)
            if why:
                return why
        return ""
    return not_a_number(value)


#: Lengths of the distortion vectors the pinhole camera models: ROS's plumb_bob (4 or 5) and
#: rational_polynomial (8), OpenCV's 5- and 8-coefficient models.
DISTORTION_LENGTHS = (4, 5, 8)


def check_distortion(value: Any, key: str = "distortion", where: str = "") -> np.ndarray:
    """Validate a distortion vector: (k1, k2, p1, p2[, k3]) or (k1, k2, p1, p2, k3, k4, k5, k6).

    Returns 5 coefficients (4 are padded with k3 = 0; 8 whose k4..k6 are zero are the plain
    model) or 8. Other lengths (OpenCV's 12- and 14-coefficient thin-prism and tilt models)
    are refused by name, never truncated.
    """
    prefix = f"{where}: " if where else ""
    arr = as_array(value, (-1,), key, where)
    if arr.size not in DISTORTION_LENGTHS:
        raise CalibrationError(
            f"{prefix}{key}: {arr.size} coefficients; give 5 (k1, k2, p1, p2, k3: plumb_bob) or 8 (k1, k2, "
            "p1, p2, k3, k4, k5, k6: rational_polynomial). The 12- and 14-coefficient models (thin prism, "
            "tilted sensor) are not modelled: rectify the images first"
        )
    if arr.size == 4:
        arr = np.r_[arr, 0.0]
    if arr.size == 8 and not np.any(arr[5:]):
        arr = arr[:5]
    return arr


def check_image_size(value: Any, key: str = "image_size", where: str = "") -> tuple[int, int]:
    """Validate ``[W, H]`` in pixels (16 to 8192 each)."""
    prefix = f"{where}: " if where else ""
    arr = as_array(value, (2,), key, where)
    if not np.all(arr == np.round(arr)) or arr.min() < 16 or arr.max() > 8192:
        raise CalibrationError(f"{prefix}{key}: expected two integers [W, H] in 16..8192, got {value!r}")
    return int(arr[0]), int(arr[1])


def check_rigid(T: np.ndarray, key: str, where: str = "") -> np.ndarray:
    """Validate a 4x4 rigid transform: orthonormal rotation with det +1 and last row 0 0 0 1."""
    prefix = f"{where}: " if where else ""
    T = as_array(T, (4, 4), key, where)
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise CalibrationError(f"{prefix}{key}: last row must be [0, 0, 0, 1]")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not math.isclose(
        np.linalg.det(R), 1.0, abs_tol=1e-6
    ):
        raise CalibrationError(f"{prefix}{key}: the 3x3 block is not a rotation (orthonormal, det +1)")
    return T


def write_mapping(path: str | Path, data: dict[str, Any]) -> Path:
    """Write ``data`` as block-style YAML (numpy arrays become nested lists)."""

    def plain(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            return v.tolist()
        if isinstance(v, (np.floating, np.integer)):
            return v.item()
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(yaml.safe_dump({k: plain(v) for k, v in data.items()}, sort_keys=False))
    return p

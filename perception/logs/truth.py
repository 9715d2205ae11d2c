"""The ground truth beside a recorded log, and the errors of an estimator's replay against it.

``rover record`` writes, beside its log, ``truth.csv``: one row per control step of the mission
with the time on the log's clock and the true state under the estimate's names
(:data:`TRUTH_COLUMNS`): the planar pose (x, y [m], yaw [rad], world frame), the height z [m],
the body's roll and pitch [rad], and every state field of
:data:`perception.estimator.STATE_ESTIMATES` that has a truth (twist, wheel rates, slip ratios
and angles, axle roll, height and steering). ``rover replay LOG --rig RIG --truth truth.csv``
scores what an estimator returned against it (:func:`score`): per field, over the ticks where
the estimator returned it, the truth taken at the tick's time on the log's clock.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from perception.models.drive_geometry import AXLES, WHEELS
from perception.models.validation import ConfigError

#: The columns of ``truth.csv``: the log's time [s], the pose, then the state under the estimate's names.
TRUTH_COLUMNS: tuple[str, ...] = (
    "t_log",
    "x",
    "y",
    "yaw",
    "z",
    "roll",
    "pitch",
    "v_x",
    "v_y",
    "omega",
    *(f"wheel_rate_{w}" for w in WHEELS),
    *(f"slip_{w}" for w in WHEELS),
    *(f"slip_angle_{w}" for w in WHEELS),
    *(f"axle_roll_{a}" for a in AXLES),
    *(f"axle_height_{a}" for a in AXLES),
    *(f"steering_{a}" for a in AXLES),
)
#: The fields :func:`score` compares (those of both the truth and an estimate, on one reference).
SCORED: tuple[str, ...] = tuple(c for c in TRUTH_COLUMNS if c not in ("t_log", "z"))
#: Fields that are angles: compared modulo a turn.
_ANGLES = frozenset(("yaw", "roll", "pitch"))
_UNITS = {
    "x": "m", "y": "m", "yaw": "rad", "roll": "rad", "pitch": "rad", "v_x": "m/s", "v_y": "m/s",
    "omega": "rad/s", "wheel_rate": "rad/s", "slip": "1", "slip_angle": "rad", "axle_roll": "rad",
    "axle_height": "m", "steering": "rad",
}  # fmt: skip


def unit_of(name: str) -> str:
    """The unit of a truth column."""
    if name in _UNITS:
        return _UNITS[name]
    return _UNITS.get(name.rsplit("_", 1)[0], "")


def write_truth(path: str | Path, rows: Sequence[Mapping[str, float]]) -> Path:
    """Write ``truth.csv``: one row per mapping of :data:`TRUTH_COLUMNS` (every column required)."""
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(TRUTH_COLUMNS)
        for r in rows:
            out.writerow([f"{r['t_log']:.9f}", *(repr(float(r[c])) for c in TRUTH_COLUMNS[1:])])
    return Path(path)


def read_truth(path: str | Path) -> dict[str, np.ndarray]:
    """``truth.csv`` as columns (float arrays), checked.

    Raises:
        ConfigError: Not readable, a missing or unknown column, a value that is not a number, or
            times that are not finite and increasing (the message names the file, row and column).
    """
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not a readable truth file ({exc})") from None
    if not rows:
        raise ConfigError(f"{path}: empty; a truth file has the header {', '.join(TRUTH_COLUMNS)}")
    header = [c.strip() for c in rows[0]]
    missing = [c for c in TRUTH_COLUMNS if c not in header]
    if missing:
        raise ConfigError(
            f"{path}: no column {missing[0]!r}; a truth file (rover record) has {list(TRUTH_COLUMNS)}"
        )
    out: dict[str, list[float]] = {c: [] for c in TRUTH_COLUMNS}
    where = {c: header.index(c) for c in TRUTH_COLUMNS}
    for k, row in enumerate(rows[1:], start=2):
        for c, i in where.items():
            try:
                out[c].append(float(row[i]))
            except (IndexError, ValueError):
                cell = row[i] if i < len(row) else "(none)"
                raise ConfigError(f"{path}: row {k}, column {c}: {cell!r} is not a number") from None
    data = {c: np.asarray(v, dtype=np.float64) for c, v in out.items()}
    t = data["t_log"]
    if len(t) < 2 or not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
        raise ConfigError(f"{path}: t_log must hold two or more finite, increasing times [s]")
    return data


@dataclass(frozen=True)
class FieldError:
    """An estimate's error in one field against the truth.

    Attributes:
        name: The field. unit: Its unit. n: Ticks compared (the estimator returned it, the truth
        covers the time). mae: Mean absolute error. p95: 95th percentile. max: Largest.
    """

    name: str
    unit: str
    n: int
    mae: float
    p95: float
    max: float


def score(
    estimates: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], skip: float = 0.0
) -> list[FieldError]:
    """Per field of :data:`SCORED`, the estimate's errors against the truth at the same log times.

    Args:
        estimates: Columns of a replay's ``estimates.csv`` (``t_log`` and the fields; NaN where
            the estimator returned nothing).
        truth: :func:`read_truth`'s columns.
        skip: Ticks within this of the first one [s] are not scored (the filters' start-up).

    Returns:
        One :class:`FieldError` per field; a field never estimated has n = 0 and NaN errors.
    """
    t = np.asarray(estimates["t_log"], dtype=np.float64)
    tt = truth["t_log"]
    start = t[0] + skip if len(t) else 0.0
    inside = (t >= tt[0] - 1e-6) & (t <= tt[-1] + 1e-6) & (t >= start - 1e-9)
    out = []
    for name in SCORED:
        est = np.asarray(estimates.get(name, np.full(len(t), math.nan)), dtype=np.float64)
        ref = truth[name]
        if name in _ANGLES:
            ref = np.unwrap(ref)
        at = np.interp(t, tt, ref)
        err = est - at
        if name in _ANGLES:
            err = (err + math.pi) % (2 * math.pi) - math.pi
        err = np.abs(err[inside & np.isfinite(err)])
        if err.size:
            out.append(FieldError(name, unit_of(name), int(err.size), float(err.mean()),
                                  float(np.percentile(err, 95)), float(err.max())))  # fmt: skip
        else:
            out.append(FieldError(name, unit_of(name), 0, math.nan, math.nan, math.nan))
    return out


def errors_table(errors: Sequence[FieldError]) -> str:
    """``errors.csv``'s text: field, unit, n, mae, p95, max (an unestimated field's figures empty)."""
    lines = ["field,unit,n,mae,p95,max"]
    for e in errors:
        figures = ("", "", "") if e.n == 0 else (f"{e.mae:.6g}", f"{e.p95:.6g}", f"{e.max:.6g}")
        lines.append(",".join([e.name, e.unit, str(e.n), *figures]))
    return "\n".join(lines) + "\n"


def read_estimates(path: str | Path) -> dict[str, np.ndarray]:
    """A replay's ``estimates.csv`` as float columns (NaN where a cell is empty)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        return {}
    return {c: np.array([float(r[c]) if r[c] else math.nan for r in rows]) for c in rows[0]}

"""Side-by-side table of two ``rover eval`` summaries (``summary.csv``): before and after a change.

Per mission and controller: success rate, time of the successful runs, the true goal error (where
the rover ended, from the judge) and the dead-reckoning error at the end, old -> new.

Run: python benchmarks/compare_summaries.py OLD/summary.csv NEW/summary.csv
"""

from __future__ import annotations

import argparse
import csv
import math


def _read(path: str) -> dict[tuple[str, str], dict[str, str]]:
    with open(path, newline="") as fh:
        return {(r["mission"], r["controller"]): r for r in csv.DictReader(fh)}


def _num(row: dict[str, str] | None, key: str) -> float:
    if row is None or not row.get(key):
        return math.nan
    try:
        return float(row[key])
    except ValueError:
        return math.nan


def _fmt(v: float, pct: bool = False, digits: int = 2) -> str:
    if not math.isfinite(v):
        return "–"
    return f"{100 * v:.0f} %" if pct else f"{v:.{digits}f}"


def side_by_side(old: dict, new: dict) -> str:
    """Markdown table: one row per (mission, controller) in ``new``, old -> new values."""
    lines = [
        "| mission | controller | success | time [s] | true goal error [m] | dead-reckoning error [m] |",
        "|---|---|---|---|---|---|",
    ]
    for key, row in new.items():
        was = old.get(key)
        cells = []
        for col, pct, digits in (
            ("success", True, 0),
            ("time", False, 1),
            ("goal_error", False, 2),
            ("est_position_error_final", False, 2),
        ):
            cells.append(f"{_fmt(_num(was, col), pct, digits)} → {_fmt(_num(row, col), pct, digits)}")
        lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old")
    ap.add_argument("new")
    args = ap.parse_args(argv)
    print(side_by_side(_read(args.old), _read(args.new)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Slip events in closed loop, per controller and mission, from a ``rover eval`` sweep's ``results.csv``.

Recall is the true events caught over the true events; false events and events "in band" (on
true slip that rose above 0.15 but made no true event) are per run. A second table pools every
controller's runs per mission and over the sweep into the F1 score. The scoring is
``rover_env.tools.estimator_metrics.slip_metrics`` (hysteresis band, two frames of grace), as
``rover eval`` applies it to each estimated-observation run.

Run: ``python benchmarks/slip_events_table.py OUT/results.csv`` after, for example,
``rover eval --controllers slip_unaware@imu slip_aware@imu slip_unaware slip_aware --missions
Rover-v0 RoverRoughSlippery-v0 RoverSlopeLoose-v0 --seeds 100-109 --workers 2 --camera-effects
field --randomize off --out OUT``.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict


def table(path: str) -> list[str]:
    """The Markdown rows of the slip-event table of the sweep whose ``results.csv`` is ``path``."""
    with open(path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("obs_source") == "estimated"]
    if not rows:
        raise ValueError(f"{path}: no estimated-observation runs (slip events are scored on those only)")
    groups: dict[tuple[str, str], list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["controller"], r["mission"])].append(r)
    out = [
        "| controller | mission | runs | success | true events | caught | recall "
        "| false events / run | in band / run |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for (controller, mission), rs in sorted(groups.items()):
        n = len(rs)
        events = sum(int(float(r["est_slip_events"])) for r in rs)
        caught = sum(int(float(r["est_slip_events_matched"])) for r in rs)
        false = sum(float(r["est_slip_events_false"]) for r in rs)
        band = sum(float(r["est_slip_events_in_band"]) for r in rs)
        success = sum(r["success"] == "True" for r in rs) / n
        recall = f"{caught / events:.2f}" if events else "–"
        out.append(
            f"| {controller} | `{mission}` | {n} | {success:.0%} | {events} | {caught} | {recall} "
            f"| {false / n:.2f} | {band / n:.2f} |"
        )
    return out


def f1_table(path: str) -> list[str]:
    """Markdown rows of the slip-event F1 per mission and over the sweep, every controller's runs pooled.

    F1 = 2 caught / (2 caught + false events + missed events); events in band count on neither side.
    """
    with open(path, newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("obs_source") == "estimated"]
    if not rows:
        raise ValueError(f"{path}: no estimated-observation runs (slip events are scored on those only)")
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        groups[f"`{r['mission']}`"].append(r)
    groups["all missions"] = rows
    out = ["| missions | runs | true events | caught | false events | F1 |", "|---|---:|---:|---:|---:|---:|"]
    for name, rs in groups.items():
        events = sum(int(float(r["est_slip_events"])) for r in rs)
        caught = sum(int(float(r["est_slip_events_matched"])) for r in rs)
        false = sum(float(r["est_slip_events_false"]) for r in rs)
        den = 2 * caught + false + (events - caught)
        f1 = f"{2 * caught / den:.3f}" if den else "–"
        out.append(f"| {name} | {len(rs)} | {events} | {caught} | {false:g} | {f1} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", help="a rover eval sweep's results.csv")
    args = ap.parse_args(argv)
    print("\n".join(table(args.results)))
    print()
    print("\n".join(f1_table(args.results)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The closed-loop slip-event table of ``benchmarks/slip_events_table.py`` against counts made by hand."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import slip_events_table  # noqa: E402

FIELDS = (
    "controller", "mission", "obs_source", "success", "est_slip_events", "est_slip_events_matched",
    "est_slip_events_false", "est_slip_events_in_band",
)  # fmt: skip


def _write(path: Path, rows: list[tuple]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(FIELDS)
        w.writerows(rows)


def test_recall_and_false_events_per_run_are_pooled_over_a_controllers_runs(tmp_path):
    path = tmp_path / "results.csv"
    _write(
        path,
        [
            ("slip_unaware", "Rover-v0", "estimated", "True", 3, 3, 1, 0),
            ("slip_unaware", "Rover-v0", "estimated", "False", 2, 1, 0, 2),
            ("slip_aware", "Rover-v0", "estimated", "True", 0, 0, 2, 1),
            ("slip_aware", "Rover-v0", "ground_truth", "True", 0, 0, 0, 0),  # no estimates: left out
        ],
    )
    rows = slip_events_table.table(str(path))
    assert rows[2] == "| slip_aware | `Rover-v0` | 1 | 100% | 0 | 0 | – | 2.00 | 1.00 |"
    # 4 of 5 true events caught; 1 false event and 2 in band over 2 runs
    assert rows[3] == "| slip_unaware | `Rover-v0` | 2 | 50% | 5 | 4 | 0.80 | 0.50 | 1.00 |"


def test_a_sweep_without_estimated_runs_is_refused(tmp_path):
    path = tmp_path / "results.csv"
    _write(path, [("slip_aware", "Rover-v0", "ground_truth", "True", 0, 0, 0, 0)])
    with pytest.raises(ValueError, match="no estimated-observation runs"):
        slip_events_table.table(str(path))


def test_the_f1_pools_every_controller_per_mission_and_over_the_sweep(tmp_path):
    path = tmp_path / "results.csv"
    _write(
        path,
        [
            ("slip_unaware", "Rover-v0", "estimated", "True", 3, 3, 1, 0),
            ("slip_aware", "Rover-v0", "estimated", "True", 0, 0, 2, 1),
            ("slip_unaware", "RoverSlopeLoose-v0", "estimated", "False", 4, 2, 0, 0),
        ],
    )
    rows = slip_events_table.f1_table(str(path))
    # Rover-v0: 3 caught, 3 false, 0 missed: 6 / 9; the slope: 2 caught, 2 missed: 4 / 6; all: 10 / 15
    assert rows[2] == "| `Rover-v0` | 2 | 3 | 3 | 3 | 0.667 |"
    assert rows[3] == "| `RoverSlopeLoose-v0` | 1 | 4 | 2 | 0 | 0.667 |"
    assert rows[4] == "| all missions | 3 | 7 | 5 | 3 | 0.667 |"

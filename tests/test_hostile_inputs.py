"""Hostile and careless input: each case gets a one-line error naming the input, or a flagged
result, never a traceback, a silently wrong answer or lost work."""

from __future__ import annotations

import pytest

from rover_env.cli import build_parser


def _cli_error(capsys, argv: list[str]) -> str:
    """The one-line error argparse prints for ``argv`` (exit status 2)."""
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(argv)
    assert exc.value.code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "error:" in ln]
    assert len(lines) == 1
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["eval", "--out", "o", "--seeds", "5-2"], ["--seeds", "'5-2'", "empty range"]),
        (["eval", "--out", "o", "--seeds", "0-100000000"], ["--seeds", "100000001 seeds", "10000"]),
        (["eval", "--out", "o", "--seeds", "x"], ["--seeds", "N or N-M"]),
        (["eval", "--out", "o", "--workers", "0"], ["--workers", "from 1 to"]),
        (["eval", "--out", "o", "--workers", "1000"], ["--workers", "1000"]),
        (["train", "--out", "o", "--eval-every", "0"], ["--eval-every", ">= 1"]),
        (["train", "--out", "o", "--eval-every", "-5"], ["--eval-every", ">= 1"]),
        (["train", "--out", "o", "--steps", "0"], ["--steps"]),
        (["train", "--out", "o", "--reward", "foo=1"], ["--reward", "'foo'", "slip"]),
        (["train", "--out", "o", "--reward", "slip=nan"], ["--reward", "0 to 1e6"]),
        (["train", "--out", "o", "--reward", "slip"], ["--reward", "TERM=NUMBER"]),
        (["bench", "--steps", "0"], ["--steps", "from 1"]),
        (["demo", "--out", "o", "--seed", "-1"], ["--seed", "from 0"]),
        (["odometry", "imgs", "--calib", "c.yaml", "--out", "o", "--fps", "1e300"], ["--fps", "1e300"]),
        (["odometry", "imgs", "--calib", "c.yaml", "--out", "o", "--fps", "0"], ["--fps", "above 0"]),
        (["kinematics", "imgs", "--camera", "c", "--rover", "r", "--out", "o", "--fps", "nan"], ["--fps"]),
    ],
)
def test_cli_rejects_out_of_range_arguments(capsys, argv, names):
    msg = _cli_error(capsys, argv)
    for name in names:
        assert name in msg, msg


def test_cli_accepts_the_edges():
    p = build_parser()
    assert p.parse_args(["eval", "--out", "o", "--seeds", "3-3", "7"]).seeds == [[3], [7]]
    assert p.parse_args(["eval", "--out", "o", "--seeds", "0-9999"]).seeds[0][-1] == 9999
    assert p.parse_args(["train", "--out", "o", "--reward", "slip=5", "time=0"]).reward == [
        ("slip", 5.0),
        ("time", 0.0),
    ]
    assert p.parse_args(["eval", "--out", "o", "--workers", "1"]).workers == 1

"""The judge: named reward terms with weights, and the ordered table of termination reasons."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from rover_env.task.judge import REWARD_TERM_NAMES, TERMINATIONS, Judge, RewardConfig, StepFacts


def facts(**kw) -> StepFacts:
    gt = SimpleNamespace(
        t=1.0,
        slip_ratio=np.array([0.1, -0.3, 0.0, 0.2]),
        wheel_rate=np.array([2.0, 2.0, 1.0, 1.0]),  # [rad/s]
        wheel_v_long=np.array([0.2, 0.3, 0.1, 0.1]),  # [m/s]
        wheel_torque=np.array([1.0, -2.0, 0.5, 0.0]),  # [N m]
    )
    base = dict(gt=gt, progress_gain=0.05, cross_track=-0.4, heading_error=0.3, wheel_radius=0.1, dt=0.1,
                tipped=False, left_terrain=False, off_target=False, arrived=False)  # fmt: skip
    return StepFacts(**(base | kw))


def test_each_term_is_its_weight_times_its_measure_and_the_reward_their_sum():
    w = RewardConfig(slip_speed=0.5)
    v = Judge(w, duration=60.0)(facts())
    assert tuple(v.terms) == REWARD_TERM_NAMES == tuple(f.name for f in dataclasses.fields(RewardConfig))
    dt = 0.1
    expected = {
        "progress": 1.0 * 0.05,
        "cross_track": -0.2 * 0.4 * dt,
        "heading": -0.05 * 0.3 * dt,
        "slip": -0.5 * 0.15 * dt,  # mean |slip ratio|
        "slip_speed": -0.5 * np.mean([0.0, 0.1, 0.0, 0.0]) * dt,  # |omega r - v|
        "energy": -0.002 * (2.0 + 4.0 + 0.5) * dt,  # sum |torque * rate| [W]
        "time": -0.05 * dt,
        "success": 0.0,
        "failure": 0.0,
    }
    for name, value in expected.items():
        assert v.terms[name] == pytest.approx(value, abs=1e-15), name
    assert v.reward == pytest.approx(sum(expected.values()), abs=1e-15)
    assert (v.terminated, v.truncated, v.success, v.reason) == (False, False, False, None)
    # a zero weight switches its term off
    assert Judge(dataclasses.replace(w, energy=0.0), 60.0)(facts()).terms["energy"] == 0.0


@pytest.mark.parametrize(
    ("flags", "reason"),
    [
        ({"tipped": True, "left_terrain": True, "off_target": True, "arrived": True}, "tipped_over"),
        ({"left_terrain": True, "off_target": True, "arrived": True}, "left_terrain"),
        ({"off_target": True, "arrived": True}, "off_target"),
        ({"arrived": True}, "success"),
        ({"tipped": True}, "tipped_over"),
    ],
)
def test_the_first_termination_reason_that_holds_names_the_end(flags, reason):
    w = RewardConfig()
    v = Judge(w, duration=60.0)(facts(**flags))
    assert v.reason == reason and v.terminated and not v.truncated
    assert v.success == (reason == "success")
    assert v.terms["success"] == (w.success if reason == "success" else 0.0)
    assert v.terms["failure"] == (-w.failure if reason != "success" else 0.0)


def test_the_table_is_in_its_documented_order():
    assert [(r.name, r.failure) for r in TERMINATIONS] == [
        ("tipped_over", True),
        ("left_terrain", True),
        ("stuck", True),
        ("off_target", True),
        ("success", False),
    ]


def test_the_duration_truncates_an_episode_that_no_reason_ended():
    judge = Judge(RewardConfig(), duration=1.0)
    v = judge(facts())  # t = 1.0 s
    assert (v.terminated, v.truncated, v.reason) == (False, True, "time_limit")
    v = judge(facts(arrived=True))  # success at the last instant is success, not a time limit
    assert (v.terminated, v.truncated, v.reason) == (True, False, "success")
    assert Judge(RewardConfig(), duration=2.0)(facts()).truncated is False


def test_stuck_ends_an_episode_as_a_failure_before_the_goal_counts():
    judge = Judge(RewardConfig(), duration=10.0)
    v = judge(facts(stuck=True, arrived=True))
    assert (v.terminated, v.reason, v.success) == (True, "stuck", False)
    assert judge(facts(stuck=False)).reason is None

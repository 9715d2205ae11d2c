"""The judge's optional "stuck" end: a rover spinning its wheels in place."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import flat_scenario

from rover_env.config.io import ConfigError
from rover_env.envs import RoverEnv


def _env(stuck_after, mu=0.05):
    sc = dataclasses.replace(flat_scenario(mu=mu), stuck_after=stuck_after, duration=8.0)
    return RoverEnv(scenario=sc, obs_source="ground_truth", action_mode="wheels")


def test_a_rover_spinning_in_place_is_stuck_after_the_scenarios_window():
    env = _env(2.0)
    try:
        env.reset(seed=0)
        # on ice with the wheels at full speed against each other: the treads turn, the body stays
        action = np.array([1.0, -1.0, 1.0, -1.0, 0.0, 0.0], dtype=np.float32)
        ends = []
        for k in range(240):
            _, _, term, trunc, info = env.step(action)
            if term or trunc:
                ends.append((k, info["termination"]))
                break
        assert ends and ends[0][1] == "stuck"
        assert 2.0 <= (ends[0][0] + 1) * env.control_dt <= 2.5
    finally:
        env.close()


def test_without_the_key_a_rover_is_never_stuck():
    env = _env(None)
    try:
        env.reset(seed=0)
        action = np.array([1.0, -1.0, 1.0, -1.0, 0.0, 0.0], dtype=np.float32)
        for _ in range(90):
            _, _, term, trunc, info = env.step(action)
            assert info["termination"] != "stuck"
    finally:
        env.close()


def test_stuck_after_is_checked():
    with pytest.raises(ConfigError, match="stuck_after"):
        dataclasses.replace(flat_scenario(), stuck_after=0.0)

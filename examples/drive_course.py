"""Drive the default course with the pure-pursuit controller and print what happened."""

import gymnasium as gym
import numpy as np

import rover_env  # noqa: F401  (registers Rover-v0)
from controllers import PurePursuit
from perception.observation import OBS_FIELDS


def run(max_steps: int = 3000, seed: int = 0) -> dict:
    env = gym.make("Rover-v0", scenario="flat_patches")
    ctrl = PurePursuit(OBS_FIELDS)
    obs, info = env.reset(seed=seed)
    slip = []
    for _ in range(max_steps):
        obs, reward, terminated, truncated, info = env.step(ctrl.act(obs))
        slip.append(np.abs(info["ground_truth"]["slip_ratio"]).max())
        if terminated or truncated:
            break
    env.close()
    return {
        "t": info["t"],
        "success": info["is_success"],
        "progress_m": info["progress"],
        "max_slip": float(np.max(slip)),
    }


if __name__ == "__main__":
    print(run())

"""The environments behave as they did when the baseline was recorded: the same rollouts.

For every registered id (``rover_env.ENV_IDS``), in both observation sources, and with an IMU
on the estimated one, a 60-step rollout from a fixed seed and fixed actions gives the same
observations, rewards, ground truth and estimates as the recorded baseline
(``tests/data/rollouts_baseline.npz``).
Refactoring the package must not move them by more than the last bits that the float libraries
below it leave to their versions: within 1e-6 (absolute and relative). A fresh install with
NumPy 2.4 and OpenCV 5.0 moved the true state by at most 6e-16 from the values recorded with
earlier versions, and the estimates, whose filters amplify it, by at most 1.1e-7; a change of
behaviour moves them by orders of magnitude more. The
cameras are drawn with PyBullet's TinyRenderer (compiled code, the same on any CPU; llvmpipe's
JIT may differ between CPUs).

Re-record (only when a behaviour change is intended and explained):

    python tests/test_same_behaviour.py --record

A newly registered id is added to the baseline, the recorded cases left as they are, with:

    python tests/test_same_behaviour.py --record-missing
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

BASELINE = Path(__file__).parent / "data" / "rollouts_baseline.npz"
STEPS = 60
TOL = 1e-6  # float libraries' last bits, amplified by the filters (see the module's docstring)
#: Every registered id (read without importing the package: the list is rover_env.ENV_IDS,
#: which a test below checks), each in both sources and with an IMU.
ENV_IDS = (
    "Rover-v0",
    "RoverRoughSlippery-v0",
    "RoverShadows-v0",
    "RoverSlopeLoose-v0",
    "RoverSlopeLoose-v1",
    "RoverSoftSand-v0",
)
CASES = [
    (env_id, source, imu)
    for env_id in ENV_IDS
    for source, imu in (("ground_truth", None), ("estimated", None), ("estimated", "bmi088"))
]


def _flat(prefix: str, value, out: dict) -> None:
    """Numbers of a nested info dict as flat float arrays keyed by their path."""
    if isinstance(value, dict):
        for k, v in value.items():
            _flat(f"{prefix}/{k}", v, out)
        return
    if value is None or isinstance(value, str):
        return
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return
    out[prefix] = arr


def rollout(env_id: str, source: str, imu: str | None) -> dict[str, np.ndarray]:
    """A 60-step rollout's observations, rewards and info numbers, stacked over the steps."""
    import gymnasium as gym

    import rover_env  # noqa: F401

    # TinyRenderer: the same bits on any CPU; the images as rendered (the baseline predates the
    # field cameras' default; their chain has its own tests in test_camera_effects.py)
    kwargs = {"obs_source": source, "renderer": "tiny"}
    if source == "estimated":
        kwargs["camera_effects"] = "ideal"
    if imu:
        kwargs["imu"] = imu
    env = gym.make(env_id, **kwargs)
    try:
        rng = np.random.default_rng(7)
        obs, info = env.reset(seed=11)
        steps: dict[str, list] = {}

        def add(key: str, value) -> None:
            steps.setdefault(key, []).append(np.asarray(value, dtype=np.float64))

        add("obs", obs)
        flat: dict = {}
        _flat("info", info, flat)
        for k, v in flat.items():
            add(f"reset/{k}", v)
        for _ in range(STEPS):
            action = rng.uniform(-1.0, 1.0, env.action_space.shape)
            action[0] = 0.3 + 0.5 * abs(action[0])  # mostly forward, so the rover drives somewhere
            obs, reward, terminated, truncated, info = env.step(action.astype(np.float32))
            add("obs", obs)
            add("reward", reward)
            add("done", float(terminated or truncated))
            flat = {}
            _flat("info", info, flat)
            for k, v in flat.items():
                add(k, v)
            if terminated or truncated:
                break
    finally:
        env.close()
    return {k: np.stack(v) for k, v in steps.items() if len({a.shape for a in v}) == 1}


def _key(env_id: str, source: str, imu: str | None) -> str:
    return f"{env_id}|{source}|{imu or 'none'}"


def record(missing_only: bool = False) -> None:
    data = {}
    if missing_only and BASELINE.exists():
        with np.load(BASELINE) as z:
            data = {k: z[k] for k in z.files}
    for case in CASES:
        if missing_only and any(k.startswith(f"{_key(*case)}::") for k in data):
            continue
        for k, v in rollout(*case).items():
            data[f"{_key(*case)}::{k}"] = v
        print(f"recorded {_key(*case)}")
    BASELINE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(BASELINE, **data)
    print(f"wrote {BASELINE} ({BASELINE.stat().st_size / 1e6:.1f} MB)")


def test_the_cases_cover_every_registered_id():
    import rover_env

    assert set(ENV_IDS) == set(rover_env.ENV_IDS)


@pytest.mark.parametrize(("env_id", "source", "imu"), CASES)
def test_a_fixed_rollout_matches_the_baseline(env_id, source, imu):
    if not BASELINE.exists():
        pytest.fail(f"{BASELINE} is missing; record it with: python {Path(__file__).name} --record")
    with np.load(BASELINE) as z:
        prefix = f"{_key(env_id, source, imu)}::"
        want = {k[len(prefix) :]: z[k] for k in z.files if k.startswith(prefix)}
    got = rollout(env_id, source, imu)
    assert want, f"no baseline for {prefix}"
    assert sorted(got) == sorted(want), set(got) ^ set(want)
    for k in sorted(want):
        np.testing.assert_allclose(
            got[k], want[k], rtol=TOL, atol=TOL, err_msg=f"{env_id} {source} {imu}: {k}"
        )


if __name__ == "__main__":
    if "--record-missing" in sys.argv:
        record(missing_only=True)
    elif "--record" in sys.argv:
        record()
    else:
        print(__doc__)

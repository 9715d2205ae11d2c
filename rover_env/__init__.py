"""PyBullet simulation of a four-wheel double-Ackermann planetary rover, as Gymnasium environments.

``import rover_env`` registers the environments listed in :data:`ENV_IDS`.
"""

from __future__ import annotations

from rover_env.config_io import ConfigError
from rover_env.geometry import WHEELS, RoverGeometry
from rover_env.scenario import ScenarioConfig, list_scenarios, load_scenario

__version__ = "0.1.0"

ENV_IDS: tuple[str, ...] = ("Rover-v0",)


def register_envs() -> None:
    """Register every id of :data:`ENV_IDS` with Gymnasium; calling it again does nothing."""
    import gymnasium

    for env_id in ENV_IDS:
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="rover_env.envs:RoverEnv",
            kwargs={"scenario": "flat_patches"},
            disable_env_checker=False,
        )


register_envs()

__all__ = [
    "ENV_IDS",
    "WHEELS",
    "ConfigError",
    "RoverGeometry",
    "ScenarioConfig",
    "list_scenarios",
    "load_scenario",
    "register_envs",
]

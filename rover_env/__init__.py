"""PyBullet simulation of a four-wheel double-Ackermann planetary rover, as Gymnasium environments.

``import rover_env`` registers the environments listed in :data:`ENV_IDS`.
"""

from __future__ import annotations


def _import_pybullet_quietly() -> None:
    """Import pybullet with its build banner ("pybullet build time: ...") kept off stdout."""
    import sys

    if "pybullet" in sys.modules:
        return
    from rover_env.sim._quiet import quiet_c_output

    with quiet_c_output():
        import pybullet  # noqa: F401


_import_pybullet_quietly()

from rover_env.config.io import ConfigError  # noqa: E402
from rover_env.config.scenario import ScenarioConfig, list_scenarios, load_scenario  # noqa: E402
from rover_env.sim.geometry import WHEELS, RoverGeometry  # noqa: E402

__version__ = "0.1.0"

#: Registered missions: id -> shipped scenario.
MISSIONS: dict[str, str] = {
    "Rover-v0": "flat_patches",  # flat, with low-friction patches (the default mission)
    "RoverRoughSlippery-v0": "rough_slippery",  # rough sand with loose-sand pockets
    "RoverShadows-v0": "shadow_heavy",  # low sun behind the rover, slip patches
    "RoverSlopeLoose-v0": "slope_loose",  # start up a loose-sand slope that gives way under spinning wheels
    "RoverSlopeLoose-v1": "slope_soil",  # the same climb on a deformable soil (terramechanics), no dig
    "RoverSoftSand-v0": "soft_sand",  # a hillside with loose-sand patches where the rover can get stuck
}

ENV_IDS: tuple[str, ...] = tuple(MISSIONS)


def register_envs() -> None:
    """Register every id of :data:`ENV_IDS` with Gymnasium; calling it again does nothing."""
    import gymnasium

    for env_id, scenario in MISSIONS.items():
        if env_id in gymnasium.registry:
            continue
        gymnasium.register(
            id=env_id,
            entry_point="rover_env.envs:RoverEnv",
            kwargs={"scenario": scenario},
            disable_env_checker=False,
        )


register_envs()

__all__ = [
    "ENV_IDS",
    "MISSIONS",
    "WHEELS",
    "ConfigError",
    "RoverGeometry",
    "ScenarioConfig",
    "list_scenarios",
    "load_scenario",
    "register_envs",
]

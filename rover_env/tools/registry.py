"""The named controllers of sweeps and demos: how each is built and which action mode it needs.

A name is ``<controller>`` (a key of :data:`CONTROLLERS`, or ``policy:<folder>``), optionally
with ``@<obs_source>`` (``@ground_truth``: drive on the simulator's state) or ``@imu`` /
``@imu:<preset>`` (drive on the estimates with an IMU on the rover).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast, get_args

from rover_env.envs.rover_env import ActionModeName


@dataclass(frozen=True)
class ControllerSpec:
    """How to build a named controller.

    Attributes:
        mode: The environment's action mode it needs, or a function that reads it (a saved
            policy's, from its folder).
        make: Builds the controller for an environment (``make(env)``).
        description: One line for listings.
    """

    mode: str | Callable[[], str]
    make: Callable
    description: str

    @property
    def action_mode(self) -> ActionModeName:
        """The environment's action mode the controller needs."""
        mode = self.mode() if callable(self.mode) else self.mode
        if mode not in get_args(ActionModeName):
            raise ValueError(f"action mode {mode!r}: use one of {list(get_args(ActionModeName))}")
        return cast(ActionModeName, mode)


def _slip_unaware(env):
    from controllers import PathFollower

    return PathFollower.for_env(env)


def _slip_aware(env):
    from controllers import SlipAwareController

    return SlipAwareController.for_env(env)


def _pure_pursuit(env):
    from controllers import PurePursuit, PurePursuitConfig

    base = env.unwrapped
    return PurePursuit(
        [f.name for f in base.obs_fields],
        PurePursuitConfig(cruise_speed=base.scenario.course.speed, v_max=base.v_max),
    )


def _shipped_policy_folder() -> Path:
    from controllers.rl import shipped_policy

    return shipped_policy()


def _policy_spec(folder: Callable[[], str | Path], description: str) -> ControllerSpec:
    """A saved policy's spec; ``folder()`` gives its folder, read only when the spec is used."""

    def make(env):
        from controllers.rl import PolicyController

        return PolicyController(folder(), env)

    def mode() -> str:
        from controllers.rl import policy_action_mode

        return policy_action_mode(folder())

    return ControllerSpec(mode, make, description)


#: Named controllers for sweeps.
CONTROLLERS: dict[str, ControllerSpec] = {
    "slip_unaware": ControllerSpec("drive", _slip_unaware, "path follower, no traction control"),
    "slip_aware": ControllerSpec("wheels", _slip_aware, "path follower with per-wheel traction control"),
    "pure_pursuit": ControllerSpec("drive", _pure_pursuit, "pure pursuit toward the next waypoint"),
    "ppo": _policy_spec(
        _shipped_policy_folder,
        "the shipped residual PPO policy (controllers/policies); trained with the BMI088: ppo@imu",
    ),
}
OBS_SOURCES = ("estimated", "ground_truth")


def controller_imu(name: str) -> str | None:
    """The IMU preset of ``name``: ``<controller>@imu`` (``bmi088``) or ``@imu:<preset>``; else None."""
    source = name.rpartition("@")[2] if "@" in name else ""
    if source != "imu" and not source.startswith("imu:"):
        return None
    from rover_env.config.imu import IMU_PRESETS

    preset = source.partition(":")[2] or "bmi088"
    if preset not in IMU_PRESETS:
        raise ValueError(f"controller {name!r}: IMU preset {preset!r} is not one of {sorted(IMU_PRESETS)}")
    return preset


def parse_controller(name: str) -> tuple[ControllerSpec, str]:
    """(spec, observation source) of ``name``: ``<controller>`` or ``<controller>@<obs_source>``.

    ``policy:<folder>`` is a policy that ``rover train`` wrote to ``<folder>``. ``@imu`` (or
    ``@imu:<preset>``) drives on the estimates with an IMU on the rover (:func:`controller_imu`).
    """
    base, _, source = name.rpartition("@") if "@" in name else (name, "", "")
    source = "estimated" if controller_imu(name) else (source or "estimated")
    if base.startswith("policy:"):
        folder = base[len("policy:") :]
        if not Path(folder).is_dir():
            raise ValueError(f"controller {name!r}: no folder {folder!r}; train one with `rover train --out`")
        spec = _policy_spec(lambda: folder, f"the trained policy in {folder}")
    elif base in CONTROLLERS:
        spec = CONTROLLERS[base]
    else:
        raise ValueError(
            f"controller {base!r}: unknown; choose one of {sorted(CONTROLLERS)} or policy:<folder>"
        )
    if source not in OBS_SOURCES:
        raise ValueError(f"controller {name!r}: observation source {source!r} is not one of {OBS_SOURCES}")
    return spec, source

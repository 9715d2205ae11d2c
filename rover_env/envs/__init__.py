"""Gymnasium environments of the rover."""

from perception.observation import OBS_FIELDS
from rover_env.envs.rover_env import ActionMode, ObsSource, RoverEnv

__all__ = ["OBS_FIELDS", "ActionMode", "ObsSource", "RoverEnv"]

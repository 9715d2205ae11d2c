"""Gymnasium environments of the rover."""

from rover_env.envs.rover_env import OBS_FIELDS, ActionMode, ObsSource, RoverEnv

__all__ = ["OBS_FIELDS", "ActionMode", "ObsSource", "RoverEnv"]

"""Controllers that drive the rover from observations (never from the simulator)."""

from controllers.base import Controller
from controllers.pure_pursuit import PurePursuit, PurePursuitConfig

__all__ = ["Controller", "PurePursuit", "PurePursuitConfig"]

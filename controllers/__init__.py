"""Controllers that drive the rover from observations (never from the simulator).

Every controller satisfies :class:`Controller`: ``reset()`` and ``act(obs) -> action``.
"""

from controllers.base import Controller
from controllers.path_follower import PathFollower, PathFollowerConfig
from controllers.pure_pursuit import PurePursuit, PurePursuitConfig
from controllers.traction import SlipAwareController, TractionConfig

__all__ = [
    "Controller",
    "PathFollower",
    "PathFollowerConfig",
    "PurePursuit",
    "PurePursuitConfig",
    "SlipAwareController",
    "TractionConfig",
]

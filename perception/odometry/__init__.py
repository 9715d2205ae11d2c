"""Visual odometry: the body's planar twist from a downward camera or the downward fisheye.

- :mod:`~perception.odometry.flow`: :class:`FlowOdometry`, optical-flow odometry from a downward
  pinhole camera, robust to the rover's own shadow (the odometry paper);
- :mod:`~perception.odometry.fisheye`: :class:`FisheyeOdometry`, ground features through the
  omnidirectional model (the one-camera rig);
- :mod:`~perception.odometry.wheel_tracks`: the wheels' contacts, which set the fisheye's scale on
  rough ground;
- :mod:`~perception.odometry.trajectory`: TUM files and the odometry paper's path-segment error.

Imports :mod:`perception.models` only.
"""

from perception.odometry.fisheye import FisheyeOdometry, FisheyeOdometryConfig
from perception.odometry.flow import FlowOdometry, FlowOdometryConfig, OdometryEstimate, integrate_twist

__all__ = [
    "FisheyeOdometry",
    "FisheyeOdometryConfig",
    "FlowOdometry",
    "FlowOdometryConfig",
    "OdometryEstimate",
    "integrate_twist",
]

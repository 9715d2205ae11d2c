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

from __future__ import annotations

from typing import TYPE_CHECKING

from perception.models._lazy import lazy_exports

#: Each public name and the module that defines it (imported on first use).
_PUBLIC: dict[str, str] = {
    "FisheyeOdometry": "perception.odometry.fisheye",
    "FisheyeOdometryConfig": "perception.odometry.fisheye",
    "FlowOdometry": "perception.odometry.flow",
    "FlowOdometryConfig": "perception.odometry.flow",
    "OdometryEstimate": "perception.odometry.flow",
    "integrate_twist": "perception.odometry.flow",
}
__all__ = list(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC, globals())

if TYPE_CHECKING:  # the names as their modules define them, for type checkers
    from perception.odometry.fisheye import FisheyeOdometry as FisheyeOdometry
    from perception.odometry.fisheye import FisheyeOdometryConfig as FisheyeOdometryConfig
    from perception.odometry.flow import FlowOdometry as FlowOdometry
    from perception.odometry.flow import FlowOdometryConfig as FlowOdometryConfig
    from perception.odometry.flow import OdometryEstimate as OdometryEstimate
    from perception.odometry.flow import integrate_twist as integrate_twist

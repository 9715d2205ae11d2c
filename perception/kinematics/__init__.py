"""Kinematic state from the downward fisheye: axle roll and height, steering, wheel rotation.

- :mod:`~perception.kinematics.fisheye`: :class:`KinematicStateEstimator`, all 10 joint degrees
  of freedom (the kinematics paper);
- :mod:`~perception.kinematics.markers`: the fiducial markers and the joint angles they give;
- :mod:`~perception.kinematics.wheel_rotation`: wheel rotation from the treads.

Imports :mod:`perception.models` only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from perception.models._lazy import lazy_exports

#: Each public name and the module that defines it (imported on first use).
_PUBLIC: dict[str, str] = {
    "DOF_NAMES": "perception.kinematics.fisheye",
    "KinematicState": "perception.kinematics.fisheye",
    "KinematicStateEstimator": "perception.kinematics.fisheye",
    "KinematicsConfig": "perception.kinematics.fisheye",
    "SteeringCalibration": "perception.kinematics.markers",
}
__all__ = list(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC, globals())

if TYPE_CHECKING:  # the names as their modules define them, for type checkers
    from perception.kinematics.fisheye import DOF_NAMES as DOF_NAMES
    from perception.kinematics.fisheye import KinematicsConfig as KinematicsConfig
    from perception.kinematics.fisheye import KinematicState as KinematicState
    from perception.kinematics.fisheye import KinematicStateEstimator as KinematicStateEstimator
    from perception.kinematics.markers import SteeringCalibration as SteeringCalibration

"""Kinematic state from the downward fisheye: axle roll and height, steering, wheel rotation.

- :mod:`~perception.kinematics.fisheye`: :class:`KinematicStateEstimator`, all 10 joint degrees
  of freedom (the kinematics paper);
- :mod:`~perception.kinematics.markers`: the fiducial markers and the joint angles they give;
- :mod:`~perception.kinematics.wheel_rotation`: wheel rotation from the treads.

Imports :mod:`perception.models` only.
"""

from perception.kinematics.fisheye import DOF_NAMES, KinematicsConfig, KinematicState, KinematicStateEstimator
from perception.kinematics.markers import SteeringCalibration

__all__ = [
    "DOF_NAMES",
    "KinematicState",
    "KinematicStateEstimator",
    "KinematicsConfig",
    "SteeringCalibration",
]

"""Camera-based state estimation for planetary rovers (images and camera models in, states out).

This package depends on numpy, OpenCV and SciPy only; it never needs the simulator.
"""

from perception.estimator import ESTIMATE_FIELDS, Estimator, EstimatorError
from perception.fusion.slip import SlipConfig, SlipEstimate, SlipEstimator, slip_events
from perception.kinematics.fisheye import DOF_NAMES, KinematicsConfig, KinematicState, KinematicStateEstimator
from perception.kinematics.markers import SteeringCalibration
from perception.models.calib_io import CalibrationError
from perception.models.calibration import ExtrinsicFit, OmniFit, calibrate_ground_camera, fit_omni_camera
from perception.models.cameras import OmniCamera, PinholeCamera
from perception.models.rover import RoverKinematicModel
from perception.models.wheel_kinematics import (
    SLIP_EPS,
    slip_angle,
    slip_ratio,
    wheel_ground_velocity,
)
from perception.odometry.flow import FlowOdometry, FlowOdometryConfig, OdometryEstimate
from perception.rig import ImuModel, Rig, SensorMessage, SensorSpec, SunSensorModel
from perception.rover_estimator import RoverEstimator

__all__ = [
    "DOF_NAMES",
    "ESTIMATE_FIELDS",
    "Estimator",
    "EstimatorError",
    "ImuModel",
    "SunSensorModel",
    "Rig",
    "RoverEstimator",
    "SensorMessage",
    "SensorSpec",
    "SLIP_EPS",
    "CalibrationError",
    "ExtrinsicFit",
    "FlowOdometry",
    "FlowOdometryConfig",
    "KinematicState",
    "KinematicStateEstimator",
    "KinematicsConfig",
    "OdometryEstimate",
    "OmniCamera",
    "OmniFit",
    "PinholeCamera",
    "RoverKinematicModel",
    "SlipConfig",
    "SlipEstimate",
    "SlipEstimator",
    "SteeringCalibration",
    "calibrate_ground_camera",
    "fit_omni_camera",
    "slip_angle",
    "slip_events",
    "slip_ratio",
    "wheel_ground_velocity",
]
__version__ = "0.1.0"

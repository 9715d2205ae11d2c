"""Camera-based state estimation for planetary rovers (images and camera models in, states out).

This package depends on numpy, OpenCV and SciPy only; it never needs the simulator.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from perception.models._lazy import lazy_exports

#: Each public name and the module that defines it (imported on first use).
_PUBLIC: dict[str, str] = {
    "DOF_NAMES": "perception.kinematics.fisheye",
    "ESTIMATE_FIELDS": "perception.estimator",
    "Estimator": "perception.estimator",
    "EstimatorError": "perception.estimator",
    "EncoderModel": "perception.rig",
    "ImuModel": "perception.rig",
    "MotorModel": "perception.rig",
    "SunSensorModel": "perception.rig",
    "Rig": "perception.rig",
    "RoverEstimator": "perception.rover_estimator",
    "SensorMessage": "perception.rig",
    "SensorSpec": "perception.rig",
    "SLIP_EPS": "perception.models.wheel_kinematics",
    "CalibrationError": "perception.models.calib_io",
    "ExtrinsicFit": "perception.models.calibration",
    "FlowOdometry": "perception.odometry.flow",
    "FlowOdometryConfig": "perception.odometry.flow",
    "KinematicState": "perception.kinematics.fisheye",
    "KinematicStateEstimator": "perception.kinematics.fisheye",
    "KinematicsConfig": "perception.kinematics.fisheye",
    "OdometryEstimate": "perception.odometry.flow",
    "OmniCamera": "perception.models.cameras",
    "OmniFit": "perception.models.calibration",
    "PinholeCamera": "perception.models.cameras",
    "RoverKinematicModel": "perception.models.rover",
    "SlipConfig": "perception.fusion.slip",
    "SlipEstimate": "perception.fusion.slip",
    "SlipEstimator": "perception.fusion.slip",
    "SteeringCalibration": "perception.kinematics.markers",
    "calibrate_ground_camera": "perception.models.calibration",
    "fit_omni_camera": "perception.models.calibration",
    "slip_angle": "perception.models.wheel_kinematics",
    "slip_events": "perception.fusion.slip",
    "slip_ratio": "perception.models.wheel_kinematics",
    "wheel_ground_velocity": "perception.models.wheel_kinematics",
}
__all__ = list(_PUBLIC)
__version__ = "0.1.0"
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC, globals())

if TYPE_CHECKING:  # the names as their modules define them, for type checkers
    from perception.estimator import ESTIMATE_FIELDS as ESTIMATE_FIELDS
    from perception.estimator import Estimator as Estimator
    from perception.estimator import EstimatorError as EstimatorError
    from perception.fusion.slip import SlipConfig as SlipConfig
    from perception.fusion.slip import SlipEstimate as SlipEstimate
    from perception.fusion.slip import SlipEstimator as SlipEstimator
    from perception.fusion.slip import slip_events as slip_events
    from perception.kinematics.fisheye import DOF_NAMES as DOF_NAMES
    from perception.kinematics.fisheye import KinematicsConfig as KinematicsConfig
    from perception.kinematics.fisheye import KinematicState as KinematicState
    from perception.kinematics.fisheye import KinematicStateEstimator as KinematicStateEstimator
    from perception.kinematics.markers import SteeringCalibration as SteeringCalibration
    from perception.models.calib_io import CalibrationError as CalibrationError
    from perception.models.calibration import ExtrinsicFit as ExtrinsicFit
    from perception.models.calibration import OmniFit as OmniFit
    from perception.models.calibration import calibrate_ground_camera as calibrate_ground_camera
    from perception.models.calibration import fit_omni_camera as fit_omni_camera
    from perception.models.cameras import OmniCamera as OmniCamera
    from perception.models.cameras import PinholeCamera as PinholeCamera
    from perception.models.rover import RoverKinematicModel as RoverKinematicModel
    from perception.models.wheel_kinematics import SLIP_EPS as SLIP_EPS
    from perception.models.wheel_kinematics import slip_angle as slip_angle
    from perception.models.wheel_kinematics import slip_ratio as slip_ratio
    from perception.models.wheel_kinematics import wheel_ground_velocity as wheel_ground_velocity
    from perception.odometry.flow import FlowOdometry as FlowOdometry
    from perception.odometry.flow import FlowOdometryConfig as FlowOdometryConfig
    from perception.odometry.flow import OdometryEstimate as OdometryEstimate
    from perception.rig import EncoderModel as EncoderModel
    from perception.rig import ImuModel as ImuModel
    from perception.rig import MotorModel as MotorModel
    from perception.rig import Rig as Rig
    from perception.rig import SensorMessage as SensorMessage
    from perception.rig import SensorSpec as SensorSpec
    from perception.rig import SunSensorModel as SunSensorModel
    from perception.rover_estimator import RoverEstimator as RoverEstimator

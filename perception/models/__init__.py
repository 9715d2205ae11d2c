"""The models every estimator stands on: cameras, calibration files, photometry, the rover's geometry.

- :mod:`~perception.models.cameras`: :class:`PinholeCamera` and :class:`OmniCamera` (project,
  unproject, load, save);
- :mod:`~perception.models.calib_io`, :mod:`~perception.models.calibration`: calibration files and fits;
- :mod:`~perception.models.photometry`: a camera's gamma, vignetting and colour-filter array;
- :mod:`~perception.models.rover`: :class:`RoverKinematicModel`, the rover's kinematic geometry;
- :mod:`~perception.models.drive_geometry`, :mod:`~perception.models.wheel_kinematics`: double-Ackermann
  steering, wheel order, slip ratio and slip angle;
- :mod:`~perception.models.rover_parts`: where the rover's parts lie in the fisheye's view;
- :mod:`~perception.models.validation`: :class:`ConfigError` and the checks of configuration values.

Nothing here imports another layer of :mod:`perception`.
"""

from perception.models.calib_io import CalibrationError
from perception.models.cameras import OmniCamera, PinholeCamera
from perception.models.rover import RoverKinematicModel
from perception.models.validation import ConfigError

__all__ = ["CalibrationError", "ConfigError", "OmniCamera", "PinholeCamera", "RoverKinematicModel"]

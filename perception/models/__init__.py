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

from __future__ import annotations

from typing import TYPE_CHECKING

from perception.models._lazy import lazy_exports

#: Each public name and the module that defines it (imported on first use).
_PUBLIC: dict[str, str] = {
    "CalibrationError": "perception.models.calib_io",
    "ConfigError": "perception.models.validation",
    "OmniCamera": "perception.models.cameras",
    "PinholeCamera": "perception.models.cameras",
    "RoverKinematicModel": "perception.models.rover",
}
__all__ = list(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC, globals())

if TYPE_CHECKING:  # the names as their modules define them, for type checkers
    from perception.models.calib_io import CalibrationError as CalibrationError
    from perception.models.cameras import OmniCamera as OmniCamera
    from perception.models.cameras import PinholeCamera as PinholeCamera
    from perception.models.rover import RoverKinematicModel as RoverKinematicModel
    from perception.models.validation import ConfigError as ConfigError

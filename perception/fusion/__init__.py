"""Fusion of the measurements into the rover's state: slip, attitude, heading.

- :mod:`~perception.fusion.slip`: :class:`SlipEstimator`, per-wheel slip from the ground's
  velocity against the wheels' spin (and the gyro);
- :mod:`~perception.fusion.soil`: :class:`SoilIdentifier`, the soil's pull curve from the
  wheels' torques, slips and sinkages and the accelerometer;
- :mod:`~perception.fusion.inertial`: roll and pitch from an IMU, IMU logs;
- :mod:`~perception.fusion.sun_heading`: absolute heading from a sun sensor;
- :mod:`~perception.fusion.allan`: Allan deviation of an inertial sensor.

Imports :mod:`perception.models` only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from perception.models._lazy import lazy_exports

#: Each public name and the module that defines it (imported on first use).
_PUBLIC: dict[str, str] = {
    "SlipConfig": "perception.fusion.slip",
    "SlipEstimate": "perception.fusion.slip",
    "SlipEstimator": "perception.fusion.slip",
    "slip_events": "perception.fusion.slip",
    "SoilCurveEstimate": "perception.fusion.soil",
    "SoilIdConfig": "perception.fusion.soil",
    "SoilIdentifier": "perception.fusion.soil",
}
__all__ = list(_PUBLIC)
__getattr__, __dir__ = lazy_exports(__name__, _PUBLIC, globals())

if TYPE_CHECKING:  # the names as their modules define them, for type checkers
    from perception.fusion.slip import SlipConfig as SlipConfig
    from perception.fusion.slip import SlipEstimate as SlipEstimate
    from perception.fusion.slip import SlipEstimator as SlipEstimator
    from perception.fusion.slip import slip_events as slip_events
    from perception.fusion.soil import SoilCurveEstimate as SoilCurveEstimate
    from perception.fusion.soil import SoilIdConfig as SoilIdConfig
    from perception.fusion.soil import SoilIdentifier as SoilIdentifier

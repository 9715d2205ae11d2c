"""Fusion of the measurements into the rover's state: slip, attitude, heading.

- :mod:`~perception.fusion.slip`: :class:`SlipEstimator`, per-wheel slip from the ground's
  velocity against the wheels' spin (and the gyro);
- :mod:`~perception.fusion.inertial`: roll and pitch from an IMU, IMU logs;
- :mod:`~perception.fusion.sun_heading`: absolute heading from a sun sensor;
- :mod:`~perception.fusion.allan`: Allan deviation of an inertial sensor.

Imports :mod:`perception.models` only.
"""

from perception.fusion.slip import SlipConfig, SlipEstimate, SlipEstimator, slip_events

__all__ = ["SlipConfig", "SlipEstimate", "SlipEstimator", "slip_events"]

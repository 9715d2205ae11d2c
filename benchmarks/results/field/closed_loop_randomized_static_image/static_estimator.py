"""The built-in estimator (train preset) with the odometry's static image on (static_rate 0.1)."""

from rover_env.sensors.rig import builtin_estimator

FACTORY = builtin_estimator("train", odometry_overrides={"static_rate": 0.1})

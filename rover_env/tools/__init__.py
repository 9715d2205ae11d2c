"""Tools on top of the environments.

The ``rover`` command, sweeps, the mission runner, training, bench, video, Rerun logs and
calibration.
"""

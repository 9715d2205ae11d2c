"""The sensors the simulation samples (cameras, fisheye, IMU) and the rig that feeds an estimator."""

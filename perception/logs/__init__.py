"""Robot logs in and results out: bags and MCAP files, their time lines, offline runs, replay.

- :mod:`~perception.logs.bags`: camera and IMU streams of ROS 1 bags, ROS 2 bag folders and MCAP
  files, and the MCAP writer;
- :mod:`~perception.logs.log_time`: the messages' times (header stamps against receive times);
- :mod:`~perception.logs.offline`: odometry and kinematics on image folders and logs;
- :mod:`~perception.logs.replay`: any estimator on a log, tick by tick, and rig files;
- :mod:`~perception.logs.truth`: the truth beside a recorded log, and an estimate's errors;
- :mod:`~perception.logs.outputs`: :class:`OutputFolder`, the one writer of every result.

The top of the stack: it may import every other layer; none imports it.
"""

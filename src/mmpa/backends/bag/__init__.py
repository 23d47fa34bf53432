"""ROS 2 bags in and out (issue 20): record the twin, read ROS 1 / ROS 2 recordings.

- :mod:`mmpa.backends.bag.messages`: mmpa values <-> ROS messages (``rosbags`` type store);
- :mod:`mmpa.backends.bag.writer`: :class:`BagWriter` (rosbag2, MCAP storage; a single ``.mcap``
  file or a bag directory);
- :mod:`mmpa.backends.bag.record`: :class:`Recorder`, which records a running twin through wrapped
  devices without touching the simulator;
- :mod:`mmpa.backends.bag.reader`: bag-backed ``Lidar`` / odometry (``/odom``, else ``/tf``) /
  ``Camera`` / joint-state sources;
- :mod:`mmpa.apps.localize`: offline localization over a bag (``mmpa localize``).
"""

from mmpa.backends.bag.record import Recorder
from mmpa.backends.bag.writer import BagWriter

__all__ = ["BagWriter", "Recorder"]

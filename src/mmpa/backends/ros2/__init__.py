"""mmpa over ROS 2 Jazzy (the optional extra ``ros2``; docs/ros2.md).

- :mod:`mmpa.backends.ros2.messages`: mmpa values <-> ``rclpy`` messages (fast paths for
  the scan, a CDR bridge that reuses every builder of :mod:`mmpa.backends.bag.messages`);
- :mod:`mmpa.backends.ros2.graph`: a ROS 2 context and node, the QoS profiles Nav2 uses, and
  waiting for publishers and subscriptions to match;
- ``interfaces/``: the ``.msg`` files of the interface packages no wheel publishes
  (``tf2_msgs``, ``nav2_msgs``' particle cloud), built into the venv by
  ``scripts/ros2-interfaces.sh``.

The modules import ``rclpy`` at module level, so import them inside a function (this package
itself imports nothing, so mmpa without the extra is unchanged).
"""

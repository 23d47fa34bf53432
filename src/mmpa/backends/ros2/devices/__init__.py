"""A ROS 2 robot behind mmpa's robot protocols (issue 35 item 4; docs/ros2.md "ROS 2 backends").

- :mod:`~mmpa.backends.ros2.devices.node`: the backend's one ``rclpy`` node (a context of its
  own, spun on a background thread) and the latest message of every topic it reads;
- :mod:`~mmpa.backends.ros2.devices.mobile`: the base (``/cmd_vel``), odometry (``/odom``),
  lidar (``/scan``), the robot's clock (``/clock`` or the wall clock), a running localizer's
  pose and the map;
- :mod:`~mmpa.backends.ros2.devices.arm`: the arm (``/joint_states``, the trajectory and
  streaming topics, limits checked before anything is sent, a watchdog) and the gripper;
- :mod:`~mmpa.backends.ros2.devices.camera`: an RGB-D camera as ``realsense2_camera``
  publishes it;
- :mod:`~mmpa.backends.ros2.devices.robot`: :class:`Ros2Robot`, the devices of a
  :class:`~mmpa.robot.backend_config.BackendConfig` as one
  :class:`~mmpa.robot.interfaces.MobileManipulator`.

The modules import ``rclpy`` at module level: import them inside a function (this package
itself imports nothing, so mmpa without the extra is unchanged).
"""

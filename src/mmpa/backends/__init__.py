"""Robot backends other than the twin: implementations of the robot interfaces
(:mod:`mmpa.robot.interfaces`) over recordings and hardware. Each imports its SDK lazily:
recordings played back (:mod:`mmpa.backends.bag.reader`), Intel RealSense cameras and their
recordings (:mod:`mmpa.backends.realsense`, the optional extra ``realsense``), Universal
Robots arms over RTDE (:mod:`mmpa.backends.ur`, the optional extra ``ur``)."""

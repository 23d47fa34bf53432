"""An RGB-D camera as ``realsense2_camera`` publishes it: ``topics.color`` (``rgb8`` /
``bgr8``), ``topics.depth`` (the depth aligned to color: ``16UC1`` mm or ``32FC1`` m) and
``topics.camera_info`` (the color camera's pinhole: the intrinsics of both).

``capture()`` returns the newest color and depth pair with the same stamp (within
``SYNC_S``) whose two images both arrived after the call, and, on a simulated clock, are
stamped no earlier than the call (so the picture shows the scene after whatever moved
before it); it waits up to the connect timeout for one, then fails naming the topics and
what arrived. The two image topics are subscribed only while frames are taken and
:data:`IDLE_S` after the last one: a camera streams ~30 MB/s of pixels that a mission
looks at for a few views, and a twin node renders only for a subscriber.
"""

from __future__ import annotations

import threading
import time
from typing import Any

from mmpa.backends.bag import messages as bag
from mmpa.backends.ros2 import graph
from mmpa.backends.ros2.devices.mobile import SimClock
from mmpa.backends.ros2.devices.node import DeviceTimeoutError, RobotNode
from mmpa.backends.ros2.localization_msgs import stamp_of
from mmpa.robot.backend_config import Ros2Topics
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import RGBDFrame

__all__ = ["IDLE_S", "SYNC_S", "Ros2Camera"]

#: s: the most a color and a depth stamp of one pair may differ
SYNC_S = 1e-3
#: wall s after the last capture before the image topics are unsubscribed
IDLE_S = 1.0


class Ros2Camera:
    """The camera of a ROS 2 robot (module docstring). ``clock``: the robot's clock when it
    is simulated (``/clock``), else None; ``timeout``: wall s to wait."""

    def __init__(
        self, node: RobotNode, topics: Ros2Topics, clock: SimClock | None, timeout: float
    ) -> None:
        self._node, self._clock, self._timeout = node, clock, timeout
        img = "sensor_msgs/msg/Image"
        qos = graph.SENSOR_DATA
        self.color = node.subscribe("camera", topics.color, img, qos, keep=8, listen=False)
        self.depth = node.subscribe("camera", topics.depth, img, qos, keep=8, listen=False)
        self._lock = threading.Lock()
        self._users = 0  # captures in progress
        self._idle: threading.Timer | None = None
        self.info = node.subscribe(
            "camera", topics.camera_info, "sensor_msgs/msg/CameraInfo", graph.SENSOR_DATA,
            convert=bag.from_camera_info,
        )  # fmt: skip

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """From the latest ``camera_info``."""
        return self._node.first(self.info, self._timeout)

    def _pair(self, c0: int, d0: int, t_call: float | None) -> tuple[Any, Any] | None:
        depths = [(stamp_of(m.header), m) for k, m in self.depth.snapshot() if k > d0]
        for k, cm in reversed(self.color.snapshot()):
            if k <= c0:
                break
            t = stamp_of(cm.header)
            if t_call is not None and t < t_call - 1e-9:
                continue
            for td, dm in depths:
                if abs(td - t) <= SYNC_S:
                    return cm, dm
        return None

    def _listen(self) -> None:
        with self._lock:
            self._users += 1
            if self._idle is not None:
                self._idle.cancel()
                self._idle = None
            self._node.listen(self.color)
            self._node.listen(self.depth)

    def _done(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0:
                self._idle = threading.Timer(IDLE_S, self._stop)
                self._idle.daemon = True
                self._idle.start()

    def _stop(self) -> None:
        with self._lock:
            if self._users == 0:
                self._node.stop_listening(self.color)
                self._node.stop_listening(self.depth)

    def capture(self) -> RGBDFrame:
        """A fresh synchronized color + depth pair (module docstring)."""
        k = self.intrinsics
        self._listen()
        try:
            return self._capture(k)
        finally:
            self._done()

    def _capture(self, k: CameraIntrinsics) -> RGBDFrame:
        c0, d0 = self.color.count, self.depth.count
        t_call = self._clock.time if self._clock is not None else None
        deadline = time.monotonic() + self._timeout
        while (pair := self._pair(c0, d0, t_call)) is None:
            if time.monotonic() > deadline:
                raise DeviceTimeoutError(
                    f"camera: no color ({self.color.topic}) and depth ({self.depth.topic}) "
                    f"pair with one stamp newer than the call within {self._timeout:g} s "
                    f"({self._node.where}; {self.color.count - c0} color and "
                    f"{self.depth.count - d0} depth images arrived): is the camera driver "
                    "running with aligned depth?"
                )
            seen = self.color.count + self.depth.count
            self.color.wait(lambda seen=seen: self.color.count + self.depth.count > seen, 0.02)
        cm, dm = pair
        return RGBDFrame(
            bag.from_image_rgb(cm),
            bag.from_depth_image(dm),
            k,
            stamp_of(cm.header),
            str(cm.header.frame_id) or "camera",
        )

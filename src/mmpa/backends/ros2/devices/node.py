"""The ROS 2 backend's node: one ``rclpy`` context and node of its own (the DDS domain of the
robot file or ``$ROS_DOMAIN_ID``), spun by a single-threaded executor on a background thread.
Subscription callbacks only store what arrived (:class:`Topic`: the latest message, a short
history, its arrival time on the monotonic clock); the devices read them from the caller's
thread. A device that waits for its first message and gets none raises
:class:`DeviceTimeoutError` naming the device, the topic, the domain and how long it waited.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import rclpy
from pydantic import BaseModel, ConfigDict, Field
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions

from mmpa.backends.ros2 import graph, messages
from mmpa.core.errors import MMPAError

__all__ = ["DeviceTimeoutError", "RobotNode", "Ros2DeviceConfig", "Topic"]


class DeviceTimeoutError(MMPAError):
    """A ROS 2 device did not answer in time: no message on its topic, nothing subscribed to
    its command topic, or its messages stopped (a watchdog)."""


class Ros2DeviceConfig(BaseModel):
    """How the ROS 2 devices command and wait (s of the robot's clock unless said otherwise;
    rad; Hz)."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    trajectory_rate_hz: float = Field(50.0, gt=0)  # samples of a planned move_joints
    stream_rate_hz: float = Field(100.0, gt=0)  # wall Hz of the streaming set-points
    goal_tolerance: float = Field(1e-3, gt=0)  # rad: the encoders at a motion's end
    approach_tolerance: float = Field(1e-3, gt=0)  # rad: a path's start farther: approach
    move_settle_s: float = Field(0.3, ge=0)  # held at the target after move_joints
    follow_settle_s: float = Field(0.3, ge=0)  # held at the end after follow
    goal_timeout_s: float = Field(3.0, gt=0)  # after a motion's planned end
    gripper_s: float = Field(0.6, ge=0)  # a gripper stroke
    reflector_wait_s: float = Field(2.0, ge=0)  # wall s for /reflectors after /map
    truth_wait_s: float = Field(2.0, ge=0)  # wall s for the twin node's /truth/base_pose


class Topic:
    """What one subscription received: the latest message, the last ``keep`` ones, how many
    and when the latest arrived (monotonic s); every one while tapped (:meth:`tap`).
    Thread-safe; :meth:`wait` blocks until a predicate over it holds."""

    def __init__(self, device: str, topic: str, keep: int = 1) -> None:
        self.device, self.topic = device, topic
        self._cond = threading.Condition()
        self.msg: Any = None
        self.count = 0
        self.arrived = -math.inf
        self.history: deque[tuple[int, Any]] = deque(maxlen=max(1, keep))
        self.refused = 0  # messages the device's conversion refused
        self.last_refusal = ""
        self._taps: list[list[Any]] = []
        self.subscription: Any = None  # the rclpy subscription while it listens
        self.opener: Callable[[], Any] | None = None  # creates it (RobotNode.listen)

    def put(self, msg: Any) -> None:
        with self._cond:
            self.msg = msg
            self.count += 1
            self.arrived = time.monotonic()
            self.history.append((self.count, msg))
            for kept in self._taps:
                kept.append(msg)
            self._cond.notify_all()

    def tap(self) -> list[Any]:
        """Keep every message from now on (not only the last ``keep``) until
        :meth:`untap`: the list they are appended to, in arrival order."""
        kept: list[Any] = []
        with self._cond:
            self._taps.append(kept)
        return kept

    def untap(self, kept: list[Any]) -> None:
        with self._cond:
            self._taps = [k for k in self._taps if k is not kept]

    def wait(self, done: Callable[[], bool], timeout: float) -> bool:
        """Block until ``done()`` (called under the lock) or ``timeout`` wall s; its value."""
        with self._cond:
            return bool(self._cond.wait_for(done, max(0.0, timeout)))

    def age(self) -> float:
        """Wall seconds since the latest message (inf before the first)."""
        return time.monotonic() - self.arrived

    def snapshot(self) -> list[tuple[int, Any]]:
        with self._cond:
            return list(self.history)


class RobotNode:
    """The backend's node (module docstring); a context manager that closes it."""

    def __init__(self, name: str = "mmpa_robot", domain_id: int | None = None) -> None:
        env = os.environ.get("ROS_DOMAIN_ID", "0")
        self.domain = str(domain_id) if domain_id is not None else env
        self.context = rclpy.Context()
        rclpy.init(
            context=self.context,
            domain_id=domain_id,
            signal_handler_options=SignalHandlerOptions.NO,  # Ctrl-C stays the caller's
        )
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True, name=f"{name}-spin")
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # the context was shut down under the spin: closing
            if not self._closing.is_set():
                raise

    @property
    def where(self) -> str:
        return f"ROS_DOMAIN_ID {self.domain}"

    def subscribe(
        self,
        device: str,
        topic: str,
        type_name: str,
        qos: Any = None,
        keep: int = 1,
        convert: Callable[[Any], Any] | None = None,
        listen: bool = True,
    ) -> Topic:
        """A :class:`Topic` filled by a subscription to ``topic`` (``pkg/msg/Name``); QoS
        default: best effort, volatile (matches reliable and best-effort publishers).
        ``convert``: what is stored of each message (None: the message); a message it
        refuses (an :class:`MMPAError`) is dropped, counted in ``store.refused`` and logged;
        one it maps to None is not for this device (ignored). ``listen=False``: subscribed
        only between :meth:`listen` and :meth:`stop_listening` (a topic of large messages
        read now and then, such as a camera's images)."""
        store = Topic(device, topic, keep)
        log = self.node.get_logger()

        def put(msg: Any) -> None:
            if convert is None:
                return store.put(msg)
            try:
                value = convert(msg)
            except MMPAError as e:  # a malformed message: never kills the executor
                store.refused += 1
                store.last_refusal = str(e)
                log.warning(f"{device}: refused on {topic}: {e}", throttle_duration_sec=2.0)
                return None
            return None if value is None else store.put(value)

        store.opener = lambda: self.node.create_subscription(
            messages.message_class(type_name), topic, put, qos or graph.SENSOR_DATA
        )
        if listen:
            self.listen(store)
        return store

    def listen(self, store: Topic) -> None:
        """Subscribe ``store``'s topic again (nothing when it listens)."""
        if store.subscription is None and store.opener is not None:
            store.subscription = store.opener()

    def stop_listening(self, store: Topic) -> None:
        """Drop ``store``'s subscription (what it received stays); :meth:`listen` renews it."""
        sub, store.subscription = store.subscription, None
        if sub is not None and not self._closing.is_set():
            try:
                self.node.destroy_subscription(sub)
            except Exception:  # the node closed meanwhile: its subscriptions went with it
                if not self._closing.is_set():
                    raise

    def publisher(self, topic: str, type_name: str, qos: Any = None) -> Any:
        """A publisher of ``type_name`` on ``topic`` (default QoS: reliable, volatile)."""
        return self.node.create_publisher(
            messages.message_class(type_name), topic, qos or graph.RELIABLE
        )

    def first(self, store: Topic, timeout: float, hint: str = "") -> Any:
        """The latest message of ``store``, waiting up to ``timeout`` wall s for the first
        (:class:`DeviceTimeoutError` naming the device, the topic and the wait)."""
        if not store.wait(lambda: store.count > 0, timeout):
            if store.refused:
                hint = f": {store.refused} refused, the last: {store.last_refusal}"
            raise DeviceTimeoutError(
                f"{store.device}: no message on {store.topic} within {timeout:g} s "
                f"({self.where}){hint or ': is its driver running, is the topic name right?'}"
            )
        return store.msg

    def wait_subscriber(self, device: str, pub: Any, timeout: float) -> None:
        """Wait until something subscribes to ``pub``'s topic (its controller is there)."""
        if not graph.wait_until_matched(pub, 1, timeout):
            raise DeviceTimeoutError(
                f"{device}: nothing subscribes to {pub.topic_name} after {timeout:g} s "
                f"({self.where}): is its controller running, is the topic name right?"
            )

    def close(self) -> None:
        self._closing.set()
        self.executor.shutdown()
        self.node.destroy_node()
        if self.context.ok():
            rclpy.shutdown(context=self.context)
        self._thread.join(timeout=5.0)

    def __enter__(self) -> RobotNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""``mmpa ros2 play BAG``: a recorded bag's messages published on ROS 2, as ``ros2 bag play``
does, so the nodes can run on a recording (docs/ros2.md "Playback").

The bag (MCAP file, rosbag2 folder, ROS 1 bag: whatever ``rosbags``' ``AnyReader`` opens) is
read in log-time order and each message is published as the bytes the bag stores (CDR, with
its encapsulation header), through ``rclpy``'s raw publishing: nothing is deserialized, so a
message arrives exactly as it was recorded. One publisher per topic, of the recorded type (a
type whose ``rclpy`` interface is not installed is skipped, logged), with the QoS the bag
recorded it with (``offered_qos_profiles``: reliability, durability, depth); a topic recorded
without one gets rosbag2's default (reliable, volatile, keep last 10), except ``/tf_static``,
``/map`` and ``/reflectors``, which get map_server's latched profile (reliable, transient
local, keep last 1) so that a late subscriber still gets them.

Pacing: message ``i`` goes out at ``wall_0 + (t_i - t_0) / rate`` (``t``: the bag's log time,
s). ``/clock`` (``rosgraph_msgs/Clock``, reliable, the bag's log time) is published before each
message whose time is later than the last clock, and every ``1 / clock_hz`` wall s while
waiting (not when the bag holds ``/clock`` itself): the clock is at ``t_i`` when message ``i``
is published, and the last ``/clock`` of a pass is the last message's time (``/clock`` is
another writer than the topics': a subscriber may take it after the message). Run the other
nodes with ``use_sim_time:=true``. ``loop`` plays the bag again from the start (the clock
goes back); ``delay`` s are waited after the publishers are created (for discovery) before
the first message.

End: after the last pass the player waits up to ``ack_timeout`` wall s until every reliable
subscriber has acknowledged every message and ``/clock`` (DDS ``wait_for_acknowledgments``,
rosbag2's ``--wait-for-all-acked``): a reliable writer deleted at exit drops what is still
unacknowledged, so without the wait the last messages can be lost on a loaded machine
(ros2/rosbag2#571). Topics still unacknowledged then are logged.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from mmpa.backends.ros2 import graph, messages
from mmpa.core.errors import ConfigError, InvalidInputError

__all__ = ["LATCHED_TOPICS", "BagPlayer", "PlayConfig", "PlayStats", "play_bag", "qos_of"]

#: topics played latched when the bag recorded no QoS for them
LATCHED_TOPICS = frozenset({"/tf_static", "/map", "/reflectors"})


class PlayConfig(BaseModel):
    """Playback settings (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    rate: float = Field(1.0, gt=0)  # bag s per wall s
    loop: bool = False
    delay: float = Field(0.0, ge=0)  # wall s before the first message (discovery)
    clock_hz: float = Field(100.0, gt=0)  # /clock while waiting between messages, per wall s
    ack_timeout: float = Field(5.0, ge=0)  # wall s for the subscribers' acks at the end
    topics: list[str] | None = None  # only these (None: all)


@dataclass
class PlayStats:
    """What was played: messages per topic, passes over the bag, the topics skipped (topic
    -> why), wall seconds."""

    published: dict[str, int] = field(default_factory=dict)
    passes: int = 0
    skipped: dict[str, str] = field(default_factory=dict)
    wall_s: float = 0.0


def qos_of(topic: str, offered: list[Any]) -> QoSProfile:
    """The ``rclpy`` QoS of a recorded topic: its first offered profile (rosbags' ``Qos``:
    reliability, durability, history depth), else the module docstring's defaults."""
    if not offered:
        return graph.LATCHED if topic in LATCHED_TOPICS else graph.RELIABLE
    q = offered[0]
    reliable = q.reliability.name != "BEST_EFFORT"
    latched = q.durability.name == "TRANSIENT_LOCAL"
    keep_all = q.history.name == "KEEP_ALL"
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if keep_all else HistoryPolicy.KEEP_LAST,
        depth=max(1, int(q.depth)) if not keep_all else 1,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
    )


class BagPlayer:
    """Plays the bag at ``path`` (module docstring); ``args``: ROS arguments. A context
    manager (closes the bag and the node)."""

    def __init__(self, path: str | Path, cfg: PlayConfig, args: list[str] | None = None):
        self.path, self.cfg = Path(path), cfg
        if not self.path.exists():
            raise InvalidInputError(f"bag {self.path} does not exist")
        try:
            self.reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_JAZZY))
            self.reader.open()
        except Exception as e:  # rosbags' errors: not a bag, unknown storage
            raise ConfigError(f"{self.path}: cannot read it as a bag: {e}") from None
        self.session = graph.Session("mmpa_play", args)
        self.stats = PlayStats()
        self.log = self.session.node.get_logger()
        self.pubs: dict[str, Any] = {}
        self.connections = self._publishers()
        self.own_clock = "/clock" not in {c.topic for c in self.reader.connections}
        self._clock = self.session.node.create_publisher(
            messages.message_class("rosgraph_msgs/msg/Clock"), "/clock", graph.RELIABLE
        )
        self._last_clock = -1

    def _publishers(self) -> list[Any]:
        """One publisher per topic played; the connections to read."""
        wanted = self.cfg.topics
        conns = []
        for c in self.reader.connections:
            if wanted is not None and c.topic not in wanted:
                continue
            if c.topic not in self.pubs:
                try:
                    cls = messages.message_class(c.msgtype)
                except messages.InterfaceMissingError as e:
                    self.stats.skipped[c.topic] = str(e)
                    self.log.warning(f"skipping {c.topic} ({c.msgtype}): {e}")
                    continue
                offered = getattr(c.ext, "offered_qos_profiles", None) or []
                self.pubs[c.topic] = self.session.node.create_publisher(
                    cls, c.topic, qos_of(c.topic, offered)
                )
            conns.append(c)
        if not conns:
            raise InvalidInputError(f"{self.path}: no topic to play (topics: {wanted})")
        return conns

    def _publish_clock(self, t_ns: int) -> None:
        if not self.own_clock or t_ns <= self._last_clock:
            return
        msg = messages.message_class("rosgraph_msgs/msg/Clock")()
        msg.clock.sec, msg.clock.nanosec = divmod(t_ns, 1_000_000_000)
        self._clock.publish(msg)
        self._last_clock = t_ns

    def _wait(self, wall_0: float, t0: int, t_ns: int) -> None:
        """Sleep until the wall time of bag time ``t_ns``, publishing /clock meanwhile."""
        rate, step = self.cfg.rate, 1.0 / self.cfg.clock_hz
        target = wall_0 + 1e-9 * (t_ns - t0) / rate
        while (now := time.monotonic()) < target:
            self._publish_clock(t0 + round(1e9 * (now - wall_0) * rate))
            time.sleep(min(step, target - now))

    def play_once(self) -> None:
        """One pass over the bag, paced."""
        wall_0, t0 = time.monotonic(), self.reader.start_time
        self._last_clock = -1
        published = self.stats.published
        for conn, t_ns, raw in self.reader.messages(connections=self.connections):
            self._wait(wall_0, t0, t_ns)
            self._publish_clock(t_ns)
            self.pubs[conn.topic].publish(bytes(raw))
            published[conn.topic] = published.get(conn.topic, 0) + 1
        self.stats.passes += 1

    def wait_acked(self) -> list[str]:
        """Wait up to ``ack_timeout`` wall s in all until the reliable subscribers have
        acknowledged everything published (best-effort publishers: at once); the topics
        still unacknowledged (logged)."""
        deadline = time.monotonic() + self.cfg.ack_timeout
        late = []
        for topic, pub in [*self.pubs.items(), ("/clock", self._clock)]:
            left = max(0.0, deadline - time.monotonic())
            if not pub.wait_for_all_acked(Duration(nanoseconds=round(left * 1e9))):
                late.append(topic)
        if late:
            self.log.warning(f"not acknowledged within {self.cfg.ack_timeout:g} s: {late}")
        return late

    def play(self) -> PlayStats:
        """Wait ``delay``, then play once (or until interrupted with ``loop``), then wait for
        the acknowledgments (module docstring)."""
        wall = time.monotonic()
        time.sleep(self.cfg.delay)
        try:
            self.play_once()
            while self.cfg.loop:
                self.play_once()
            self.wait_acked()
        finally:
            self.stats.wall_s = time.monotonic() - wall
        return self.stats

    def close(self) -> None:
        self.reader.close()
        self.session.close()

    def __enter__(self) -> BagPlayer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def play_bag(path: str | Path, cfg: PlayConfig, args: list[str] | None = None) -> PlayStats:
    """Play the bag ``path`` (Ctrl-C stops it); returns what was played."""
    with BagPlayer(path, cfg, args) as player:
        player.log.info(
            f"playing {path}: {len(player.pubs)} topics at {cfg.rate}x"
            + (", looping" if cfg.loop else "")
        )
        try:
            player.play()
        except KeyboardInterrupt:
            pass
        return player.stats

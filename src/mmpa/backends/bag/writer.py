"""Write ROS 2 bags (rosbag2, MCAP storage by default) with ``rosbags``.

``BagWriter(path)`` writes

- a single self-contained ``.mcap`` file when ``path`` ends in ``.mcap`` (what Foxglove and
  ``ros2 bag play FILE.mcap`` open; schemas are embedded), or
- a rosbag2 directory (``metadata.yaml`` + ``<name>.mcap`` or ``<name>.db3`` with
  ``storage="sqlite3"``) otherwise.

Topics are created on their first message; the message type comes from the message object
(``__msgtype__``), the log time from the message's header stamp unless given. ``latched``
topics (``/tf_static``, ``/map``) are offered with ``transient_local`` durability, as a
latched publisher is.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import TracebackType
from typing import Any

from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)
from rosbags.rosbag2 import StoragePlugin, Writer

from mmpa.backends.bag.messages import stamp_ns, typestore
from mmpa.core.errors import InvalidInputError, MMPAError

__all__ = ["LATCHED_TOPICS", "BagWriter", "log_time_ns"]

#: topics written with transient_local durability unless told otherwise
LATCHED_TOPICS = frozenset({"/tf_static", "/map", "/reflectors"})


def _latched_qos() -> Any:

    zero = QosTime(0, 0)
    return Qos(
        history=QosHistory.KEEP_LAST,
        depth=1,
        reliability=QosReliability.RELIABLE,
        durability=QosDurability.TRANSIENT_LOCAL,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


def log_time_ns(topic: str, msg: Any, stamp: float | None) -> int:
    """Log time (ns) of ``msg`` on ``topic``: ``stamp`` s, else the message's header stamp
    (a message without a header needs ``stamp``)."""
    if stamp is not None:
        return stamp_ns(stamp)
    header = getattr(msg, "header", None)
    if header is None:
        raise InvalidInputError(f"a {msg.__msgtype__} on {topic} has no header: give its stamp")
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class BagWriter:
    """A ROS 2 bag being written (see the module docstring). Use as a context manager or
    call :meth:`close`; ``counts`` holds the messages written per topic."""

    def __init__(self, path: str | Path, storage: str = "mcap", overwrite: bool = False) -> None:

        self.path = Path(path)
        self._single = self.path.suffix == ".mcap"
        if storage not in ("mcap", "sqlite3"):
            raise InvalidInputError(f"bag storage must be 'mcap' or 'sqlite3', got {storage!r}")
        if self._single and storage != "mcap":
            raise InvalidInputError(f"{self.path}: a .mcap file needs storage 'mcap'")
        if self.path.exists():
            if not overwrite:
                raise InvalidInputError(f"bag {self.path} exists already; not overwriting it")
            if self.path.is_dir():
                shutil.rmtree(self.path)
            else:
                self.path.unlink()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._dir = self.path.with_name(self.path.name + ".part") if self._single else self.path
        if self._dir.exists():
            shutil.rmtree(self._dir)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self._dir, version=9, storage_plugin=plugin)
        self._writer.open()
        self._conns: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self._closed = False

    def write(
        self, topic: str, msg: Any, stamp: float | None = None, latched: bool | None = None
    ) -> None:
        """Serialize ``msg`` (a ``rosbags`` message object) to CDR and write it on ``topic``
        at log time ``stamp`` s (default: ``msg.header.stamp``; messages without a header need
        one). ``latched``: offer the topic as transient_local (default: ``topic`` in
        :data:`LATCHED_TOPICS`); only the first message of a topic decides."""
        if self._closed:
            raise MMPAError(f"bag {self.path} is closed")
        msgtype = msg.__msgtype__
        ns = log_time_ns(topic, msg, stamp)
        conn = self._conns.get(topic)
        if conn is None:
            latch = topic in LATCHED_TOPICS if latched is None else latched
            qos = [_latched_qos()] if latch else []
            conn = self._writer.add_connection(
                topic, msgtype, typestore=typestore(), offered_qos_profiles=qos
            )
            self._conns[topic], self._types[topic] = conn, msgtype
            self.counts[topic] = 0
        elif self._types[topic] != msgtype:
            raise InvalidInputError(
                f"topic {topic} carries {self._types[topic]}, cannot write a {msgtype} on it"
            )
        self._writer.write(conn, ns, typestore().serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    def close(self) -> Path:
        """Finish the bag (idempotent); returns its path."""
        if self._closed:
            return self.path
        self._closed = True
        self._writer.close()
        if self._single:
            inner = self._dir / f"{self._dir.name}.mcap"
            inner.replace(self.path)
            shutil.rmtree(self._dir)
        return self.path

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

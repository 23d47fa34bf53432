"""A live view of a running twin in Foxglove: the recording's topics, served as they happen.

:class:`FoxgloveView` is a message sink with the interface of
:class:`~mmpa.backends.bag.writer.BagWriter` (``write(topic, msg, stamp)``, ``close()``), so the
:class:`~mmpa.backends.bag.record.Recorder` that writes a bag can feed it too (:class:`Tee` for
both). It serves Foxglove's WebSocket protocol through ``foxglove-sdk`` on localhost: each
topic becomes a channel with the ROS 2 message definition as its schema (``ros2msg``) and
the same CDR bytes as the bag, so Foxglove shows the scan, TF, particles, camera and map
with the layout of ``docs/foxglove_layout.json``. With no client connected, messages are
dropped by the server without being serialized (``Channel.has_sinks``).
"""

from __future__ import annotations

import logging
from typing import Any

from mmpa.backends.bag.messages import typestore
from mmpa.backends.bag.writer import LATCHED_TOPICS, log_time_ns
from mmpa.core.errors import InvalidInputError, MMPAError

__all__ = ["FoxgloveView", "Tee"]

_log = logging.getLogger(__name__)


class FoxgloveView:
    """A Foxglove WebSocket server (``ws://host:port``) publishing ROS 2 CDR messages."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8765, name: str = "mmpa") -> None:
        try:
            import foxglove
        except ImportError as e:  # pragma: no cover - depends on the install
            raise MMPAError("the live view needs foxglove-sdk: pip install foxglove-sdk") from e
        self._fg = foxglove
        self._context = foxglove.Context()
        #: the last message of each latched topic (map, static TF, reflectors): sent again to
        #: every client that subscribes later, as a ROS transient_local subscriber gets it
        self._latched: dict[str, tuple[bytes, int]] = {}
        view = self

        class _Listener(foxglove.ServerListener):
            def on_subscribe(self, client: Any, channel: Any) -> None:
                cached = view._latched.get(channel.topic)
                if cached is not None:
                    view._channels[channel.topic].log(cached[0], log_time=cached[1])

        try:
            self._server = foxglove.start_server(
                name=name,
                host=host,
                port=port,
                context=self._context,
                server_listener=_Listener(),
            )
        except Exception as e:  # the SDK raises its own error types (port in use, ...)
            raise MMPAError(f"cannot serve the Foxglove view on {host}:{port}: {e}") from e
        self.host, self.port = host, int(self._server.port)
        self._channels: dict[str, Any] = {}
        self._types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self._closed = False
        _log.info("Foxglove view on ws://%s:%d", self.host, self.port)

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _channel(self, topic: str, msgtype: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            msgdef, _ = typestore().generate_msgdef(msgtype, ros_version=2)
            schema = self._fg.Schema(name=msgtype, encoding="ros2msg", data=msgdef.encode())
            ch = self._fg.Channel(
                topic, schema=schema, message_encoding="cdr", context=self._context
            )
            self._channels[topic], self._types[topic] = ch, msgtype
            self.counts[topic] = 0
        elif self._types[topic] != msgtype:
            raise InvalidInputError(
                f"topic {topic} carries {self._types[topic]}, cannot publish a {msgtype} on it"
            )
        return ch

    def write(
        self, topic: str, msg: Any, stamp: float | None = None, latched: bool | None = None
    ) -> None:
        """Publish ``msg`` (a ``rosbags`` message) on ``topic`` at log time ``stamp`` s
        (default: its header stamp). ``latched`` (default: ``topic`` in ``LATCHED_TOPICS``):
        keep the message for clients that subscribe later."""
        if self._closed:
            raise MMPAError("the Foxglove view is closed")
        msgtype = msg.__msgtype__
        ch = self._channel(topic, msgtype)
        latch = topic in LATCHED_TOPICS if latched is None else latched
        if not ch.has_sinks() and not latch:
            return  # nobody listens: skip the serialization
        ns = log_time_ns(topic, msg, stamp)
        data = bytes(typestore().serialize_cdr(msg, msgtype))
        if latch:
            self._latched[topic] = (data, ns)
        ch.log(data, log_time=ns)
        self.counts[topic] += 1

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            for ch in self._channels.values():
                ch.close()
            self._server.stop()

    def __enter__(self) -> FoxgloveView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Tee:
    """One sink writing to several (a bag and the live view)."""

    def __init__(self, *sinks: Any) -> None:
        if not sinks:
            raise InvalidInputError("Tee needs at least one sink")
        self.sinks = sinks

    def write(
        self, topic: str, msg: Any, stamp: float | None = None, latched: bool | None = None
    ) -> None:
        for s in self.sinks:
            s.write(topic, msg, stamp, latched)

    def close(self) -> None:
        for s in self.sinks:
            s.close()

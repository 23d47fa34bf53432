"""What the ROS 2 tests over DDS share: a ``ROS_DOMAIN_ID`` of a test's own with discovery on
localhost, mmpa's nodes started as their console commands in processes of their own (their
output to a log file) and stopped with SIGINT as Ctrl-C stops them.

Not a test module (pytest collects ``test_*.py`` only); imported as ``tests.ros2_support``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

MMPA = [sys.executable, "-c", "from mmpa.cli.main import main; main()"]


def domain_id(key: str) -> str:
    """A ``ROS_DOMAIN_ID`` in 1..100 from ``key`` and this pytest worker and process."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw-")
    return str(1 + zlib.crc32(f"{worker}:{os.getpid()}:{key}".encode()) % 100)


@contextmanager
def ros_domain(key: str, logs: Path) -> Iterator[None]:
    """This process and the ones it starts on a domain of their own (from ``key``), discovery
    on localhost, Fast DDS, ROS logs under ``logs``; the environment restored after."""
    saved = dict(os.environ)
    os.environ |= {
        "ROS_DOMAIN_ID": domain_id(key),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_LOG_DIR": str(logs / "ros_log"),
        "RCUTILS_LOGGING_BUFFERED_STREAM": "0",
    }
    try:
        yield
    finally:
        os.environ.clear()
        os.environ.update(saved)


def start(args: list[str], log: Path) -> subprocess.Popen:
    """``mmpa ARGS...`` in a process of its own, stdout and stderr to ``log``."""
    return subprocess.Popen([*MMPA, *args], stdout=log.open("w"), stderr=subprocess.STDOUT)


def stop(proc: subprocess.Popen, log: Path | None = None) -> str:
    """SIGINT (Ctrl-C), then kill after 10 s; the log's text ('' without one)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return log.read_text() if log is not None and log.exists() else ""


class RawRecorder:
    """Records topics of a running graph as a bag does: each message's serialized bytes
    (``raw=True`` subscriptions) with its type and the receive time, then :meth:`write` puts
    them in an MCAP file with ``rosbags``' writer (schemas from the Jazzy type store with the
    interfaces mmpa builds)."""

    def __init__(self, node: Any, topics: dict[str, tuple[str, Any]]) -> None:
        from mmpa.backends.ros2 import messages

        self.types = {t: name for t, (name, _) in topics.items()}
        self.got: list[tuple[str, int, bytes]] = []
        self.subs = [
            node.create_subscription(
                messages.message_class(name),
                topic,
                lambda raw, topic=topic: self.got.append((topic, time.time_ns(), raw)),
                qos,
                raw=True,
            )
            for topic, (name, qos) in topics.items()
        ]

    def write(self, path: Path) -> Path:
        """The MCAP file ``path`` of what was recorded."""
        from rosbags.rosbag2 import StoragePlugin, Writer

        from mmpa.backends.ros2 import messages

        folder = path.with_suffix(".part")
        with Writer(folder, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {
                t: w.add_connection(t, name, typestore=messages.typestore())
                for t, name in self.types.items()
                if any(topic == t for topic, _, _ in self.got)
            }
            for topic, ns, raw in self.got:
                w.write(conns[topic], ns, raw)
        (folder / f"{folder.name}.mcap").replace(path)
        return path

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


#: the ``ROS_DOMAIN_ID`` s Fast DDS can use on Linux (its ports: 0..101 and 215..232; 0 left to
#: the user's own ROS system)
SAFE_DOMAINS = (*range(1, 102), *range(215, 233))
#: pytest-xdist workers the suite runs at most (Makefile: ``--maxprocesses 4``)
WORKERS = 4


def domain_number(key: str) -> int:
    """A ``ROS_DOMAIN_ID`` for ``key`` in this process. Each pytest-xdist worker draws from
    its own share of :data:`SAFE_DOMAINS` (every ``WORKERS``-th id), so tests running at the
    same time in different workers never share a domain; within a worker (tests run one
    after another) ``key`` and the process id spread them."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0")
    n = int(worker[2:]) if worker[2:].isdigit() else 0
    share = SAFE_DOMAINS[n % WORKERS :: WORKERS]
    return share[zlib.crc32(f"{os.getpid()}:{key}".encode()) % len(share)]


def domain_id(key: str) -> str:
    """:func:`domain_number` as the environment variable's text."""
    return str(domain_number(key))


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

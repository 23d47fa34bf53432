"""``mmpa ros2 play BAG`` over real DDS: a bag written by ``mmpa convert carmen`` (a short
synthetic CARMEN log in a room, with its map) is played by the console command in its own
process; this process subscribes to every topic of the bag raw (the serialized bytes) and
checks that every message arrives as the bag stores it, byte for byte and in order, that
``/map`` and ``/tf_static`` are offered transient local as recorded and that ``/clock`` runs
over the bag's time.

Skipped where the extra ``ros2`` is not installed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from rclpy.qos import DurabilityPolicy
from rosbags.highlevel import AnyReader
from tests.ros2_support import ros_domain, start, stop

from mmpa.apps.convert import convert_carmen
from mmpa.backends.ros2 import graph, messages
from mmpa.core.errors import InvalidInputError

TIMEOUT = 60.0
N_SCANS = 12
T0 = 50.0  # s, the log's first stamp
DT = 0.25  # s between scans
LAST = round((T0 + DT * (N_SCANS - 1)) * 1e9)  # ns: the last scan's stamp, the last /clock


def _carmen_log(path: Path) -> None:
    """``N_SCANS`` 180-beam scans of a 6 m x 4 m room (walls at x = +-3, y = +-2) from poses
    along a line, with the wheel odometry equal to them."""
    lines = ["PARAM robot_frontlaser_offset 0.0 nohost 0"]
    a = np.linspace(-np.pi / 2, np.pi / 2, 180)
    for k in range(N_SCANS):
        x, y, th = -1.0 + 0.1 * k, 0.2, 0.05 * k
        c, s = np.cos(a + th), np.sin(a + th)
        with np.errstate(divide="ignore"):
            tx = np.where(c > 0, (3 - x) / c, np.where(c < 0, (-3 - x) / c, np.inf))
            ty = np.where(s > 0, (2 - y) / s, np.where(s < 0, (-2 - y) / s, np.inf))
        r = " ".join(f"{v:.3f}" for v in np.minimum(tx, ty))
        t = T0 + DT * k
        lines.append(f"FLASER 180 {r} {x} {y} {th} {x} {y} {th} {t} host {t}")
    path.write_text("\n".join(lines) + "\n")


def _recorded(bag: Path) -> dict[str, list[bytes]]:
    """The bag's messages per topic as the bytes it stores (an independent read)."""
    out: dict[str, list[bytes]] = {}
    with AnyReader([bag]) as reader:
        for conn, _, raw in reader.messages():
            out.setdefault(conn.topic, []).append(bytes(raw))
    return out


@pytest.fixture(scope="module")
def carmen_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("play")
    _carmen_log(d / "room.log")
    convert_carmen(d / "room.log", d / "room.mcap", d / "map" / "room.yaml", 0.1)
    return d / "room.mcap"


def test_play_publishes_the_stored_bytes_with_the_recorded_qos(
    carmen_bag: Path, tmp_path: Path
) -> None:
    want = _recorded(carmen_bag)
    assert {"/scan", "/odom", "/tf", "/tf_static", "/map", "/initialpose"} <= set(want)
    types = {}
    with AnyReader([carmen_bag]) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
    got: dict[str, list[bytes]] = {t: [] for t in want}
    clock: list[int] = []
    log = tmp_path / "play.log"
    with ros_domain("play", tmp_path), graph.Session("mmpa_test_play_sub") as s:
        subs = []
        for topic in want:
            qos = graph.LATCHED if topic in ("/map", "/tf_static") else graph.TF
            subs.append(
                s.node.create_subscription(
                    messages.message_class(types[topic]),
                    topic,
                    got[topic].append,
                    qos,
                    raw=True,
                )
            )
        subs.append(
            s.node.create_subscription(
                messages.message_class("rosgraph_msgs/msg/Clock"),
                "/clock",
                lambda m: clock.append(m.clock.sec * 1_000_000_000 + m.clock.nanosec),
                graph.TF,
            )
        )
        proc = start(["ros2", "play", str(carmen_bag), "--rate", "2", "--delay", "4"], log)
        try:
            for sub in subs:
                assert graph.wait_until_matched(sub, 1, TIMEOUT), log.read_text()
            infos = {t: s.node.get_publishers_info_by_topic(t) for t in ("/map", "/tf_static")}

            def done() -> bool:
                """Every message and the last /clock taken (/clock is another writer: it may
                be taken after the last message)."""
                return all(len(got[t]) >= len(want[t]) for t in want) and LAST in clock[-1:]

            s.spin_until(lambda: done() or proc.poll() is not None, TIMEOUT)
            s.spin_until(done, 5.0)  # what is still on its way after the player's exit
            assert proc.wait(TIMEOUT) == 0, log.read_text()
        finally:
            text = stop(proc, log)
    for topic, msgs in want.items():
        assert got[topic] == msgs, (topic, len(got[topic]), len(msgs), text)
    for topic, info in infos.items():
        durability = [i.qos_profile.durability for i in info]
        assert durability == [DurabilityPolicy.TRANSIENT_LOCAL], topic
    # /clock: the bag's log time (the scans' stamps), never going back, up to the last one
    assert clock == sorted(clock) and len(clock) >= N_SCANS, clock
    assert clock[0] >= round(T0 * 1e9) and clock[-1] == LAST
    assert f"played {sum(map(len, want.values()))} messages" in text
    assert "not acknowledged" not in text, text


def test_play_refuses_a_missing_bag_and_unknown_topics(tmp_path: Path, carmen_bag: Path) -> None:
    from mmpa.apps.ros2_play import PlayConfig, play_bag

    with pytest.raises(InvalidInputError, match="does not exist"):
        play_bag(tmp_path / "nope.mcap", PlayConfig())
    with ros_domain("play-refuse", tmp_path), pytest.raises(InvalidInputError, match="no topic"):
        play_bag(carmen_bag, PlayConfig(topics=["/nope"]))
    assert math.isclose(PlayConfig().rate, 1.0)


def test_play_qos_from_the_recorded_profiles() -> None:
    """rosbags' recorded profile -> rclpy's: best effort stays best effort, transient local
    stays transient local with its depth; without one: latched for /map, else reliable."""
    from rclpy.qos import ReliabilityPolicy
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosTime
    from rosbags.interfaces import QosReliability as R

    from mmpa.apps.ros2_play import qos_of

    zero = QosTime(0, 0)
    q = Qos(
        QosHistory.KEEP_LAST, 5, R.BEST_EFFORT, QosDurability.VOLATILE, zero, zero,
        QosLiveliness.AUTOMATIC, zero, False,
    )  # fmt: skip
    got = qos_of("/scan", [q])
    assert (got.reliability, got.durability, got.depth) == (
        ReliabilityPolicy.BEST_EFFORT,
        DurabilityPolicy.VOLATILE,
        5,
    )
    q = q._replace(reliability=R.RELIABLE, durability=QosDurability.TRANSIENT_LOCAL, depth=1)
    assert qos_of("/x", [q]).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos_of("/map", []).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert qos_of("/scan", []).durability == DurabilityPolicy.VOLATILE
    assert qos_of("/scan", []).reliability == ReliabilityPolicy.RELIABLE

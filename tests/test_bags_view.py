"""The live Foxglove view: a WebSocket client on 127.0.0.1 speaks Foxglove's protocol
(foxglove.sdk.v1), sees the channels advertised with ROS 2 schemas, subscribes, and
receives scans and TF as the twin publishes them, byte-identical to the bag's CDR; a late
subscriber still gets the latched map."""

from __future__ import annotations

import asyncio
import json
import struct

import numpy as np
import pytest

pytest.importorskip("foxglove", reason="foxglove-sdk (dev dependency)")
websockets = pytest.importorskip("websockets")

from mmpa.apps.view import FoxgloveView  # noqa: E402
from mmpa.backends.bag import messages as rm  # noqa: E402
from mmpa.maps.occupancy import OccupancyGrid  # noqa: E402
from mmpa.robot.interfaces import LaserScan  # noqa: E402


def _scan(t: float) -> object:
    ranges = np.linspace(1.0, 2.0, 360)
    inc = 2 * np.pi / 360
    scan = LaserScan(-np.pi, np.pi - inc, inc, 0.0, 0.1, 0.05, 20.0, ranges, ranges * 10, t)
    return rm.laser_scan(scan, "laser")


async def _client(url: str, topics: list[str], n_expected: int, publish) -> tuple[dict, list]:
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"]) as ws:
        channels: dict[str, dict] = {}
        while not all(t in channels for t in topics):
            msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
            if msg.get("op") == "advertise":
                for ch in msg["channels"]:
                    channels[ch["topic"]] = ch
        subs = [{"id": i, "channelId": channels[t]["id"]} for i, t in enumerate(topics)]
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        await asyncio.sleep(0.2)
        publish()
        got = []
        while len(got) < n_expected:
            data = await asyncio.wait_for(ws.recv(), 5)
            if isinstance(data, bytes) and data[0] == 0x01:  # opcode: message data
                sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                got.append((topics[sub_id], log_time, data[13:]))
        return channels, got


def test_client_receives_scans_and_tf_with_ros2_schemas() -> None:
    grid = OccupancyGrid(np.zeros((20, 30), np.int8), 0.05, np.zeros(3))
    with FoxgloveView(port=0) as view:
        scan = _scan(12.5)
        tf = rm.tf_message([rm.transform_stamped(12.5, "map", "base_link", np.eye(4))])
        view.write("/map", rm.occupancy_grid(grid, 1.0))  # before anyone subscribes
        view.write("/scan", scan)  # no subscriber: dropped, but the channel is advertised
        view.write("/tf", tf, 12.5)

        def publish() -> None:
            view.write("/scan", scan)
            view.write("/tf", tf, 12.5)

        channels, got = asyncio.run(_client(view.url, ["/scan", "/tf", "/map"], 3, publish))
    assert channels["/scan"]["schemaName"] == "sensor_msgs/msg/LaserScan"
    assert channels["/scan"]["encoding"] == "cdr"
    assert channels["/scan"]["schemaEncoding"] == "ros2msg"
    assert "float32[] ranges" in channels["/scan"]["schema"]
    assert channels["/tf"]["schemaName"] == "tf2_msgs/msg/TFMessage"
    by_topic = {topic: (stamp, payload) for topic, stamp, payload in got}
    ts = rm.typestore()
    stamp, payload = by_topic["/scan"]
    assert stamp == 12_500_000_000
    assert payload == bytes(ts.serialize_cdr(scan, "sensor_msgs/msg/LaserScan"))
    back = ts.deserialize_cdr(payload, "sensor_msgs/msg/LaserScan")
    np.testing.assert_allclose(back.ranges, scan.ranges)
    assert (
        ts.deserialize_cdr(by_topic["/tf"][1], "tf2_msgs/msg/TFMessage")
        .transforms[0]
        .child_frame_id
        == "base_link"
    )
    grid_back = ts.deserialize_cdr(by_topic["/map"][1], "nav_msgs/msg/OccupancyGrid")
    assert (grid_back.info.width, grid_back.info.height) == (30, 20)  # latched: sent late
    assert view.counts["/scan"] == 1  # the scan before the client was not serialized

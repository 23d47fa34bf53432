"""``mmpa navigate`` and ``mmpa map export`` end to end."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from mmpa.cli.main import app
from mmpa.maps.map_server import load_map

runner = CliRunner()


def test_navigate_prints_parking_error(tmp_path) -> None:
    bag = tmp_path / "drive.mcap"
    res = runner.invoke(
        app, ["navigate", "--to", "2", "--out", str(tmp_path), "--record", str(bag)]
    )
    assert res.exit_code == 0, res.output
    assert "parking_error_xy_mm" in res.output
    s = json.loads((tmp_path / "summary.json").read_text())
    # realistic profile (the default), started from the operator's rough pose (0.2 m, 10 deg):
    # 8-9 mm localization error measured (DESIGN.md: 1.5-9.3 mm for this twin; reference
    # < 6 mm). This drive (seed 0, site 0 -> 2) ended 'not settled' on an AVX2 machine before
    # the final approach ran along the goal line; now it settles (200 seeded drives:
    # benchmarks/bench_drives.py), so the parking error is bounded by the localization error
    # plus the settle tolerance (4.5 mm, + 0.5 mm for the last step): no margin on the CPU
    assert s["profile"] == "realistic"
    assert s["reached"] and s["localization_error_xy_mm"] < 20
    assert s["parking_error_xy_mm"] <= s["localization_error_xy_mm"] + 5.0
    # the localizer's health over the drive: no false alarm where the estimate is right (the
    # map explains >= 0.97 of the beams on the twin's drives against the 0.5 'lost' level)
    assert s["localization_updates_not_ok"] == 0 and s["localization_explained_min"] > 0.8
    # --record: the drive as a ROS 2 bag (the run itself unchanged: the recorder only observes)
    from mmpa.backends.bag.reader import bag_topics

    topics = bag_topics(bag)
    assert topics["/scan"][0] == "sensor_msgs/msg/LaserScan" and topics["/scan"][1] > 50
    assert topics["/amcl_pose"][1] == topics["/scan"][1]
    assert topics["/map"][1] == 1 and topics["/odom"][1] > 0
    assert s["bag_messages"] == sum(n for _, n in topics.values())


def test_navigate_unknown_profile_fails_cleanly() -> None:
    res = runner.invoke(app, ["navigate", "--to", "2", "--profile", "gentle"])
    assert res.exit_code == 2 and "profile" in res.output


def test_navigate_unknown_site_fails_cleanly() -> None:
    res = runner.invoke(app, ["navigate", "--to", "9"])
    assert res.exit_code == 2 and "unknown site" in res.output


def test_map_export_round_trip(tmp_path) -> None:
    res = runner.invoke(app, ["map", "export", "--out", str(tmp_path / "m.yaml")])
    assert res.exit_code == 0, res.output
    g = load_map(tmp_path / "m.yaml")
    assert g.resolution == 0.05 and len(g.reflectors) == 9 and g.occupied.sum() > 1000

"""``mmpa --robot ros2.yaml calibrate hand-eye`` over real DDS (issue 36 item 4): the twin
node with a ChArUco board at site 0 (tests/ros2_board_twin.py, its own process, real time,
the camera at 15 Hz) and the command in another: the views planned from where the arm
stands, each reached over the trajectory topic, the board seen over the camera topics; the
twin's TRUE hand-eye (written by the helper) judges the result.

The same mission over the twin's devices behind a ros2 robot file runs by default
(tests/test_calibrate_backend.py); this one is slow. DDS domains of their own (215..232),
discovery on localhost; skipped without the extra.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "rclpy", reason="the ros2 extra is not installed (make setup installs it on x86-64 Linux)"
)

from mmpa.calibration.hand_eye import pose_error
from test_ros2_devices import domain, stop
from test_ros2_robot import MMPA, robot_file

HERE = Path(__file__).parent


@pytest.fixture(autouse=True)
def _localhost(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")


@pytest.mark.slow
def test_hand_eye_over_ros2_against_the_twin_node(tmp_path: Path) -> None:
    """8 views, opencv's methods, --yes: the hand-eye within the issue's 0.5 mm / 0.1 deg
    of the TRUE one (measured 0.022 mm, 0.010 deg; residuals 0.27 mm / 0.034 deg RMS), the
    residuals small, robot.yaml written; the twin node refused nothing. 31 s wall on 2
    cores."""
    dom = domain("hand-eye")
    truth, log = tmp_path / "truth.json", tmp_path / "twin.log"
    env = os.environ | {
        "ROS_DOMAIN_ID": str(dom),
        "ROS_LOG_DIR": str(tmp_path / "ros_log"),
        "MUJOCO_GL": os.environ.get("MUJOCO_GL", "osmesa"),
    }
    proc = subprocess.Popen(
        [sys.executable, str(HERE / "ros2_board_twin.py"), str(truth), "900"],
        stdout=log.open("w"), stderr=subprocess.STDOUT, env=env,
    )  # fmt: skip
    out = tmp_path / "out"
    try:
        args = ["--robot", str(robot_file(tmp_path, dom)), "calibrate", "hand-eye"]
        args += ["--out", str(out), "--yes", "--stations", "8", "--method", "opencv"]
        run = subprocess.run(
            [*MMPA, *args], capture_output=True, text=True, timeout=900,
            env=os.environ | {"COLUMNS": "200"},
        )  # fmt: skip
    finally:
        stop(proc)
    text = run.stdout + run.stderr
    assert run.returncode == 0, f"{text[-3000:]}\ntwin:\n{log.read_text()[-2000:]}"
    assert "refused" not in log.read_text()
    s = json.loads((out / "summary.json").read_text())
    assert s["ok"] and s["backend"] == "ros2" and s["stations_used"] == 8, s
    assert "error_trans_mm" not in s  # no truth on a hardware backend
    X = np.array(s["T_flange_camera"])
    et, er = pose_error(X, np.array(json.loads(truth.read_text())["T_flange_camera"]))
    print(f"hand-eye {et:.3f} mm, {er:.4f} deg from the truth; residuals {s['residuals']}")
    assert s["residuals"]["point_rms_mm"] < 1.0 and s["residuals"]["rot_rms_deg"] < 0.1
    assert et < 0.5 and er < 0.1, (et, er)
    assert (out / "robot.yaml").exists()

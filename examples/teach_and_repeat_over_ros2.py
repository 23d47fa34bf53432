"""Teach and repeat on a ROS 2 robot (``backend.kind: ros2``: a base on ``/cmd_vel``, a lidar,
realsense2_camera, ur_robot_driver, a gripper). The same as ``mmpa --robot robot.yaml teach
bench my_task --from X,Y,THETA`` then ``mmpa --robot robot.yaml run my_task --from ...``.

Your robot file needs (topic names: ``mmpa robot show``; docs/ros2.md)::

    backend:
      kind: ros2
      ros2: {topics: {pose: /amcl_pose}}   # or pose: "" and --from: mmpa's own localizer
      safety: {speed_scale: 0.25, watchdog_s: 0.5}

Run ``python examples/teach_and_repeat_over_ros2.py robot.yaml [X,Y,THETA]``: point the wrist
camera at the work area, press Enter, jog or guide the arm (``/joint_states`` is recorded),
press Enter; then the base drives to where it stood (localized) and the task repeats after
a question.

``--fake`` (what CI runs): the robot is the twin node (``mmpa ros2 twin --site 1 --camera
--speed 3``: three sim seconds per wall second where the CPU allows; started here on a DDS
domain of its own) and the person's demonstration a bag of
``/joint_states`` (joint 1 turned 0.1 rad and back): over real DDS, nothing here is hardware.
"""

from __future__ import annotations

import sys
from pathlib import Path

from mmpa.apps.robots import open_robot
from mmpa.apps.teach_person import teach_on_hardware
from mmpa.apps.teach_run import run_stored_task_on_robot


def main(robot_file: Path, start: str | None, bag: Path | None = None, **kw: object) -> dict:
    ask = None if "--yes" in sys.argv else (lambda q: input(f"{q} [y/N] ") == "y")
    common = {"kind": "ros2", "robot_file": robot_file, "start": start, "db": kw.get("db")}
    with open_robot(robot_file) as robot:  # its devices over ROS 2, each waited for
        print("taught:", teach_on_hardware(robot, "bench", "my_task", from_bag=bag,
              sample_q=kw.get("sample_q"), overwrite=True, **common))  # fmt: skip
        out = run_stored_task_on_robot(robot, "my_task", confirm=ask, **common)
        print("run:", {k: v for k, v in out.items() if k != "record"})
    return out


def _fake(folder: Path) -> tuple[Path, str, Path, dict, object]:
    """The twin node on a domain of this process, its robot file, the bag of a scripted
    person, where the robot stands and the view over the bench (site 1's needle view)."""
    import os
    import subprocess

    import numpy as np
    import yaml

    from mmpa.backends.bag import BagWriter
    from mmpa.backends.bag.messages import joint_state
    from mmpa.backends.twin.scene import load_scene

    dom = 215 + os.getpid() % 18
    os.environ |= {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(dom)}
    cmd = [sys.executable, "-c", "from mmpa.cli.main import main; main()", "ros2", "twin"]
    twin = ["--site", "1", "--camera", "--speed", "3"]
    node = subprocess.Popen([*cmd, *twin], stdout=subprocess.DEVNULL)
    names = [f"joint{i}" for i in range(1, 7)]  # the twin's joint names
    ros2 = {"joint_names": names, "use_sim_time": True, "domain_id": dom, "topics": {"pose": ""}}
    doc = {"backend": {"kind": "ros2", "ros2": {**ros2, "connect_timeout_s": 60.0}}}
    (folder / "robot.yaml").write_text(yaml.safe_dump(doc))
    view = np.array([2.7202, -1.909, 1.5077, -1.6534, -1.3566, -0.3969])
    t = np.arange(0.0, 2.0 + 1e-9, 0.02)
    s = 0.05 - 0.05 * np.cos(2 * np.pi * t / 2.0)  # 0 -> 0.1 rad -> 0, smoothly
    with BagWriter(folder / "demo.mcap") as bag:
        for tk, sk in zip(t, s, strict=True):
            bag.write("/joint_states", joint_state(10.0 + tk, names, view + sk * np.eye(6)[0]))
    x, y, th = load_scene().site("1").pose2d
    kw = {"sample_q": view, "db": str(folder / "tasks.db")}
    return folder / "robot.yaml", f"{x},{y},{th}", folder / "demo.mcap", kw, node


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if "--fake" in sys.argv:
        import tempfile

        with tempfile.TemporaryDirectory(prefix="mmpa_fake_ros2_") as tmp:
            path, start, bag, kw, node = _fake(Path(tmp))
            try:
                out = main(path, start, bag, **kw)
            finally:
                node.terminate()  # type: ignore[attr-defined]
                node.wait(10)  # type: ignore[attr-defined]
    elif args:
        out = main(Path(args[0]), args[1] if len(args) > 1 else None)
    else:
        sys.exit(__doc__)
    sys.exit(0 if out.get("executed") else 1)

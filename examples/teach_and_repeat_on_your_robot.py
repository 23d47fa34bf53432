"""Teach and repeat on your robot: the direct backend (a UR over RTDE, a RealSense over its
SDK, a fixed base). The same as ``mmpa --robot robot.yaml teach bench my_task`` then
``mmpa --robot robot.yaml run my_task``, in Python.

Your robot file (``mmpa robot show --out robot.yaml``, then edit) needs::

    backend:
      kind: direct
      direct: {ur_host: 192.168.1.10, realsense_serial: "123456789012", base: none}
      safety: {speed_scale: 0.25, watchdog_s: 0.2}

Run ``python examples/teach_and_repeat_on_your_robot.py robot.yaml``: put the arm where the
wrist camera sees the work area, press Enter, guide the arm by hand (UR freedrive), press
Enter again; then (move the work area a little) the task repeats after a question.

``--fake`` (what CI runs): the UR is the recording FAKE of RTDE (``mmpa.backends.ur_fake``,
replaying a scripted 'person' and a button on digital input 0) and the camera a RealSense
recording of a synthetic still scene; nothing here is hardware.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from mmpa.apps.teach_person import make_button, person_recorder, teach_on_robot
from mmpa.apps.teach_run import run_task_on_robot
from mmpa.backends.direct import open_direct
from mmpa.robot.robot_file import load_robot, robot_backend


def main(robot_file: str, button: str = "key", db: str | None = None) -> dict:
    backend, description = robot_backend(robot_file), load_robot(robot_file)[0]
    with open_direct(backend, description) as robot:  # teach: a person guides the arm
        record = person_recorder(robot, 50.0, make_button(button, robot))
        task, summary = teach_on_robot(robot, "bench", "my_task", record=record, db=db,
                                       overwrite=True, robot_id="direct")  # fmt: skip
        print("taught:", summary)
    with open_direct(backend, description) as robot:  # repeat: IPE, the adapted path
        ask = None if "--yes" in sys.argv else (lambda q: input(f"{q} [y/N] ") == "y")
        out = run_task_on_robot(robot, task, confirm=ask)
        print("run:", {k: v for k, v in out.items() if k != "record"})
    return out


def _fake_robot(folder: Path) -> str:
    """The FAKE robot of ``--fake``: a robot file whose RealSense is a recording of a still
    synthetic scene (a wavy textured surface 0.5 m away) and whose RTDE is
    :class:`~mmpa.backends.ur_fake.FakeRTDE` (handed in for ``connect_rtde``): a 'person'
    moves joint 1 by 0.2 rad over 2 s (smoothly), pressing digital input 0 at 0.1 s and 2.1 s."""
    import numpy as np

    from mmpa.backends import direct
    from mmpa.backends.realsense import record_frames
    from mmpa.backends.ur_fake import FakeRTDE
    from mmpa.robot.backend_config import BackendConfig, DirectBackend
    from mmpa.robot.description import default_robot
    from mmpa.robot.interfaces import RGBDFrame
    from mmpa.robot.robot_file import robot_to_yaml

    rb = default_robot()
    k = rb.camera.color
    v, u = np.mgrid[0 : k.height, 0 : k.width]
    depth = 0.5 + 0.03 * np.sin(u / 23.0) * np.cos(v / 17.0) + 0.02 * np.sin(u / 61.0 + v / 41.0)
    rng = np.random.default_rng(0)
    color = (rng.integers(0, 256, (k.height // 8 + 1, k.width // 8 + 1, 3)) // 1).astype(np.uint8)
    color = np.kron(color, np.ones((8, 8, 1), np.uint8))[: k.height, : k.width]
    frame = RGBDFrame(color, depth.astype(np.float32), k, 0.0)
    rec = record_frames([frame] * 100, folder / "scene.db3", depth_scale=1e-4)
    home = np.array(rb.arm.home)

    def connect(host: str, frequency: float):
        fake = FakeRTDE(home)
        t = np.arange(0.0, 2.5, 0.002)
        s = 0.5 - 0.5 * np.cos(np.pi * np.clip(t - 0.1, 0.0, 2.0) / 2.0)  # a smooth move
        fake.replay_freedrive(t, home + np.outer(s, [0.2, 0, 0, 0, 0, 0]))
        fake.digital_inputs([0.1, 0.2, 2.1, 2.2], [1, 0, 1, 0])
        return fake, fake

    direct.connect_rtde = connect  # the FAKE controller instead of ur-rtde
    backend = BackendConfig(
        kind="direct", direct=DirectBackend(ur_host="fake", realsense_playback=rec)
    )
    path = folder / "robot.yaml"
    path.write_text(robot_to_yaml(rb, backend=backend))
    return str(path)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    if "--fake" in sys.argv:
        with tempfile.TemporaryDirectory(prefix="mmpa_fake_robot_") as tmp:
            out = main(_fake_robot(Path(tmp)), button="di:0", db=str(Path(tmp) / "tasks.db"))
    elif args:
        out = main(args[0])
    else:
        sys.exit(__doc__)
    sys.exit(0 if out.get("executed") else 1)

"""``mmpa --robot R teach`` and ``mmpa --robot R run`` on the direct backend, end to end
through the CLI: the UR arm is URArm over the recording FAKE of RTDE
(mmpa.backends.ur_fake), the camera a RealSense recording played by the SDK (the twin
camera's frames: at the sampling pose for teaching, IPE's views for the run). Teaching: the
twin operator's demonstration replayed as a freedrive, a button on digital input 0. Run:
--dry-run writes the path and a picture and sends nothing after the IPE views; without
--yes it asks and "n" moves nothing; --yes streams the adapted path."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest

pytest.importorskip("pyrealsense2", reason="the optional extra 'realsense'")

from typer.testing import CliRunner

from mmpa.backends import direct
from mmpa.backends.bag.messages import joint_state
from mmpa.backends.bag.writer import BagWriter
from mmpa.backends.realsense import record_frames
from mmpa.backends.twin.operator import load_demonstrations
from mmpa.backends.twin.scene import load_scene
from mmpa.backends.twin.world import SimWorld
from mmpa.backends.ur_fake import FakeRTDE
from mmpa.cli import robot as cli_robot
from mmpa.cli.main import app
from mmpa.harness.twin_site import MMPAExperimentConfig, teach_in_world
from mmpa.missions.teach_repeat import AutomationConfig, automate
from mmpa.robot.backend_config import UR_JOINT_NAMES, BackendConfig, DirectBackend
from mmpa.robot.description import CameraIntrinsics, default_robot, set_default_robot
from mmpa.robot.interfaces import RGBDFrame, RobotDevices
from mmpa.robot.robot_file import robot_to_yaml

T0 = 0.5


def _keep(camera) -> list:
    """Keep every frame the twin's ``camera`` hands out (in the returned list)."""
    frames, capture = [], camera.capture

    def keep():
        frames.append(capture())
        return frames[-1]

    camera.capture = keep
    return frames


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """The needle task taught in the twin with its view recorded; then the twin parked off
    by (3 cm, -2 cm, 2 deg) and IPE run there without a prior (as on a fixed base), its
    views recorded: the two RealSense recordings, the twin task, IPE's result."""
    d = tmp_path_factory.mktemp("rec")
    cfg = MMPAExperimentConfig()
    w = SimWorld(load_scene(cfg.scene), errors=cfg.errors, site="1")
    frames = _keep(w.camera)
    tw = teach_in_world(w, load_demonstrations()["needle_site1"], "1", cfg)
    teach_rec = record_frames(frames, d / "teach.db3")
    pose = w.truth.base_pose2d()
    w.reset(site="1", pose2d=pose + np.array([0.03, -0.02, np.deg2rad(2.0)]))
    frames.clear()
    robot = RobotDevices(w.nominal, arm=w.arm, camera=w.camera, clock=w)
    live = automate(tw.task, robot, cfg=AutomationConfig(execute=False))
    assert live.ok, live.reason
    run_rec = record_frames(frames, d / "run.db3")
    q_home = w.arm.joint_positions()
    w.close()
    return tw.task, teach_rec, run_rec, live, q_home


@pytest.fixture
def cli(tmp_path, monkeypatch):
    """A direct robot file per recording; the CLI opens its robot (apps.robots.open_robot ->
    backends.direct.open_direct) with the fake of RTDE handed in by connect_rtde."""
    fakes: list[FakeRTDE] = []
    state = {"q0": None, "setup": None}

    def connect(host, frequency):
        fake = FakeRTDE(state["q0"])
        if state["setup"] is not None:
            state["setup"](fake)
        fakes.append(fake)
        return fake, fake

    monkeypatch.setattr(direct, "connect_rtde", connect)

    def robot_file(rec, name):
        path = tmp_path / name
        b = BackendConfig(kind="direct", direct=DirectBackend(ur_host="10.0.0.7",
                          realsense_playback=rec))  # fmt: skip
        path.write_text(robot_to_yaml(default_robot(), backend=b))
        return path

    yield robot_file, state, fakes
    set_default_robot(None)
    cli_robot._path = None
    cli_robot._frames = None


@pytest.mark.slow  # 47 s on 2 cores; the same CLI lines cheaply: the test below
def test_teach_then_run_on_the_direct_backend(recorded, cli, tmp_path) -> None:
    task, teach_rec, run_rec, live, q_home = recorded
    robot_file, state, fakes = cli
    db = str(tmp_path / "tasks.db")
    t_end = float(task.path.t[-1])

    def freedrive(fake):
        fake.replay_freedrive(T0 + task.path.t, task.path.q)
        fake.digital_inputs([T0, T0 + 0.1, T0 + t_end, T0 + t_end + 0.1], [1, 0, 1, 0])

    state["q0"], state["setup"] = q_home, freedrive
    q = ",".join(repr(float(x)) for x in task.q_sample)
    r = CliRunner().invoke(app, ["--robot", str(robot_file(teach_rec, "teach.yaml")), "teach",
                                 "1", "needle", "--button", "di:0", "--sample-q", q,
                                 "--db", db])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert "path_waypoints" in r.output and str(len(task.path.t)) in r.output
    from mmpa.tasks import TaskStore

    with TaskStore(db) as store:
        stored = store.load("needle")
    np.testing.assert_array_equal(stored.path.q, task.path.q)
    assert stored.robot_id == "direct"

    state["setup"] = None
    run_file = str(robot_file(run_rec, "run.yaml"))
    r = CliRunner().invoke(app, ["--robot", run_file, "run", "needle", "--db", db,
                                 "--dry-run", str(tmp_path / "dry")])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert {n for _, n, _ in fakes[-1].motion_commands()} == {"moveJ"}  # the views only
    for f in ("adapted_path.csv", "adapted_path.json", "adapted_path.png"):
        assert (tmp_path / "dry" / f).is_file()
    r = CliRunner().invoke(app, ["--robot", run_file, "run", "needle", "--db", db], input="n\n")
    assert r.exit_code == 1 and "move the arm along the adapted path?" in r.output, r.output
    assert "not confirmed" in r.output
    assert {n for _, n, _ in fakes[-1].motion_commands()} == {"moveJ"}
    r = CliRunner().invoke(app, ["--robot", run_file, "run", "needle", "--db", db, "--yes"])
    assert r.exit_code == 0, r.output
    _, qs = fakes[-1].servo_targets()
    assert len(qs) > 100 and "move the arm" not in r.output
    np.testing.assert_allclose(qs[-1], live.joint_path.q[-1], atol=2e-3)


def test_teach_from_a_bag_and_a_stopped_arm_on_the_direct_backend(cli, tmp_path) -> None:
    """The CLI lines without the twin: teach --from-bag (a 2 s demonstration, a flat view of
    64x48 pixels at 0.5 m), then run with the arm in protective stop: refused before
    anything is sent, exit status 1."""
    robot_file, state, fakes = cli
    home = np.array(default_robot().arm.home)
    k = CameraIntrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    view = RGBDFrame(np.full((48, 64, 3), 128, np.uint8), np.full((48, 64), 0.5, np.float32),
                     k, 0.0)  # fmt: skip
    rec = record_frames([view] * 16, tmp_path / "view.db3")
    bag = tmp_path / "demo.mcap"
    t = np.arange(101) * 0.02
    with BagWriter(bag) as b:
        for ti in t:
            q = home + np.array([0.1 * ti, 0, 0, 0, 0, 0])
            b.write("/joint_states", joint_state(7.0 + ti, list(UR_JOINT_NAMES), q))
    state["q0"] = home
    path = str(robot_file(rec, "r.yaml"))
    db = str(tmp_path / "tasks.db")
    r = CliRunner().invoke(app, ["--robot", path, "teach", "1", "demo", "--from-bag", str(bag),
                                 "--db", db])  # fmt: skip
    assert r.exit_code == 0, r.output
    from mmpa.tasks import TaskStore

    with TaskStore(db) as store:
        task = store.load("demo")
    assert len(task.cloud) == 64 * 48 and task.path.rate_hz == pytest.approx(50.0)
    np.testing.assert_allclose(task.path.q[-1], home + np.array([0.2, 0, 0, 0, 0, 0]), atol=1e-12)
    np.testing.assert_array_equal(task.T_map_base_park, np.eye(4))
    assert [n for _, n, _ in fakes[-1].motion_commands()] == ["moveJ"]  # to where it stood

    def stopped(fake):
        fake.protective_stop_at = 0.0

    state["setup"] = stopped
    r = CliRunner().invoke(app, ["--robot", path, "run", "demo", "--db", db, "--yes"])
    assert r.exit_code == 1 and "protective stop" in r.output, r.output
    assert fakes[-1].motion_commands() == []
    r = CliRunner().invoke(app, ["--robot", path, "teach", "1", "x", "--db", db])
    assert r.exit_code != 0 and "protective stop: clear it on the pendant" in r.output
    cli_robot._path = None  # back to the twin (the --robot of this process is kept)
    r = CliRunner().invoke(app, ["teach", "1", "x", "--from-bag", str(bag), "--db", db])
    assert r.exit_code != 0 and "ros2 / direct robot" in r.output

"""ROS bags in and out (issue 20): messages, writer, bag-backed sensors, recorder, offline
localization."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from mmpa.apps.localize import LocalizeConfig, grid_from_bag, localize_bag
from mmpa.backends.bag import BagWriter, Recorder
from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.reader import (
    BagCamera,
    BagLidar,
    BagOdometry,
    BagPlayback,
    BagTopics,
    EndOfBagError,
    bag_topics,
)
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import R_to_quat_xyzw, T_to_se2, rpy_to_R, se2_to_T, vec6_to_T
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import LaserScan, Odometry, RGBDFrame


def _scan(stamp: float, rng: np.random.Generator, n: int = 181) -> LaserScan:
    a0, inc = -math.pi / 2, math.pi / (n - 1)
    r = rng.uniform(0.2, 8.0, n)
    r[5] = np.inf
    inten = rng.uniform(0, 2000, n)
    return LaserScan(a0, a0 + inc * (n - 1), inc, 1e-4, 0.1, 0.05, 10.0, r, inten, stamp)


def _read_all(path) -> dict[str, list]:
    """Every message by topic, with its connection's type, through rosbags itself."""
    out: dict[str, list] = {}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            out.setdefault(conn.topic, []).append(
                (conn.msgtype, t, reader.deserialize(raw, conn.msgtype))
            )
    return out


def test_writer_round_trips_every_message_type(tmp_path) -> None:
    rng = np.random.default_rng(1)
    scans = [_scan(0.1 * (i + 1), rng) for i in range(3)]
    odo = Odometry(np.array([1.5, -0.25, 2.9]), np.array([0.3, -0.1]), 0.2)
    k = CameraIntrinsics(width=8, height=6, fx=7.0, fy=7.5, cx=3.5, cy=2.5)
    color = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    depth = rng.uniform(0.3, 3.0, (6, 8)).astype(np.float32)
    depth[0, 0] = 0.0
    frame = RGBDFrame(color, depth, k, 0.25)
    T_cam = vec6_to_T([0.1, -0.2, 0.3, 0.4, -0.5, 0.6])
    grid = OccupancyGrid(
        np.array([[0, 100, -1], [0, 0, 100]], np.int8),
        0.05,
        (-1.0, 2.0, 0.0),
        [[1, 2], [3, 4]],
        0.04,
    )
    q = np.array([0.1, -1.2, 1.0, -0.3, 0.5, 2.0])
    cov = np.diag([0.01, 0.02, 0.003])
    cov[0, 1] = cov[1, 0] = 0.004
    particles = rng.normal(0, 1, (7, 3))
    path = tmp_path / "all.mcap"
    with BagWriter(path) as bag:
        for s in scans:
            bag.write("/scan", rm.laser_scan(s))
        bag.write("/odom", rm.odometry(odo))
        bag.write(
            "/tf_static",
            rm.tf_message([rm.transform_stamped(0.0, "base_link", "laser", T_cam)]),
            0.0,
        )
        bag.write(
            "/tf", rm.tf_message([rm.transform_stamped(0.2, "odom", "base_link", odo.pose)]), 0.2
        )
        bag.write("/joint_states", rm.joint_state(0.3, [f"joint{i}" for i in range(1, 7)], q))
        bag.write("/camera/color/image_raw", rm.rgb_image(frame))
        bag.write("/camera/aligned_depth_to_color/image_raw", rm.depth_image(frame))
        bag.write("/camera/color/camera_info", rm.camera_info(k, 0.25))
        bag.write("/map", rm.occupancy_grid(grid, 0.0))
        bag.write("/reflectors", rm.reflector_markers(0.0, grid.reflectors, 0.04), 0.0)
        bag.write("/amcl_pose", rm.pose_cov_stamped(0.3, "map", [1.0, 2.0, -3.0], cov))
        bag.write("/particlecloud", rm.pose_array(0.3, "map", particles))
        bag.write("/truth/base_pose", rm.pose_stamped(0.3, "map", T_cam))
    assert path.is_file() and not (tmp_path / "all.mcap.part").exists()
    got = _read_all(path)
    types = {t: v[0][0] for t, v in got.items()}
    assert types == {
        "/scan": "sensor_msgs/msg/LaserScan",
        "/odom": "nav_msgs/msg/Odometry",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/joint_states": "sensor_msgs/msg/JointState",
        "/camera/color/image_raw": "sensor_msgs/msg/Image",
        "/camera/aligned_depth_to_color/image_raw": "sensor_msgs/msg/Image",
        "/camera/color/camera_info": "sensor_msgs/msg/CameraInfo",
        "/map": "nav_msgs/msg/OccupancyGrid",
        "/reflectors": "visualization_msgs/msg/MarkerArray",
        "/amcl_pose": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "/particlecloud": "geometry_msgs/msg/PoseArray",
        "/truth/base_pose": "geometry_msgs/msg/PoseStamped",
    }
    assert {t: len(v) for t, v in got.items()}["/scan"] == 3
    assert all(len(v) == 1 for t, v in got.items() if t != "/scan")
    # scans: log time = header stamp in ns, frame, float32 values, inf kept
    for s, (_, t_log, m) in zip(scans, got["/scan"], strict=True):
        assert t_log == round(s.stamp * 1e9)
        assert m.header.frame_id == "laser"
        np.testing.assert_array_equal(m.ranges, s.ranges.astype(np.float32))
        np.testing.assert_array_equal(m.intensities, s.intensities.astype(np.float32))
        back = rm.from_laser_scan(m)
        assert back.stamp == pytest.approx(s.stamp, abs=1e-9)
        np.testing.assert_allclose(back.angles, s.angles, atol=1e-6)
        assert np.isinf(back.ranges[5])
    o = got["/odom"][0][2]
    assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_link")
    back = rm.from_odometry(o)
    np.testing.assert_allclose(back.pose, odo.pose, atol=1e-12)
    np.testing.assert_allclose(back.twist, odo.twist)
    # the yaw as a quaternion about z, independently
    qz = o.pose.pose.orientation
    assert (qz.z, qz.w) == pytest.approx((math.sin(1.45), math.cos(1.45)))
    ts = got["/tf_static"][0][2].transforms[0]
    parent, child, T = rm.from_transform(ts)
    assert (parent, child) == ("base_link", "laser")
    np.testing.assert_allclose(T, T_cam, atol=1e-12)
    np.testing.assert_allclose(
        [
            ts.transform.rotation.x,
            ts.transform.rotation.y,
            ts.transform.rotation.z,
            ts.transform.rotation.w,
        ],
        R_to_quat_xyzw(T_cam[:3, :3]),
    )
    js = got["/joint_states"][0][2]
    assert list(js.name) == [f"joint{i}" for i in range(1, 7)]
    np.testing.assert_array_equal(js.position, q)
    img = got["/camera/color/image_raw"][0][2]
    assert (img.encoding, img.height, img.width, img.step) == ("rgb8", 6, 8, 24)
    assert img.header.frame_id == "camera_color_optical_frame"
    np.testing.assert_array_equal(rm.from_image_rgb(img), color)
    dm = got["/camera/aligned_depth_to_color/image_raw"][0][2]
    assert (dm.encoding, dm.step) == ("16UC1", 16)
    mm = np.frombuffer(bytes(dm.data), "<u2").reshape(6, 8)
    np.testing.assert_array_equal(mm, np.rint(depth * 1000).astype(np.uint16))
    assert np.abs(rm.from_depth_image(dm) - depth).max() <= 0.0005 + 1e-7
    ci = got["/camera/color/camera_info"][0][2]
    np.testing.assert_array_equal(np.asarray(ci.k).reshape(3, 3), k.K)
    assert rm.from_camera_info(ci) == k
    g = got["/map"][0][2]
    assert (g.info.width, g.info.height) == (3, 2)
    assert g.info.resolution == np.float32(0.05)  # float32 in ROS
    assert (g.info.origin.position.x, g.info.origin.position.y) == (-1.0, 2.0)
    assert list(g.data) == [0, 100, -1, 0, 0, 100]  # row 0 (bottom) first, as ROS
    mk = got["/reflectors"][0][2].markers
    assert [(m.pose.position.x, m.pose.position.y, m.scale.x) for m in mk] == [
        (1.0, 2.0, 0.08),
        (3.0, 4.0, 0.08),
    ]
    t_p, pose, cov_back = rm.from_pose_cov(got["/amcl_pose"][0][2])
    assert t_p == pytest.approx(0.3)
    np.testing.assert_allclose(pose, [1.0, 2.0, -3.0], atol=1e-12)
    np.testing.assert_array_equal(cov_back, cov)
    c36 = np.asarray(got["/amcl_pose"][0][2].pose.covariance).reshape(6, 6)
    assert c36[5, 5] == 0.003 and c36[0, 1] == 0.004 and c36[2, 2] == 0.0  # yaw in slot 5
    pa = got["/particlecloud"][0][2].poses
    np.testing.assert_allclose(
        [T_to_se2(rm.from_pose(p)) for p in pa],
        particles * [1, 1, 0]
        + [0, 0, 1] * np.arctan2(np.sin(particles[:, 2:]), np.cos(particles[:, 2:])),
        atol=1e-12,
    )
    np.testing.assert_allclose(rm.from_pose(got["/truth/base_pose"][0][2].pose), T_cam, atol=1e-12)


def test_writer_refuses_overwrite_and_mixed_types(tmp_path) -> None:
    path = tmp_path / "x.mcap"
    with BagWriter(path) as bag:
        bag.write("/pose", rm.pose_stamped(1.0, "map", [0, 0, 0]))
        with pytest.raises(InvalidInputError, match="carries geometry_msgs/msg/PoseStamped"):
            bag.write("/pose", rm.pose_cov_stamped(1.0, "map", [0, 0, 0], None))
        with pytest.raises(InvalidInputError, match="no header"):
            bag.write("/tf", rm.tf_message([]))
    with pytest.raises(InvalidInputError, match="exists already"):
        BagWriter(path)
    assert bag_topics(path) == {"/pose": ("geometry_msgs/msg/PoseStamped", 1)}


def test_sqlite3_rosbag2_folder_through_the_backend(tmp_path) -> None:
    rng = np.random.default_rng(2)
    scans = [_scan(1.0 + 0.1 * i, rng) for i in range(4)]
    path = tmp_path / "bag2"
    with BagWriter(path, storage="sqlite3") as bag:
        for i, s in enumerate(scans):
            # odometry at 20 Hz, the scans at 10 Hz, odometry stamped with each scan too
            for dt in (0.0, 0.05):
                pose = np.array([0.1 * i + dt, 0.0, 0.01 * i])
                bag.write("/odom", rm.odometry(Odometry(pose, np.zeros(2), s.stamp + dt)))
            bag.write("/scan", rm.laser_scan(s))
    assert (path / "metadata.yaml").is_file() and (path / "bag2.db3").is_file()
    pb = BagPlayback.open(path)
    lidar, odom = BagLidar(pb), BagOdometry(pb)
    assert len(lidar) == 4 and len(pb.odometry) == 8
    for i, s in enumerate(scans):
        got = lidar.scan()
        np.testing.assert_array_equal(got.ranges, s.ranges.astype(np.float32))
        # the odometry at the scan's stamp, not the one 50 ms later
        np.testing.assert_allclose(odom.odometry().pose, [0.1 * i, 0.0, 0.01 * i], atol=1e-12)
    with pytest.raises(EndOfBagError):
        lidar.scan()


def test_ros1_bag_through_the_backend(tmp_path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    LS = ts.types["sensor_msgs/msg/LaserScan"]
    Od = ts.types["nav_msgs/msg/Odometry"]
    G = {
        n: ts.types[f"geometry_msgs/msg/{n}"]
        for n in (
            "Point",
            "Quaternion",
            "Pose",
            "PoseWithCovariance",
            "Twist",
            "TwistWithCovariance",
            "Vector3",
        )
    }
    rng = np.random.default_rng(3)
    n = 91
    path = tmp_path / "old.bag"
    ranges = [rng.uniform(0.5, 5.0, n).astype(np.float32) for _ in range(3)]
    with Writer(path) as w:
        cs = w.add_connection("/front/scan", LS.__msgtype__, typestore=ts)
        co = w.add_connection("/wheel_odom", Od.__msgtype__, typestore=ts)
        for i in range(3):
            t = 5.0 + 0.1 * i
            hdr = Header(seq=i, stamp=Time(sec=5, nanosec=round(0.1 * i * 1e9)), frame_id="laser")
            yaw = 0.2 * i
            pose = G["Pose"](
                position=G["Point"](x=float(i), y=2.0, z=0.0),
                orientation=G["Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
            )
            odo = Od(
                header=Header(seq=i, stamp=hdr.stamp, frame_id="odom"),
                child_frame_id="base_link",
                pose=G["PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=G["TwistWithCovariance"](
                    twist=G["Twist"](
                        linear=G["Vector3"](x=0.5, y=0.0, z=0.0),
                        angular=G["Vector3"](x=0.0, y=0.0, z=0.1),
                    ),
                    covariance=np.zeros(36),
                ),
            )
            w.write(co, round(t * 1e9), ts.serialize_ros1(odo, Od.__msgtype__))
            scan = LS(
                header=hdr,
                angle_min=-1.5,
                angle_max=1.5,
                angle_increment=3.0 / (n - 1),
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.1,
                range_max=20.0,
                ranges=ranges[i],
                intensities=np.zeros(0, np.float32),
            )
            w.write(cs, round(t * 1e9), ts.serialize_ros1(scan, LS.__msgtype__))
    pb = BagPlayback.open(path, BagTopics(scan="/front/scan", odom="/wheel_odom"))
    lidar, odom = BagLidar(pb), BagOdometry(pb)
    assert len(lidar) == 3
    for i in range(3):
        s = lidar.scan()
        assert s.stamp == pytest.approx(5.0 + 0.1 * i) and s.frame_id == "laser"
        np.testing.assert_array_equal(s.ranges, ranges[i])
        np.testing.assert_array_equal(s.intensities, np.zeros(n))  # none recorded
        assert s.angles[-1] == pytest.approx(1.5, abs=1e-6)
        o = odom.odometry()
        np.testing.assert_allclose(o.pose, [i, 2.0, 0.2 * i], atol=1e-12)
        np.testing.assert_allclose(o.twist, [0.5, 0.1])


def _ros_precision(scan: LaserScan) -> LaserScan:
    """The scan as a ROS LaserScan carries it (float32 fields), back as mmpa's value."""
    return rm.from_laser_scan(rm.laser_scan(scan))


class _RosPrecisionLidar:
    def __init__(self, inner) -> None:
        self._inner = inner

    def scan(self) -> LaserScan:
        return _ros_precision(self._inner.scan())


class _RosPrecisionWorld:
    """A (recording) world whose lidar hands out scans at ROS precision."""

    def __init__(self, world) -> None:
        self._world = world

    @property
    def lidar(self) -> _RosPrecisionLidar:
        return _RosPrecisionLidar(self._world.lidar)

    def __getattr__(self, k):
        return getattr(self._world, k)


@pytest.fixture(scope="module")
def twin_recording(tmp_path_factory):
    """A short standing localization in the twin, recorded; live estimates for two lidars:
    the twin's own, and the same scans at ROS precision."""
    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
    from mmpa.backends.twin.world import SimWorld
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.navigate import localize_standing

    d = tmp_path_factory.mktemp("twin")
    out = {}
    for name in ("plain", "ros_precision"):
        with SimWorld() as world:
            grid = twin_map(world)
            with BagWriter(d / f"{name}.mcap") as bag:
                rec = Recorder(bag, world)
                w = rec.world()
                rec.write_map(grid)
                rng = np.random.default_rng(7)
                loc = rec.localizer(make_localizer("enhanced", grid, laser_pose2d(world), rng))
                loc.initialize(rough_initial_pose(world))
                live_world = _RosPrecisionWorld(w) if name == "ros_precision" else w
                live = localize_standing(live_world, loc, scans=4)  # type: ignore[arg-type]
                frame = w.camera.capture() if name == "plain" else None
                truth = world.truth.base_pose2d()
                counts = dict(bag.counts)
            out[name] = (d / f"{name}.mcap", grid, live, truth, frame, counts)
    return out


def test_recorded_twin_topics(twin_recording) -> None:
    path, grid, _live, truth, frame, counts = twin_recording["plain"]
    topics = bag_topics(path)
    assert {k: v[1] for k, v in topics.items()} == counts
    assert counts["/scan"] == 4 and counts["/amcl_pose"] == 4 and counts["/particlecloud"] == 4
    assert counts["/odom"] == 4  # one per new odometry reading (each before a scan)
    assert counts["/joint_states"] == counts["/truth/base_pose"] == 5  # 4 scans + 1 capture
    for t in ("/map", "/reflectors", "/tf_static", "/initialpose", "/camera/color/image_raw"):
        assert counts[t] == 1
    with AnyReader([path]) as r:
        qos = {c.topic: c.ext.offered_qos_profiles for c in r.connections}
    assert "transient_local" in str(qos["/tf_static"]).lower() or "TRANSIENT_LOCAL" in str(
        qos["/tf_static"]
    )
    pb = BagPlayback.open(path)
    # the static mounts are the NOMINAL ones
    from mmpa.robot.description import default_robot

    rob = default_robot()
    np.testing.assert_allclose(
        pb.static_transform("base_link", "laser"), rob.lidar.T_base_link_laser, atol=1e-12
    )
    np.testing.assert_allclose(
        pb.static_transform("flange", "camera_color_optical_frame"),
        rob.camera.T_flange_camera,
        atol=1e-12,
    )
    # truth at the last scan: the base stood still, so it is the truth at the end
    np.testing.assert_allclose(pb.truth_base[1][-1], truth, atol=1e-9)
    # the map and landmarks come back from the bag
    g = grid_from_bag(path)
    np.testing.assert_array_equal(g.data, grid.data)
    np.testing.assert_allclose(g.reflectors, grid.reflectors, atol=1e-12)
    assert g.resolution == grid.resolution and g.origin == pytest.approx(grid.origin)
    # the camera frame: colour exact, depth to the millimetre, same intrinsics
    cam = BagCamera(path)
    f = cam.capture()
    np.testing.assert_array_equal(f.color, frame.color)
    ok = frame.depth > 0
    assert np.array_equal(f.depth > 0, ok & (np.rint(frame.depth * 1000) > 0))
    assert np.abs(f.depth[ok] - frame.depth[ok]).max() <= 0.0005 + 1e-6
    assert f.intrinsics == frame.intrinsics and f.stamp == pytest.approx(frame.stamp)


def test_offline_localization_reproduces_the_live_run(twin_recording) -> None:
    cfg = LocalizeConfig(method="enhanced", seed=7, force=True)
    # same scans at ROS precision live and offline: the same estimate, to float noise
    # (measured 4e-8 m: the poses pass through quaternions and float32 stamps)
    path, grid, live, _, _, _ = twin_recording["ros_precision"]
    res = localize_bag(BagPlayback.open(path), grid, cfg)
    assert len(res.t) == 4
    np.testing.assert_allclose(res.estimate[-1], live, rtol=0, atol=1e-6)
    # the twin's float64 scans live vs their float32 ROS copies offline: micrometres apart
    path, grid, live, truth, _, _ = twin_recording["plain"]
    res = localize_bag(BagPlayback.open(path), grid, cfg)
    assert np.hypot(*(res.estimate[-1][:2] - live[:2])) < 5e-5
    # a different seed is a different particle filter run: the test can tell them apart
    other = localize_bag(BagPlayback.open(path), grid, cfg.model_copy(update={"seed": 8}))
    assert np.abs(other.estimate[-1] - res.estimate[-1]).max() > 1e-5
    err = res.errors()
    assert err is not None
    assert err["error_final_mm"] == pytest.approx(
        np.hypot(*(res.estimate[-1][:2] - truth[:2])) * 1e3, abs=1e-3
    )


def test_localize_cli_writes_the_run_folder(twin_recording, tmp_path) -> None:
    from typer.testing import CliRunner

    from mmpa.cli.main import app

    path = twin_recording["plain"][0]
    out = tmp_path / "loc"
    r = CliRunner().invoke(
        app, ["localize", "--bag", str(path), "--out", str(out), "--seed", "7", "--force"]
    )
    assert r.exit_code == 0, r.output
    s = json.loads((out / "summary.json").read_text())
    assert s["scans"] == 4 and s["truth"] is True and s["error_mean_mm"] < 50.0
    rows = np.loadtxt(out / "estimate.csv", delimiter=",", skiprows=1)
    assert rows.shape == (4, 15)  # + ok, explained, crossed, spread_xy (health)
    np.testing.assert_allclose(rows[-1, 1:4], s["final_estimate"], atol=1e-6)
    assert (out / "trajectory.png").stat().st_size > 1000
    got = bag_topics(out / "estimate.mcap")
    assert got["/amcl_pose"] == ("geometry_msgs/msg/PoseWithCovarianceStamped", 4)
    # the same run on the map given as a map_server file: the same estimates
    from mmpa.maps.map_server import save_map

    map_yaml = save_map(twin_recording["plain"][1], tmp_path / "map" / "map.yaml")
    out2 = tmp_path / "loc2"
    args = ["localize", "--bag", str(path), "--map", str(map_yaml), "--out", str(out2)]
    r = CliRunner().invoke(app, [*args, "--seed", "7", "--force"])
    assert r.exit_code == 0, r.output
    rows2 = np.loadtxt(out2 / "estimate.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows2, rows, atol=1e-9)
    # a map without reflectors plus the reflectors as their own file: the same estimates
    import dataclasses

    from mmpa.maps.reflector_map import ReflectorMap, save_reflector_map

    grid = twin_recording["plain"][1]
    bare = dataclasses.replace(grid, reflectors=np.zeros((0, 2)), reflector_radius=0.0)
    bare_yaml = save_map(bare, tmp_path / "bare" / "map.yaml")
    n = len(grid.reflectors)
    rm_path = save_reflector_map(
        ReflectorMap(np.arange(n), grid.reflectors, np.full(n, grid.reflector_radius)),
        tmp_path / "reflectors.yaml",
    )
    out3 = tmp_path / "loc3"
    args = ["localize", "--bag", str(path), "--map", str(bare_yaml), "--out", str(out3)]
    r = CliRunner().invoke(app, [*args, "--reflectors", str(rm_path), "--seed", "7", "--force"])
    assert r.exit_code == 0, r.output
    rows3 = np.loadtxt(out3 / "estimate.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows3, rows, atol=1e-9)
    # the reflector map named by the robot file (mmpa --robot FILE): the same estimates
    robot_yaml = tmp_path / "robot.yaml"
    robot_yaml.write_text("reflector_map: reflectors.yaml\n")
    out4 = tmp_path / "loc4"
    args4 = ["--robot", str(robot_yaml), *args[:-1], str(out4), "--seed", "7", "--force"]
    r = CliRunner().invoke(app, args4)
    assert r.exit_code == 0, r.output
    rows4 = np.loadtxt(out4 / "estimate.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(rows4, rows, atol=1e-9)
    r = CliRunner().invoke(app, [*args, "--seed", "7", "--force"])  # no reflectors at all
    assert r.exit_code == 2 and "needs >= 3 reflector landmarks; the map holds 0" in r.output
    bad = CliRunner().invoke(
        app, ["localize", "--bag", str(tmp_path / "nope.mcap"), "--out", str(out)]
    )
    assert bad.exit_code == 2 and "does not exist" in bad.output


def test_se2_quaternion_helpers_agree() -> None:
    T = se2_to_T(0.5, -0.2, 2.5)
    msg = rm.pose_stamped(0.0, "map", [0.5, -0.2, 2.5])
    np.testing.assert_allclose(rm.from_pose(msg.pose), T, atol=1e-12)
    np.testing.assert_allclose(rm.from_pose(rm.pose_stamped(0.0, "map", T).pose), T, atol=1e-12)
    assert rpy_to_R(0, 0, 2.5) == pytest.approx(T[:3, :3])


def test_fast_quaternion_matches_the_geometry_module() -> None:
    from scipy.spatial.transform import Rotation

    from mmpa.core.geometry import R_to_quat_xyzw

    Rs = [*Rotation.random(200, random_state=3).as_matrix(), np.diag([1.0, -1, -1])]
    Rs += [np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)]
    for R in Rs:
        np.testing.assert_allclose(rm._quat_xyzw(R), R_to_quat_xyzw(R), atol=1e-12)


def test_recorder_clock_stays_monotonic_over_a_reset() -> None:
    rec = Recorder.__new__(Recorder)  # the clock reads nothing but these two fields
    rec._offset, rec._last = 0.0, 0.0
    assert [rec.stamp(t) for t in (0.5, 1.0, 2.0)] == [0.5, 1.0, 2.0]  # sim time as is
    assert rec.stamp(0.0) == 2.0  # the sim clock restarted: continue from the last stamp
    assert rec.stamp(0.25) == pytest.approx(2.25)  # and keep the shift


def test_demo_has_a_record_option() -> None:
    from typer.testing import CliRunner

    from mmpa.cli.main import app

    r = CliRunner().invoke(app, ["demo", "--help"])
    assert r.exit_code == 0 and "--record" in r.output


def test_foxglove_layout_names_only_recorded_topics() -> None:
    import re
    from pathlib import Path

    from mmpa.backends.bag.record import TOPICS

    text = (Path(__file__).parents[1] / "docs" / "foxglove_layout.json").read_text()
    layout = json.loads(text)
    assert set(layout["configById"]) >= {"3D!mmpa3d", "Image!mmpacolor", "Plot!mmpaxy"}
    named = set(re.findall(r'"(/[a-z_/]+)', text))
    assert named and named <= set(TOPICS.values()), named - set(TOPICS.values())


def test_reading_topics_absent_from_the_bag_gives_empty_lists(tmp_path) -> None:
    from mmpa.backends.bag.reader import read_messages

    path = tmp_path / "one.mcap"
    with BagWriter(path) as w:
        w.write("/tf", rm.tf_message([rm.transform_stamped(1.0, "map", "odom", np.eye(4))]), 1.0)
    assert read_messages(path, ["/cam/rgb"]) == {"/cam/rgb": []}  # not every topic of the bag
    assert len(read_messages(path, ["/tf", "/cam/rgb"])["/tf"]) == 1

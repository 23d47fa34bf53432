"""Bag-backed sources (issue 20): the arm's joint states from a bag (``BagJointStates``), and
odometry from ``/tf`` in a bag that has no ``/odom``. Every bag here is written by the test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mmpa.backends.bag import BagWriter
from mmpa.backends.bag import messages as rm
from mmpa.backends.bag.reader import (
    BagJointStates,
    BagLidar,
    BagPlayback,
    EndOfBagError,
    odometry_from_tf,
)
from mmpa.backends.bag.record import JOINT_NAMES
from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import se2_to_T
from mmpa.robot.interfaces import LaserScan


def _scan(stamp: float, n: int = 31) -> LaserScan:
    a0, inc = -math.pi / 2, math.pi / (n - 1)
    r = np.linspace(1.0, 4.0, n)
    return LaserScan(a0, a0 + inc * (n - 1), inc, 0.0, 0.1, 0.05, 10.0, r, np.zeros(n), stamp)


@pytest.fixture(params=["mcap", "sqlite3"])
def joint_bag(request, tmp_path):
    """10 arm joint states at 50 Hz from t = 1 s (one of them in reversed joint order), a
    gripper-only state between them, and two scans; returns the bag and the truth."""
    rng = np.random.default_rng(3)
    t = 1.0 + 0.02 * np.arange(10)
    q = rng.uniform(-3, 3, (10, 6))
    qd = rng.uniform(-1, 1, (10, 6))
    path = tmp_path / ("j.mcap" if request.param == "mcap" else "j_bag")
    with BagWriter(path, storage=request.param) as bag:
        for i in range(10):
            if i == 5:  # the same state with its joints listed in reverse order
                msg = rm.joint_state(t[i], JOINT_NAMES[::-1], q[i, ::-1], qd[i, ::-1])
            elif i == 7:  # no velocities
                msg = rm.joint_state(t[i], JOINT_NAMES, q[i])
            else:
                msg = rm.joint_state(t[i], JOINT_NAMES, q[i], qd[i])
            bag.write("/joint_states", msg)
            if i == 2:
                bag.write("/joint_states", rm.joint_state(t[i] + 0.005, ["finger"], [0.01]))
        bag.write("/scan", rm.laser_scan(_scan(1.05), "laser"))
        bag.write("/scan", rm.laser_scan(_scan(1.1), "laser"))
    return path, t, q, qd


def test_joint_states_from_a_bag(joint_bag) -> None:
    path, t, q, qd = joint_bag
    pb = BagPlayback.open(path)
    js = BagJointStates(pb)
    assert js.names == JOINT_NAMES and len(js) == 10  # the gripper-only state is skipped
    np.testing.assert_allclose(js.times, t, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(js.positions, q)  # float64 on the wire: exact
    np.testing.assert_array_equal(js.velocities[[0, 5, 9]], qd[[0, 5, 9]])
    assert np.all(np.isnan(js.velocities[7]))
    with pytest.raises(InvalidInputError, match="no joint state at or before"):
        js.joint_positions()  # the clock has not started
    lidar = BagLidar(pb)
    lidar.scan()  # the clock moves to 1.05 s: the state of 1.04 s is the latest
    np.testing.assert_array_equal(js.joint_positions(), q[2])
    np.testing.assert_array_equal(js.joint_velocities(), qd[2])
    lidar.scan()  # 1.10 s: the reordered message, back in the arm's order
    np.testing.assert_array_equal(js.joint_positions(), q[5])
    np.testing.assert_array_equal(js.joint_velocities(), qd[5])
    # a subset, in the caller's order
    sub = BagJointStates(pb, names=["joint3", "joint1"])
    np.testing.assert_array_equal(sub.positions, q[:, [2, 0]])
    np.testing.assert_array_equal(sub.at(1.0 + 0.02 * 7 + 1e-3).q, q[7, [2, 0]])
    assert sub.at(1.0 + 0.02 * 7).qd is None  # that message has no velocities


def test_iterating_joint_states_moves_the_clock(joint_bag) -> None:
    path, t, _, _ = joint_bag
    js = BagJointStates.open(path)
    seen = []
    for s in js:
        seen.append(s.stamp)
        np.testing.assert_array_equal(js.joint_positions(), s.q)  # the clock is at s
    np.testing.assert_allclose(seen, t, rtol=0, atol=1e-9)
    with pytest.raises(EndOfBagError):
        js.read()
    with pytest.raises(InvalidInputError, match="has all of the joints"):
        BagJointStates.open(path, names=["joint1", "elbow"])
    with pytest.raises(InvalidInputError, match="distinct"):
        BagJointStates.open(path, names=["joint1", "joint1"])


def test_no_joint_states_is_a_clear_error(tmp_path) -> None:
    with BagWriter(tmp_path / "s.mcap") as bag:
        bag.write("/scan", rm.laser_scan(_scan(1.0), "laser"))
    with pytest.raises(InvalidInputError, match="no joint states on /joint_states"):
        BagJointStates.open(tmp_path / "s.mcap")


def test_odometry_from_tf_recovers_an_arc_twist() -> None:
    """A base driving a circle arc at v = 0.3 m/s, w = 0.5 rad/s, its pose (closed form) in
    /tf at 20 Hz (ROS 1 names with a leading slash, some other transforms among them)."""
    v, w = 0.3, 0.5
    ts = 2.0 + 0.05 * np.arange(12)
    tau = ts - ts[0]
    x0, y0, th0 = 1.0, -2.0, 0.4
    th = th0 + w * tau
    x = x0 + v / w * (np.sin(th) - np.sin(th0))
    y = y0 - v / w * (np.cos(th) - np.cos(th0))
    tfs = [
        (t, "/odom", "/base_link", se2_to_T(a, b, c))
        for t, a, b, c in zip(ts, x, y, th, strict=True)
    ]
    tfs += [(t, "map", "odom", np.eye(4)) for t in ts]
    odo = odometry_from_tf(tfs[::-1])  # any order in, stamp order out
    assert [o.stamp for o in odo] == list(ts)
    np.testing.assert_allclose([o.pose for o in odo], np.c_[x, y, th], rtol=0, atol=1e-12)
    np.testing.assert_allclose(odo[0].twist, [0.0, 0.0])
    np.testing.assert_allclose([o.twist for o in odo[1:]], [[v, w]] * 11, rtol=0, atol=1e-9)
    # backwards along a straight line: negative speed, no turn
    line = [(t, "odom", "base_link", se2_to_T(-0.2 * t, 0.0, 0.0)) for t in (0.0, 0.1, 0.2)]
    np.testing.assert_allclose(odometry_from_tf(line)[2].twist, [-0.2, 0.0], atol=1e-12)


class _WithoutOdom:
    """A bag sink that drops ``/odom``: a robot that publishes its odometry only as TF."""

    def __init__(self, inner) -> None:
        self.inner = inner

    def write(self, topic, msg, stamp=None, latched=None) -> None:
        if topic != "/odom":
            self.inner.write(topic, msg, stamp, latched)


@pytest.fixture(scope="module")
def driving_bags(tmp_path_factory):
    """The twin's base driving an arc while a localizer runs, recorded twice at once: with
    /odom, and with only /tf (+ /scan and the rest)."""
    from mmpa.apps.view import Tee
    from mmpa.backends.bag import Recorder
    from mmpa.backends.twin.operator import rough_initial_pose
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
    from mmpa.backends.twin.world import SimWorld
    from mmpa.localization.localizer import make_localizer

    d = tmp_path_factory.mktemp("driving")
    with SimWorld() as world, BagWriter(d / "odom.mcap") as a, BagWriter(d / "tf.mcap") as b:
        grid = twin_map(world)
        rec = Recorder(Tee(a, _WithoutOdom(b)), world)
        w = rec.world()
        rec.write_map(grid)
        loc = rec.localizer(
            make_localizer("enhanced", grid, laser_pose2d(world), np.random.default_rng(7))
        )
        loc.initialize(rough_initial_pose(world))
        for _ in range(12):
            w.base.set_velocity(0.25, 0.3)
            w.step(0.1)
            loc.update(w.odometry.odometry().pose, w.lidar.scan(), force=True)
        w.base.stop()
        live = loc.pose_at(w.odometry.odometry().pose)
    return d / "odom.mcap", d / "tf.mcap", grid, live


def test_localize_on_tf_odometry_equals_odom(driving_bags, tmp_path) -> None:
    from mmpa.apps.localize import LocalizeConfig, localize_bag, run_localize
    from mmpa.backends.bag.reader import bag_topics

    with_odom, tf_only, grid, live = driving_bags
    assert "/odom" in bag_topics(with_odom) and "/odom" not in bag_topics(tf_only)
    pa, pb = BagPlayback.open(with_odom), BagPlayback.open(tf_only)
    assert pa.odometry_source == "/odom" and pb.odometry_source.startswith("/tf")
    assert len(pa.odometry) == len(pb.odometry) == 12
    # the same poses (the odom -> base_link TF carries the /odom pose); the arc twist is
    # close to the commanded one once the base is up to speed
    np.testing.assert_array_equal([o.pose for o in pb.odometry], [o.pose for o in pa.odometry])
    np.testing.assert_allclose(pb.odometry[-1].twist, pa.odometry[-1].twist, atol=0.05)
    assert np.ptp([o.pose[0] for o in pa.odometry]) > 0.1  # the base did drive
    cfg = LocalizeConfig(method="enhanced", seed=7, force=True)
    ra, rb = localize_bag(pa, grid, cfg), localize_bag(pb, grid, cfg)
    np.testing.assert_array_equal(rb.estimate, ra.estimate)
    np.testing.assert_array_equal(rb.odom, ra.odom)
    assert np.hypot(*(ra.estimate[-1][:2] - live[:2])) < 5e-5  # and the live run's estimate
    # the run folder of `mmpa localize --bag` on the TF-only bag: the same final estimate
    s = run_localize(tf_only, tmp_path / "loc", cfg=cfg)
    assert s["odometry_source"].startswith("/tf") and s["scans"] == 12
    np.testing.assert_allclose(s["final_estimate"], ra.estimate[-1], atol=1e-6)


def test_a_bag_without_any_odometry_says_so(tmp_path) -> None:
    with BagWriter(tmp_path / "s.mcap") as bag:
        bag.write("/scan", rm.laser_scan(_scan(1.0), "laser"))
    pb = BagPlayback.open(tmp_path / "s.mcap")
    assert pb.odometry_source == ""
    with pytest.raises(InvalidInputError, match="nor odom -> base_link transforms on /tf"):
        pb.odometry_at(1.0)

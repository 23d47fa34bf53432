"""A robot backend that plays a bag back: the ``Lidar`` / ``Odometry`` / ``Camera`` protocols of
:mod:`mmpa.robot.interfaces` served from a recording.

Reads ROS 1 bags (``.bag``) and ROS 2 bags (rosbag2 directories with sqlite3 or MCAP storage,
or a bare ``.mcap`` / ``.db3`` file) through ``rosbags.highlevel.AnyReader``; message
definitions come from the bag (the ROS 2 Humble store is the fallback for old rosbag2 bags
that carry none). Topic names are configurable (:class:`BagTopics`).

Replay model: one clock per :class:`BagPlayback`. :meth:`BagLidar.scan` returns the next scan
and moves the clock to its stamp; :meth:`BagOdometry.odometry` returns the latest odometry
message stamped at or before the clock (the reading a live robot has when the scan arrives);
:meth:`BagCamera.capture` returns the next RGB-D frame (colour, depth and camera info matched
by stamp) and moves the clock. Past the last message a read raises :class:`EndOfBagError`.
:class:`BagJointStates` serves the arm's ``/joint_states`` the same way: the sample at or
before the clock (``joint_positions``), or the samples in order (iteration moves the clock).

Odometry: the ``/odom`` messages, or, in a bag without them, the ``odom -> base_link``
transforms of ``/tf`` (frame names in :class:`BagTopics`; many robots publish only the TF),
with the body twist differenced from consecutive poses (:func:`odometry_from_tf`).
"""

from __future__ import annotations

import bisect
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from mmpa.backends.bag import messages as rm
from mmpa.core.errors import ConfigError, InvalidInputError, MMPAError
from mmpa.core.geometry import Array, se2_compose, se2_inv, wrap_angle
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import LaserScan, Odometry, RGBDFrame

__all__ = [
    "BagCamera",
    "BagJointStates",
    "BagLidar",
    "BagOdometry",
    "BagPlayback",
    "BagTopics",
    "EndOfBagError",
    "JointSample",
    "odometry_from_tf",
    "read_messages",
]

_STAMP_TOL = 1e-6  # s: an odometry message this far after the clock still counts as "now"


class EndOfBagError(MMPAError):
    """A bag-backed sensor was read past its last message."""


class BagTopics(BaseModel):
    """Topic names of a recording (ROS defaults; ``--set`` them for other robots)."""

    model_config = ConfigDict(extra="forbid")

    scan: str = "/scan"
    odom: str = "/odom"
    tf: str = "/tf"
    tf_static: str = "/tf_static"
    color: str = "/camera/color/image_raw"
    depth: str = "/camera/aligned_depth_to_color/image_raw"
    camera_info: str = "/camera/color/camera_info"
    initial_pose: str = "/initialpose"
    estimate: str = "/amcl_pose"
    map: str = "/map"
    reflectors: str = "/reflectors"
    truth_base: str = "/truth/base_pose"
    joint_states: str = "/joint_states"
    # frames of the odometry transform in /tf (used when the bag has no odometry topic)
    odom_frame: str = "odom"
    base_frame: str = "base_link"


def _open(path: Path) -> Any:

    if not path.exists():
        raise InvalidInputError(f"bag {path} does not exist")
    try:
        return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
    except Exception as e:  # rosbags' reader errors: not a bag, unknown storage
        raise ConfigError(f"{path}: cannot read it as a ROS 1 or ROS 2 bag: {e}") from None


def read_messages(path: str | Path, topics: Iterable[str]) -> dict[str, list[Any]]:
    """Every message of ``topics`` (deserialized, in log-time order) of the bag at ``path``;
    topics absent from the bag map to empty lists."""
    path = Path(path)
    wanted = set(topics)
    out: dict[str, list[Any]] = {t: [] for t in wanted}
    reader = _open(path)
    try:
        with reader:
            conns = [c for c in reader.connections if c.topic in wanted]
            if not conns:  # rosbags reads every topic when given no connection
                return out
            for conn, _t, raw in reader.messages(connections=conns):
                out[conn.topic].append(reader.deserialize(raw, conn.msgtype))
    except MMPAError:
        raise
    except Exception as e:
        raise ConfigError(f"{path}: cannot read the bag: {e}") from None
    return out


def bag_topics(path: str | Path) -> dict[str, tuple[str, int]]:
    """``topic -> (message type, message count)`` of the bag at ``path``."""
    path = Path(path)
    reader = _open(path)
    with reader:
        out: dict[str, tuple[str, int]] = {}
        for c in reader.connections:
            n = out.get(c.topic, (c.msgtype, 0))[1] + int(c.msgcount)
            out[c.topic] = (c.msgtype, n)
    return out


def odometry_from_tf(
    transforms: Iterable[tuple[float, str, str, Array]],
    odom_frame: str = "odom",
    base_frame: str = "base_link",
) -> list[Odometry]:
    """Odometry from ``/tf``: the planar part ``[x, y, theta]`` of every ``odom_frame ->
    base_frame`` transform of ``transforms`` (``(stamp s, parent, child, 4x4)``; a leading
    ``/`` of ROS 1 frame names is ignored), in stamp order (of equal stamps the last one).
    A TF carries no twist: the body twist ``[v, w]`` (m/s, rad/s) is that of the constant-
    twist arc from the previous pose, ``d = se2_inv(p[i-1]) (+) p[i]`` over ``dt``:
    ``w = dtheta / dt``, ``v = sign(dx) |(dx, dy)| (dtheta / 2) / sin(dtheta / 2) / dt``
    (exact for a differential base driving an arc; zero for the first pose): what the robot
    knows at ``t[i]``."""
    by_t: dict[float, Array] = {}
    for t, parent, child, Tm in transforms:
        if parent.lstrip("/") == odom_frame and child.lstrip("/") == base_frame:
            by_t[float(t)] = rm._planar(Tm)
    out: list[Odometry] = []
    prev: tuple[float, Array] | None = None
    for t in sorted(by_t):
        pose = by_t[t]
        twist = np.zeros(2)
        if prev is not None and t > prev[0]:
            d = se2_compose(se2_inv(prev[1]), pose)
            dt = t - prev[0]
            dth = float(wrap_angle(d[2]))
            half = 0.5 * dth
            arc = half / np.sin(half) if abs(half) > 1e-9 else 1.0
            v = float(np.copysign(np.hypot(d[0], d[1]) * arc, d[0])) / dt
            twist = np.array([v, dth / dt])
        out.append(
            Odometry(
                pose=pose, twist=twist, stamp=t, frame_id=odom_frame, child_frame_id=base_frame
            )
        )
        prev = (t, pose)
    return out


@dataclass
class BagPlayback:
    """The data of one bag for the bag-backed sensors, and their shared clock (s)."""

    path: Path
    topics: BagTopics = field(default_factory=BagTopics)
    scans: list[LaserScan] = field(default_factory=list)
    odometry: list[Odometry] = field(default_factory=list)
    transforms: list[tuple[float, str, str, Array]] = field(default_factory=list)
    static_transforms: dict[tuple[str, str], Array] = field(default_factory=dict)
    initial_pose: tuple[float, Array, Array] | None = None
    truth_base: tuple[Array, Array] | None = None  # (t (N,), [x, y, theta] (N, 3))
    extra: dict[str, list[Any]] = field(default_factory=dict)
    clock: float = -np.inf
    odometry_source: str = ""  # where :attr:`odometry` came from ("" : nowhere)
    _odom_t: list[float] = field(default_factory=list, repr=False)

    @classmethod
    def open(
        cls, path: str | Path, topics: BagTopics | None = None, extra: Iterable[str] = ()
    ) -> BagPlayback:
        """Load scans, odometry, transforms, the initial pose and the ground truth (when
        recorded) of the bag at ``path``; ``extra`` topics are kept raw in :attr:`extra`."""
        path = Path(path)
        tp = topics or BagTopics()
        names = [tp.scan, tp.odom, tp.tf, tp.tf_static, tp.initial_pose, tp.truth_base]
        raw = read_messages(path, [*names, *extra])
        pb = cls(path, tp)
        pb.scans = [rm.from_laser_scan(m) for m in raw[tp.scan]]
        pb.odometry = sorted((rm.from_odometry(m) for m in raw[tp.odom]), key=lambda o: o.stamp)
        for m in raw[tp.tf_static]:
            for ts in m.transforms:
                parent, child, Tm = rm.from_transform(ts)
                pb.static_transforms[(parent, child)] = Tm
        for m in raw[tp.tf]:
            for ts in m.transforms:
                parent, child, Tm = rm.from_transform(ts)
                t = float(ts.header.stamp.sec) + 1e-9 * float(ts.header.stamp.nanosec)
                pb.transforms.append((t, parent, child, Tm))
        if raw[tp.initial_pose]:
            pb.initial_pose = rm.from_pose_cov(raw[tp.initial_pose][0])
        if raw[tp.truth_base]:
            ts_ = np.array([rm._stamp_of(m.header) for m in raw[tp.truth_base]])
            poses = np.array([rm._planar(rm.from_pose(m.pose)) for m in raw[tp.truth_base]])
            pb.truth_base = (ts_, poses)
        pb.extra = {k: raw[k] for k in extra}
        if pb.odometry:
            pb.odometry_source = tp.odom
        else:  # no odometry topic: the odom -> base_link transforms of /tf
            pb.odometry = odometry_from_tf(pb.transforms, tp.odom_frame, tp.base_frame)
            pb.odometry_source = (
                f"{tp.tf} ({tp.odom_frame} -> {tp.base_frame})" if pb.odometry else ""
            )
        pb._odom_t = [o.stamp for o in pb.odometry]
        return pb

    def odometry_at(self, t: float) -> Odometry:
        """The latest odometry stamped at or before ``t`` (s)."""
        if not self.odometry:
            tp = self.topics
            raise InvalidInputError(
                f"{self.path}: no odometry on {tp.odom}, nor {tp.odom_frame} -> "
                f"{tp.base_frame} transforms on {tp.tf}"
            )
        i = bisect.bisect_right(self._odom_t, t + _STAMP_TOL) - 1
        if i < 0:
            raise InvalidInputError(
                f"{self.path}: no odometry at or before t = {t:.3f} s "
                f"(the first is at {self._odom_t[0]:.3f} s)"
            )
        return self.odometry[i]

    def static_transform(self, parent: str, child: str) -> Array | None:
        """``child`` in ``parent`` (4x4) from ``/tf_static``: one recorded transform, or the
        chain of recorded transforms (either way round) that links the two frames, as
        ``tf2`` resolves it (a leading ``/`` of ROS 1 names is ignored); None if the two
        frames are not linked."""

        edges: dict[str, list[tuple[str, Array]]] = {}
        for (p, c), Tm in self.static_transforms.items():
            p, c = p.lstrip("/"), c.lstrip("/")
            edges.setdefault(p, []).append((c, Tm))
            edges.setdefault(c, []).append((p, np.linalg.inv(Tm)))
        start, goal = parent.lstrip("/"), child.lstrip("/")
        if start not in edges or goal not in edges:
            return None
        seen: dict[str, Array] = {start: np.eye(4)}  # frame -> its pose in ``parent``
        todo = deque([start])
        while todo:
            f = todo.popleft()
            if f == goal:
                return seen[f]
            for g, Tm in edges[f]:
                if g not in seen:
                    seen[g] = seen[f] @ Tm
                    todo.append(g)
        return None

    def static_frames(self) -> list[str]:
        """The frames named in ``/tf_static`` (sorted; a leading ``/`` dropped)."""
        return sorted({f.lstrip("/") for pc in self.static_transforms for f in pc})

    def truth_at(self, t: float) -> Array | None:
        """The recorded true base pose ``[x, y, theta]`` nearest ``t``; None without truth."""
        if self.truth_base is None:
            return None
        ts, poses = self.truth_base
        i = int(np.argmin(np.abs(ts - t)))
        return poses[i].copy()


class BagLidar:
    """:class:`~mmpa.robot.interfaces.Lidar` from a bag: the recorded scans in order."""

    def __init__(self, playback: BagPlayback) -> None:
        self._pb = playback
        self._i = 0

    def __len__(self) -> int:
        return len(self._pb.scans)

    def __iter__(self) -> Iterator[LaserScan]:
        while self._i < len(self._pb.scans):
            yield self.scan()

    def scan(self) -> LaserScan:
        if self._i >= len(self._pb.scans):
            raise EndOfBagError(f"{self._pb.path}: no more scans on {self._pb.topics.scan}")
        s = self._pb.scans[self._i]
        self._i += 1
        self._pb.clock = max(self._pb.clock, s.stamp)
        return s


class BagOdometry:
    """Odometry from a bag: the latest message at or before the playback clock."""

    def __init__(self, playback: BagPlayback) -> None:
        self._pb = playback

    def odometry(self) -> Odometry:
        return self._pb.odometry_at(self._pb.clock)


class BagCamera:
    """:class:`~mmpa.robot.interfaces.Camera` from a bag: colour + aligned depth frames
    (matched by stamp, with the nearest camera info), in order."""

    def __init__(self, path: str | Path, topics: BagTopics | None = None) -> None:
        tp = topics or BagTopics()
        raw = read_messages(path, [tp.color, tp.depth, tp.camera_info])
        self._path = Path(path)
        depth = {rm._stamp_of(m.header): m for m in raw[tp.depth]}
        infos = [(rm._stamp_of(m.header), rm.from_camera_info(m)) for m in raw[tp.camera_info]]
        if not infos:
            raise InvalidInputError(f"{path}: no camera info on {tp.camera_info}")
        self._frames: list[tuple[float, Any, Any, CameraIntrinsics]] = []
        for m in raw[tp.color]:
            t = rm._stamp_of(m.header)
            d = depth.get(t)
            if d is None:
                continue
            k = min(infos, key=lambda x: abs(x[0] - t))[1]
            self._frames.append((t, m, d, k))
        if not self._frames:
            raise InvalidInputError(
                f"{path}: no colour frame on {tp.color} with a depth frame of the same stamp "
                f"on {tp.depth}"
            )
        self._i = 0

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._frames[min(self._i, len(self._frames) - 1)][3]

    def capture(self) -> RGBDFrame:
        if self._i >= len(self._frames):
            raise EndOfBagError(f"{self._path}: no more camera frames")
        t, c, d, k = self._frames[self._i]
        self._i += 1
        return RGBDFrame(
            color=rm.from_image_rgb(c),
            depth=rm.from_depth_image(d),
            intrinsics=k,
            stamp=t,
            frame_id=str(c.header.frame_id),
        )


@dataclass(frozen=True)
class JointSample:
    """One recorded joint state: ``stamp`` s, ``q`` (n,) rad, ``qd`` (n,) rad/s or None."""

    stamp: float
    q: Array
    qd: Array | None


class BagJointStates:
    """The arm's joint states from a bag (``sensor_msgs/JointState`` on ``topics.joint_states``):
    the joint-state source of a robot, played back.

    ``names``: the joints to serve, in this order (default: the first message's names);
    messages that lack one of them (another group's states on the same topic) are skipped.
    :meth:`joint_positions` is the latest sample at or before the playback clock (the
    encoders a live robot reads when the scan or frame that moved the clock arrives);
    iterating (or :meth:`read`) returns the samples in stamp order and moves the clock to
    each. :attr:`times` (N,) s, :attr:`positions` (N, n) rad and :attr:`velocities` (N, n)
    rad/s (NaN where a message carries none) hold them all, e.g. to teach from a recording.
    """

    def __init__(self, playback: BagPlayback, names: Iterable[str] | None = None) -> None:
        self._pb = playback
        topic = playback.topics.joint_states
        msgs = read_messages(playback.path, [topic])[topic]
        if not msgs:
            raise InvalidInputError(f"{playback.path}: no joint states on {topic}")
        decoded = [rm.from_joint_state(m) for m in msgs]
        want = list(names) if names is not None else decoded[0][1]
        if not want or len(set(want)) != len(want):
            raise InvalidInputError(f"joint names must be distinct and not none, got {want}")
        rows: dict[float, tuple[Array, Array]] = {}
        for t, nm, q, v in decoded:
            idx = {n: i for i, n in enumerate(nm)}
            if not all(n in idx for n in want):
                continue
            sel = [idx[n] for n in want]
            rows[t] = (q[sel], v[sel] if v is not None else np.full(len(sel), np.nan))
        if not rows:
            raise InvalidInputError(
                f"{playback.path}: no message on {topic} has all of the joints {want}"
            )
        self.names: list[str] = want
        self.times = np.array(sorted(rows))
        self.positions = np.array([rows[t][0] for t in self.times])
        self.velocities = np.array([rows[t][1] for t in self.times])
        self._t = self.times.tolist()
        self._i = 0

    @classmethod
    def open(
        cls,
        path: str | Path,
        topics: BagTopics | None = None,
        names: Iterable[str] | None = None,
    ) -> BagJointStates:
        """The joint states of the bag at ``path`` on a playback clock of their own."""
        return cls(BagPlayback(Path(path), topics or BagTopics()), names)

    def __len__(self) -> int:
        return len(self._t)

    def _sample(self, i: int) -> JointSample:
        v = self.velocities[i]
        return JointSample(
            float(self.times[i]),
            self.positions[i].copy(),
            None if np.all(np.isnan(v)) else v.copy(),
        )

    def at(self, t: float) -> JointSample:
        """The latest sample stamped at or before ``t`` (s)."""
        i = bisect.bisect_right(self._t, t + _STAMP_TOL) - 1
        if i < 0:
            raise InvalidInputError(
                f"{self._pb.path}: no joint state at or before t = {t:.3f} s "
                f"(the first is at {self._t[0]:.3f} s)"
            )
        return self._sample(i)

    def joint_positions(self) -> Array:
        """Encoder readings (rad), shape (n,), at the playback clock."""
        return self.at(self._pb.clock).q

    def joint_velocities(self) -> Array:
        """Joint velocities (rad/s), shape (n,), at the playback clock (NaN if not recorded)."""
        s = self.at(self._pb.clock)
        return s.qd if s.qd is not None else np.full(len(self.names), np.nan)

    def read(self) -> JointSample:
        """The next sample in stamp order; moves the playback clock to its stamp."""
        if self._i >= len(self._t):
            raise EndOfBagError(
                f"{self._pb.path}: no more joint states on {self._pb.topics.joint_states}"
            )
        s = self._sample(self._i)
        self._i += 1
        self._pb.clock = max(self._pb.clock, s.stamp)
        return s

    def __iter__(self) -> Iterator[JointSample]:
        while self._i < len(self._t):
            yield self.read()

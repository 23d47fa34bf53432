"""Record a running twin to a ROS 2 bag without touching the simulator.

:class:`Recorder` wraps the world's devices: :meth:`Recorder.world` returns a stand-in for
the :class:`~mmpa.backends.twin.world.SimWorld` whose ``lidar``, ``odometry`` and ``camera`` record
each
reading as software reads it (so topics come at the rate the algorithm used them), plus the
transforms and the ground truth of that moment; :meth:`Recorder.localizer` wraps a localizer
so its estimates (``/amcl_pose``, ``map -> odom``, ``/particlecloud``) and the operator's
initial pose (``/initialpose``) are recorded. Everything else passes straight through, and
nothing consumes a random draw, so a recorded run is the same run as an unrecorded one.

Topics (REP-105 frames, stamps = sim time; see :mod:`mmpa.backends.bag.messages`):

==============================================  ==========================================
``/scan``                                        every scan read (``laser``)
``/odom``, ``/tf`` odom -> base_link             every new odometry reading
``/joint_states``, ``/tf`` arm links             with every scan and camera frame; with
(``arm_base`` -> ``link1`` .. ``flange``)        ``joint_rate_hz``, also every
                                                 ``1 / joint_rate_hz`` s of stepped sim
                                                 time (every arm motion), with
                                                 ``/truth/tcp_pose``
``/camera/color/image_raw`` (rgb8),              every capture (``camera_color_optical_frame``)
``/camera/aligned_depth_to_color/image_raw``
(16UC1 mm), ``/camera/color/camera_info``
``/tf_static``                                   base_link -> laser, arm_base; flange -> tcp,
                                                 camera (NOMINAL mounts, as software knows them)
``/map``, ``/reflectors``                        latched: the localizer's map and its landmarks
``/initialpose``, ``/amcl_pose``,                the localizer's input and output
``/particlecloud``, ``/tf`` map -> odom
``/truth/base_pose``, ``/truth/tcp_pose``,       ground truth (evaluation only)
``/truth/camera_pose``, ``/truth/reflectors``
==============================================  ==========================================

``mmpa demo``, ``mmpa navigate``, ``mmpa run`` and ``mmpa experiment`` record with
``joint_rate_hz`` = :data:`ARM_RATE_HZ` (a task's path rate when higher). A kinematic twin
(the fiducial search: nothing steps the world) records at every state it is set to
(:meth:`Recorder.on_kinematic`): the arm, the truth and the tool's photosensor beam on
``/photosensor`` (``sensor_msgs/Range``).

The arm moves inside the simulator's ``step`` (``SimArm.move_joints`` and ``follow`` run the
whole motion in one call), which no device wrapper sees. With ``joint_rate_hz`` the recorder
therefore wraps the world's ``step`` on the instance (the class and the simulator are
untouched; :meth:`Recorder.close` removes the wrapper): a call for ``n`` physics steps runs
as the same ``n`` steps in chunks of ``round(1 / (joint_rate_hz * dt))`` steps, and after
each chunk and at the end of every call the arm's state is recorded. The chunks step the same
physics in the same order (MuJoCo's ``mj_forward`` between them recomputes derived
quantities only), so the run is unchanged; a reader of the encoders after a ``step`` (as
``follow`` with ``record_hz`` is) finds that very sample in the bag.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

import mmpa.backends.bag.messages as rm
from mmpa.backends.bag.writer import BagWriter
from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array, inv, se2_to_T
from mmpa.robot.kinematics import link_steps

if TYPE_CHECKING:  # pragma: no cover
    from mmpa.backends.twin.world import SimWorld
    from mmpa.maps.occupancy import OccupancyGrid

__all__ = ["ARM_FRAMES", "ARM_RATE_HZ", "JOINT_NAMES", "TOPICS", "Recorder"]

#: Hz: the rate of the arm's ``/joint_states`` (and its ``/tf``) in the twin commands'
#: recordings (``Recorder(joint_rate_hz=...)``; a recorded task runs at its path's rate when
#: that is higher): a ROS 2 ``joint_state_broadcaster``'s usual rate
ARM_RATE_HZ = 50.0

JOINT_NAMES = [f"joint{i}" for i in range(1, 7)]
#: frames of the DH chain ``arm_base`` -> ... -> ``flange`` (link_transforms indices 1..6)
ARM_FRAMES = ["link1", "link2", "link3", "link4", "link5", rm.FRAMES["flange"]]
TOPICS = {
    "scan": "/scan",
    "odom": "/odom",
    "tf": "/tf",
    "tf_static": "/tf_static",
    "joint_states": "/joint_states",
    "color": "/camera/color/image_raw",
    "depth": "/camera/aligned_depth_to_color/image_raw",
    "camera_info": "/camera/color/camera_info",
    "map": "/map",
    "reflectors": "/reflectors",
    "initial_pose": "/initialpose",
    "estimate": "/amcl_pose",
    "particles": "/particlecloud",
    "photosensor": "/photosensor",
    "truth_base": "/truth/base_pose",
    "truth_tcp": "/truth/tcp_pose",
    "truth_camera": "/truth/camera_pose",
    "truth_reflectors": "/truth/reflectors",
}


class Recorder:
    """Records what a twin run reads (see the module docstring) into ``writer``.

    ``max_particles``: at most this many particles per ``/particlecloud`` message (evenly
    subsampled; 0: no particle cloud). Building and serializing a PoseArray costs ~10 us per
    pose, so 500 poses per scan at 10 Hz would cost ~15 % of a twin run's wall time.
    Bag stamps are sim time; should the sim clock go back (a ``world.reset``), later stamps
    are shifted to keep the bag's time monotonic.

    ``joint_rate_hz`` (None: off): also record the arm (``/joint_states``, the arm's
    ``/tf`` and ``/truth/tcp_pose``; the true base pose stays with the scans and frames,
    and a scan or frame at the time of such a sample adds no second arm state) every
    ``1 / joint_rate_hz`` s of stepped sim time (rounded to whole physics steps:
    :attr:`joint_period_s`) and at the end of every ``world.step``, so every arm motion is
    in the bag (see the module docstring). Call :meth:`close` (or use the recorder as a
    context manager) to unhook.
    """

    def __init__(
        self,
        writer: BagWriter,
        world: SimWorld,
        max_particles: int = 100,
        joint_rate_hz: float | None = None,
    ) -> None:
        self.writer = writer
        self._world = world
        self.max_particles = int(max_particles)
        if joint_rate_hz is not None and not (np.isfinite(joint_rate_hz) and joint_rate_hz > 0):
            raise InvalidInputError(f"joint_rate_hz must be a positive rate, got {joint_rate_hz}")
        self.joint_rate_hz = joint_rate_hz
        #: s between two arm samples within a step (whole physics steps); None: not sampled
        self.joint_period_s: float | None = None
        self._last_arm = -np.inf
        self._hooked = False
        self._pending: list[tuple[float, Array, Array, Array]] = []
        self._offset = 0.0
        self._last = 0.0
        self._last_odom: float | None = None
        self._static_done = False
        self._proxy: _RecordingWorld | None = None

    # --- clock ------------------------------------------------------------------------------
    def stamp(self, t: float) -> float:
        """Bag time (s) of sim time ``t``: ``t`` plus the shift accumulated over resets."""
        s = float(t) + self._offset
        if s < self._last - 1e-9:  # the sim clock went back (reset): keep the bag monotonic
            self._offset += self._last - s
            s = self._last
        self._last = s
        return s

    # --- wrapping -----------------------------------------------------------------------------
    def world(self) -> SimWorld:
        """The recording stand-in for the world (typed as the world: it behaves as one)."""
        if self._proxy is None:
            self._proxy = _RecordingWorld(self._world, self)
        self.write_static()
        if self.joint_rate_hz is not None and not self._hooked:
            self._hook_steps(float(self.joint_rate_hz))
        return self._proxy  # type: ignore[return-value]

    def _hook_steps(self, rate_hz: float) -> None:
        """Wrap the world's ``step`` (on the instance) to sample the arm while it steps."""
        w = self._world
        if "step" in vars(w):
            raise MMPAError("the world's stepping is recorded already (one Recorder per world)")
        step = w.step  # the class's method, bound
        dt = float(w.model.opt.timestep)
        k = max(1, round(1.0 / (rate_hz * dt)))
        self.joint_period_s = k * dt

        def recording_step(duration: float) -> None:
            if not (np.isfinite(duration) and duration >= 0):
                return step(duration)  # the world's own error
            left = round(duration / dt)  # the physics steps SimWorld.step would take
            try:
                while left > k:
                    step(k * dt)
                    left -= k
                    self.on_arm()
                step(left * dt)
                self.on_arm()
            finally:
                self._flush_arm()
            return None

        w.step = recording_step  # type: ignore[method-assign]
        self._hooked = True

    def close(self) -> None:
        """Unhook the world's ``step`` (idempotent). The writer stays open: its owner closes
        it."""
        if self._hooked:
            self._flush_arm()
            vars(self._world).pop("step", None)
            self._hooked = False

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def localizer(self, loc: Any) -> Any:
        """``loc`` with its ``initialize`` and ``update`` recorded."""
        return _RecordingLocalizer(loc, self)

    # --- one-off topics -----------------------------------------------------------------------
    def write_static(self) -> None:
        """``/tf_static`` (nominal mounts) and ``/truth/reflectors``, once."""
        if self._static_done:
            return
        self._static_done = True
        w, F = self._world, rm.FRAMES
        rob = w.nominal
        t = self.stamp(w.time)
        tfs = [
            rm.transform_stamped(t, F["base"], F["laser"], rob.lidar.T_base_link_laser),
            rm.transform_stamped(t, F["base"], F["arm_base"], rob.T_base_link_arm_base),
            rm.transform_stamped(t, F["flange"], F["tcp"], rob.gripper.T_flange_tcp),
            rm.transform_stamped(t, F["flange"], F["camera"], rob.camera.T_flange_camera),
        ]
        self.writer.write(TOPICS["tf_static"], rm.tf_message(tfs), t)
        radius = float(w.scene.reflectors.radius)
        self.writer.write(
            TOPICS["truth_reflectors"],
            rm.reflector_markers(t, w.truth.reflector_positions()[:, :2], radius, "truth"),
            t,
            latched=True,
        )

    def write_map(self, grid: OccupancyGrid) -> None:
        """``/map`` and the localizer's landmarks ``/reflectors`` (latched)."""
        t = self.stamp(self._world.time)
        self.writer.write(TOPICS["map"], rm.occupancy_grid(grid, t), t)
        self.writer.write(
            TOPICS["reflectors"],
            rm.reflector_markers(t, grid.reflectors, grid.reflector_radius),
            t,
        )

    # --- readings -----------------------------------------------------------------------------
    def _arm_state(self, t: float) -> tuple[float, Array, Array, Array] | None:
        """``(t, q, qd, T_map_tcp true)`` now, for bag time ``t``; None when the stepping
        recorded the arm at that very time already."""
        if self._hooked and t <= self._last_arm:
            return None
        self._last_arm = t
        arm = self._world.arm
        return t, arm.joint_positions(), arm.joint_velocities(), self._world.truth.T_map_tcp()

    def _write_arm(
        self, state: tuple[float, Array, Array, Array], T_map_base: Array | None = None
    ) -> None:
        """``/joint_states``, the arm's ``/tf`` (and the true base pose when given) and
        ``/truth/tcp_pose`` of an :meth:`_arm_state`."""
        t, q, qd, T_tcp = state
        F = rm.FRAMES
        self.writer.write(TOPICS["joint_states"], rm.joint_state(t, JOINT_NAMES, q, qd))
        A = link_steps(self._world.nominal.arm.dh, q)  # each link in its parent's frame
        parents = [F["arm_base"], *ARM_FRAMES[:-1]]
        tfs = [rm.transform_stamped(t, parents[i], ARM_FRAMES[i], A[i]) for i in range(6)]
        self.writer.write(TOPICS["tf"], rm.tf_message(tfs), t)
        if T_map_base is not None:
            self.writer.write(TOPICS["truth_base"], rm.pose_stamped(t, F["map"], T_map_base))
        self.writer.write(TOPICS["truth_tcp"], rm.pose_stamped(t, F["map"], T_tcp))

    def _flush_arm(self) -> None:
        """Write the arm states sampled during a ``step`` (kept until it returns: building
        the messages in one go after the physics, not between its chunks, took ~30 % less
        CPU in ``mmpa run``; the bag stays in time order, as nothing else is written while
        the world steps)."""
        pending, self._pending = self._pending, []
        for state in pending:
            self._write_arm(state)

    def _arm_and_truth(self, t: float) -> None:
        """The arm and the true base pose at bag time ``t`` (the arm unless the stepping
        recorded it at that very time already)."""
        state = self._arm_state(t)
        T_base = self._world.truth.T_map_base_link()
        if state is not None:
            self._write_arm(state, T_base)
        else:
            self.writer.write(TOPICS["truth_base"], rm.pose_stamped(t, rm.FRAMES["map"], T_base))

    def on_arm(self) -> None:
        """The arm's state now (the stepping hook calls it; the base's true pose comes with
        the scans and frames)."""
        state = self._arm_state(self.stamp(self._world.time))
        if state is not None:
            self._pending.append(state)

    def on_kinematic(self) -> None:
        """A kinematic twin's state now (:meth:`SimWorld.set_kinematic_state`: no stepping
        records it): the arm, the true base pose and the tool's photosensor beam
        (``/photosensor``, ``sensor_msgs/Range``: the distance to the first surface on the
        beam)."""
        w = self._world
        t = self.stamp(w.time)
        self._arm_and_truth(t)
        _, dist = w.photosensor.hit()
        ps = w.nominal.photosensor
        msg = rm.range_msg(t, rm.FRAMES["photosensor"], dist, ps.max_range)
        self.writer.write(TOPICS["photosensor"], msg)

    def on_scan(self, scan: Any) -> None:
        t = self.stamp(scan.stamp)
        self.writer.write(TOPICS["scan"], rm.laser_scan(_restamp(scan, t), rm.FRAMES["laser"]))
        self._arm_and_truth(t)

    def on_odometry(self, odo: Any) -> None:
        if self._last_odom is not None and odo.stamp == self._last_odom:
            return
        self._last_odom = odo.stamp
        t = self.stamp(odo.stamp)
        F = rm.FRAMES
        self.writer.write(TOPICS["odom"], rm.odometry(_restamp(odo, t)))
        tf = rm.transform_stamped(t, F["odom"], F["base"], odo.pose)
        self.writer.write(TOPICS["tf"], rm.tf_message([tf]), t)

    def on_frame(self, frame: Any, intrinsics: Any) -> None:
        t = self.stamp(frame.stamp)
        f = _restamp(frame, t)
        self.writer.write(TOPICS["color"], rm.rgb_image(f))
        self.writer.write(TOPICS["depth"], rm.depth_image(f))
        self.writer.write(TOPICS["camera_info"], rm.camera_info(intrinsics, t))
        self.writer.write(
            TOPICS["truth_camera"],
            rm.pose_stamped(t, rm.FRAMES["map"], self._world.truth.T_map_camera()),
        )
        self._arm_and_truth(t)

    def on_initial(self, pose: Array, cov: Array | None) -> None:
        t = self.stamp(self._world.time)
        self.writer.write(
            TOPICS["initial_pose"], rm.pose_cov_stamped(t, rm.FRAMES["map"], pose, cov)
        )

    def on_estimate(self, loc: Any, est: Any, odom_pose: Array, stamp: float) -> None:
        t = self.stamp(stamp)
        F = rm.FRAMES
        pose = loc.pose_at(odom_pose)
        self.writer.write(
            TOPICS["estimate"], rm.pose_cov_stamped(t, F["map"], pose, getattr(est, "cov", None))
        )
        T_map_odom = se2_to_T(*pose) @ inv(se2_to_T(*np.asarray(odom_pose, float)))
        self.writer.write(
            TOPICS["tf"],
            rm.tf_message([rm.transform_stamped(t, F["map"], F["odom"], T_map_odom)]),
            t,
        )
        parts = getattr(loc, "particles", None)
        if parts is None:
            parts = getattr(getattr(loc, "amcl", None), "particles", None)
        if self.max_particles > 0 and parts is not None and len(parts):
            P = np.asarray(parts)
            if len(P) > self.max_particles:
                P = P[np.linspace(0, len(P) - 1, self.max_particles).astype(int)]
            self.writer.write(TOPICS["particles"], rm.pose_array(t, F["map"], P))


def _restamp(value: Any, t: float) -> Any:
    """``value`` (a frozen dataclass with ``stamp``) with its stamp set to bag time ``t``."""

    return value if value.stamp == t else dataclasses.replace(value, stamp=t)


class _Delegate:
    """Forwards every attribute it does not define to ``_inner``."""

    _inner: Any

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)


class _RecordingLidar(_Delegate):
    def __init__(self, inner: Any, rec: Recorder) -> None:
        self._inner, self._rec = inner, rec

    def scan(self) -> Any:
        s = self._inner.scan()
        self._rec.on_scan(s)
        return s


class _RecordingOdometry(_Delegate):
    def __init__(self, inner: Any, rec: Recorder) -> None:
        self._inner, self._rec = inner, rec

    def odometry(self) -> Any:
        o = self._inner.odometry()
        self._rec.on_odometry(o)
        return o


class _RecordingCamera(_Delegate):
    def __init__(self, inner: Any, rec: Recorder) -> None:
        self._inner, self._rec = inner, rec

    def capture(self) -> Any:
        f = self._inner.capture()
        self._rec.on_frame(f, f.intrinsics)
        return f


class _RecordingWorld(_Delegate):
    """The world, with recording ``lidar`` / ``odometry`` / ``camera``; attribute writes go
    to the world."""

    def __init__(self, world: Any, rec: Recorder) -> None:
        object.__setattr__(self, "_inner", world)
        object.__setattr__(self, "_rec", rec)
        object.__setattr__(self, "_wrapped", {})

    def __setattr__(self, name: str, value: Any) -> None:
        setattr(self._inner, name, value)

    def _wrap(self, name: str, cls: type) -> Any:
        dev = getattr(self._inner, name)
        cached = self._wrapped.get(name)
        if cached is None or cached._inner is not dev:  # the world may rebuild a device
            cached = cls(dev, self._rec)
            self._wrapped[name] = cached
        return cached

    @property
    def lidar(self) -> Any:
        return self._wrap("lidar", _RecordingLidar)

    @property
    def odometry(self) -> Any:
        return self._wrap("odometry", _RecordingOdometry)

    @property
    def camera(self) -> Any:
        return self._wrap("camera", _RecordingCamera)


class _RecordingLocalizer(_Delegate):
    def __init__(self, inner: Any, rec: Recorder) -> None:
        self._inner, self._rec = inner, rec
        self.name = inner.name

    def initialize(self, pose: Array, cov: Array | None = None) -> None:
        self._inner.initialize(pose, cov)
        self._rec.on_initial(np.asarray(pose, float), cov)

    def update(self, odom_pose: Array, scan: Any, force: bool = False) -> Any:
        est = self._inner.update(odom_pose, scan, force=force)
        self._rec.on_estimate(self._inner, est, odom_pose, scan.stamp)
        return est

    def pose_at(self, odom_pose: Array) -> Array:
        return self._inner.pose_at(odom_pose)

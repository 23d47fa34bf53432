"""Settings of the tracking grasp (:class:`mmpa.servo.grasp.TrackingGrasp`), one section per
phase: ``detect`` (detection -> located object point), ``track`` (the IBVS tracking, the
predictor's use, standoffs, the base), ``search`` (second views), ``descent`` (the blind
descent and the grasp height), ``stream`` (the streamed set-points and their limits),
``intercept`` (the jerk-limited online intercept, ``stream.accel_limit="intercept"``) and
``close`` (close, lift, further attempts); ``ibvs`` and ``predictor`` as before.

Lengths m, times s, speeds m/s, angles rad unless noted. Defaults are the improved grasp;
:meth:`GraspConfig.paper` is paper 001's. Measurements behind the defaults: ``docs/servo.md``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from mmpa.servo.ibvs import IBVSConfig
from mmpa.servo.predictor import PredictorConfig

__all__ = [
    "CloseConfig",
    "DescentConfig",
    "DetectConfig",
    "GraspConfig",
    "InterceptConfig",
    "SearchConfig",
    "StreamConfig",
    "TrackConfig",
]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class DetectConfig(_Section):
    """Detection -> the located object point (:mod:`mmpa.servo.tracker`)."""

    # the paper's dark preprocessing; off: measured to hurt a detector trained on dark images
    preprocess_dark: bool = False
    # "top": the top center and top height from all the box's depth pixels (servo.target,
    # improvement); "box": the paper's box center deprojected at its depth
    grasp_point: Literal["top", "box"] = "top"
    center_correction: bool = True  # "box" only: object center behind the surface point
    axis_from_depth: bool = True  # "box" only: principal axis of the depth foreground
    # improvement: a detection away from the track (beyond the predictor's gate) needs this
    # score to restart the track
    reinit_score: float = Field(0.6, ge=0, le=1)
    # improvement (track-aware threshold): with a track and no detection at the detector's
    # threshold, a box of the object's class scoring at least ``track_score`` counts when
    # located within ``track_gate`` of the prediction or the last measurement;
    # ``track_score`` >= the detector's threshold: off
    track_score: float = Field(0.15, ge=0, le=1)
    track_gate: float = Field(0.06, gt=0)  # m


class TrackConfig(_Section):
    """The tracking servo: IBVS at ``rate_hz`` toward the tracking point over the object."""

    use_predictor: bool = True  # the constant-velocity Kalman filter (improvement)
    rate_hz: float = Field(20.0, gt=0)  # control ticks (capture, detect, servo)
    align_tol: float = Field(0.012, gt=0)  # m, lateral error of the tracking point
    align_ticks: int = Field(3, ge=1)
    # grasp trigger (improvement): descend only while the predictor's last ``steady_ticks``
    # innovations stay below ``steady_tol``
    steady_tol: float = Field(0.004, gt=0)  # m
    steady_ticks: int = Field(3, ge=0)
    final_standoff: float = Field(0.16, gt=0)  # m: last tracking height before the descent
    # an object faster than this (m/s, in the desk plane) counts as moving: ``moving_``
    # gain, standoff and descent speed, ``moving_final_standoff`` instead of
    # ``final_standoff`` (improvement)
    final_standoff_max_speed: float = Field(0.05, ge=0)  # m/s
    moving_final_standoff: float = Field(0.25, gt=0)  # m
    # improvement: the object counts as moving only when the least-squares line through its
    # measurements of the last ``still_window`` s (at least ``still_min_measurements``,
    # spanning half the window) is faster than ``final_standoff_max_speed`` too; a still
    # object is servoed and descends on that line. 0: the predictor alone
    still_window: float = Field(1.0, ge=0)  # s
    still_min_measurements: int = Field(8, ge=2)
    # a still object unseen for less than this is servoed on its line and may be grasped
    # without a fresh detection
    still_coast: float = Field(2.0, ge=0)  # s
    # s of following the prediction without detections
    coast_time: float = Field(0.3, ge=0)
    # lost (after coasting): back up to ``ibvs.standoff`` over the last measured position
    # while waiting (False: hold still, the paper's behaviour)
    reacquire: bool = True
    null_gain: float = Field(2.0, ge=0)  # null-space manipulability gain (eq. 13)
    reach_limit: float = Field(0.72, gt=0)  # m, horizontal from the arm base
    base_speed: float = Field(0.08, ge=0)  # m/s, the base's creep toward a far object


class SearchConfig(_Section):
    """Second views (improvement; the paper waits at the first view): when the target has
    not been seen ``after`` s after the start, each candidate (a box of the target's class
    scoring at least ``candidate_score``, then of other classes scoring at least
    ``other_candidate_score``, located from its depth; best first, at most ``candidates``) is
    looked at from each of ``views`` in turn: (azimuth deg from the direction toward the arm
    base, horizontal distance m, height m above the desk) of the camera, which looks at the
    candidate's mid-height. Empty ``views``: the paper's behaviour."""

    views: list[tuple[float, float, float]] = Field(
        default_factory=lambda: [(0.0, 0.2, 0.4), (0.0, 0.12, 0.4)]
    )
    after: float = Field(0.5, ge=0)  # s
    candidate_score: float = Field(0.05, ge=0, le=1)
    other_candidate_score: float = Field(0.05, ge=0)  # > 1: no look-alikes
    candidates: int = Field(3, ge=0)
    gate: float = Field(0.08, gt=0)  # m, horizontal: one candidate per object
    settle: float = Field(0.3, ge=0)  # s at a view before detecting
    frames: int = Field(2, ge=1)  # frames detected at a view
    joint_step: float = Field(1.6, gt=0)  # rad: a view needing more is skipped
    # m above the desk kept by the flange, the camera and the TCP on the way to a view
    # (joint-space straight line); a view that needs less is skipped
    clearance: float = Field(0.26, ge=0)


class DescentConfig(_Section):
    """The descent to the grasp height (:mod:`mmpa.servo.descent`)."""

    speed: float = Field(1.2, gt=0)  # m/s of the blind descent
    # m/s^2: the descent's vertical speed ramps up and down at most this fast, and its speed
    # and acceleration need at most ``joint_margin`` of the descent's joint speed and the
    # stream's acceleration limits at the start and the end pose
    accel: float = Field(3.0, gt=0)
    joint_margin: float = Field(0.75, gt=0, le=1)
    # s: the set-point closes its offset from the planned path with this time constant
    track_time: float = Field(0.06, gt=0)
    # m: an acceleration-limited descent onto a moving object stops when a detection on its
    # way lies this far off the prediction, and the tracking goes on; 0: no
    abort_innovation: float = Field(0.012, ge=0)
    rate_hz: float = Field(50.0, gt=0)  # set-points of the descent
    # joint speed limit of the descent (a fraction of the arm's qd_max) for a still and for
    # a moving object
    joint_speed_fraction: float = Field(0.6, gt=0, le=1)
    moving_joint_speed_fraction: float = Field(0.9, gt=0, le=1)
    arm_lag: float = Field(0.03, ge=0)  # s, set-point to TCP (latency compensation)
    # improvement: for a moving object the descent keeps detecting at ``track.rate_hz`` and
    # updates the predictor while the TCP is more than ``update_height`` above the grasp
    # height, for boxes keeping ``update_margin`` of the image clear
    updates: bool = True
    update_height: float = Field(0.05, ge=0)  # m
    update_margin: float = Field(0.0, ge=0, lt=0.5)  # fraction of width / height
    close_delay: float = Field(0.0, ge=0)  # s from the arrival to closing
    settle_tol: float = Field(0.006, gt=0)  # m: the TCP this near the grasp height = arrived
    settle_max: float = Field(0.3, ge=0)  # s waited at most for the arrival
    pad_clearance: float = Field(0.024, gt=0)  # m, TCP above the desk at the lowest
    palm_clearance: float = Field(0.065, gt=0)  # m, TCP at most this far below the top


class StreamConfig(_Section):
    """The streamed set-points (:mod:`mmpa.servo.stream`, issue 22)."""

    # "always": within ``joint_accel_fraction`` of qdd_max (the arm's streaming interface
    # enforcing qdd_max), the descent along an ``descent.accel`` ramp; "never": qd_max and
    # the arm's hard stream limit ``qdd_stream_max`` only, a constant-speed descent (the
    # paper's way); "still": limited except while the object moves and in the descent onto a
    # moving object; "intercept": limited throughout, a moving object tracked and descended
    # onto by the jerk-limited online intercept (:mod:`mmpa.servo.intercept`)
    accel_limit: Literal["always", "still", "never", "intercept"] = "still"
    # the streamed set-points change each joint's velocity by at most this fraction of its
    # qdd_max per second
    joint_accel_fraction: float = Field(0.8, gt=0, le=1)
    # between the control ticks the set-points are streamed at this rate along the
    # acceleration-limited velocity profile
    rate_hz: float = Field(100.0, gt=0)
    joint_margin: float = Field(0.05, ge=0)  # rad kept from the joint limits


class InterceptConfig(_Section):
    """``stream.accel_limit="intercept"``: the online intercept of a moving object."""

    lead: float = Field(0.03, ge=0)  # s ahead of the prediction the goal is placed
    jerk_scale: float = Field(5.0, gt=0)  # the plans' jerk limit, x the arm's qddd_max
    accel_fraction: float = Field(1.0, gt=0, le=1)  # of qdd_max kept by the plans
    standoff: float = Field(0.18, gt=0)  # m, the final tracking standoff over a moving object
    descend_max: float = Field(2.0, gt=0)  # s the descent may take before it closes anyway
    # the tracking too follows the intercept (False: the IBVS velocity law within the
    # stream's acceleration limits; the descent by the intercept)
    track: bool = True
    # m, a descent stops when a detection on its way lies this far off the prediction (0:
    # never)
    abort_innovation: float = Field(0.0, ge=0)
    settle_tol: float = Field(0.015, gt=0)  # m, the TCP this near the grasp height closes
    weak_updates: bool = False  # detections on the descent take the weak boxes on the track
    update_height: float = Field(0.15, ge=0)  # m above the grasp height: no more detections
    # s of measurements whose least-squares line predicts the object during the descent (0:
    # the predictor)
    line_window: float = Field(0.0, ge=0)
    # s at least of each plan while tracking / descending (0: time-optimal)
    track_time: float = Field(0.4, ge=0)
    descend_time: float = Field(0.0, ge=0)


class CloseConfig(_Section):
    """Close, lift and further attempts."""

    lift: float = Field(0.12, gt=0)  # m
    # improvement: grasp attempts per run: when the fingers close on nothing or lose the
    # object on the lift (gap at most ``held_min_width``), they open and the tracking goes
    # on ("retry" event) while time remains; 1: the paper's single attempt
    max_attempts: int = Field(3, ge=1)
    held_min_width: float = Field(0.005, ge=0)  # m


class GraspConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ibvs: IBVSConfig = IBVSConfig()
    predictor: PredictorConfig = PredictorConfig()
    detect: DetectConfig = DetectConfig()
    track: TrackConfig = TrackConfig()
    search: SearchConfig = SearchConfig()
    descent: DescentConfig = DescentConfig()
    stream: StreamConfig = StreamConfig()
    intercept: InterceptConfig = InterceptConfig()
    close: CloseConfig = CloseConfig()
    max_time: float = Field(25.0, gt=0)  # s

    @classmethod
    def paper(cls) -> GraspConfig:
        """Paper 001's tracking grasp (§3.2.2, §4.3.3), the improvements off: no predictor
        (the last measurement is servoed), the dark preprocessing, the box center, any
        detection restarts the track and no weak boxes count, no second views, hold still
        when the object is lost, a constant-speed descent at qd_max and the hard stream
        limit, a single close."""
        return cls(
            detect=DetectConfig(
                preprocess_dark=True, grasp_point="box", reinit_score=0.0, track_score=1.0
            ),
            track=TrackConfig(use_predictor=False, reacquire=False),
            search=SearchConfig(views=[]),
            stream=StreamConfig(accel_limit="never"),
            close=CloseConfig(max_attempts=1),
        )

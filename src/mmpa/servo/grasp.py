"""The tracking grasp (paper 001 §3.2.2, Fig. 5, §4.3.3): detect, servo, approach, close, lift.

:class:`TrackingGrasp` runs over the robot interfaces (an arm that accepts streaming set-points
``command(q)``, a gripper, an RGB-D camera, a base) and a ``wait(dt)`` clock (the twin steps
its physics; a real robot sleeps). Each tick (``rate_hz``): capture, detect the named object,
locate it in ``arm_base`` (nominal kinematics; by default its top center and top height from
all the box's depth pixels, :mod:`mmpa.servo.target`; the paper's box center with
``grasp_point="box"``), update the constant-velocity Kalman filter, and run IBVS (eq. 10-12)
toward the tracking point ``standoff`` above the object with the object's estimated velocity
as feed-forward, plus the null-space manipulability term (eq. 13-14). When the error stays
small (and, with the predictor, the object has moved predictably for ``steady_ticks``) the TCP
descends blind at ``descend_speed`` to the grasp height (:func:`mmpa.servo.target.
grasp_height`), following the object's predicted position ``arm_lag`` ahead of each
set-point; it closes as soon as the encoders say the TCP arrived, then lifts. When the object
leaves the view the arm waits for it to reappear (the paper's behaviour), backing up to the
tracking standoff over where it was last seen (``reacquire``); with the predictor it first
keeps following the prediction for ``coast_time``; a weak detection
(score below ``reinit_score``) away from the track does not restart it. The base creeps
forward when the object lies beyond ``reach_limit``. Every set-point is clipped to the joint
limits and the stream keeps the joint speed limits.

Joint acceleration limits (issue 22, ``stream_accel_limit``): a limited stream keeps
``joint_accel_fraction`` of ``qdd_max`` and the arm's streaming interface is told to enforce
``qdd_max``: the IBVS velocity is reached at bounded acceleration
(:func:`mmpa.robot.limits.limit_acceleration`), moves to a pose brake in time
(:func:`mmpa.robot.limits.limit_setpoint`), the descent follows a vertical speed profile
whose acceleration the joints can give (and stops when a detection on the way shows the
object turned, ``descend_abort_innovation``), and the set-points are streamed at
``servo_rate_hz`` between the control ticks (a single set-point per tick, which the
interface holds at its velocity, jumps by the velocity change times the period at every
tick: the arm's limiter follows it late, 0.036 rad at 20 Hz and 0.8 ``qdd_max``). Under
``qdd_max`` (4 rad/s^2 on joints 1-3) the descent takes 0.9-1.5 s instead of 0.2-0.4 s, and
a turn of a moving object needs 0.2 s of the arm's acceleration to follow: a moving object
turns during the descent. Measured with :func:`mmpa.experiments.paper001.grasp.grasp_trial` (seed
0; grasped / trials, close error mean / max mm; static: the oracle detector, tennis ball,
yida bottle, cube, blue stick x 3; tracking: the tennis ball, the shipped detector, 6
trials):

===================  ==================  ===============  ===============
setting              static              tracking 0.1     tracking 0.2
===================  ==================  ===============  ===============
before issue 22      12/12 10.3 / 17.0   6/6 12.7 / 21.0  5/6 13.0 / 27.6
"never"              12/12 10.3 / 17.0   6/6 14.7 / 22.8  4/6 16.7 / 27.3
"still" (default)    12/12 3.7 / 6.4     5/6 14.0 / 47.4  4/6 19.5 / 38.2
"always"             as "still"          4/6 28.0 / 83.1  0/6 157 / 170
"intercept"          12/12 3.7 / 6.4     5/6 30.2 / 109   1/6 137 / 228
===================  ==================  ===============  ===============

(seed 1, 0.1 / 0.2 m/s: "still" 6/6 11.3 / 15.7, 4/6 25.0 / 44.9; "never" 6/6 16.2 / 25.6,
4/6 24.7 / 37.5.)
"before" and "never" stream past ``qdd_max`` up to 630-790 times (a step per set-point);
"still" keeps it on the static grasps and lifts it while the object moves; "always" keeps it
throughout and grasps moving objects rarely: the safe setting for a real arm whose servo
interface enforces ``qdd_max``.

The hard stream limit (issue 22, since stop 22): a stream not held to ``qdd_max`` ("never",
"still" while the object moves) is held to the arm's ``qdd_stream_max`` (40 rad/s^2, what
ur_rtde accepts; a UR's own acceleration limits are planning values) by the arm's interface
and by the grasp's own stream, which is then streamed at ``servo_rate_hz`` too: no set-point
streams an unbounded acceleration any more (a moving-ball trial reached 74.6 rad/s^2 at the
applied set-points before). Tracking, the shipped detector, the predictor, realistic, seed
0, 60 trials per speed (0.1 / 0.2 m/s, ``mmpa experiment tracking --trials 60 --set
"predictor=[true]" --set "speeds=[0.1,0.2]" --workers 2``):

==============================================================  =========  =========
stream while the object moves                                   0.1 m/s    0.2 m/s
==============================================================  =========  =========
unbounded (before)                                              0.917      0.817
40 rad/s^2, streamed at 100 Hz (the default)                    0.883      0.800
40 rad/s^2, one set-point a 50 ms tick, held to it there        0.883      0.633
a velocity step a tick (as before), the arm's limiter shapes it 0.500      0.283
==============================================================  =========  =========

Against the unbounded stream, the default gains 9 trials and loses 12 of 120 (within
chance); the coarse limit lags a tick, and the arm's limiter overshoots a stream of steps.

"intercept" (selectable, the default unchanged): the arm's limiter stays on throughout and a
moving object is followed by the jerk-limited online intercept (:mod:`mmpa.servo.intercept`,
ruckig replanned every 10 ms from the stream's state toward the tracking pose, then the grasp
pose on a vertical ramp, over the predicted object position in joint space, moving with it).
The stream follows its goal within a few mm and every set-point keeps qd_max and qdd_max, but
moving grasps stay short of "never": under qdd_max the descent takes 0.55-0.9 s, the camera
(95 mm beside the tool) loses the ball 0.15 m above its top, so nearly all of it is blind,
and the operator turns the ball every 0.5-1.5 s: the prediction is 3-5 cm off at the close at
0.1 m/s, 11-23 cm at 0.2 m/s (traced against the twin's truth). Measured (seed 0, 6 trials,
the table above): 5/6 at 0.1 m/s and 1/6 at 0.2 m/s ("always": 4/6, 0/6), the applied
set-points (``d.ctrl``, every physics step) at most 0.9994 qd_max and 1.0000 qdd_max in every
trial, static grasps as "still". Tried and measured worse (3 trials each): a joint-space plan
straight to the grasp pose (the TCP bows 2 cm sideways, the pads hit the ball), stopping the
descent on a turn seen on the way (tracks lost after the stop), weak detections on the
descent (boxes at the image border located 3 cm off), a time-optimal catch-up while tracking
(0.5 m/s, overshoots 0.1-0.2 m when the ball turns), a least-squares line for the descent's
prediction (its measurements shift as the camera closes in).

Second views (improvement; the paper waits at the first view): when the object has not been
seen ``search_after`` s after the start, the weak boxes of its class in the current view (and
then the boxes of look-alike objects named otherwise) are candidates; the camera looks at each
from the ``search_views`` (from the arm base's side, more oblique than the straight-down first
view, the arm kept ``search_clearance`` above the desk), and a detection there on the
candidate starts the track. In high light a bottle seen from straight above is a white disc
clipped at 255 that the detector misses or names wrongly; from the side its label and shape
show (``mmpa experiment grasp``, high light, bottles).

Still objects (improvement): the located point of a static object jitters from frame to frame
(a lying stick's box slides along it, the camera moves) and the predictor, tuned to follow
turns, then reports speeds up to 0.06 m/s: a static stick was taken for a moving one (farther
standoff, descent chasing a phantom velocity: closed 106 mm along it). While the least-squares
line through the last ``still_window`` s of measurements (:func:`mmpa.servo.predictor.
fit_line`) is no faster than ``final_standoff_max_speed``, the object is still: it is servoed
on that line and its descent follows it.

Moving objects (measured with ``mmpa experiment tracking``): the wrist camera sits 95 mm beside
the tool axis, so at the final standoff the object lies at the lower image border; a moving
object tracked there drifts out of the view (and its truncated box biases the estimate), so
the final standoff is ``moving_final_standoff`` (farther) for an object faster than
``final_standoff_max_speed``. The blind descent is the main risk at speed (the object may turn
while the TCP comes down: every miss at 0.2 m/s we traced had a turn of the object then).

Another attempt (improvement; the paper closes once): when the gripper closes on nothing or
loses the object on the lift (the finger gap at most ``held_min_width``), it opens, the
tracking goes on from where the arm is ("retry" event: in the twin the operator takes the
object again and moves it on), up to ``max_attempts`` closes within ``max_time``. At 0.2 m/s
the object turns or bounces off the edge of the operator's region about twice a second, and
the last 0.2-0.3 s of a descent are blind (the object has left the view of the camera beside
the tool): a turn then throws the object 30-130 mm off the prediction, past the ~10 mm the
open fingers leave each side of a tennis ball. A miss that leaves the object on the desk is
tried again from the same loop; one that knocks it off the desk is final.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.core.errors import InvalidInputError, MMPAError, UnknownNameError, UnreachableError
from mmpa.core.geometry import Array, apply, inv, make_T
from mmpa.perception.locate import DepthMissingError, locate, look_at
from mmpa.perception.preprocess import dark_preprocess, is_dark
from mmpa.robot.description import RobotDescription
from mmpa.robot.kinematics import fk, ik_nearest, jacobian
from mmpa.robot.limits import (
    JointLimits,
    limit_acceleration,
    limit_setpoint,
    synchronized_limits,
)
from mmpa.servo.ibvs import (
    IBVSConfig,
    camera_velocity,
    desired_point,
    limit_velocity,
    orientation_velocity,
    pinv,
)
from mmpa.servo.intercept import (
    InterceptError,
    InterceptLimits,
    StreamState,
    intercept_step,
)
from mmpa.servo.nullspace import manipulability_gradient, null_space_projector
from mmpa.servo.predictor import ConstantVelocityKF, PredictorConfig, fit_line
from mmpa.servo.target import box_points, desk_height, grasp_height, top_surface

__all__ = ["GraspConfig", "GraspResult", "TrackingGrasp", "look_configuration"]

SYMMETRIC = {"tennis_ball", "yida_bottle", "water_bottle", "paper_cup", "glue_stick"}


class GraspConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    ibvs: IBVSConfig = IBVSConfig()
    predictor: PredictorConfig = PredictorConfig()
    use_predictor: bool = True
    rate_hz: float = Field(20.0, gt=0)
    align_tol: float = Field(0.012, gt=0)  # m, lateral error of the tracking point
    align_ticks: int = Field(3, ge=1)
    # grasp trigger (improvement): descend only while the object moves predictably, i.e. the
    # predictor's last ``steady_ticks`` innovations stay below ``steady_tol`` (a turn of the
    # object during the blind descent is the main cause of misses at speed)
    steady_tol: float = Field(0.004, gt=0)  # m
    steady_ticks: int = Field(3, ge=0)
    final_standoff: float = Field(0.16, gt=0)  # m: last tracking height before the descent
    # improvement: ``final_standoff`` only for an object slower than this (the predictor's
    # estimate), else ``moving_final_standoff``: at 0.16 m the object lies at the image border
    # (the camera sits 95 mm beside the tool axis), a moving one leaves the view and the
    # truncated box biases the estimate
    final_standoff_max_speed: float = Field(0.05, ge=0)  # m/s
    moving_final_standoff: float = Field(0.25, gt=0)  # m (0.18: 11/20 at 0.2 m/s, 0.25: 13/20)
    # improvement: a detection away from the track (beyond the predictor's gate) needs this
    # score to restart the track (weak detections of other objects hijacked it)
    reinit_score: float = Field(0.6, ge=0, le=1)
    # improvement (track-aware threshold): with a track and no detection of the object at the
    # detector's threshold, a box of its class scoring at least ``track_score`` counts when
    # it is located within ``track_gate`` of the prediction or the last measurement (a bottle
    # seen from above in high light scores 0.15-0.3 where it stands: the arm waited over it
    # to the timeout); ``track_score`` >= the detector's threshold: off
    track_score: float = Field(0.15, ge=0, le=1)
    track_gate: float = Field(0.06, gt=0)  # m
    # improvement: a static object's located point jitters (a lying stick's box slides along
    # it from frame to frame) and the predictor, tuned to follow turns, then reports up to
    # 0.06 m/s: the object counts as moving only when the least-squares line through its
    # measurements of the last ``still_window`` s (at least ``still_min_measurements``,
    # spanning half the window) is faster than ``final_standoff_max_speed`` too; a still
    # object is servoed and descends on that line (measured: the blue stick in high light,
    # 20 trials, seeds 0 / 1: 0.90 / 0.95 -> 1.00 / 1.00). 0: the predictor alone
    still_window: float = Field(1.0, ge=0)  # s
    still_min_measurements: int = Field(8, ge=2)
    # a still object unseen for less than this is servoed on its line and may be grasped
    # without a fresh detection (a bottle tracked in high light went undetected straight
    # under the camera at the final standoff: the arm waited there to the timeout)
    still_coast: float = Field(2.0, ge=0)  # s
    descend_speed: float = Field(1.2, gt=0)  # m/s of the blind descent
    # m/s^2: the descent's vertical speed ramps up and down at most this fast, and its
    # speed and acceleration need at most ``descend_joint_margin`` of the descent's joint
    # speed and the stream's acceleration limits at the start and the end pose (the rest:
    # following the object sideways, the change of the joint velocities along the way)
    descend_accel: float = Field(3.0, gt=0)
    descend_joint_margin: float = Field(0.75, gt=0, le=1)
    # issue 22: when the streamed set-points keep qdd_max too ("limited": at most
    # ``joint_accel_fraction`` of it, streamed at ``servo_rate_hz``, the descent along a
    # ``descend_accel`` ramp, and the arm's streaming interface told to enforce qdd_max: an
    # arm with a ``stream_acceleration_limited`` switch, ``mmpa.backends.twin.world.SimArm``); else
    # qd_max and the arm's hard stream limit ``qdd_stream_max`` only (40 rad/s^2, ur_rtde's
    # limit: a UR's own acceleration limits are planning values), streamed at
    # ``servo_rate_hz`` too, a constant-speed descent (the paper's way). "always": limited;
    # "never": never; "still": limited except while the object moves (its least-squares line over
    # ``still_window`` faster than ``final_standoff_max_speed``) and in the descent onto a
    # moving object. Under qdd_max (4 rad/s^2 on joints 1-3) a descent takes 0.9-1.5 s
    # instead of 0.2-0.4 s and a moving object turns meanwhile (measured, seed 0, 6
    # trials, grasped / close error mean mm: see the issue-22 note in the module docstring)
    # "intercept": limited throughout (the arm's interface enforces qdd_max all the time);
    # static objects as "always"; a moving object is tracked and descended onto by the
    # jerk-limited online intercept (:mod:`mmpa.servo.intercept`): every set-point is the
    # next state of a ruckig plan from the stream's state to the grasp (or tracking) pose
    # over the object's predicted position in joint space, moving with it
    stream_accel_limit: Literal["always", "still", "never", "intercept"] = "still"
    # "intercept": s ahead of the prediction the goal is placed (the arm's lag behind its
    # set-points, 23-61 ms in the twin), and the plans' jerk limit as a multiple of the
    # arm's qddd_max (jerk is no limit of issue 22; a higher one shortens the descent)
    intercept_lead: float = Field(0.03, ge=0)
    intercept_jerk_scale: float = Field(5.0, gt=0)
    # "intercept": the plans keep this fraction of qdd_max (the arm's limiter enforces all of
    # it; the ruckig plans are smooth, so no room is needed for it to follow corners)
    intercept_accel_fraction: float = Field(1.0, gt=0, le=1)
    # "intercept": m, the final tracking standoff over a moving object (instead of
    # ``moving_final_standoff``): a shorter blind descent
    intercept_standoff: float = Field(0.18, gt=0)
    # "intercept": s the descent onto a moving object may take before it closes anyway
    intercept_descend_max: float = Field(2.0, gt=0)
    # "intercept": the tracking too follows the intercept (False: the IBVS velocity law
    # within the stream's acceleration limits, as "always"; the descent by the intercept)
    intercept_track: bool = True
    # "intercept": m, a descent stops when a detection on its way lies this far off the
    # prediction (0: never; 0.012 measured worse: tracks lost after the stop)
    intercept_abort_innovation: float = Field(0.0, ge=0)
    # "intercept": m, the TCP this near the grasp height (encoders) closes the gripper (the
    # stream goes on down to it while the fingers close; 0.006 hovered 0.2 s near it)
    intercept_settle_tol: float = Field(0.015, gt=0)
    # "intercept": detections on the descent take the weak boxes on the track too
    # (``track_score``, as the tracking does; measured worse: boxes at the image border
    # are located off and send the prediction away)
    intercept_weak_updates: bool = False
    # "intercept": m above the grasp height the descent stops taking detections (closer, the
    # ball lies at the image border and its located point drifts: one such detection 0.12 m
    # up, 29 mm off, doubled the predicted speed and the TCP ran 150 mm past the ball)
    intercept_update_height: float = Field(0.15, ge=0)
    # "intercept": s of measurements whose least-squares line predicts the object during
    # the descent (0: the predictor). The predictor's velocity was off by up to 0.08 m/s at
    # 0.1 m/s, 5 cm over a 0.65 s descent; a 0.5 s line measured worse with the closer
    # ``intercept_standoff`` (its measurements shift as the camera comes closer)
    intercept_line_window: float = Field(0.0, ge=0)
    # "intercept": s at least of each plan while tracking / descending (0: time-optimal; a
    # time-optimal catch-up reaches 0.5 m/s and overshoots by 0.1-0.2 m when the object
    # turns, and the camera loses it)
    intercept_track_time: float = Field(0.4, ge=0)
    intercept_descend_time: float = Field(0.0, ge=0)
    # issue 22: the streamed set-points change each joint's velocity by at most this
    # fraction of its qdd_max per second (the rest: room for the arm's own limiter, which
    # enforces qdd_max, to follow the stream's corners without lag)
    joint_accel_fraction: float = Field(0.8, gt=0, le=1)
    # issue 22: between the control ticks the set-points are streamed at this rate along
    # the acceleration-limited velocity profile (one set-point per tick, held at its
    # velocity by the arm's interface, jumps by the velocity change x the period at every
    # tick: the arm's own limiter then lagged the stream by up to 76 mm at 20 Hz)
    servo_rate_hz: float = Field(100.0, gt=0)
    # s: the descent's set-point closes its offset from the planned path (a turn of the
    # object seen on the way) with this time constant, on top of the path's own velocity
    descend_track_time: float = Field(0.06, gt=0)
    # m: an acceleration-limited descent (long: 0.9-1.5 s) onto a moving object stops when a
    # detection on its way lies this far off the prediction (the object turned), and the
    # tracking goes on from there (the descent starts again when aligned and steady); 0: no
    descend_abort_innovation: float = Field(0.012, ge=0)
    descend_rate_hz: float = Field(50.0, gt=0)  # set-points of the descent
    # joint speed limit of the blind descent (a fraction of the arm's qd_max) for an object
    # slower than ``final_standoff_max_speed`` and for a moving one: a moving object may
    # turn while the TCP comes down (every miss traced at 0.2 m/s had a turn then), a static
    # one is grasped more precisely slower (the arm lags its set-points: 2 cm off at 0.9)
    descend_joint_speed_fraction: float = Field(0.6, gt=0, le=1)
    moving_descend_joint_speed_fraction: float = Field(0.9, gt=0, le=1)
    arm_lag: float = Field(0.03, ge=0)  # s, set-point to TCP (latency compensation)
    # improvement: for a moving object the descent keeps detecting at ``rate_hz`` and updates
    # the predictor while the TCP is more than ``descend_update_height`` m above the grasp
    # height (a turn during the descent is seen). Tracking at 0.2 m/s, 20 trials x seeds
    # 0/1/2: blind descent 0.80/0.60/0.65, updates 0.90/0.75/0.85. Boxes at the image border
    # count too although the located point drifts toward the camera there (13 mm at 90 % of
    # the height): keeping ``descend_update_margin`` of the image clear measured worse
    # (pooled over the seeds 0.01: 0.80, 0.08: 0.67 against 0.83 at 0; 0.15 on seed 0:
    # 0.70 against 0.90)
    descend_updates: bool = True
    descend_update_height: float = Field(0.05, ge=0)
    descend_update_margin: float = Field(0.0, ge=0, lt=0.5)  # fraction of width / height
    close_delay: float = Field(0.0, ge=0)  # s from the arrival to closing
    settle_tol: float = Field(0.006, gt=0)  # m: the TCP this near the grasp height = arrived
    settle_max: float = Field(0.3, ge=0)  # s waited at most for the arrival
    # s of following the prediction without detections (longer: the arm runs after a stale
    # prediction while the object turns, and looks at the wrong place)
    coast_time: float = Field(0.3, ge=0)
    # lost (after coasting): back up to ``ibvs.standoff`` over the last measured position
    # while waiting (False: hold still, the paper's behaviour)
    reacquire: bool = True
    max_time: float = Field(25.0, gt=0)  # s
    # improvement (second views): when the target has not been seen ``search_after`` s after
    # the start, each candidate (a box of the target's class scoring at least
    # ``candidate_score`` in the current view, located from its depth; best first, at most
    # ``search_candidates``) is looked at from each of ``search_views`` in turn: (azimuth deg
    # from the direction toward the arm base, horizontal distance m, height m above the desk)
    # of the camera, which looks at the candidate's mid-height. There a detection at the
    # detector's threshold on the candidate (within ``search_gate`` or the candidate inside
    # its box), or one anywhere scoring ``reinit_score`` (a rolling stick moves away from its
    # candidate), starts the track; else back to the first view. In high light a bottle seen
    # from above is a white disc clipped at 255 (60-98 % of its pixels), from the side its
    # label and shape show; empty: the paper's behaviour (wait for it to appear). Measured
    # with ``track_score`` (``mmpa experiment grasp``, high light, 20 trials, seed 0 / 1, grasp
    # rate yida, water, glue, blue): neither 0.90 0.95 0.95 1.00 / 0.90 0.85 1.00 0.90, both
    # 1.00 1.00 1.00 1.00 / 1.00 1.00 1.00 0.85 (blue: a rolling stick, a trial at 14.7 s of 15
    # before; both fail with neither when replayed alone)
    search_views: list[tuple[float, float, float]] = Field(
        default_factory=lambda: [(0.0, 0.2, 0.4), (0.0, 0.12, 0.4)]
    )
    search_after: float = Field(0.5, ge=0)  # s
    candidate_score: float = Field(0.05, ge=0, le=1)
    # then the boxes of other classes scoring at least this (a look-alike may be the
    # target: a water bottle seen from straight above is taken for the yida bottle); > 1: no.
    # A candidate needs depth pixels standing out of the desk in its box (not a desk patch)
    other_candidate_score: float = Field(0.05, ge=0)
    search_candidates: int = Field(3, ge=0)
    search_gate: float = Field(0.08, gt=0)  # m, horizontal
    search_settle: float = Field(0.3, ge=0)  # s at a view before detecting
    search_frames: int = Field(2, ge=1)  # frames detected at a view
    search_joint_step: float = Field(1.6, gt=0)  # rad: a view needing more is skipped
    # m above the desk kept by the flange, the camera and the TCP on the way to a view
    # (joint-space straight line): the objects on the desk stand up to 0.243 m (the bottles;
    # a view 0.3 m up, the TCP 0.16 m, knocked one over); a view that needs less is skipped
    search_clearance: float = Field(0.26, ge=0)
    lift: float = Field(0.12, gt=0)  # m
    # improvement: grasp attempts per run: when the fingers close on nothing or lose the
    # object on the lift (gap at most ``held_min_width``), they open and the tracking goes on
    # ("retry" event) while time remains; 1: the paper's single attempt. Tracking at 0.2 m/s,
    # 20 trials x seeds 0/1/2: one attempt 0.75/0.70/0.60, three 0.90/0.80/0.70 (the misses
    # left knocked the ball off the desk)
    max_attempts: int = Field(3, ge=1)
    held_min_width: float = Field(0.005, ge=0)  # m
    pad_clearance: float = Field(0.024, gt=0)  # m, TCP above the desk at the lowest
    null_gain: float = Field(2.0, ge=0)
    reach_limit: float = Field(0.72, gt=0)  # m, horizontal from the arm base
    base_speed: float = Field(0.08, ge=0)
    # the paper's dark preprocessing; off: measured to hurt a detector trained on dark images
    preprocess_dark: bool = False
    # improvement: "top" = the top center and top height from all the box's depth pixels
    # (servo.target); "box" = the paper's box center deprojected at its depth
    grasp_point: Literal["top", "box"] = "top"
    palm_clearance: float = Field(0.065, gt=0)  # m, TCP at most this far below the top
    center_correction: bool = True  # "box" only: object center behind the surface point
    axis_from_depth: bool = True  # "box" only: principal axis of the depth foreground
    joint_margin: float = Field(0.05, ge=0)  # rad kept from the joint limits


@dataclass
class GraspResult:
    """``closed_on_object``: the fingers stopped on something and still hold it after the
    lift (the last attempt); ``reason``: "grasped", "missed", "not found", "unreachable",
    "timeout", "depth"; times in s. ``found_view``: where the target was first found: 0 the
    starting view, k >= 1 the k-th second view taken
    (``GraspConfig.search_views``), -1 never; ``views``: second views taken; ``descent_s``:
    s from the start of the (last) descent to its close (NaN: no descent); ``attempts``:
    closes of the gripper (``GraspConfig.max_attempts``)."""

    closed_on_object: bool
    reason: str
    detected_first: bool
    time_to_grasp: float
    ticks: int
    lost_ticks: int
    detect_ms: list[float] = field(default_factory=list)
    capture_ms: list[float] = field(default_factory=list)
    loop_s: list[float] = field(default_factory=list)
    found_view: int = -1
    views: int = 0
    descent_s: float = float("nan")
    attempts: int = 0


@dataclass(frozen=True)
class Measurement:
    """One located detection: ``p`` (3,) the tracked object point in ``arm_base`` (m; the top
    center, or the paper's box center), ``top_z``/``desk_z`` heights (m; ``desk_z`` NaN when
    unknown), ``axis`` (2,) unit horizontal grasp axis in ``arm_base`` or None."""

    p: Array
    top_z: float
    desk_z: float
    axis: Array | None


def look_configuration(
    robot: RobotDescription, target_arm_base: Array, height: float, q_ref: Array | None = None
) -> Array:
    """Joint angles (6,) with the wrist camera ``height`` m above ``target_arm_base`` looking
    straight down, image up = arm_base +x (nominal IK). Raises UnreachableError."""
    t = np.asarray(target_arm_base, float)
    T_cam = look_at(t + np.array([0.0, 0.0, height]), t, up_hint=(1.0, 0.0, 0.0))
    T_fl = T_cam @ inv(robot.camera.T_flange_camera)
    q_min, q_max = robot.arm.q_limits
    return ik_nearest(
        robot.arm.dh,
        T_fl,
        np.asarray(robot.arm.home if q_ref is None else q_ref, float),
        q_min,
        q_max,
    )


def _tool_down(yaw: float) -> Array:
    """Tool rotation: z down, x along ``(cos yaw, sin yaw, 0)``."""
    x = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    return np.column_stack([x, np.cross(z, x), z])


def ramp_profile(distance: float, v_max: float, a_max: float) -> tuple[float, Callable]:
    """Rest-to-rest motion over ``distance`` m (>= 0) at most ``v_max`` m/s and ``a_max``
    m/s^2 (trapezoidal speed, triangular when too short to reach ``v_max``): returns
    ``(duration s, s(t))``, ``s(t)`` the distance covered at ``t`` s (``distance`` from the
    duration on); ``a_max = inf``: at ``v_max`` throughout. Raises
    :class:`InvalidInputError` on a negative distance, a non-positive limit or an infinite
    ``v_max``."""
    if not (distance >= 0 and 0 < v_max < np.inf and a_max > 0):
        raise InvalidInputError(
            f"a ramp needs distance >= 0 and positive limits, got {distance}, {v_max}, {a_max}"
        )
    if np.isinf(a_max):
        T = distance / v_max
        return T, lambda t: v_max * min(max(t, 0.0), T)
    v = min(v_max, float(np.sqrt(distance * a_max)))  # peak speed
    t_acc = v / a_max
    duration = distance / v + t_acc if v > 0 else 0.0

    def s(t: float) -> float:
        t = min(max(t, 0.0), duration)
        if t < t_acc:
            return 0.5 * a_max * t * t
        if t > duration - t_acc:
            return distance - 0.5 * a_max * (duration - t) ** 2
        return 0.5 * a_max * t_acc * t_acc + v * (t - t_acc)

    return duration, s


@dataclass(frozen=True)
class _Segment:
    """One control period of the stream: ``duration`` s toward the joint velocity ``v_des``
    (6,) rad/s, or, with ``q_goal`` (6,), toward that goal at the period's end moving at
    ``v_goal`` (6,) rad/s; within ``limits``."""

    duration: float
    v_des: Array
    limits: JointLimits
    q_goal: Array | None = None
    v_goal: Array = field(default_factory=lambda: np.zeros(6))
    #: toward ``q_goal`` (at the period's start, moving at ``v_goal``) by the online
    #: intercept (:func:`mmpa.servo.intercept.intercept_step`), also past ``duration``
    intercept: bool = False
    min_duration: float = 0.0  # s, of each intercept plan


class TrackingGrasp:
    def __init__(self, detector: Any, robot: RobotDescription, cfg: GraspConfig | None = None):
        self.det = detector
        self.robot = robot
        self.cfg = cfg or GraspConfig()
        rb = robot
        self._T_fc = rb.camera.T_flange_camera
        self._T_ft = rb.gripper.T_flange_tcp
        self._P_star = desired_point(self._T_fc, self._T_ft, self.cfg.ibvs.standoff)
        q_min, q_max = rb.arm.q_limits
        self._q_lo = q_min + self.cfg.joint_margin
        self._q_hi = q_max - self.cfg.joint_margin
        self._qd = np.asarray(rb.arm.qd_max) * self.cfg.ibvs.joint_speed_fraction
        self._axis_ok = False
        #: limits of the streamed set-points: the arm's qd_max, ``joint_accel_fraction`` of
        #: its qdd_max (issue 22)
        qd = np.asarray(rb.arm.qd_max, float)
        qdd = np.asarray(rb.arm.qdd_max, float) * self.cfg.joint_accel_fraction
        self._lim_acc = JointLimits(self._q_lo, self._q_hi, qd, qdd)
        # not ``limited``: qd_max and the arm's hard stream limit ``qdd_stream_max``, streamed
        # at ``servo_rate_hz`` too (one set-point a control tick, 50 ms, held to it there
        # lagged a tick: 0.63 at 0.2 m/s; a velocity step a tick that the arm's limiter
        # shaped overshot: 0.28; N = 60, see the module docstring)
        qdd_hard = np.asarray(rb.arm.qdd_stream_max, float)
        self._lim_hard = JointLimits(self._q_lo, self._q_hi, qd, qdd_hard)
        #: limits of the intercept plans ("intercept"): the stream's, and the jerk limit
        jerk = np.asarray(rb.arm.qddd_max, float) * self.cfg.intercept_jerk_scale
        qdd_i = np.asarray(rb.arm.qdd_max, float) * self.cfg.intercept_accel_fraction
        self._ilim = InterceptLimits(self._q_lo, self._q_hi, qd, qdd_i, jerk)
        self._a_s = np.zeros(6)  # the stream's acceleration (rad/s^2)
        #: whether the stream keeps qdd_max now (``stream_accel_limit``)
        self.limited = self.cfg.stream_accel_limit != "never"
        #: the last descent stopped on a turn of the object (``descend_abort_innovation``)
        self.aborted = False
        # the stream: last set-point sent (rad (6,)), its velocity (rad/s), when (clock s;
        # None: not yet) and its period (s)
        self._q_s: Array | None = None
        self._v_s = np.zeros(6)
        self._t_s: float | None = None
        self._h_s = 0.0
        self._seg: _Segment | None = None  # the pending control period (None: brake)
        self._seg_t = 0.0  # s streamed of it
        self._clock: Callable[[], float] | None = None

    # ------------------------------------------------------------------ perception
    def _detect(self, img: Array, score_threshold: float | None = None) -> list[Any]:
        """The detector on ``img`` (the dark preprocessing first when configured); boxes
        scoring at least ``score_threshold`` (default: the detector's)."""
        if self.cfg.preprocess_dark and is_dark(img):
            img = dark_preprocess(img)
        if score_threshold is None:
            return list(self.det.detect(img))
        return list(self.det.detect(img, score_threshold))

    def _measure(
        self,
        frame: Any,
        name: str,
        q: Array,
        kf: ConstantVelocityKF | None = None,
        near: Array | None = None,
        track: list[Array] | None = None,
    ) -> tuple[Any, Measurement | None]:
        """Detect ``name`` in ``frame`` (when several: the detection nearest ``near`` (3,)
        ``arm_base``, by default the prediction of ``kf``) and locate it with the nominal
        kinematics at the encoder reading ``q``. With ``track`` (points (3,) ``arm_base``:
        the prediction, the last measurement) and no detection at the detector's threshold,
        the boxes scoring ``track_score`` or more are tried, nearest first, and the first
        located within ``track_gate`` of a track point is taken."""
        cfg = self.cfg
        th = float(self.det.cfg.score_threshold)
        weak_ok = bool(track) and cfg.track_score < th
        dets = [
            d
            for d in self._detect(frame.color, cfg.track_score if weak_ok else None)
            if d.name == name
        ]
        strong = [d for d in dets if d.score >= th]
        if not dets or (not strong and not weak_ok):
            return None, None
        T_cam = fk(self.robot.arm.dh, q) @ self._T_fc
        K = frame.intrinsics.K
        if near is None and kf is not None and kf.initialized:
            near = kf.position()
        if near is not None and len(dets) > 1:  # the detection nearest the expected place
            P = apply(inv(T_cam), near)
            if P[2] > 0:
                uv = K[:2, :2] @ (P[:2] / P[2]) + K[:2, 2]
                dets.sort(key=lambda d: float(np.linalg.norm(d.center - uv)))
                strong = [d for d in dets if d.score >= th]
        if strong:
            return self._locate(frame, strong[0], T_cam)
        assert track is not None
        for d in dets:  # weak boxes only: the first on the track
            d_, m = self._locate(frame, d, T_cam)
            if m is not None and min(np.linalg.norm(m.p - t) for t in track) < cfg.track_gate:
                return d_, m
        return None, None

    def _locate(self, frame: Any, d: Any, T_cam: Array) -> tuple[Any, Measurement | None]:
        """Locate detection ``d`` in ``frame`` taken from the camera pose ``T_cam``
        (``arm_base``): ``grasp_point`` "top" or the paper's "box" center."""
        K = frame.intrinsics.K
        dz = desk_height(frame.depth, K, T_cam, d.box)
        if self.cfg.grasp_point == "top":
            if dz is None:
                return d, None
            # every pixel of a 320-wide frame, every 2nd of a 640-wide one (same rays)
            stride = max(1, frame.depth.shape[1] // 320)
            top = top_surface(frame.depth, K, T_cam, d.box, dz, stride=stride)
            if top is None:
                return d, None
            return d, Measurement(top.p_top, float(top.p_top[2]), dz, top.axis_xy)
        # the paper's box center (+ the center correction and the principal axis of the depth
        # foreground in the image)
        try:
            loc = locate(d.box, frame.depth, K, T_cam)
        except DepthMissingError:
            return d, None
        axis = None
        if self.cfg.axis_from_depth and dz is not None:
            a2 = self._axis_from_depth(frame, d.box, K, T_cam, dz)
            if a2 is not None:
                loc = locate(d.box, frame.depth, K, T_cam, axis_2d=a2)
                axis = loc.axis_arm_base[:2] / max(np.linalg.norm(loc.axis_arm_base[:2]), 1e-9)
        elif not self.cfg.axis_from_depth:
            bw, bh = d.box[2] - d.box[0], d.box[3] - d.box[1]
            if max(bw, bh) >= 1.3 * min(bw, bh) and abs(loc.axis_arm_base[2]) < 0.9:
                axis = loc.axis_arm_base[:2] / max(np.linalg.norm(loc.axis_arm_base[:2]), 1e-9)
        p = loc.center_arm_base if self.cfg.center_correction else loc.p_arm_base
        z_desk = dz if dz is not None else float("nan")
        return d, Measurement(np.asarray(p, float), float(loc.p_arm_base[2]), z_desk, axis)

    @staticmethod
    def _axis_from_depth(
        frame: Any, box: Array, K: Array, T_cam: Array, desk_z: float
    ) -> Array | None:
        """The principal image axis of the pixels in the box that stand above the desk."""
        h, w = frame.depth.shape
        x1, y1, x2, y2 = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
        vv, uu = np.mgrid[y1:y2, x1:x2]
        uu, vv = uu.ravel(), vv.ravel()
        p, keep = box_points(frame.depth, K, T_cam, uu, vv)
        mask = p[:, 2] > desk_z + 0.008
        if mask.sum() < 20:
            return None
        c = np.cov(np.stack([uu[keep][mask], vv[keep][mask]]).astype(float))
        ev, V = np.linalg.eigh(c)
        if ev[1] < 1.5 * max(ev[0], 1e-9):  # no clear long axis (ball, cube, upright cylinder)
            return None
        return V[:, 1]

    def _candidates(self, frame: Any, name: str, q: Array) -> list[tuple[Array, float, float]]:
        """Where ``name`` may be although no detection reached the threshold: the boxes of
        its class scoring at least ``candidate_score`` in ``frame`` (camera at the encoder
        reading ``q``), best first, then those of other classes scoring at least
        ``other_candidate_score``, each located as its top center ``p`` (3,) ``arm_base``
        with the desk height ``z_desk`` under it (:mod:`mmpa.servo.target`); returns
        ``(p, z_desk, score)``, one per ``search_gate`` (the boxes of one object)."""
        cfg = self.cfg
        low = min(cfg.candidate_score, cfg.other_candidate_score)
        every = self._detect(frame.color, low)
        dets = sorted((d for d in every if d.name == name), key=lambda d: -d.score)
        dets = [d for d in dets if d.score >= cfg.candidate_score] + sorted(
            (d for d in every if d.name != name and d.score >= cfg.other_candidate_score),
            key=lambda d: -d.score,
        )
        T_cam = fk(self.robot.arm.dh, q) @ self._T_fc
        K = frame.intrinsics.K
        stride = max(1, frame.depth.shape[1] // 320)
        out: list[tuple[Array, float, float]] = []
        for d in dets:
            dz = desk_height(frame.depth, K, T_cam, d.box)
            if dz is None:
                continue
            top = top_surface(frame.depth, K, T_cam, d.box, dz, stride=stride)
            if top is None:  # nothing stands out of the desk in the box
                continue
            if all(np.linalg.norm(top.p_top[:2] - p[:2]) > cfg.search_gate for p, _, _ in out):
                out.append((top.p_top, dz, float(d.score)))
        return out

    def view_configuration(
        self, p: Array, z_desk: float, view: tuple[float, float, float], q_ref: Array
    ) -> Array:
        """Joint angles (6,) of a second view of the object with top center ``p`` (3,)
        ``arm_base`` on the desk at height ``z_desk``: ``view = (azimuth deg, r m, h m)``, the
        camera ``r`` from the object horizontally, in the direction toward the arm base
        turned by the azimuth (counter-clockwise seen from above), ``h`` above the desk,
        looking at the object's mid-height, image up toward +z. The IK solution nearest
        ``q_ref`` within the joint limits less ``joint_margin``; raises UnreachableError."""
        az, r, h = view
        p = np.asarray(p, float)
        u = -p[:2] / max(float(np.linalg.norm(p[:2])), 1e-9)  # toward the arm base
        c, s = np.cos(np.radians(az)), np.sin(np.radians(az))
        d = np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])
        eye = np.array([*(p[:2] + r * d), z_desk + h])
        target = np.array([p[0], p[1], 0.5 * (p[2] + z_desk)])
        T_fl = look_at(eye, target, up_hint=(0.0, 0.0, 1.0)) @ inv(self._T_fc)
        return ik_nearest(self.robot.arm.dh, T_fl, q_ref, self._q_lo, self._q_hi)

    def _lowest(self, q0: Array, q1: Array, n: int = 12) -> float:
        """Lowest height (m, ``arm_base`` z) of the flange, camera and TCP on the joint-space
        straight line from ``q0`` to ``q1`` (``n`` + 1 samples, nominal kinematics)."""
        dh = self.robot.arm.dh
        low = np.inf
        for a in np.linspace(0.0, 1.0, n + 1):
            T = fk(dh, (1 - a) * np.asarray(q0) + a * np.asarray(q1))
            for T_f in (np.eye(4), self._T_fc, self._T_ft):
                low = min(low, float((T @ T_f)[2, 3]))
        return low

    def _move_to(
        self,
        arm: Any,
        q_cmd: Array,
        q_goal: Array,
        wait: Callable[[float], None],
        until: Callable[[], bool],
    ) -> Array:
        """Stream set-points (control ticks at ``rate_hz``) from the stream's set-point
        (``q_cmd`` when none yet) to ``q_goal`` within the IBVS joint speed limits and the
        stream's acceleration limits, along the joint-space straight line when starting at
        rest (:func:`synchronized_limits`), braking to stop there; until there or
        ``until()``; returns the last set-point."""
        dt = 1.0 / self.cfg.rate_hz
        if self._q_s is None:
            self._start_stream(q_cmd)
        assert self._q_s is not None
        wait = self._streaming(arm, wait)
        q_goal = np.clip(q_goal, self._q_lo, self._q_hi)
        lim = dataclasses.replace(self.stream_limits, qd_max=self._qd)
        if np.all(np.abs(self._v_s) <= lim.qdd_max * dt):  # at rest: a straight line
            lim = synchronized_limits(self._q_s, q_goal, lim)
        q_cmd = self._q_s
        while np.max(np.abs(q_goal - q_cmd)) > 1e-6 and not until():
            q_cmd = self._send_toward(arm, q_goal, 0.0, lim, dt)
            wait(dt)
        return q_cmd

    def _search(
        self,
        name: str,
        frame: Any,
        q_meas: Array,
        q_cmd: Array,
        arm: Any,
        camera: Any,
        wait: Callable[[float], None],
        until: Callable[[], bool],
    ) -> tuple[Array, Any, Measurement | None, int]:
        """Second views (``search_views``) of the candidates of ``name`` in ``frame`` (taken
        at the encoder reading ``q_meas``): returns ``(set-point, detection, measurement,
        views taken)``, the measurement None when no view confirmed a candidate (the arm is
        then at the last view)."""
        cfg = self.cfg
        views = 0
        cands = self._candidates(frame, name, q_meas)[: cfg.search_candidates]
        for p, dz, _ in cands:
            for view in cfg.search_views:
                if until():
                    return q_cmd, None, None, views
                try:
                    q_view = self.view_configuration(p, dz, view, q_cmd)
                except UnreachableError:
                    continue
                if np.max(np.abs(q_view - q_cmd)) > cfg.search_joint_step:
                    continue  # another arm configuration: a long detour past the desk
                if self._lowest(q_cmd, q_view) < dz + cfg.search_clearance:
                    continue  # the arm would sweep through the objects on the desk
                q_cmd = self._move_to(arm, q_cmd, q_view, wait, until)
                views += 1
                wait(cfg.search_settle)
                for _ in range(cfg.search_frames):
                    q_now = np.asarray(arm.joint_positions(), float)
                    fr = camera.capture()
                    det, meas = self._measure(fr, name, q_now, near=p)
                    if meas is not None and (
                        det.score >= cfg.reinit_score  # as sure as a track restart needs
                        or self._same_object(fr, q_now, det.box, meas.p, p)
                    ):
                        return q_cmd, det, meas, views
                    wait(1.0 / cfg.rate_hz)
        return q_cmd, None, None, views

    def _same_object(self, frame: Any, q: Array, box: Array, p_det: Array, p_cand: Array) -> bool:
        """A detection (``box`` in ``frame`` at the encoder reading ``q``, located at
        ``p_det``) is of the candidate at ``p_cand`` (both (3,) ``arm_base``): their top
        centers lie within ``search_gate`` horizontally, or the candidate's top center
        projects into the box (a long object the first view saw in part)."""
        if np.linalg.norm(np.asarray(p_det)[:2] - np.asarray(p_cand)[:2]) < self.cfg.search_gate:
            return True
        T_cam = fk(self.robot.arm.dh, q) @ self._T_fc
        P = apply(inv(T_cam), p_cand)
        if P[2] <= 0:
            return False
        K = frame.intrinsics.K
        u, v = K[:2, :2] @ (P[:2] / P[2]) + K[:2, 2]
        x1, y1, x2, y2 = box
        return bool(x1 <= u <= x2 and y1 <= v <= y2)

    # ------------------------------------------------------------------ control
    @property
    def stream_limits(self) -> JointLimits:
        """Limits of the streamed set-points now: the arm's qd_max, and
        ``joint_accel_fraction`` of its qdd_max while ``limited``, else its hard stream
        limit ``qdd_stream_max`` (issue 22)."""
        return self._lim_acc if self.limited else self._lim_hard

    def _set_limited(self, arm: Any, on: bool) -> None:
        """Stream within qdd_max (``on``) or qd_max and the hard ``qdd_stream_max`` from now
        on, the arm's streaming interface told the same (when it has a
        ``stream_acceleration_limited`` switch)."""
        self.limited = bool(on)
        if hasattr(arm, "stream_acceleration_limited"):
            arm.stream_acceleration_limited = self.limited

    def _fast(self, hist: list[tuple[float, Array]]) -> bool:
        """The measurements ``hist`` ((time, point) of the last ``still_window`` s) show a
        moving object: enough of them (``still_min_measurements``) on a least-squares line
        faster than ``final_standoff_max_speed`` when they span (90 % of) the window, twice
        that when they span at least half of it (the first measurements of a still object,
        taken as the camera comes closer, shift by up to 3 cm: lines of 0.07 m/s over 0.5
        s)."""
        cfg = self.cfg
        if len(hist) < max(cfg.still_min_measurements, 2):
            return False
        t = np.array([h[0] for h in hist])
        span = t[-1] - t[0]
        if span < 0.5 * cfg.still_window:
            return False
        v = fit_line(t, np.array([h[1] for h in hist]))[1]
        factor = 1.0 if span >= 0.9 * cfg.still_window else 2.0
        return bool(np.hypot(v[0], v[1]) > factor * cfg.final_standoff_max_speed)

    def _start_stream(self, q: Array) -> Array:
        """A new stream of set-points from ``q`` (6,) at rest (the arm stands there)."""
        self._q_s = np.clip(np.asarray(q, float), self._q_lo, self._q_hi)
        self._v_s = np.zeros(6)
        self._a_s = np.zeros(6)
        self._t_s = None
        self._seg = None
        return self._q_s.copy()

    def _sub_steps(self, duration: float) -> tuple[int, float]:
        """``(m, h)``: the set-points streamed over ``duration`` s, ``h = duration / m`` s
        apart (``servo_rate_hz``, at least one)."""
        m = max(1, round(duration * self.cfg.servo_rate_hz))
        return m, duration / m

    def _stream_step(
        self, q: Array, v: Array, t: float, h: float, a: Array | None = None
    ) -> tuple[Array, Array, Array]:
        """The stream's set-point and velocity ``h`` s after ``(q, v)`` (both (6,)), ``t`` s
        into the pending segment: toward its velocity at the acceleration limits
        (:func:`limit_acceleration`, the direction of the change kept), or toward its goal
        (:func:`limit_setpoint`, the goal ``q_goal - v_goal (T - t')`` at the sub-step's end
        ``t'``); past the segment's duration ``T`` (no new one sent): braking to rest; an intercept
        segment (``a`` the stream's acceleration (6,)) goes on meeting its moving goal.
        Returns ``(q, v, a)``."""
        seg = self._seg
        if seg is not None and seg.intercept and seg.q_goal is not None:
            acc = np.zeros(6) if a is None else a
            lim = self._ilim
            state = StreamState(
                q,
                np.clip(v, -lim.qd_max, lim.qd_max),
                np.clip(acc, -lim.qdd_max, lim.qdd_max),
            )
            try:
                new, _ = intercept_step(
                    state,
                    seg.q_goal + seg.v_goal * t,
                    seg.v_goal,
                    h,
                    lim,
                    min_duration=seg.min_duration,
                )
                q_clip = np.clip(new.q, self._q_lo, self._q_hi)
                v_new = np.where(q_clip != new.q, (q_clip - q) / h, new.v)
                return q_clip, v_new, new.a
            except InterceptError:  # fall back on the second-order limiter
                goal = seg.q_goal + seg.v_goal * (t + h)
                q_new, v_new = limit_setpoint(q, v, goal, h, self.stream_limits, seg.v_goal)
                q_clip = np.clip(q_new, self._q_lo, self._q_hi)
                v_new = np.where(q_clip != q_new, (q_clip - q) / h, v_new)
                return q_clip, v_new, (v_new - v) / h
        if seg is None or t >= seg.duration - 1e-9:
            v_new = limit_acceleration(v, np.zeros(6), h, self.stream_limits)
            q_new = q + v_new * h
        elif seg.q_goal is None:
            v_new = limit_acceleration(v, seg.v_des, h, seg.limits)
            q_new = q + v_new * h
        else:
            goal = seg.q_goal - seg.v_goal * (seg.duration - (t + h))
            q_new, v_new = limit_setpoint(q, v, goal, h, seg.limits, seg.v_goal)
        q_clip = np.clip(q_new, self._q_lo, self._q_hi)
        v_new = np.where(q_clip != q_new, (q_clip - q) / h, v_new)
        return q_clip, v_new, (v_new - v) / h

    def _resync(self) -> None:
        """When the clock moved on without the stream (the world stepped elsewhere: the
        gripper, a planned move) the arm held the last set-point's velocity one sub-step and
        stopped: the stream goes on from there at rest."""
        if self._clock is None or self._t_s is None or self._q_s is None:
            return
        if self._clock() - self._t_s > 1.5 * self._h_s + 1e-9:
            self._q_s = np.clip(self._q_s + self._v_s * self._h_s, self._q_lo, self._q_hi)
            self._v_s = np.zeros(6)
            self._a_s = np.zeros(6)
            self._t_s = None

    def _plan(self, seg: _Segment) -> Array:
        """Make ``seg`` the pending segment; returns the set-point at its end (the waits
        stream it, :meth:`_streaming`)."""
        if self._q_s is None:
            raise InvalidInputError("no stream started")
        self._resync()
        self._seg, self._seg_t = seg, 0.0
        m, h = self._sub_steps(seg.duration)
        q, v, a = self._q_s, self._v_s, self._a_s
        for i in range(m):
            q, v, a = self._stream_step(q, v, i * h, h, a)
        return q.copy()

    def _send(self, arm: Any, qdot: Array, dt: float) -> Array:
        """Stream toward the joint velocity ``qdot`` (6,) rad/s for the control period ``dt``
        s, reached at the stream's acceleration limits (:func:`limit_acceleration`); the
        waits stream the set-points (``servo_rate_hz``). Returns the set-point at the end of
        the period."""
        del arm  # streamed by the wait (:meth:`_streaming`)
        return self._plan(_Segment(dt, np.asarray(qdot, float), self.stream_limits))

    def _send_toward(
        self, arm: Any, q_goal: Array, v_goal: Array | float, limits: JointLimits, dt: float
    ) -> Array:
        """Stream toward ``q_goal`` (6,) at the end of the control period ``dt`` s, a goal
        moving at ``v_goal`` (rad/s), within ``limits`` (:func:`limit_setpoint` every
        sub-step: lands on it when reachable, else brakes in time). Returns the set-point at
        the end of the period."""
        del arm
        v_g = np.broadcast_to(np.asarray(v_goal, float), (6,)).copy()
        return self._plan(_Segment(dt, np.zeros(6), limits, np.asarray(q_goal, float), v_g))

    def _streaming(self, arm: Any, wait: Callable[[float], None]) -> Callable[[float], None]:
        """``wait`` that streams the pending segment meanwhile: every ``1 / servo_rate_hz``
        s (about) the next set-point goes to ``arm.command``, sent one sub-step ahead (the
        arm's interface holds a set-point's velocity until the next one)."""
        if getattr(wait, "streams", False):
            return wait

        def streaming_wait(duration: float) -> None:
            if self._q_s is None or duration <= 0:
                wait(duration)
                return
            self._resync()
            m, h = self._sub_steps(duration)
            for _ in range(m):
                self._q_s, self._v_s, self._a_s = self._stream_step(
                    self._q_s, self._v_s, self._seg_t, h, self._a_s
                )
                self._seg_t += h
                self._h_s = h
                arm.command(self._q_s)
                wait(h)
                self._t_s = self._clock() if self._clock is not None else None

        streaming_wait.streams = True  # type: ignore[attr-defined]
        return streaming_wait

    def _moving(self, v_obj: Array | None) -> bool:
        """An object whose (predicted) velocity ``v_obj`` (3,) m/s exceeds
        ``final_standoff_max_speed`` in the desk plane counts as moving (gain, standoff and
        descent speed switch to their ``moving_`` values)."""
        return (
            v_obj is not None
            and float(np.linalg.norm(np.asarray(v_obj)[:2])) > self.cfg.final_standoff_max_speed
        )

    def servo_step(
        self,
        q_cmd: Array,
        p_obj: Array,
        v_obj: Array | None,
        yaw: float | None,
        dt: float,
        standoff: float | None = None,
    ) -> tuple[Array, Array]:
        """One IBVS + null-space step from set-point ``q_cmd`` toward object ``p_obj``
        (arm_base) with the tracking point ``standoff`` m above it (default: the config's);
        returns ``(q_next, [lateral error, depth error] m)``."""
        cfg = self.cfg
        dh = self.robot.arm.dh
        T_fl = fk(dh, q_cmd)
        T_cam = T_fl @ self._T_fc
        P = apply(inv(T_cam), p_obj)
        if P[2] <= 0.05:
            raise UnreachableError("the object is behind or too close to the camera")
        P_star = (
            self._P_star if standoff is None else desired_point(self._T_fc, self._T_ft, standoff)
        )
        gain = cfg.ibvs.moving_gain if self._moving(v_obj) else cfg.ibvs.gain
        v_cam = camera_velocity(P, P_star, gain)
        n = np.linalg.norm(v_cam)
        if n > cfg.ibvs.max_linear_speed:
            v_cam *= cfg.ibvs.max_linear_speed / n
        R_tool = T_fl[:3, :3] @ self._T_ft[:3, :3]
        if yaw is None:  # keep the current heading of the tool x axis
            x = R_tool[:, 0]
            yaw_now = float(np.arctan2(x[1], x[0]))
        else:
            yaw_now = yaw
        w = orientation_velocity(R_tool, _tool_down(yaw_now), cfg.ibvs.orientation_gain)
        v = T_cam[:3, :3] @ v_cam
        if v_obj is not None:
            v = v + v_obj
        J = jacobian(dh, q_cmd, self._T_fc)
        if yaw is None and cfg.null_gain > 0:  # 5-D task, eq. 13 in the free yaw
            Jt = J[:5]
            qdot = pinv(Jt, cfg.ibvs.damping) @ np.concatenate([v, w[:2]])
            g = manipulability_gradient(dh, q_cmd, self._T_ft)
            qdot += null_space_projector(Jt, cfg.ibvs.damping) @ (cfg.null_gain * g)
        else:
            qdot = pinv(J, cfg.ibvs.damping) @ np.concatenate([v, w])
        qdot = limit_velocity(qdot, self._qd)
        lateral = P[:2] - P_star[:2] * P[2] / P_star[2]
        return q_cmd + qdot * dt, np.array([np.linalg.norm(lateral), abs(P[2] - P_star[2])])

    def run(
        self,
        name: str,
        arm: Any,
        gripper: Any,
        camera: Any,
        base: Any,
        wait: Callable[[float], None],
        clock: Callable[[], float],
        on_event: Callable[[str], None] | None = None,
    ) -> GraspResult:
        """Track and grasp the object called ``name``; the arm starts at a view of the desk.

        Phases: track at ``ibvs.standoff`` above the object's top, then at ``final_standoff``
        once aligned; when aligned again, :meth:`_descend` (the object's predicted motion
        followed, the grasp height from the top and the desk), close, lift. ``on_event`` gets
        "descend" and "close" when those phases start, and "retry" when the gripper opens
        again after a missed grasp (``max_attempts``)."""
        import time

        classes = self.det.cfg.classes
        if name not in classes:
            raise UnknownNameError("object", name, list(classes))
        if not hasattr(arm, "command"):
            raise InvalidInputError("the tracking grasp needs an arm with streaming command(q)")
        cfg = self.cfg
        dt = 1.0 / cfg.rate_hz
        kf = ConstantVelocityKF(cfg.predictor)
        self._clock = clock
        self._set_limited(arm, cfg.stream_accel_limit != "never")
        wait = self._streaming(arm, wait)  # set-points at servo_rate_hz between the ticks
        q_cmd = self._start_stream(arm.joint_positions())
        t0 = clock()
        last_seen = -np.inf
        p_meas: Array | None = None
        desk_z: float | None = None
        top_z: float | None = None
        yaw = None
        aligned = 0
        standoff = cfg.ibvs.standoff
        lost_close = False
        ticks = lost = 0
        first = None
        innovations: list[float] = []
        hist: list[tuple[float, Array]] = []  # (time s, measured point) of the still window
        searched = False
        res = GraspResult(False, "timeout", False, float("nan"), 0, 0)

        def out_of_time() -> bool:
            return clock() - t0 >= cfg.max_time

        gripper.open()
        while clock() - t0 < cfg.max_time:
            w0 = time.perf_counter()
            ticks += 1
            q_meas = np.asarray(arm.joint_positions(), float)
            c0 = time.perf_counter()
            frame = camera.capture()
            d0 = time.perf_counter()
            res.capture_ms.append(1000 * (d0 - c0))
            track = None
            if p_meas is not None:  # points of the track for weak detections
                track = [p_meas, kf.position()] if kf.initialized else [p_meas]
            det, meas = self._measure(frame, name, q_meas, kf, track=track)
            if (
                meas is not None
                and kf.initialized
                and det.score < cfg.reinit_score
                and np.linalg.norm(meas.p - kf.position()) > cfg.predictor.gate
            ):
                meas = None  # a weak detection away from the track: not taken for the object
            res.detect_ms.append(1000 * (time.perf_counter() - d0))
            if first is None:
                first = meas is not None
            if (
                meas is None
                and p_meas is None
                and not searched
                and cfg.search_views
                and cfg.search_candidates > 0
                and clock() - t0 >= cfg.search_after
            ):
                # improvement: look at the weak candidates from other viewpoints
                searched = True
                q_start = q_cmd
                q_cmd, det, meas, res.views = self._search(
                    name, frame, q_meas, q_cmd, arm, camera, wait, out_of_time
                )
                if meas is None:  # back to the first view, wait there (the paper's way)
                    q_cmd = self._move_to(arm, q_cmd, q_start, wait, out_of_time)
            if meas is not None and p_meas is None:
                res.found_view = res.views
            now = clock()
            if meas is not None:
                p_meas = meas.p
                kf.update(p_meas)
                innovations.append(kf.innovation)
                if not np.isfinite(kf.innovation):  # the track (re)started
                    hist.clear()
                hist.append((now, p_meas))
                hist[:] = [h for h in hist if h[0] >= now - cfg.still_window]
                top_z = meas.top_z
                if np.isfinite(meas.desk_z):
                    dz = meas.desk_z
                    desk_z = dz if desk_z is None else 0.7 * desk_z + 0.3 * dz
                if name not in SYMMETRIC and meas.axis is not None:
                    yaw = self._grasp_yaw(meas.axis, q_cmd)
                last_seen = now
            else:
                lost += 1
                innovations.append(float("inf"))
            coasting = cfg.use_predictor and kf.initialized and now - last_seen < cfg.coast_time
            line = self._still_line(hist) if cfg.use_predictor else None
            # a still object unseen for a while stays where its line says (improvement)
            still_coasting = line is not None and now - last_seen < cfg.still_coast
            if meas is None and not (coasting or still_coasting):
                # paper: stop and wait for the object to reappear; improvement (reacquire):
                # first back up to the tracking standoff over where it was last seen (it left
                # the view at the closer final standoff, or moved out of it)
                aligned = 0
                if standoff < cfg.ibvs.standoff:
                    lost_close = True  # lost at the final standoff: descend from farther
                standoff = cfg.ibvs.standoff
                qdot = np.zeros(6)  # stop (at the stream's acceleration limits)
                if cfg.reacquire and p_meas is not None:
                    try:
                        q_back, _ = self.servo_step(q_cmd, p_meas, None, yaw, dt, standoff)
                        qdot = (q_back - q_cmd) / dt
                    except UnreachableError:
                        pass
                q_cmd = self._send(arm, qdot, dt)
                base.stop()
                wait(dt)
                kf.predict(dt)
                res.loop_s.append(time.perf_counter() - w0)
                continue
            if line is not None:  # a still object: its least-squares line
                # extrapolated at most ``coast_time`` past the last measurement (the slope of
                # a still object's line is mostly jitter)
                p_obj = line[0] + line[1] * (min(now - hist[-1][0], cfg.coast_time) + dt)
                v_obj = line[1]
            elif cfg.use_predictor:
                p_obj = kf.position(ahead=dt)
                v_obj = kf.velocity()
            else:
                p_obj, v_obj = p_meas, None
            assert p_obj is not None
            reach = float(np.hypot(p_obj[0], p_obj[1]))
            if reach > cfg.reach_limit:
                base.set_velocity(cfg.base_speed, 0.0)
            else:
                base.stop()
            try:
                q_next, err = self.servo_step(q_cmd, p_obj, v_obj, yaw, dt, standoff)
            except UnreachableError:
                res.reason = "unreachable"
                break
            if cfg.stream_accel_limit == "still":  # qdd_stream_max while the object moves
                self._set_limited(arm, not self._fast(hist))
            if cfg.intercept_track and self._intercepting(kf, line):  # intercept the pose
                # the goal now (the segment moves it on): the prediction at this tick
                q_goal, v_goal = self._intercept_goal(
                    q_cmd, kf.position(), kf.velocity(), standoff, yaw
                )
                q_cmd = self._send_intercept(q_goal, v_goal, dt, cfg.intercept_track_time)
            else:
                q_cmd = self._send(arm, (q_next - q_cmd) / dt, dt)
            seen = meas is not None or still_coasting
            ok = seen and err[0] < cfg.align_tol and err[1] < 0.03
            aligned = aligned + 1 if ok else 0
            recent = innovations[-cfg.steady_ticks :] if cfg.steady_ticks else []
            steady = not (cfg.use_predictor and recent) or max(recent) < cfg.steady_tol
            if cfg.use_predictor and len(recent) < cfg.steady_ticks:
                steady = False
            if line is not None:  # still: no turn to wait out (jitter is not motion)
                steady = True
            wait(dt)
            kf.predict(dt)
            res.loop_s.append(time.perf_counter() - w0)
            moving = cfg.use_predictor and self._moving(kf.velocity()) and line is None
            final = cfg.moving_final_standoff if moving else cfg.final_standoff
            if moving and cfg.stream_accel_limit == "intercept":
                final = cfg.intercept_standoff
            if aligned >= cfg.align_ticks and standoff > final and not lost_close:
                standoff, aligned = final, 0  # closer, still in view
                continue
            if aligned >= cfg.align_ticks and steady and desk_z is not None and top_z is not None:
                base.stop()
                if on_event:
                    on_event("descend")
                if line is not None:  # the line at the descent's start
                    ahead = min(clock() - hist[-1][0], cfg.coast_time)
                    line = (line[0] + line[1] * ahead, line[1])
                t_descend = clock()
                self.aborted = False
                try:
                    if self._intercepting(kf, line):
                        q_cmd = self._descend_intercept(
                            arm, q_cmd, kf, top_z, desk_z, yaw, wait, camera, name, hist, clock
                        )
                    else:
                        q_cmd = self._descend(
                            arm, q_cmd, kf, p_meas, top_z, desk_z, yaw, wait, camera, name, line
                        )
                except (UnreachableError, MMPAError):
                    res.reason = "unreachable"
                    break
                if self.aborted:  # the object turned on the way down: track on
                    aligned = 0
                    innovations.append(float("inf"))  # steady again before the next descent
                    continue
                res.descent_s = clock() - t_descend
                if on_event:
                    on_event("close")
                held = bool(gripper.close())
                self._lift(arm, q_cmd)
                res.attempts += 1
                held = held and gripper.width() > cfg.held_min_width  # still held, lifted
                res.closed_on_object = held
                res.reason = "grasped" if held else "missed"
                res.time_to_grasp = clock() - t0
                if held or res.attempts >= cfg.max_attempts or out_of_time():
                    break
                # improvement: missed (closed on nothing, or lost on the lift): open and
                # track again from here; the reacquire backs up over the last measurement
                if on_event:
                    on_event("retry")
                gripper.open()
                q_cmd = self._start_stream(arm.joint_positions())
                kf.reset()
                hist.clear()
                innovations.clear()
                aligned, standoff, lost_close = 0, cfg.ibvs.standoff, False
                last_seen = -np.inf
                res.reason = "timeout"
        base.stop()
        res.detected_first = bool(first)
        res.ticks, res.lost_ticks = ticks, lost
        if res.reason == "timeout" and res.attempts:
            res.reason = "missed"  # and no time left for another attempt
        if res.reason == "timeout" and p_meas is None:
            res.reason = "not found"
        return res

    def _still_line(self, hist: list[tuple[float, Array]]) -> tuple[Array, Array] | None:
        """The least-squares line ``(p at the last measurement (3,), v (3,))`` through the
        measurements ``hist`` ((time, point) of the last ``still_window`` s) when it shows a
        still object (horizontal speed at most ``final_standoff_max_speed``); None when it
        does not, or too few measurements span too short a time to tell."""
        cfg = self.cfg
        if cfg.still_window <= 0 or len(hist) < cfg.still_min_measurements:
            return None
        t = np.array([h[0] for h in hist])
        if t[-1] - t[0] < 0.5 * cfg.still_window:
            return None
        p, v = fit_line(t, np.array([h[1] for h in hist]))
        return None if self._moving(v) else (p, v)

    def _grasp_yaw(self, axis_xy: Array, q_cmd: Array) -> float:
        """Tool x along the object's horizontal long axis ``axis_xy`` (the fingers close
        across it): of the two equivalent headings, the one nearest the current tool x."""
        target = float(np.arctan2(axis_xy[1], axis_xy[0]))
        T = fk(self.robot.arm.dh, q_cmd, self._T_ft)
        now = float(np.arctan2(T[1, 0], T[0, 0]))
        k = np.round((now - target) / np.pi)
        return target + k * np.pi

    def _vertical_limits(
        self, q_a: Array, q_b: Array, qd_max: Array, qdd_max: Array
    ) -> tuple[float, float]:
        """The vertical TCP speed (m/s) and acceleration (m/s^2) of a descent between the
        joint poses ``q_a`` and ``q_b`` (6,) that keep every joint within
        ``descend_joint_margin`` of ``qd_max`` / ``qdd_max`` (6,) at both ends, capped at
        ``descend_speed`` / ``descend_accel``: with ``u = max(|J^+ e_z|)`` over the two poses
        (the joint rates of a unit vertical TCP speed), ``v_z = min(descend_speed, m
        min(qd_max / u))`` and alike for the acceleration."""
        cfg, dh = self.cfg, self.robot.arm.dh
        u = np.zeros(6)
        for q_ in (q_a, q_b):
            J = jacobian(dh, q_, self._T_ft)
            u = np.maximum(u, np.abs(np.linalg.pinv(J) @ np.array([0, 0, 1.0, 0, 0, 0])))
        with np.errstate(divide="ignore"):
            m = cfg.descend_joint_margin
            v_z = min(cfg.descend_speed, m * float(np.min(qd_max / u)))
            a_z = min(cfg.descend_accel, m * float(np.min(qdd_max / u)))
        return v_z, a_z

    def _descend(
        self,
        arm: Any,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        p_meas: Array | None,
        top_z: float,
        desk_z: float,
        yaw: float | None,
        wait: Callable[[float], None],
        camera: Any = None,
        name: str | None = None,
        line: tuple[Array, Array] | None = None,
    ) -> Array:
        """Descent of the TCP to the grasp height (:func:`grasp_height`) along a vertical
        :func:`ramp_profile` (at most ``descend_speed`` and ``descend_accel``, less where the
        joints would need more than ``descend_joint_margin`` of the descent's joint speed or
        the stream's acceleration limits at the start or the end pose: the joint velocity
        per unit vertical TCP speed there, ``J^+ e_z``), set-points at ``descend_rate_hz``
        through :func:`limit_setpoint` (the descent's joint speed, the stream's
        acceleration limits). Horizontally the TCP follows the
        object: each set-point is the predicted position ``arm_lag`` s after it is sent
        (latency compensation); without the predictor, the last measured position; for a
        still object (``line``: its least-squares line, position now (3,) and velocity (3,),
        see ``still_window``), that line. For a moving object with ``descend_updates`` (and a
        ``camera``) the predictor keeps taking detections at ``rate_hz`` on the upper part of
        the descent."""
        cfg = self.cfg
        dh = self.robot.arm.dh
        dt = 1.0 / cfg.descend_rate_hz
        if self._q_s is None or np.max(np.abs(self._q_s - q_cmd)) > 1e-6:
            self._start_stream(q_cmd)  # called on its own (not from run)
        wait = self._streaming(arm, wait)
        T0 = fk(dh, q_cmd, self._T_ft)
        R = T0[:3, :3] if yaw is None else _tool_down(yaw)
        z0 = T0[2, 3]
        zg = grasp_height(top_z, desk_z, cfg.pad_clearance, cfg.palm_clearance)
        q_min, q_max = self.robot.arm.q_limits
        n_settle = int(np.ceil(cfg.settle_max / dt))
        moving = (
            cfg.use_predictor and kf.initialized and self._moving(kf.velocity()) and line is None
        )
        fraction = (
            cfg.moving_descend_joint_speed_fraction if moving else cfg.descend_joint_speed_fraction
        )
        qd_descend = np.asarray(self.robot.arm.qd_max) * fraction
        lim = dataclasses.replace(self.stream_limits, qd_max=qd_descend)
        # the vertical profile the joints can give: J^+ e_z at the start and the end pose
        T_end = make_T(R, np.array([T0[0, 3], T0[1, 3], zg])) @ inv(self._T_ft)
        q_end = ik_nearest(dh, T_end, q_cmd, q_min, q_max)
        v_z, a_z = self._vertical_limits(q_cmd, q_end, qd_descend, lim.qdd_max)
        if not self.limited:  # at constant speed (the joints' speed scaled into qd_max)
            v_z, a_z = cfg.descend_speed, np.inf
        t_down, ramp = ramp_profile(abs(z0 - zg), v_z, a_z)
        n = max(int(np.ceil(t_down / dt - 1e-9)), 1)
        q_ik = q_cmd  # the planned set-point now (the IK branch followed)
        tau = max(cfg.descend_track_time, dt) if self.limited else dt
        look = moving and cfg.descend_updates and camera is not None and name is not None
        every = max(1, round(cfg.descend_rate_hz / cfg.rate_hz))
        for k in range(1, n + 1 + n_settle):
            if look and k % every == 0 and k <= n:
                q_now = np.asarray(arm.joint_positions(), float)
                z_now = fk(dh, q_now, self._T_ft)[2, 3]
                if z_now - zg > cfg.descend_update_height:
                    inn = self._descent_update(camera, name, q_now, kf)
                    abort = cfg.descend_abort_innovation
                    if self.limited and abort > 0 and inn is not None and inn > abort:
                        self.aborted = True  # the object turned: track on from here
                        return q_cmd
            if cfg.use_predictor and line is not None:
                p = line[0] + line[1] * (k * dt + cfg.arm_lag)
            elif cfg.use_predictor and kf.initialized:
                p = kf.position(ahead=dt + cfg.arm_lag)
            else:
                p = p_meas
            assert p is not None
            if k > n:  # arrived? (encoders, nominal kinematics): close as soon as it is there
                z_meas = fk(dh, np.asarray(arm.joint_positions(), float), self._T_ft)[2, 3]
                if abs(z_meas - zg) < cfg.settle_tol:
                    break
            z = zg if k >= n else z0 + np.sign(zg - z0) * ramp(k * dt)
            T = make_T(R, np.array([p[0], p[1], z])) @ inv(self._T_ft)
            q = ik_nearest(dh, T, q_ik, q_min, q_max)
            if np.max(np.abs(q - q_ik)) > 0.5:
                raise UnreachableError("the descent needs a jump in joint space")
            # the path's joint velocity, plus closing the set-point's offset from the path
            qdot = (q - q_ik) / dt + (q_ik - q_cmd) / tau
            q_cmd = self._plan(_Segment(dt, qdot, lim))
            q_ik = q
            wait(dt)
            kf.predict(dt)
        if cfg.close_delay > 0:
            wait(cfg.close_delay)
        return q_cmd

    def _intercepting(self, kf: ConstantVelocityKF, line: tuple[Array, Array] | None) -> bool:
        """Whether the stream follows the online intercept now: ``stream_accel_limit``
        "intercept" and a moving object (the predictor's velocity, no still line)."""
        cfg = self.cfg
        return (
            cfg.stream_accel_limit == "intercept"
            and cfg.use_predictor
            and kf.initialized
            and line is None
            and self._moving(kf.velocity())
        )

    def _intercept_goal(
        self,
        q_ref: Array,
        p_obj: Array,
        v_obj: Array | None,
        height: float,
        yaw: float | None,
        v_z: float = 0.0,
    ) -> tuple[Array, Array]:
        """The intercept's goal: joint angles (6,) with the TCP ``height`` m above the object
        point ``p_obj`` (3,) ``arm_base``, ``intercept_lead`` s ahead on its velocity ``v_obj``
        (3,) m/s, the tool pointing down (x along ``yaw``; None: the heading at ``q_ref``),
        the IK solution nearest ``q_ref`` within the joint limits less ``joint_margin``; and
        the joint velocity (6,) rad/s moving the TCP with the object there (``J^+ [v; 0]``,
        ``v`` its horizontal velocity and ``v_z`` m/s vertically). Raises UnreachableError."""
        dh = self.robot.arm.dh
        v = np.zeros(3) if v_obj is None else np.array([v_obj[0], v_obj[1], 0.0])
        v_lead = v.copy()
        v[2] = v_z
        p = np.asarray(p_obj, float) + v_lead * self.cfg.intercept_lead
        if yaw is None:  # the heading now, turned with the azimuth (joint 1 free of joint 6)
            T0 = fk(dh, q_ref, self._T_ft)
            turn = np.arctan2(p[1], p[0]) - np.arctan2(T0[1, 3], T0[0, 3])
            yaw = float(np.arctan2(T0[1, 0], T0[0, 0]) + turn)
        T = make_T(_tool_down(yaw), np.array([p[0], p[1], p[2] + height])) @ inv(self._T_ft)
        q_goal = ik_nearest(dh, T, q_ref, self._q_lo, self._q_hi)
        J = jacobian(dh, q_goal, self._T_ft)
        v_goal = pinv(J, self.cfg.ibvs.damping) @ np.concatenate([v, np.zeros(3)])
        return q_goal, v_goal

    def _send_intercept(
        self, q_goal: Array, v_goal: Array, dt: float, min_duration: float = 0.0
    ) -> Array:
        """Stream the online intercept of ``q_goal`` (6,) moving at ``v_goal`` (6,) rad/s for
        the control period ``dt`` s (and on, until the next segment), each plan at least
        ``min_duration`` s; returns the set-point at the period's end."""
        seg = _Segment(dt, np.zeros(6), self.stream_limits, q_goal, v_goal, True, min_duration)
        return self._plan(seg)

    def _descend_intercept(
        self,
        arm: Any,
        q_cmd: Array,
        kf: ConstantVelocityKF,
        top_z: float,
        desk_z: float,
        yaw: float | None,
        wait: Callable[[float], None],
        camera: Any = None,
        name: str | None = None,
        hist: list[tuple[float, Array]] | None = None,
        clock: Callable[[], float] | None = None,
    ) -> Array:
        """Descent onto a moving object by the online intercept ("intercept"): every
        ``1 / descend_rate_hz`` s the goal is the tool pose over the predicted object
        position (the predictor, or the line of ``intercept_line_window``) at the height of a
        vertical :func:`ramp_profile` down to :func:`grasp_height` (at most ``descend_speed``
        and ``descend_accel``, and ``descend_joint_margin`` of the intercept's joint limits at
        the start and the end pose), moving with the object and the ramp
        (:meth:`_intercept_goal`), the set-points the jerk-limited plans toward it; the
        predictor keeps taking detections (``descend_updates``) above
        ``intercept_update_height``. Ends when the encoders say
        the TCP is near the grasp height (``intercept_settle_tol``), at most
        ``intercept_descend_max`` s, or stops (``aborted``) when a detection lies
        ``intercept_abort_innovation`` off the prediction (the object turned)."""
        cfg = self.cfg
        dh = self.robot.arm.dh
        dt = 1.0 / cfg.descend_rate_hz
        if self._q_s is None or np.max(np.abs(self._q_s - q_cmd)) > 1e-6:
            self._start_stream(q_cmd)
        wait = self._streaming(arm, wait)
        zg = grasp_height(top_z, desk_z, cfg.pad_clearance, cfg.palm_clearance)
        if yaw is None:
            R0 = fk(dh, q_cmd, self._T_ft)[:3, :3]
            yaw = float(np.arctan2(R0[1, 0], R0[0, 0]))
        look = cfg.descend_updates and camera is not None and name is not None
        every = max(1, round(cfg.descend_rate_hz / cfg.rate_hz))
        n_max = int(np.ceil(cfg.intercept_descend_max / dt))
        # the goal's height: a vertical ramp (a joint-space plan straight to the grasp pose
        # bows the TCP 2 cm sideways on the way and the pads hit the ball), as fast as
        # ``descend_joint_margin`` of the joint limits allow at the start and the end pose
        T0 = fk(dh, q_cmd, self._T_ft)
        z0 = float(T0[2, 3])
        T_end = make_T(_tool_down(yaw), np.array([T0[0, 3], T0[1, 3], zg])) @ inv(self._T_ft)
        q_end = ik_nearest(dh, T_end, q_cmd, self._q_lo, self._q_hi)
        v_z, a_z = self._vertical_limits(q_cmd, q_end, self._ilim.qd_max, self._ilim.qdd_max)
        t_down, ramp = ramp_profile(abs(z0 - zg), v_z, a_z)
        sign = float(np.sign(zg - z0))
        n_max = max(n_max, int(np.ceil((t_down + cfg.settle_max) / dt)))
        # the prediction of the descent: the least-squares line through the measurements
        # of the last ``intercept_line_window`` s (``hist``: (time, point)) when there are
        # enough, else the predictor (its velocity follows turns, and noise with them)
        line = None
        w = cfg.intercept_line_window
        if w > 0 and hist and clock is not None:
            recent = [h for h in hist if h[0] >= hist[-1][0] - w]
            t_r = np.array([h[0] for h in recent])
            if len(recent) >= 4 and t_r[-1] - t_r[0] >= 0.5 * w:
                p_l, v_l = fit_line(t_r, np.array([h[1] for h in recent]))
                line = (p_l, v_l, float(t_r[-1]))
        for k in range(1, n_max + 1):
            z_now = fk(dh, np.asarray(arm.joint_positions(), float), self._T_ft)[2, 3]
            if abs(z_now - zg) < cfg.intercept_settle_tol:
                break
            if look and k % every == 0 and z_now - zg > cfg.intercept_update_height:
                assert name is not None
                q_now = np.asarray(arm.joint_positions(), float)
                if cfg.intercept_weak_updates:  # weak boxes on the track count (tracking)
                    _, meas = self._measure(
                        camera.capture(), name, q_now, kf, track=[kf.position()]
                    )
                    inn = None
                    if meas is not None and (
                        np.linalg.norm(meas.p - kf.position()) <= cfg.predictor.gate
                    ):
                        kf.update(meas.p)
                        inn = kf.innovation
                else:
                    inn = self._descent_update(camera, name, q_now, kf)
                abort = cfg.intercept_abort_innovation
                if abort > 0 and inn is not None and inn > abort:
                    self.aborted = True  # the object turned: track on from here
                    return q_cmd
            if line is not None and clock is not None:
                p = line[0] + line[1] * (clock() - line[2])
                v_obj = line[1]
            else:
                p, v_obj = kf.position(), kf.velocity()
            # the goal's TCP on the ramp (the object point is its top)
            t_k = k * dt
            z_k = z0 + sign * ramp(t_k)
            vz_k = sign * (ramp(t_k + 1e-3) - ramp(t_k)) / 1e-3
            q_goal, v_goal = self._intercept_goal(
                q_cmd, np.array([p[0], p[1], z_k]), v_obj, 0.0, yaw, vz_k
            )
            q_cmd = self._send_intercept(q_goal, v_goal, dt, cfg.intercept_descend_time)
            wait(dt)
            kf.predict(dt)
        if cfg.close_delay > 0:
            wait(cfg.close_delay)
        return q_cmd

    def _descent_update(
        self, camera: Any, name: str, q: Array, kf: ConstantVelocityKF
    ) -> float | None:
        """One detection during the descent: the predictor takes it when the box keeps
        ``descend_update_margin`` of the image clear and lies within the gate; returns its
        innovation (m), None when not taken."""
        frame = camera.capture()
        det, meas = self._measure(frame, name, q, kf)
        if meas is None or det is None:
            return None
        h, w = frame.color.shape[:2]
        x1, y1, x2, y2 = det.box
        m = self.cfg.descend_update_margin
        if min(x1 / w, y1 / h) < m or max(x2 / w, y2 / h) > 1.0 - m:
            return None
        if np.linalg.norm(meas.p - kf.position()) <= self.cfg.predictor.gate:
            kf.update(meas.p)
            return kf.innovation
        return None

    def _lift(self, arm: Any, q_cmd: Array) -> None:
        dh = self.robot.arm.dh
        T = fk(dh, q_cmd)
        T[2, 3] += self.cfg.lift
        q_min, q_max = self.robot.arm.q_limits
        q = ik_nearest(dh, T, q_cmd, q_min, q_max)
        arm.move_joints(q)

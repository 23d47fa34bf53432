"""The IPE loop of paper 000 Fig. 4, over the hardware-neutral Arm and Camera interfaces.

Frames and equations (:mod:`mmpa.ipe.core`; m, rad): ``T_Bo_Co`` the camera in the arm base at
teaching (eq. 1), ``T_Bk_Ck`` at the k-th view (eq. 2, nominal kinematics and hand-eye),
``dT_C`` the registration of the taught cloud ``X_i(O)`` to the view's ``X_i(k)`` (eq. 3),
``dT_B = T_Bk_Ck dT_C inv(T_Bo_Co)`` the parking offset (eq. 9-10), the next camera target
``T_Bk_C* = dT_B T_Bo_Co`` (eq. 11).

1. Set the sampling pose to the taught one (the taught joints ``q_sample``).
2. Loop ``k = 1 .. beta``: if the sampling pose is unreachable, stop with False (the arm does
   not move); move there and capture ``X_i(k)`` (:meth:`IPE._capture_view`), register the
   taught cloud to it (:meth:`IPE._register_view`, :meth:`IPE._refine_view`), update
   ``dT_B``; if ``dT_C`` is below ``alpha`` stop with True (:meth:`IPE._converged_view`);
   otherwise move the camera back to its taught pose in the world and go on. After ``beta``
   registrations, stop with False.

A failed registration (``ok=False``) or an implausible estimate stops IPE with False and a
reason; the arm never moves on a failed estimate. Beyond the paper (:class:`IPEConfig`): a
localization prior for the first view, a retreat when the first view fails, the projective
and photometric refinements of every view, the 4 mm final registration, the witness view.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from mmpa.core.errors import InvalidInputError, UnreachableError
from mmpa.core.geometry import Array, as_transform, inv, make_T
from mmpa.ipe.config import (
    FINAL_REFINEMENT,
    PRIOR_SCALES,
    IPEConfig,
    IPEIteration,
    IPEResult,
)
from mmpa.ipe.core import (
    camera_target,
    converged,
    delta_T_B,
    pose_difference,
)
from mmpa.registration import (
    Prepared,
    ProjectiveResult,
    Registration,
    RegistrationConfig,
    prepare,
    refine_projective,
    register,
)
from mmpa.robot.description import RobotDescription
from mmpa.robot.interfaces import Arm, Camera, PointCloud, RGBDFrame, mean_frame
from mmpa.robot.kinematics import fk, ik_nearest

_log = logging.getLogger(__name__)

__all__ = [
    "FINAL_REFINEMENT",
    "IPE",
    "PRIOR_SCALES",
    "IPEConfig",
    "IPEIteration",
    "IPEResult",
    "capture_cloud",
    "view_consistency",
]


_PREPARED: list[tuple[PointCloud, tuple, Prepared]] = []


def prepared(cloud: PointCloud, cfg: RegistrationConfig) -> Prepared:
    """``prepare(cloud, cfg)`` with a small cache (a taught cloud is prepared once per task).

    FPFH descriptors are left to first use (:meth:`Prepared.fpfh`): only a registration
    without ``init`` needs them (the final 4 mm refinement never does)."""
    key = cfg.preprocessing_key()
    for c, k, p in _PREPARED:
        if c is cloud and k == key:
            return p
    p = prepare(cloud, cfg, features=False)
    _PREPARED.append((cloud, key, p))
    del _PREPARED[:-6]
    return p


def capture_cloud(camera: Camera, frames: int, min_depth: float, max_depth: float) -> PointCloud:
    """Capture ``frames`` RGB-D frames, average them, deproject to a colored cloud."""
    return capture(camera, frames, min_depth, max_depth)[1]


def capture(
    camera: Camera, frames: int, min_depth: float, max_depth: float
) -> tuple[RGBDFrame, PointCloud]:
    """The averaged frame of ``frames`` captures and its colored cloud."""
    frame = mean_frame([camera.capture() for _ in range(frames)])
    return frame, frame.to_point_cloud(min_depth=min_depth, max_depth=max_depth)


Progress = Callable[[str, float], None]


class IPE:
    """Iterative pose estimation by eye & hand (Fig. 4) for one robot (NOMINAL model)."""

    def __init__(self, robot: RobotDescription, cfg: IPEConfig | None = None) -> None:
        self.robot = robot
        self.cfg = cfg or IPEConfig()
        self._T_flange_camera = robot.camera.T_flange_camera

    def T_arm_base_camera(self, q: Array) -> Array:
        """Nominal camera pose in the arm base at joints ``q`` (forward kinematics + hand-eye)."""
        return fk(self.robot.arm.dh, q) @ self._T_flange_camera

    def camera_joints(self, T_B_camera: Array, q_ref: Array) -> Array:
        """Joints that put the camera at ``T_B_camera`` (nearest ``q_ref``); UnreachableError."""
        lo, hi = self.robot.arm.q_limits
        T_B_flange = T_B_camera @ inv(self._T_flange_camera)
        return ik_nearest(self.robot.arm.dh, T_B_flange, q_ref, lo, hi)

    def _move_duration(self, arm: Arm, q: Array) -> float | None:
        """Duration (s) of a move to ``q`` at ``cfg.move_speed`` of the limits: the slower of
        the constant-velocity and the triangular-acceleration times of the farthest joint."""
        s = self.cfg.move_speed
        if s is None:
            return None
        dq = np.abs(np.asarray(q, float) - arm.joint_positions())
        v = np.asarray(self.robot.arm.qd_max, float) * s
        a = np.asarray(self.robot.arm.qdd_max, float) * s * s
        return float(np.max(np.maximum(dq / v, 2.0 * np.sqrt(dq / a))))

    def _projective(
        self, src: tuple[Array, Array | None], frame: RGBDFrame, T: Array
    ) -> ProjectiveResult:
        """The projective refinement (``cfg.projective``, depth only) of the taught points
        ``src[0]`` on the view's depth image, from ``T`` (``T_view_taught``, 4x4)."""
        assert self.cfg.projective is not None
        cam = self.robot.camera
        return refine_projective(
            src[0],
            frame.depth,
            frame.intrinsics,
            T,
            self.cfg.projective,
            disparity_fb=cam.depth_focal_native * cam.baseline,
        )

    def _witness(
        self,
        arm: Arm,
        camera: Camera,
        source: Prepared,
        src: tuple[Array, Array | None] | None,
        T_Bo_Co: Array,
        q: Array,
        result: IPEResult,
    ) -> None:
        """The witness view (``IPEConfig.witness``) of a converged ``result``: sets
        ``result.witness_*``, and refuses the estimate (``ok`` False, no ``dT_B``) when the
        witness is out of reach, its registration fails, or it disagrees."""
        cfg = self.cfg
        assert cfg.witness is not None and result.dT_B is not None
        t0 = time.perf_counter()
        side = make_T(np.eye(3), [cfg.witness, 0.0, 0.0])
        try:
            q_w = self.camera_joints(camera_target(result.dT_B, T_Bo_Co) @ side, q)
        except UnreachableError as e:
            result.ok, result.dT_B = False, None
            result.reason = f"the witness view is unreachable: {e}"
            return
        arm.move_joints(q_w, self._move_duration(arm, q_w))
        frame, cloud = capture(camera, cfg.frames, cfg.min_depth, cfg.max_depth)
        t1 = time.perf_counter()
        T_Bw_Cw = self.T_arm_base_camera(arm.joint_positions())
        init = inv(T_Bw_Cw) @ result.dT_B @ T_Bo_Co  # the taught cloud, as the estimate sees it
        reg = register(source, cloud, cfg.registration, init=init)
        dT_C = reg.T
        if reg.ok and cfg.projective is not None and src is not None:
            pr = self._projective(src, frame, reg.T)
            if pr.ok:
                pc = _photometric(src, cfg, pr, frame, self.robot)
                dT_C = pc.T if pc is not None else pr.T
        result.seconds_witness = time.perf_counter() - t1
        _log.debug("IPE witness view: %.2f s", time.perf_counter() - t0)
        if not reg.ok:
            result.ok, result.dT_B = False, None
            result.reason = f"the witness view's registration failed: {reg.reason}"
            return
        result.witness_dT_B = delta_T_B(T_Bw_Cw, dT_C, T_Bo_Co)
        d, a = view_consistency(result.dT_B, result.witness_dT_B, T_Bo_Co)
        result.witness_disagreement = (d, a)
        tol = cfg.witness_tolerance
        if d > tol[0] or a > tol[1]:
            result.ok, result.dT_B = False, None
            result.reason = (
                f"the witness view disagrees with the estimate by {d * 1e3:.2f} mm / "
                f"{np.rad2deg(a):.3f} deg at the camera (tolerance {tol[0] * 1e3:.1f} mm / "
                f"{np.rad2deg(tol[1]):.2f} deg): a registration slid; no estimate"
            )

    def run(
        self,
        arm: Arm,
        camera: Camera,
        q_sample: Array,
        T_Bo_Co: Array,
        taught: PointCloud | Prepared,
        progress: Progress | None = None,
        dT_B_prior: Array | None = None,
    ) -> IPEResult:
        """Run Fig. 4. ``taught`` is ``X_i(O)`` (camera frame at teaching), ``T_Bo_Co`` the
        nominal camera pose in the arm base at teaching, ``q_sample`` the taught joints.

        ``dT_B_prior`` (beyond the paper): a rough ``dT_B`` from the base localization (the
        planar park pose now vs at teaching). The first view is then taken where the camera
        should see the taught scene, and the first registration starts from the prior
        (falling back to global registration when that fails)."""
        cfg = self.cfg
        T_Bo_Co = as_transform(T_Bo_Co, "T_Bo_Co")
        q_next = np.asarray(q_sample, dtype=float)
        if q_next.shape != (6,) or not np.all(np.isfinite(q_next)):
            raise InvalidInputError(f"q_sample must be 6 finite joint angles, got {q_next}")
        t0 = time.perf_counter()
        if not cfg.use_color and isinstance(taught, PointCloud) and taught.colors is not None:
            taught = _colorless(taught)
        source = taught if isinstance(taught, Prepared) else prepared(taught, cfg.registration)
        result = IPEResult(ok=False, dT_B=None, seconds_prepare=time.perf_counter() - t0)
        lo, hi = self.robot.arm.q_limits
        prior, q_next = self._first_view(dT_B_prior, T_Bo_Co, q_next)
        retreated = False
        src: tuple[Array, Array | None] | None = None  # taught points, colours in the crop
        for k in range(1, cfg.beta + 1):
            if progress:
                progress(f"IPE iteration {k}", (k - 1) / cfg.beta)
            if not np.all((q_next >= lo) & (q_next <= hi)):  # False for a NaN too
                result.reason = f"iteration {k}: the sampling pose is outside the joint limits"
                return result
            q, frame, cloud, times = self._capture_view(arm, camera, q_next)
            T_Bk_Ck = self.T_arm_base_camera(q)
            reg = self._register_view(source, cloud, T_Bk_Ck, T_Bo_Co, result.dT_B, prior)
            pr, dT_C, src = self._refine_view(reg, taught, src, frame)
            t4 = time.perf_counter()
            dT_B = delta_T_B(T_Bk_Ck, dT_C, T_Bo_Co) if reg.ok else None  # eq. 9-10
            _record(result, k, q, T_Bk_Ck, reg, dT_B, dT_C, (*times, t4), pr)
            if not reg.ok or dT_B is None:
                if result.dT_B is None and not retreated and cfg.retreat > 0 and k < cfg.beta:
                    # beyond the paper: no estimate yet (little overlap, e.g. a tilted base):
                    # step the camera back along its optical axis for a wider view, try again
                    retreated = True
                    q_back = self._retreat(T_Bk_Ck, q)
                    if q_back is not None:  # keep the prior: the wider view starts from it
                        q_next = q_back
                        continue
                result.reason = f"iteration {k}: registration failed: {reg.reason}"
                return result
            if _implausible(dT_B, k, cfg, result):
                return result
            result.dT_B = dT_B
            if converged(dT_C, cfg.alpha):
                view = (T_Bk_Ck, q, reg, pr, frame, cloud)
                return self._converged_view(
                    arm, camera, source, src, taught, T_Bo_Co, view, k, result
                )
            if k == cfg.beta:
                break
            target = camera_target(dT_B, T_Bo_Co)  # eq. 11
            try:
                q_next = self.camera_joints(target, q)
            except UnreachableError as e:
                result.reason = f"iteration {k}: the next sampling pose is unreachable: {e}"
                result.dT_B = None
                return result
        result.reason = (
            f"not converged after beta={cfg.beta} iterations (last pose difference "
            f"{_fmt(result.iterations[-1].difference)})"
        )
        result.dT_B = None
        return result

    def _first_view(
        self, dT_B_prior: Array | None, T_Bo_Co: Array, q_next: Array
    ) -> tuple[Array | None, Array]:
        """The prior (None without one or when its view is out of reach) and the joints of
        the first view: where the prior puts the taught camera, else the taught joints."""
        prior = None if dT_B_prior is None else as_transform(dT_B_prior, "dT_B_prior")
        if prior is not None:
            try:
                q_next = self.camera_joints(camera_target(prior, T_Bo_Co), q_next)
            except UnreachableError:
                prior = None  # the taught joints, as in the paper
        return prior, q_next

    def _capture_view(
        self, arm: Arm, camera: Camera, q_next: Array
    ) -> tuple[Array, RGBDFrame, PointCloud, tuple[float, float, float]]:
        """Move to ``q_next`` and capture ``X_i(k)``: the joints reached, the averaged frame,
        its cloud (without colours unless ``use_color``) and the times before the move, the
        capture and after it."""
        cfg = self.cfg
        t1 = time.perf_counter()
        arm.move_joints(q_next, self._move_duration(arm, q_next))
        q = arm.joint_positions()
        t2 = time.perf_counter()
        frame, cloud = capture(camera, cfg.frames, cfg.min_depth, cfg.max_depth)
        if not cfg.use_color:
            cloud = PointCloud(cloud.points, None, cloud.frame)
        t3 = time.perf_counter()
        return q, frame, cloud, (t1, t2, t3)

    def _register_view(
        self,
        source: Prepared,
        cloud: PointCloud,
        T_Bk_Ck: Array,
        T_Bo_Co: Array,
        dT_B: Array | None,
        prior: Array | None,
    ) -> Registration:
        """``dT_C`` (eq. 3): the taught cloud registered to the view's. After the first view
        the camera is back near its taught pose: the previous estimate ``dT_B`` (or the
        prior) predicts ``dT_C`` (~ identity) and the fine stage starts there; the first
        view from the prior with a wider gate, falling back to global registration."""
        cfg = self.cfg
        init = None
        guess = dT_B if dT_B is not None else prior
        if guess is not None and not cfg.global_each_iteration:
            init = inv(T_Bk_Ck) @ guess @ T_Bo_Co
        if init is not None and dT_B is None:  # first view, from the prior
            wide = cfg.registration.model_copy(
                update={
                    "init_scales": PRIOR_SCALES,
                    "max_init_shift": cfg.prior_max_shift,
                    "max_init_rotation_deg": float(np.rad2deg(cfg.prior_max_rotation)),
                }
            )
            reg = register(source, cloud, wide, init=init)
            if not reg.ok:  # the prior was off: global registration as in the paper
                reg = register(source, cloud, cfg.registration)
            return reg
        return register(source, cloud, cfg.registration, init=init)

    def _refine_view(
        self,
        reg: Registration,
        taught: PointCloud | Prepared,
        src: tuple[Array, Array | None] | None,
        frame: RGBDFrame,
    ) -> tuple[ProjectiveResult | None, Array, tuple[Array, Array | None] | None]:
        """Beyond the paper: every accepted view refined at full resolution (the 1 cm voxel
        registration has a 1-3 mm aliasing bias that can keep the loop from meeting alpha).
        The refinement (None when off), ``dT_C`` (from it when ok) and the taught points in
        the depth crop (``src``, cropped once per run)."""
        cfg = self.cfg
        pr = None
        dT_C = reg.T
        if reg.ok and cfg.projective is not None and isinstance(taught, PointCloud):
            if src is None:  # cropped once per run
                src = _source(taught, cfg)
            pr = self._projective(src, frame, reg.T)
            if pr.ok:
                dT_C = pr.T
        return pr, dT_C, src

    def _retreat(self, T_Bk_Ck: Array, q: Array) -> Array | None:
        """The joints of the camera stepped back ``retreat`` along its optical axis (None
        when out of reach)."""
        back = T_Bk_Ck @ make_T(np.eye(3), [0.0, 0.0, -self.cfg.retreat])
        try:
            return self.camera_joints(back, q)
        except UnreachableError:
            return None

    def _converged_view(
        self,
        arm: Arm,
        camera: Camera,
        source: Prepared,
        src: tuple[Array, Array | None] | None,
        taught: PointCloud | Prepared,
        T_Bo_Co: Array,
        view: tuple[Array, Array, Registration, ProjectiveResult | None, RGBDFrame, PointCloud],
        k: int,
        result: IPEResult,
    ) -> IPEResult:
        """``dT_C`` is below ``alpha``: the depth-scale check, then (beyond the paper) the
        photometric refinement of the converged view, the 4 mm final registration where the
        projective one is off or refused, and the witness view. ``view`` = (``T_Bk_Ck``, the
        joints, the registration, its projective refinement, the frame, its cloud)."""
        cfg = self.cfg
        T_Bk_Ck, q, reg, pr, frame, cloud = view
        if _scale_fault(pr, cfg):
            # at the taught viewpoint the refinement saw the scene at another depth scale
            # than at teaching: a depth calibration fault (3 % moves dT_B by ~1 cm), not
            # a pose offset; no estimate from this camera is trusted. (Away from the
            # viewpoint the scale trades with depth-wise motion and is not checked.)
            result.reason = (
                f"iteration {k}: depth scale {_depth_scale(pr):.4f} against the teaching "
                f"capture (accepted 1 +- {cfg.projective.max_scale_error}): a depth "
                "calibration fault of the camera; no estimate"
            )
            result.dT_B = None
            return result
        result.ok = True
        t5 = time.perf_counter()
        if pr is not None and pr.ok and src is not None:
            # beyond the paper: the converged view once more with its colour image
            # (depth + photometric); the depth alone cannot tell a rotation about the
            # scene from a drift of the disparity between the sessions
            pc = _photometric(src, cfg, pr, frame, self.robot)
            if pc is not None:
                pr = pc
                result.dT_B = delta_T_B(T_Bk_Ck, pc.T, T_Bo_Co)
        result.projective = pr  # dT_B above already comes from it when ok
        if isinstance(taught, PointCloud):
            if (pr is None or not pr.ok) and cfg.final is not None:
                fin = register(prepared(taught, cfg.final), cloud, cfg.final, init=reg.T)
                result.final = fin
                if fin.ok:
                    result.dT_B = delta_T_B(T_Bk_Ck, fin.T, T_Bo_Co)
            result.seconds_final = time.perf_counter() - t5
        if cfg.witness is not None and result.dT_B is not None:
            self._witness(arm, camera, source, src, T_Bo_Co, q, result)
        return result


def _record(
    result: IPEResult,
    k: int,
    q: Array,
    T_Bk_Ck: Array,
    reg: Registration,
    dT_B: Array | None,
    dT_C: Array,
    times: tuple[float, float, float, float],
    pr: ProjectiveResult | None,
) -> None:
    """Append the iteration to ``result`` (``times``: before the move, the capture, the
    registration, after the refinement) and log it."""
    t1, t2, t3, t4 = times
    it = IPEIteration(
        k, q, T_Bk_Ck, reg, dT_B, pose_difference(dT_C), t2 - t1, t3 - t2, t4 - t3, pr
    )
    result.iterations.append(it)
    _log.debug(
        "IPE iteration %d: registration %s (fitness %.3f, rmse %.2f mm)%s",
        k,
        "ok" if reg.ok else f"refused: {reg.reason}",
        reg.fitness,
        1e3 * reg.rmse,
        "" if pr is None else f"; projective {'ok' if pr.ok else pr.reason}",
    )


def _implausible(dT_B: Array, k: int, cfg: IPEConfig, result: IPEResult) -> bool:
    """``dT_B`` beyond ``max_translation`` / ``max_rotation`` (sets ``result.reason``)."""
    if np.linalg.norm(dT_B[:3, 3]) > cfg.max_translation or _angle(dT_B) > cfg.max_rotation:
        result.reason = (
            f"iteration {k}: implausible parking offset "
            f"({np.linalg.norm(dT_B[:3, 3]):.3f} m, {np.rad2deg(_angle(dT_B)):.1f} deg)"
        )
        return True
    return False


def view_consistency(dT_B_a: Array, dT_B_b: Array, T_Bo_Co: Array) -> tuple[float, float]:
    """How far two estimates of the parking offset disagree: the distance (m) between the
    taught camera's position moved by each, ``|dT_B_a c - dT_B_b c|`` with ``c`` the
    translation of ``T_Bo_Co`` (4, 4), and the angle (rad) of ``R_a R_b^T``."""
    c = np.append(np.asarray(T_Bo_Co, float)[:3, 3], 1.0)
    d = float(np.linalg.norm((np.asarray(dT_B_a) @ c - np.asarray(dT_B_b) @ c)[:3]))
    return d, _angle(np.asarray(dT_B_a) @ inv(np.asarray(dT_B_b)))


def _photometric(
    src: tuple[Array, Array | None],
    cfg: IPEConfig,
    pr: ProjectiveResult,
    frame: RGBDFrame,
    robot: RobotDescription,
) -> ProjectiveResult | None:
    """The joint depth + colour refinement of the converged view from the depth-only
    refinement ``pr`` (:func:`refine_projective` with the source colours and the target
    colour image); ``src`` the taught points and colours in the depth crop
    (:func:`_source`). None when it is off (``photometric_sigma`` None, a cloud without
    colours) or refused (the depth-only result then stands)."""
    pcfg = cfg.projective
    points, colors = src
    if pcfg is None or pcfg.photometric_sigma is None or colors is None:
        return None
    cam = robot.camera
    res = refine_projective(
        points,
        frame.depth,
        frame.intrinsics,
        pr.T,
        pcfg.model_copy(update={"photometric_depth_pass": False}),  # pr is that pass
        disparity_fb=cam.depth_focal_native * cam.baseline,
        source_colors=colors,
        target_color=frame.color,
    )
    if not res.ok:
        _log.info("IPE: the photometric refinement refused (%s); depth only", res.reason)
        return None
    return res


def _scale_fault(pr: ProjectiveResult | None, cfg: IPEConfig) -> bool:
    """The projective refinement refused a view for its depth scale alone: enough inliers,
    ``|s - 1|`` beyond ``max_scale_error`` (``s`` with the disparity offset folded in)."""
    return (
        pr is not None
        and cfg.projective is not None
        and not pr.ok
        and pr.n_inliers >= cfg.projective.min_inliers
        and abs(_depth_scale(pr) - 1.0) > cfg.projective.max_scale_error
    )


def _depth_scale(pr: ProjectiveResult) -> float:
    """The relative depth scale of the two captures at the scene's median depth (the scale
    and the disparity offset together: ``stages["effective_scale"]``)."""
    return float(pr.stages.get("effective_scale", pr.scale))


def _source(taught: PointCloud, cfg: IPEConfig) -> tuple[Array, Array | None]:
    """The taught points inside the depth crop (the source of the projective refinement)
    and their colours (None for a cloud without colours)."""
    p = np.asarray(taught.points, float)
    z = p[:, 2]
    keep = (z >= cfg.min_depth) & (z <= cfg.max_depth)
    colors = None if taught.colors is None else np.asarray(taught.colors)[keep]
    return p[keep], colors


_COLORLESS: list[tuple[PointCloud, PointCloud]] = []


def _colorless(cloud: PointCloud) -> PointCloud:
    """The same cloud without colors (one object per input, so preparation stays cached)."""
    for c, g in _COLORLESS:
        if c is cloud:
            return g
    g = PointCloud(cloud.points, None, cloud.frame)
    _COLORLESS.append((cloud, g))
    del _COLORLESS[:-4]
    return g


def _angle(T: Array) -> float:
    return float(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1.0, 1.0)))


def _fmt(d: Array) -> str:
    return (
        f"{d[0] * 1e3:.2f}/{d[1] * 1e3:.2f}/{d[2] * 1e3:.2f} mm, "
        f"{np.rad2deg(d[3]):.3f}/{np.rad2deg(d[4]):.3f}/{np.rad2deg(d[5]):.3f} deg"
    )

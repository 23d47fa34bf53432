"""Eye-in-hand calibration: the camera's pose on the flange from views of a fixed board.

Notation (all 4x4 homogeneous transforms, m): at station ``i`` the arm reports
``G_i = T_base_flange(q_i)`` (forward kinematics of the measured joints) and the camera
measures ``C_i = T_camera_board`` (PnP on the board). The unknowns are the hand-eye
``X = T_flange_camera`` and the board's pose ``Y = T_base_board``; every station gives

    Y = G_i X C_i                                                      (1)

so for two stations ``i, j``, with the flange motion ``A = G_i^-1 G_j`` and the camera motion
``B = C_i C_j^-1``, ``A X = X B`` (AX = XB; Shiu & Ahmad 1989, Tsai & Lenz 1989).
``cv2.calibrateHandEye`` solves it with five methods: Tsai-Lenz (rotation axes, then a
linear translation), Park-Martin (Lie-group least squares), Horaud-Dornaika (quaternions),
Andreff (a linear Kronecker form) and Daniilidis (dual quaternions).

Residuals. The board is fixed, so (1) predicted from every station must agree. For a
solution ``X`` the prediction ``Y_i = G_i X C_i`` maps the board corners ``p_k`` (board
frame) to ``Y_i p_k`` (base frame); with ``ybar_k`` their mean over stations,

    point spread   = sqrt(mean_ik |Y_i p_k - ybar_k|^2)    (mm; rotation and translation
                                                            errors both show as corner motion)
    rotation spread = sqrt(mean_i angle(R_i, Rbar)^2)      (deg; Rbar the chordal mean)

The method with the smallest point spread is picked (Tsai & Lenz's own criterion is the
consistency of the solution over stations; with noise-free data every method is exact).

Pose selection (Tsai & Lenz 1989, section V): large rotations between stations about
non-parallel axes, the camera close to the board, many stations. :func:`plan_stations`
makes candidate views on cones around the board normal (tilts, azimuths, rolls about the
optical axis), keeps those reachable within the joint limits (IK nearest to a reference
configuration) with the whole board in the image, and picks a diverse set greedily
(each next view the one farthest in rotation from those already chosen).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from mmpa.core.errors import InvalidInputError, MMPAError, UnreachableError
from mmpa.core.geometry import Array, inv, make_T
from mmpa.robot.description import DHParameters
from mmpa.robot.kinematics import fk, ik_nearest

__all__ = [
    "METHODS",
    "HandEyeResult",
    "MethodResult",
    "Station",
    "board_consistency",
    "calibrate_hand_eye",
    "look_at",
    "pair_motion_stats",
    "plan_stations",
    "pose_error",
    "solve_hand_eye",
]

#: OpenCV's hand-eye methods by name
METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis")


def _cv_method(name: str) -> int:

    table = {
        "tsai": cv2.CALIB_HAND_EYE_TSAI,
        "park": cv2.CALIB_HAND_EYE_PARK,
        "horaud": cv2.CALIB_HAND_EYE_HORAUD,
        "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
        "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
    }
    if name not in table:
        raise InvalidInputError(f"unknown hand-eye method {name!r}; one of {list(METHODS)}")
    return int(table[name])


def _rot_angle(R: Array) -> float:
    """Rotation angle (rad) of a 3x3 rotation matrix: ``atan2(|w|, (tr R - 1) / 2)`` with
    ``w = vee(R - R^T) / 2`` (``sin`` times the axis), accurate near 0 unlike ``arccos``."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2.0
    return float(np.arctan2(np.linalg.norm(w), (np.trace(R) - 1.0) / 2.0))


def pose_error(T_est: Array, T_true: Array) -> tuple[float, float]:
    """``(translation error mm, rotation error deg)`` of ``T_est`` against ``T_true``:
    ``|t_est - t_true|`` and the angle of ``R_true^T R_est``."""
    T_est, T_true = np.asarray(T_est, float), np.asarray(T_true, float)
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])) * 1e3
    return dt, float(np.rad2deg(_rot_angle(T_true[:3, :3].T @ T_est[:3, :3])))


def _as_stack(T: Array, name: str) -> Array:
    T = np.asarray(T, float)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
        raise InvalidInputError(f"{name} must be a finite (N, 4, 4) stack, got shape {T.shape}")
    return T


def solve_hand_eye(T_base_flange: Array, T_camera_board: Array, method: str = "park") -> Array:
    """``X = T_flange_camera`` (4, 4) from ``N >= 3`` stations: ``T_base_flange`` (N, 4, 4)
    and ``T_camera_board`` (N, 4, 4), by ``cv2.calibrateHandEye`` with ``method`` (one of
    :data:`METHODS`). OpenCV's names: gripper2base = ``G_i``, target2cam = ``C_i``,
    cam2gripper = ``X``."""

    G = _as_stack(T_base_flange, "T_base_flange")
    C = _as_stack(T_camera_board, "T_camera_board")
    if G.shape[0] != C.shape[0]:
        raise InvalidInputError(f"{G.shape[0]} flange poses but {C.shape[0]} board poses")
    if G.shape[0] < 3:
        raise InvalidInputError(f"hand-eye needs at least 3 stations, got {G.shape[0]}")
    R, t = cv2.calibrateHandEye(
        [g[:3, :3] for g in G],
        [g[:3, 3].reshape(3, 1) for g in G],
        [c[:3, :3] for c in C],
        [c[:3, 3].reshape(3, 1) for c in C],
        method=_cv_method(method),
    )
    X = make_T(np.asarray(R, float), np.asarray(t, float).ravel())
    if not np.all(np.isfinite(X)):
        raise MMPAError(f"hand-eye method {method!r} returned a non-finite solution")
    return X


def _chordal_mean(Rs: Array) -> Array:
    """The rotation closest (Frobenius) to the mean of ``Rs`` (N, 3, 3)."""
    U, _, Vt = np.linalg.svd(np.mean(Rs, axis=0))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


@dataclass(frozen=True)
class Consistency:
    """How well the stations agree on the board pose ``Y_i = G_i X C_i`` (module docstring):
    corner point spread RMS / max (mm), origin spread RMS (mm), rotation spread RMS / max
    (deg), and the mean board pose ``Y`` (4, 4)."""

    point_rms_mm: float
    point_max_mm: float
    origin_rms_mm: float
    rot_rms_deg: float
    rot_max_deg: float
    T_base_board: Array

    def as_dict(self) -> dict[str, float]:
        return {
            "point_rms_mm": self.point_rms_mm,
            "point_max_mm": self.point_max_mm,
            "origin_rms_mm": self.origin_rms_mm,
            "rot_rms_deg": self.rot_rms_deg,
            "rot_max_deg": self.rot_max_deg,
        }


def board_consistency(
    T_base_flange: Array, T_camera_board: Array, X: Array, corners: Array
) -> Consistency:
    """The AX = XB consistency of ``X`` over the stations: ``Y_i = G_i X C_i`` and the spread
    of the board corners ``corners`` (K, 3) (board frame, m) and rotations (module
    docstring)."""
    G = _as_stack(T_base_flange, "T_base_flange")
    C = _as_stack(T_camera_board, "T_camera_board")
    P = np.asarray(corners, float).reshape(-1, 3)
    Y = G @ np.asarray(X, float) @ C  # (N, 4, 4)
    pts = np.einsum("nij,kj->nki", Y[:, :3, :3], P) + Y[:, None, :3, 3]  # (N, K, 3)
    dev = np.linalg.norm(pts - pts.mean(axis=0), axis=2) * 1e3
    org = np.linalg.norm(Y[:, :3, 3] - Y[:, :3, 3].mean(axis=0), axis=1) * 1e3
    Rbar = _chordal_mean(Y[:, :3, :3])
    ang = np.rad2deg([_rot_angle(Rbar.T @ R) for R in Y[:, :3, :3]])
    return Consistency(
        point_rms_mm=float(np.sqrt(np.mean(dev**2))),
        point_max_mm=float(dev.max()),
        origin_rms_mm=float(np.sqrt(np.mean(org**2))),
        rot_rms_deg=float(np.sqrt(np.mean(np.square(ang)))),
        rot_max_deg=float(np.max(ang)),
        T_base_board=make_T(Rbar, Y[:, :3, 3].mean(axis=0)),
    )


def axxb_residual(T_base_flange: Array, T_camera_board: Array, X: Array) -> tuple[float, float]:
    """RMS over station pairs ``i < j`` of ``A X`` against ``X B`` (``A = G_i^-1 G_j``,
    ``B = C_i C_j^-1``): ``(translation mm, rotation deg)``."""
    G = _as_stack(T_base_flange, "T_base_flange")
    C = _as_stack(T_camera_board, "T_camera_board")
    et, er = [], []
    for i in range(len(G)):
        for j in range(i + 1, len(G)):
            A = inv(G[i]) @ G[j]
            B = C[i] @ inv(C[j])
            t, r = pose_error(A @ X, X @ B)
            et.append(t)
            er.append(r)
    return float(np.sqrt(np.mean(np.square(et)))), float(np.sqrt(np.mean(np.square(er))))


@dataclass(frozen=True)
class MethodResult:
    """One method's ``X = T_flange_camera`` and its residuals."""

    method: str
    T_flange_camera: Array
    consistency: Consistency
    axxb_trans_mm: float
    axxb_rot_deg: float


@dataclass(frozen=True)
class HandEyeResult:
    """All methods' results and the one picked (smallest corner point spread)."""

    methods: dict[str, MethodResult]
    best: str
    n_stations: int
    failed: dict[str, str] = field(default_factory=dict)

    @property
    def T_flange_camera(self) -> Array:
        return self.methods[self.best].T_flange_camera


def calibrate_hand_eye(
    T_base_flange: Array,
    T_camera_board: Array,
    corners: Array,
    methods: tuple[str, ...] = METHODS,
) -> HandEyeResult:
    """Solve with every method in ``methods``, score each by :func:`board_consistency` of the
    board ``corners`` (K, 3) and :func:`axxb_residual`, and pick the smallest point spread.
    A method that fails is reported in ``failed``; all failing raises :class:`MMPAError`."""
    out: dict[str, MethodResult] = {}
    failed: dict[str, str] = {}
    for m in methods:
        try:
            X = solve_hand_eye(T_base_flange, T_camera_board, m)
        except MMPAError as e:
            if isinstance(e, InvalidInputError) and "unknown" in str(e):
                raise
            failed[m] = str(e)
            continue
        except Exception as e:  # OpenCV raises cv2.error on degenerate data
            failed[m] = f"{type(e).__name__}: {e}"
            continue
        cons = board_consistency(T_base_flange, T_camera_board, X, corners)
        t, r = axxb_residual(T_base_flange, T_camera_board, X)
        out[m] = MethodResult(m, X, cons, t, r)
    if not out:
        raise MMPAError(f"every hand-eye method failed: {failed}")
    best = min(out, key=lambda k: out[k].consistency.point_rms_mm)
    return HandEyeResult(out, best, int(np.asarray(T_base_flange).shape[0]), failed)


# --- pose selection -----------------------------------------------------------------------


def look_at(eye: Array, target: Array, up_hint: Array, roll: float = 0.0) -> Array:
    """Optical-frame pose (4, 4) at ``eye`` (3,) looking at ``target`` (3,): z toward the
    target, x the component of ``up_hint`` (3,) across z, then turned by ``roll`` rad about
    z."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    n = np.linalg.norm(z)
    if n < 1e-9:
        raise InvalidInputError("eye and target coincide")
    z /= n
    x = np.asarray(up_hint, float) - z * float(np.dot(up_hint, z))
    if np.linalg.norm(x) < 1e-6:
        raise InvalidInputError("up_hint is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    R = np.column_stack([c * x + s * y, -s * x + c * y, z])
    return make_T(R, eye)


@dataclass(frozen=True)
class Station:
    """A calibration view: joints ``q`` (6,) rad and the planned (nominal) camera pose in the
    board frame; its cone ``tilt_deg`` from the board normal, ``azimuth_deg`` about it, and
    ``roll_deg`` about the optical axis, at ``distance`` m from the board centre."""

    q: Array
    T_board_camera: Array
    tilt_deg: float
    azimuth_deg: float
    roll_deg: float
    distance: float


def _in_view(
    T_board_camera: Array, corners: Array, K: Array, size: tuple[int, int], margin: float
) -> bool:
    T = inv(T_board_camera)
    p = corners @ T[:3, :3].T + T[:3, 3]
    if np.any(p[:, 2] < 0.05):
        return False
    u = p[:, :2] / p[:, 2:3] * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    w, h = size
    return bool(
        np.all(u[:, 0] > margin)
        and np.all(u[:, 0] < w - 1 - margin)
        and np.all(u[:, 1] > margin)
        and np.all(u[:, 1] < h - 1 - margin)
    )


def plan_stations(
    dh: DHParameters,
    q_limits: tuple[Array, Array],
    T_base_board: Array,
    T_flange_camera: Array,
    board_corners: Array,
    K: Array,
    image_size: tuple[int, int],
    n_stations: int,
    q_ref: Array,
    *,
    distances: tuple[float, ...] = (0.40, 0.48),
    tilts_deg: tuple[float, ...] = (0.0, 15.0, 25.0, 35.0),
    azimuths_deg: tuple[float, ...] = tuple(range(0, 360, 45)),
    rolls_deg: tuple[float, ...] = (-40.0, 0.0, 40.0),
    margin_px: float = 25.0,
    max_joint_step: float = 2.5,
) -> list[Station]:
    """``n_stations`` diverse, reachable views of the board (module docstring).

    ``dh`` (:class:`~mmpa.robot.description.DHParameters`) and ``T_flange_camera`` are the
    model used (the nominal: the truth is unknown); ``T_base_board`` (4, 4) the board pose
    estimate in the arm base frame; ``board_corners`` (K, 3) its corners (board frame) that
    must all project inside ``image_size`` = ``(W, H)`` px with ``K`` (3, 3), ``margin_px``
    from the border; ``q_ref`` (6,) the configuration IK stays near (no joint farther than
    ``max_joint_step`` rad from it, so no view needs a wrist flip). Candidates: the camera on
    a cone ``tilt`` from the board normal at ``azimuth``, ``distance`` from the board centre,
    looking at the centre, rolled ``roll`` about its axis. Selection: greedy farthest-point in
    the rotation of ``T_base_flange`` (the first is the candidate nearest ``q_ref``). The
    chosen views are ordered nearest-neighbour in joint space (short moves). Raises
    :class:`UnreachableError` when fewer than ``n_stations`` candidates qualify."""

    if n_stations < 3:
        raise InvalidInputError(f"need at least 3 stations, got {n_stations}")
    P = np.asarray(board_corners, float).reshape(-1, 3)
    centre = np.array([*(P.min(axis=0)[:2] + P.max(axis=0)[:2]) / 2, 0.0])
    K = np.asarray(K, float)
    q_ref = np.asarray(q_ref, float)
    X_inv = inv(np.asarray(T_flange_camera, float))
    Y = np.asarray(T_base_board, float)
    # camera x ("right" in the image) along the board's x: the image shows the board upright
    cands: list[tuple[Station, Array]] = []
    for d in distances:
        for tilt in tilts_deg:
            for az in azimuths_deg if tilt > 0 else (0.0,):
                t, a = np.deg2rad(tilt), np.deg2rad(az)
                # the viewing side is the board's -z half-space
                v = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), -np.cos(t)])
                for roll in rolls_deg:
                    T_bc = look_at(
                        centre + d * v, centre, np.array([1.0, 0.0, 0.0]), np.deg2rad(roll)
                    )
                    if not _in_view(T_bc, P, K, image_size, margin_px):
                        continue
                    T_bf = Y @ T_bc @ X_inv
                    try:
                        q = ik_nearest(dh, T_bf, q_ref, *q_limits)
                    except UnreachableError:
                        continue
                    if np.max(np.abs(q - q_ref)) > max_joint_step:
                        continue
                    if np.max(np.abs(fk(dh, q) - T_bf)) > 1e-6:
                        continue
                    cands.append((Station(q, T_bc, tilt, float(az), roll, d), T_bf))
    if len(cands) < n_stations:
        raise UnreachableError(
            f"only {len(cands)} reachable board views with the whole board in the image, "
            f"need {n_stations}: move the board or the robot, or ask for fewer stations"
        )
    Rs = np.array([T[:3, :3] for _, T in cands])
    first = int(np.argmin([np.linalg.norm(s.q - q_ref) for s, _ in cands]))
    chosen = [first]
    dmin = np.array([_rot_angle(Rs[first].T @ R) for R in Rs])
    while len(chosen) < n_stations:
        nxt = int(np.argmax(dmin))
        chosen.append(nxt)
        dmin = np.minimum(dmin, [_rot_angle(Rs[nxt].T @ R) for R in Rs])
    # order: nearest neighbour in joint space from q_ref
    left = list(chosen)
    order: list[int] = []
    cur = q_ref
    while left:
        k = min(left, key=lambda i: float(np.linalg.norm(cands[i][0].q - cur)))
        order.append(k)
        left.remove(k)
        cur = cands[k][0].q
    return [cands[i][0] for i in order]


def pair_motion_stats(T_base_flange: Array) -> dict[str, float]:
    """Tsai-Lenz conditioning of a station set: over all pairs ``i < j`` the rotation angle of
    ``A = G_i^-1 G_j`` (min / median deg) and the spread of the rotation axes,
    ``axis_conditioning = s_min / s_max`` of the singular values of the stacked
    ``angle * axis`` vectors (M, 3) (0: all axes parallel, 1: isotropic)."""
    G = _as_stack(T_base_flange, "T_base_flange")

    angles, vecs = [], []
    for i in range(len(G)):
        for j in range(i + 1, len(G)):
            R = G[i][:3, :3].T @ G[j][:3, :3]
            rv, _ = cv2.Rodrigues(R)
            angles.append(np.rad2deg(np.linalg.norm(rv)))
            vecs.append(rv.ravel())
    s = np.linalg.svd(np.array(vecs), compute_uv=False)
    return {
        "min_pair_rotation_deg": float(np.min(angles)),
        "median_pair_rotation_deg": float(np.median(angles)),
        "max_pair_rotation_deg": float(np.max(angles)),
        "axis_conditioning": float(s[-1] / s[0]) if s[0] > 0 else 0.0,
    }

"""Joint kinematic + hand-eye calibration ("robot calibration with a camera") from views of a
fixed board: the arm's DH corrections, the hand-eye and the board pose in one MAP estimate.

Model (m, rad, px). Station ``i`` has encoder readings ``q_i`` (6,) and detected board
corners ``u_ik`` (px) of board points ``p_k`` (board frame, m). With the DH corrections
``delta = (dtheta, da, dd, dalpha)`` (4 x 6, added to the nominal DH as a UR controller's
``calibration.conf`` does: ``theta_offset += dtheta``, ``a += da``, ...), the hand-eye
``X = T_flange_camera`` and the board ``Y = T_base_board``,

    x_ik = (fk(dh + delta, q_i) X)^-1 Y p_k           (the corner in the camera frame)
    u_ik ~ pi(K, x_ik) + e,   e ~ N(0, sigma_px^2 I)   (pinhole, no distortion)

Prior: ``delta_j ~ N(0, s_j^2)`` independently, ``s_j`` the published size of an
uncalibrated UR arm's DH error (``prior_length_sigma_mm`` on ``a, d``,
``prior_angle_sigma_deg`` on ``theta, alpha``); ``X`` and ``Y`` flat. The MAP estimate
minimises

    sum_ik |pi(K, x_ik) - u_ik|^2 / sigma_px^2  +  sum_j (delta_j / s_j)^2

(regularized nonlinear least squares, :func:`scipy.optimize.least_squares`, trust region).
Unknowns in scaled units: ``z_j = delta_j / s_j`` (24), ``X = X0 [R(w_x) | t_x]`` and
``Y = Y0 [R(w_y) | t_y]`` with ``t`` in mm and the rotation vector ``w`` in mrad (6 + 6),
started at ``z = 0`` and the best OpenCV hand-eye ``X0`` with its board pose ``Y0``.

Identifiability. Some DH combinations do not change any observation: the last link's
``theta_6, d_6, a_6, alpha_6`` act after ``Rz(q_6)`` (``A_6 = Rz(q_6) B_6``) so only the
product ``B_6 X`` is seen (the split of the flange from the camera is not observable from
camera data alone); ``theta_1, d_1`` act before ``Rz(q_1)`` on the base side and trade with
``Y``; ``d_2, d_3, d_4`` of the parallel joints 2-4 only act through their sum. Without the
prior the normal matrix ``J^T J`` is singular along these directions; with it the MAP is
unique and leaves them at the prior mean (zero correction). The posterior covariance
``(J^T J)^-1`` of the whole stacked system (data rows / sigma_px and prior rows / s_j)
reports it: a parameter whose posterior SD is close to its prior SD (ratio ~ 1) was not
learnt from the data; the singular values of the data-only Jacobian in scaled units count
the directions the data pin better than the prior (singular value > 1).

Consequence for the hand-eye: whatever the data, ``X`` is only found as
``X_eff = E_6 X_true`` with ``E_6 = B_6,nom^-1 B_6,true`` the last link's true error (the
camera chain ``fk X`` is right; the flange frame is the nominal last link's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from mmpa.core.errors import InvalidInputError, MMPAError
from mmpa.core.geometry import Array, make_T
from mmpa.robot.description import DHParameters

__all__ = [
    "DH_GROUPS",
    "GAUGE_INDICES",
    "BoardObservations",
    "JointCalibrationConfig",
    "JointCalibrationResult",
    "apply_dh_deltas",
    "calibrate_kinematics_hand_eye",
    "fk_batch",
    "fk_point_error",
    "project",
    "random_configurations",
]

#: the DH correction groups in the order of the parameter vector (6 joints each)
DH_GROUPS = ("delta_theta", "delta_a", "delta_d", "delta_alpha")
_LENGTH = (False, True, True, False)  # per group: length (m) or angle (rad)
#: parameter-vector indices of the DH corrections no camera data can see (module docstring):
#: theta_1, d_1 (trade with the board pose), theta_6, a_6, d_6, alpha_6 (with the hand-eye)
#: and d_2, d_3 (only d_2 + d_3 + d_4 acts); index = 6 * group + joint
GAUGE_INDICES = np.array([0, 12, 5, 11, 17, 23, 13, 14])


class JointCalibrationConfig(BaseModel):
    """The MAP problem's settings: prior SDs of the DH corrections (the published size of an
    uncalibrated UR arm's error: about 1 mm on ``a, d`` and 0.1 deg on ``theta, alpha``),
    the corner noise ``pixel_sigma`` (px), the robust ``loss`` on the corner residuals
    (``linear``: plain least squares) and the solver's evaluation budget."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    prior_length_sigma_mm: float = Field(1.0, gt=0, le=100)
    prior_angle_sigma_deg: float = Field(0.1, gt=0, le=10)
    pixel_sigma: float = Field(0.25, gt=0, le=100)
    loss: str = Field("linear", pattern="^(linear|soft_l1|huber|cauchy)$")
    max_nfev: int = Field(200, ge=5, le=10000)
    station_rot_sigma_deg: float = Field(0.0, ge=0, le=10)
    station_shift_sigma_mm: float = Field(0.0, ge=0, le=100)


@dataclass(frozen=True)
class BoardObservations:
    """Corners seen from ``N`` stations: ``q`` (N, 6) rad, and per corner (M in all) its
    ``station`` index (M,) int, ``object_points`` (M, 3) m in the board frame and
    ``image_points`` (M, 2) px."""

    q: Array
    station: np.ndarray
    object_points: Array
    image_points: Array

    def __post_init__(self) -> None:
        q = np.asarray(self.q, float)
        st = np.asarray(self.station)
        P = np.asarray(self.object_points, float)
        u = np.asarray(self.image_points, float)
        if q.ndim != 2 or q.shape[1] != 6 or not np.all(np.isfinite(q)):
            raise InvalidInputError(f"q must be a finite (N, 6) array, got shape {q.shape}")
        m = st.shape[0] if st.ndim == 1 else -1
        if P.shape != (m, 3) or u.shape != (m, 2):
            raise InvalidInputError(
                f"station (M,), object_points (M, 3) and image_points (M, 2) must agree, got "
                f"{st.shape}, {P.shape}, {u.shape}"
            )
        if not (np.all(np.isfinite(P)) and np.all(np.isfinite(u))):
            raise InvalidInputError("object_points and image_points must be finite")
        if m and (not np.issubdtype(st.dtype, np.integer) or st.min() < 0 or st.max() >= len(q)):
            raise InvalidInputError(f"station indices must be integers in [0, {len(q)})")

    @property
    def n_stations(self) -> int:
        return int(np.asarray(self.q).shape[0])

    @classmethod
    def from_lists(
        cls, q: list[Array], object_points: list[Array], image_points: list[Array]
    ) -> BoardObservations:
        """From per-station lists: ``q[i]`` (6,), ``object_points[i]`` (K_i, 3),
        ``image_points[i]`` (K_i, 2)."""
        if not (len(q) == len(object_points) == len(image_points)):
            raise InvalidInputError(
                f"{len(q)} stations but {len(object_points)} / {len(image_points)} corner sets"
            )
        if not q:
            raise InvalidInputError("no stations")
        st = np.concatenate([np.full(len(np.asarray(p)), i) for i, p in enumerate(object_points)])
        return cls(
            q=np.array(q, float),
            station=st.astype(int),
            object_points=np.concatenate(
                [np.asarray(p, float).reshape(-1, 3) for p in object_points]
            ),
            image_points=np.concatenate(
                [np.asarray(u, float).reshape(-1, 2) for u in image_points]
            ),
        )


def apply_dh_deltas(dh: DHParameters, deltas: dict[str, Array]) -> DHParameters:
    """``dh`` with the corrections ``deltas`` (keys :data:`DH_GROUPS`, 6 values each, rad or
    m) added as a UR controller adds its ``calibration.conf``."""
    a, d, alpha, th = dh.as_arrays()
    g = {k: np.asarray(deltas.get(k, np.zeros(6)), float).reshape(6) for k in DH_GROUPS}
    return DHParameters(
        a=tuple((a + g["delta_a"]).tolist()),
        d=tuple((d + g["delta_d"]).tolist()),
        alpha=tuple((alpha + g["delta_alpha"]).tolist()),
        theta_offset=tuple((th + g["delta_theta"]).tolist()),
    )


def fk_batch(a: Array, d: Array, alpha: Array, theta_offset: Array, q: Array) -> Array:
    """``T_arm_base_flange`` (N, 4, 4) for joints ``q`` (N, 6) with DH arrays (6,) each:
    ``prod_i Rz(q_i + theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)`` (the model of
    :func:`mmpa.robot.kinematics.fk`, arrays instead of a DHParameters)."""
    th = np.asarray(q, float) + theta_offset
    ct, st = np.cos(th), np.sin(th)
    ca, sa = np.cos(alpha), np.sin(alpha)
    n = th.shape[0]
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    for i in range(6):
        A = np.zeros((n, 4, 4))
        A[:, 0, 0], A[:, 0, 1], A[:, 0, 2], A[:, 0, 3] = (
            ct[:, i],
            -st[:, i] * ca[i],
            st[:, i] * sa[i],
            a[i] * ct[:, i],
        )
        A[:, 1, 0], A[:, 1, 1], A[:, 1, 2], A[:, 1, 3] = (
            st[:, i],
            ct[:, i] * ca[i],
            -ct[:, i] * sa[i],
            a[i] * st[:, i],
        )
        A[:, 2, 1], A[:, 2, 2], A[:, 2, 3] = sa[i], ca[i], d[i]
        A[:, 3, 3] = 1.0
        T = T @ A
    return T


def project(K: Array, p_cam: Array) -> Array:
    """Pinhole projection ``(K p / p_z)[:2]`` (M, 2) px of camera-frame points ``p_cam``
    (M, 3) m (z > 0)."""
    p = np.asarray(p_cam, float)
    h = p @ np.asarray(K, float).T
    return h[:, :2] / h[:, 2:3]


def _small_T(v: Array) -> Array:
    """``[R(w) | t]`` from ``v = [t (mm), w (mrad)]``."""
    return make_T(Rotation.from_rotvec(v[3:] * 1e-3).as_matrix(), v[:3] * 1e-3)


@dataclass(frozen=True)
class JointCalibrationResult:
    """The MAP estimate (module docstring). ``dh`` the calibrated DH, ``deltas`` its
    corrections (keys :data:`DH_GROUPS`, (6,) rad or m), ``T_flange_camera`` and
    ``T_base_board`` (4, 4); corner residual RMS before (at the start) and after (px);
    ``posterior_sd`` (keys :data:`DH_GROUPS`, (6,), rad or m) and its ratio to the prior SD
    (~1: not learnt from the data); ``hand_eye_sd_mm`` / ``hand_eye_sd_deg`` the posterior
    SDs of ``X`` (translation per axis mm, rotation per axis deg); ``singular_values`` of the
    data-only Jacobian in scaled units (descending) and ``n_identified`` of them above 1."""

    dh: DHParameters
    deltas: dict[str, Array]
    T_flange_camera: Array
    T_base_board: Array
    rms_px_start: float
    rms_px: float
    max_px: float
    n_observations: int
    n_stations: int
    posterior_sd: dict[str, Array]
    sd_ratio: dict[str, Array]
    hand_eye_sd_mm: Array
    hand_eye_sd_deg: Array
    singular_values: Array
    n_identified: int
    nfev: int
    success: bool

    def summary(self) -> dict[str, object]:
        """JSON-ready figures (mm and deg for the DH corrections)."""

        def conv(k: str, v: Array) -> list[float]:
            s = 1e3 if _LENGTH[DH_GROUPS.index(k)] else np.rad2deg(1.0)
            return [float(x) * s for x in v]

        return {
            "units": "delta_a, delta_d: mm; delta_theta, delta_alpha: deg",
            "deltas": {k: conv(k, v) for k, v in self.deltas.items()},
            "posterior_sd": {k: conv(k, v) for k, v in self.posterior_sd.items()},
            "posterior_to_prior_sd": {k: [float(x) for x in v] for k, v in self.sd_ratio.items()},
            "hand_eye_sd_mm": [float(x) for x in self.hand_eye_sd_mm],
            "hand_eye_sd_deg": [float(x) for x in self.hand_eye_sd_deg],
            "singular_values": [float(x) for x in self.singular_values],
            "n_identified": self.n_identified,
            "rms_px_start": self.rms_px_start,
            "rms_px": self.rms_px,
            "max_px": self.max_px,
            "n_observations": self.n_observations,
            "nfev": self.nfev,
            "success": self.success,
        }


def _check_inputs(K: Array, X0: Array, Y0: Array, obs: BoardObservations) -> None:
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InvalidInputError(f"K must be a finite 3x3 camera matrix, got shape {K.shape}")
    for name, T in (("X0", X0), ("Y0", Y0)):
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InvalidInputError(f"{name} must be a finite 4x4 transform, got {T.shape}")
    if obs.n_stations < 3:
        raise InvalidInputError(
            f"joint calibration needs at least 3 stations, got {obs.n_stations}"
        )


class _JointProblem:
    """The MAP problem in scaled units (module docstring): the parameter vector ``x`` is the
    24 scaled DH corrections, the hand-eye and board updates (6 + 6), and with per-station
    displacement priors 6 per station; :meth:`residuals` stacks the corner residuals
    (``/ pixel_sigma``) and the prior rows."""

    def __init__(
        self,
        dh_nominal: DHParameters,
        obs: BoardObservations,
        K: Array,
        X0: Array,
        Y0: Array,
        cfg: JointCalibrationConfig,
    ) -> None:
        self.cfg, self.K, self.X0, self.Y0 = cfg, K, X0, Y0
        self.q = np.asarray(obs.q, float)
        self.sid = np.asarray(obs.station, int)
        self.P = np.asarray(obs.object_points, float)
        self.uv = np.asarray(obs.image_points, float)
        self.a0, self.d0, self.al0, self.th0 = dh_nominal.as_arrays()
        s_len = cfg.prior_length_sigma_mm * 1e-3
        s_ang = np.deg2rad(cfg.prior_angle_sigma_deg)
        self.sig = np.concatenate(
            [np.full(6, s_len if is_len else s_ang) for is_len in _LENGTH]
        )  # (24,)
        self.n_st = obs.n_stations
        self.per_station = cfg.station_rot_sigma_deg > 0 or cfg.station_shift_sigma_mm > 0
        self.n_par = 36 + (6 * self.n_st if self.per_station else 0)
        # per-station arm-base displacement D_i = [R(w_i) | t_i] in scaled units
        self.s_st = np.array(
            [cfg.station_shift_sigma_mm * 1e-3] * 3 + [np.deg2rad(cfg.station_rot_sigma_deg)] * 3
        )

    def unpack(self, x: Array) -> tuple[Array, Array, Array]:
        delta = x[:24] * self.sig
        return delta, self.X0 @ _small_T(x[24:30]), self.Y0 @ _small_T(x[30:36])

    def predict(self, x: Array) -> Array:
        """The corners in the camera frame (M, 3) m."""
        delta, X, Y = self.unpack(x)
        dth, da, dd, dal = delta.reshape(4, 6)
        a0, d0, al0, th0 = self.a0, self.d0, self.al0, self.th0
        G = fk_batch(a0 + da, d0 + dd, al0 + dal, th0 + dth, self.q) @ X  # T_base_camera (N,4,4)
        if self.per_station:
            n_st = self.n_st
            v = x[36:].reshape(n_st, 6) * self.s_st
            D = np.broadcast_to(np.eye(4), (n_st, 4, 4)).copy()
            D[:, :3, :3] = Rotation.from_rotvec(v[:, 3:]).as_matrix()
            D[:, :3, 3] = v[:, :3]
            G = D @ G
        R = np.swapaxes(G[:, :3, :3], 1, 2)  # camera <- base
        t = -np.einsum("nij,nj->ni", R, G[:, :3, 3])
        pb = self.P @ Y[:3, :3].T + Y[:3, 3]  # board -> base (M, 3)
        pc = np.einsum("mij,mj->mi", R[self.sid], pb) + t[self.sid]
        return pc

    def residuals(self, x: Array) -> Array:
        pc = self.predict(x)
        pc[:, 2] = np.maximum(pc[:, 2], 1e-6)
        u = project(self.K, pc)
        return np.concatenate([((u - self.uv) / self.cfg.pixel_sigma).ravel(), x[:24], x[36:]])

    def sparsity(self) -> Array | None:
        """The Jacobian's sparsity with per-station priors (a station's displacement moves
        only its own corners); None without them."""
        if not self.per_station:
            return None
        m, n_par, n_st = 2 * len(self.P), self.n_par, self.n_st
        sparsity = np.ones((m + n_par - 12, n_par), dtype=bool)
        rows = np.repeat(self.sid, 2)
        sparsity[:m, 36:] = rows[:, None] == np.repeat(np.arange(n_st), 6)[None, :]
        sparsity[m:, :] = False
        prior_cols = np.r_[np.arange(24), np.arange(36, n_par)]
        sparsity[m + np.arange(len(prior_cols)), prior_cols] = True
        return sparsity


def _posterior(J: Array, n_par: int) -> tuple[Array, Array, Array]:
    """From the stacked Jacobian ``J`` (scaled units): the posterior SDs of all parameters,
    the singular values of the data's information on the DH corrections, and the hand-eye's
    SD (6,) with the unobservable DH directions held."""
    # posterior covariance (scaled units) of the stacked data + prior system
    JtJ = J.T @ J
    cov = np.linalg.pinv(JtJ)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    # the data's information on the DH corrections (scaled units), the other unknowns
    # marginalised with their priors: Schur complement of J^T J minus the DH prior (I)
    Hn = JtJ[24:, 24:]
    H_dh = JtJ[:24, :24] - JtJ[:24, 24:] @ np.linalg.pinv(Hn) @ JtJ[24:, :24] - np.eye(24)
    sv = np.sqrt(np.clip(np.sort(np.linalg.eigvalsh((H_dh + H_dh.T) / 2))[::-1], 0.0, None))
    # the hand-eye's SD with the exactly unobservable DH directions held (the gauge: the
    # flange is the nominal last link's, the base frame the nominal first joint's)
    keep = np.setdiff1d(np.arange(n_par), GAUGE_INDICES)
    cov_g = np.linalg.inv(JtJ[np.ix_(keep, keep)])
    sd_g = np.sqrt(np.clip(np.diag(cov_g), 0.0, None))[16:22]
    return sd, sv, sd_g


def calibrate_kinematics_hand_eye(
    dh_nominal: DHParameters,
    obs: BoardObservations,
    K: Array,
    X0: Array,
    Y0: Array,
    config: JointCalibrationConfig | None = None,
) -> JointCalibrationResult:
    """MAP estimate of the DH corrections, ``X = T_flange_camera`` and ``Y = T_base_board``
    from the board corners ``obs`` seen with intrinsics ``K`` (3, 3), started from ``X0``,
    ``Y0`` (4, 4) (module docstring). Raises :class:`InvalidInputError` on malformed input
    (fewer than 3 stations, a corner behind the camera at the start) and
    :class:`MMPAError` when the solver does not converge to finite values."""
    cfg = config or JointCalibrationConfig()
    K = np.asarray(K, float)
    X0, Y0 = np.asarray(X0, float), np.asarray(Y0, float)
    _check_inputs(K, X0, Y0, obs)
    pr = _JointProblem(dh_nominal, obs, K, X0, Y0, cfg)
    x0 = np.zeros(pr.n_par)
    if np.any(pr.predict(x0)[:, 2] <= 0):
        raise InvalidInputError("board corners behind the camera at the start: check X0 and Y0")
    m = 2 * len(pr.P)
    r0 = pr.residuals(x0)[:m] * cfg.pixel_sigma
    sol = least_squares(
        pr.residuals,
        x0,
        jac_sparsity=pr.sparsity(),
        method="trf",
        loss=cfg.loss,
        f_scale=3.0,
        max_nfev=cfg.max_nfev,
        x_scale=1.0,
        xtol=1e-10,
        ftol=1e-10,
        gtol=1e-10,
    )
    if not np.all(np.isfinite(sol.x)):
        raise MMPAError("joint calibration diverged (non-finite parameters)")
    x = sol.x
    J = sol.jac  # rows of the scaled residuals; robust loss folded in by scipy
    J = np.asarray(J.toarray() if hasattr(J, "toarray") else J)
    r = pr.residuals(x)[:m] * cfg.pixel_sigma
    e = np.linalg.norm(r.reshape(-1, 2), axis=1)
    sd, sv, sd_g = _posterior(J, pr.n_par)
    delta, X, Y = pr.unpack(x)
    groups = delta.reshape(4, 6)
    sd_groups = (sd[:24] * pr.sig).reshape(4, 6)
    ratio = sd[:24].reshape(4, 6)
    dh = apply_dh_deltas(dh_nominal, dict(zip(DH_GROUPS, groups, strict=True)))
    return JointCalibrationResult(
        dh=dh,
        deltas={k: groups[i].copy() for i, k in enumerate(DH_GROUPS)},
        T_flange_camera=X,
        T_base_board=Y,
        rms_px_start=float(np.sqrt(np.mean(np.sum(r0.reshape(-1, 2) ** 2, axis=1)))),
        rms_px=float(np.sqrt(np.mean(e**2))),
        max_px=float(e.max()),
        n_observations=len(pr.P),
        n_stations=obs.n_stations,
        posterior_sd={k: sd_groups[i] for i, k in enumerate(DH_GROUPS)},
        sd_ratio={k: ratio[i] for i, k in enumerate(DH_GROUPS)},
        hand_eye_sd_mm=sd_g[:3],
        hand_eye_sd_deg=np.rad2deg(sd_g[3:] * 1e-3),
        singular_values=sv,
        n_identified=int(np.sum(sv > 1.0)),
        nfev=int(sol.nfev),
        success=bool(sol.success),
    )


def random_configurations(
    n: int, seed: int, q_min: Array | None = None, q_max: Array | None = None
) -> Array:
    """``n`` joint configurations (n, 6) rad drawn uniformly in ``[q_min, q_max]`` (default
    ``[-pi, pi]`` per joint) from ``seed``."""
    if n < 1:
        raise InvalidInputError(f"need at least one configuration, got {n}")
    lo = np.full(6, -np.pi) if q_min is None else np.maximum(np.asarray(q_min, float), -np.pi)
    hi = np.full(6, np.pi) if q_max is None else np.minimum(np.asarray(q_max, float), np.pi)
    return np.random.default_rng(seed).uniform(lo, hi, size=(n, 6))


def fk_point_error(
    dh_a: DHParameters,
    dh_b: DHParameters,
    q: Array,
    T_flange_point_a: Array | None = None,
    T_flange_point_b: Array | None = None,
) -> dict[str, float]:
    """How far two kinematic models put a point: ``|fk_a(q) T_a p - fk_b(q) T_b p|`` over
    configurations ``q`` (N, 6), the point the origin of ``T_flange_point`` (4, 4; default
    the flange), RMS and max in mm, and the frame's rotation error RMS / max in deg."""
    q = np.asarray(q, float)
    if q.ndim != 2 or q.shape[1] != 6:
        raise InvalidInputError(f"q must be (N, 6), got {q.shape}")
    Ta = fk_batch(*dh_a.as_arrays(), q) @ (
        np.eye(4) if T_flange_point_a is None else T_flange_point_a
    )
    Tb = fk_batch(*dh_b.as_arrays(), q) @ (
        np.eye(4) if T_flange_point_b is None else T_flange_point_b
    )
    e = np.linalg.norm(Ta[:, :3, 3] - Tb[:, :3, 3], axis=1) * 1e3
    Rr = np.einsum("nji,njk->nik", Ta[:, :3, :3], Tb[:, :3, :3])
    ang = np.rad2deg(Rotation.from_matrix(Rr).magnitude())
    return {
        "rms_mm": float(np.sqrt(np.mean(e**2))),
        "max_mm": float(e.max()),
        "rot_rms_deg": float(np.sqrt(np.mean(ang**2))),
        "rot_max_deg": float(ang.max()),
    }

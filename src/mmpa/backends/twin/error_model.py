"""The error model of DESIGN.md: every error source, named, seeded, configurable, in profiles.

The simulator builds its TRUE robot and world from the nominal description plus the
perturbations sampled here; software only ever receives the nominal values. A robot
instance is fixed by ``ErrorModelConfig.seed``: the same seed gives the same true robot.

Profiles (DESIGN.md, "Error model v2"): ``ideal`` (every error zero: the algorithms' own
limit), ``reference`` (the founding model, kept for comparison), ``realistic`` (the default:
published hardware figures, dominated by what changes between the teaching session and the
repeat session) and ``harsh`` (upper published values). A profile supplies every field that
is not given explicitly: ``ErrorModelConfig(profile="harsh", camera={"subpixel": 0.2})`` is
the harsh model with another subpixel figure. The field defaults in code are ``realistic``.

A *session* is one teaching or one repeat (a new park): per-session draws (the camera's
correlated depth noise and depth/colour drift, the scene's loose objects) are fixed within a
session and redrawn for the next (:meth:`ErrorModel.session_rng`).

Units: m, rad (configuration fields ending in ``_deg`` are degrees, ``_px`` disparity pixels).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mmpa.core.errors import UnknownNameError
from mmpa.core.geometry import Array, T_to_vec6, vec6_to_T
from mmpa.robot.description import DHParameters, RobotDescription

__all__ = [
    "PARKING_TABLE2",
    "PROFILES",
    "BaseCompliance",
    "CameraNoise",
    "ErrorModel",
    "ErrorModelConfig",
    "KinematicsError",
    "LidarNoise",
    "OdometryNoise",
    "OperatorError",
    "ParkingNoise",
    "ProfileName",
    "SceneChange",
]

ProfileName = Literal["ideal", "reference", "realistic", "harsh"]


class _Cfg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class KinematicsError(_Cfg):
    """Arm and hand-eye errors (fixed per robot instance)."""

    dh_length_sigma: float = Field(0.5e-3, ge=0)  # m, on a and d (uncalibrated UR: several mm)
    dh_angle_sigma_deg: float = Field(0.05, ge=0)  # on alpha and theta offsets
    joint_repeatability_tool: float = Field(0.03e-3, ge=0)  # m at the tool (UR5e +-0.03 mm)
    hand_eye_trans_sigma: float = Field(1.0e-3, ge=0)  # m per axis (librealsense #11736)
    hand_eye_rot_sigma_deg: float = Field(0.5, ge=0)  # per axis


class CameraNoise(_Cfg):
    """D435-like depth and colour errors (DESIGN.md tables).

    Depth errors are disparity errors ``dd`` (pixels of the native depth stream) turned into
    depth by ``dz = -z^2 dd / (f_native baseline)``. Per pixel the disparity noise has SD
    ``subpixel``; a fraction ``correlated_fraction`` of its variance is a spatially correlated
    field (Gaussian correlation ``correlation_px``) fixed within a session, the rest is drawn
    per frame, so averaging frames leaves the correlated part. Per session, the disparity
    also drifts by an offset, a gradient (its value at the image edge) and a low-frequency
    wave; per robot, a fixed ring-shaped bias pattern. Colour per session: an exposure gain,
    a white balance per channel and a lighting gradient across the image (relative SDs).
    """

    subpixel: float = Field(0.08, ge=0)  # px, disparity noise per pixel (Intel D400 tuning)
    correlated_fraction: float = Field(0.75, ge=0, le=1)  # of the variance, fixed per session
    correlation_px: float = Field(3.0, ge=0)  # px, Gaussian correlation length of that part
    session_offset_px: float = Field(0.06, ge=0)  # disparity offset SD per session
    session_gradient_px: float = Field(0.035, ge=0)  # gradient SD, value at the image edge
    session_wave_px: float = Field(0.02, ge=0)  # low-frequency wave SD (RMS over the image)
    bias_pattern_px: float = Field(0.05, ge=0)  # fixed ring pattern SD (per robot)
    invalid_fraction: float = Field(0.02, ge=0, le=1)  # random holes
    flying_pixel_fraction: float = Field(0.5, ge=0, le=1)  # of depth-edge pixels that fly
    edge_threshold: float = Field(0.05, gt=0)  # m, depth jump that counts as an edge
    depth_scale_sigma: float = Field(0.001, ge=0)  # per capture, relative
    color_sigma: float = Field(2.0 / 255.0, ge=0)
    exposure_gain_sigma: float = Field(0.10, ge=0)  # relative, per session
    white_balance_sigma: float = Field(0.02, ge=0)  # relative per channel, per session
    lighting_gradient_sigma: float = Field(0.05, ge=0)  # relative at the image edge, per session
    lighting_gain: float = Field(1.0, gt=0)  # multiplies colour (experiment flag)


class LidarNoise(_Cfg):
    """2D lidar errors, the reflector map and the occupancy map the localizer gets.

    Reflector range bias (range walk): a retroreflective return's range is off by
    ``reflector_bias_mean + N(0, reflector_bias_sd)`` (fixed per reflector) plus
    ``reflector_incidence_bias (1 - cos incidence)``. The beam has a footprint of
    ``beam_width + beam_divergence * range`` (mixed returns at edges). The mount's true pose
    differs from the nominal by ``mount_trans_sigma`` per axis and ``mount_rot_sigma_deg`` per
    axis (fixed per robot). The occupancy map is warped by a smooth displacement field of SD
    ``map_warp_sigma`` and correlation length ``map_warp_length``.
    """

    range_sigma: float = Field(0.015, ge=0)  # m
    reflector_map_sigma: float = Field(0.010, ge=0)  # m, surveyed (map) vs true positions
    reflector_intensity: float = 3000.0
    surface_intensity: float = 200.0
    mount_trans_sigma: float = Field(0.003, ge=0)  # m per axis
    mount_rot_sigma_deg: float = Field(0.3, ge=0)  # per axis
    reflector_bias_mean: float = -0.010  # m (Sedek et al. 2024)
    reflector_bias_sd: float = Field(0.005, ge=0)  # m, fixed per reflector
    reflector_incidence_bias: float = 0.010  # m at grazing incidence, times (1 - cos)
    beam_width: float = Field(0.020, ge=0)  # m at the scanner (SICK NAV350)
    beam_divergence: float = Field(0.005, ge=0)  # rad, footprint growth per metre
    map_warp_sigma: float = Field(0.010, ge=0)  # m
    map_warp_length: float = Field(3.0, gt=0)  # m


class OdometryNoise(_Cfg):
    """Differential-drive odometry noise (Thrun et al., Probabilistic Robotics, Table 5.6).

    The odometry increments ``(rot1, trans, rot2)`` are perturbed with variance
    ``alpha1 rot^2 + alpha2 trans^2`` (rotations) and ``alpha3 trans^2 + alpha4 rot^2``
    (translation), as Nav2 AMCL's ``DifferentialMotionModel`` assumes.
    """

    alpha1: float = Field(0.05, ge=0)
    alpha2: float = Field(0.05, ge=0)
    alpha3: float = Field(0.05, ge=0)
    alpha4: float = Field(0.05, ge=0)


class BaseCompliance(_Cfg):
    """Compliant mount between the chassis and the arm (in the physics): moving the arm from
    its folded pose to full reach tilts the arm base by ``tilt_full_reach_deg``."""

    tilt_full_reach_deg: float = Field(0.05, ge=0)


class SceneChange(_Cfg):
    """Loose objects nudged between teaching and a repeat: with ``probability`` per repeat
    session, 1 to ``max_objects`` of them move by ``N(0, trans_sigma)`` per planar axis and
    ``N(0, rot_sigma_deg)`` about the vertical. Fixtures, backboards and the task's target
    never move."""

    probability: float = Field(0.3, ge=0, le=1)
    max_objects: int = Field(3, ge=1)
    trans_sigma: float = Field(0.002, ge=0)  # m
    rot_sigma_deg: float = Field(1.0, ge=0)


class OperatorError(_Cfg):
    """The initial pose a person gives the localizer ('2D Pose Estimate'): the truth plus
    ``N(0, initial_pos_sigma)`` per axis and ``N(0, initial_yaw_sigma_deg)``."""

    initial_pos_sigma: float = Field(0.2, ge=0)  # m
    initial_yaw_sigma_deg: float = Field(10.0, ge=0)


# Paper 000 Table 2: mean and SD of [tx, ty, tz, r, p, y] (m, m, m, deg, deg, deg).
PARKING_TABLE2: dict[str, dict[str, tuple[float, ...]]] = {
    "1": {
        "mean": (0.0011, -0.0995, -0.0012, 0.2151, -0.0036, 0.0023),
        "sd": (0.0281, 0.0179, 0.0013, 0.1593, 0.1439, 2.9214),
    },
    "2": {
        "mean": (0.0505, 0.0539, -0.0011, 0.1155, -0.1733, 1.6706),
        "sd": (0.0287, 0.0287, 0.0014, 0.0784, 0.1295, 2.7079),
    },
    "2'": {
        "mean": (0.0779, 0.0261, -0.0042, 0.0079, 0.7932, -1.9701),
        "sd": (0.0569, 0.1060, 0.0054, 1.2595, 2.6967, 14.7211),
    },
}


class ParkingNoise(_Cfg):
    """Sampled-mode parking error: per-site normal with paper 000 Table 2 mean and SD (the
    same in every profile: it is the task's premise, not a sensor error)."""

    table: dict[str, dict[str, tuple[float, ...]]] = Field(default_factory=lambda: PARKING_TABLE2)


# The sources the founding (reference) model did not have, switched off.
_NO_V2_SOURCES: dict[str, dict[str, Any]] = {
    "camera": {
        "correlated_fraction": 0.0,
        "session_offset_px": 0.0,
        "session_gradient_px": 0.0,
        "session_wave_px": 0.0,
        "bias_pattern_px": 0.0,
        "exposure_gain_sigma": 0.0,
        "white_balance_sigma": 0.0,
        "lighting_gradient_sigma": 0.0,
    },
    "lidar": {
        "mount_trans_sigma": 0.0,
        "mount_rot_sigma_deg": 0.0,
        "reflector_bias_mean": 0.0,
        "reflector_bias_sd": 0.0,
        "reflector_incidence_bias": 0.0,
        "beam_width": 0.0,
        "beam_divergence": 0.0,
        "map_warp_sigma": 0.0,
    },
    "compliance": {"tilt_full_reach_deg": 0.0},
    "scene_change": {"probability": 0.0},
    "operator": {"initial_pos_sigma": 0.0, "initial_yaw_sigma_deg": 0.0},
}

#: Field values of each profile (DESIGN.md "Error model v2"); fields not named keep the
#: code defaults, which are ``realistic``.
PROFILES: dict[str, dict[str, dict[str, Any]]] = {
    "realistic": {},
    "reference": {
        **_NO_V2_SOURCES,
        "kinematics": {
            "dh_length_sigma": 0.2e-3,
            "dh_angle_sigma_deg": 0.02,
            "joint_repeatability_tool": 0.01e-3,
            "hand_eye_trans_sigma": 1.0e-3,
            "hand_eye_rot_sigma_deg": 0.2,
        },
        "lidar": {**_NO_V2_SOURCES["lidar"], "reflector_map_sigma": 0.002},
    },
    "harsh": {
        "kinematics": {
            "dh_length_sigma": 1.0e-3,
            "dh_angle_sigma_deg": 0.1,
            "joint_repeatability_tool": 0.05e-3,
            "hand_eye_trans_sigma": 3.0e-3,
            "hand_eye_rot_sigma_deg": 0.7,
        },
        "camera": {
            "subpixel": 0.10,
            "correlated_fraction": 0.85,
            "correlation_px": 4.0,
            "session_offset_px": 0.1,
            "session_gradient_px": 0.06,
            "session_wave_px": 0.04,
            "bias_pattern_px": 0.1,
            "depth_scale_sigma": 0.002,
            "exposure_gain_sigma": 0.15,
            "white_balance_sigma": 0.03,
            "lighting_gradient_sigma": 0.10,
        },
        "lidar": {
            "range_sigma": 0.020,
            "reflector_map_sigma": 0.020,
            "mount_trans_sigma": 0.005,
            "mount_rot_sigma_deg": 0.5,
            "reflector_bias_mean": -0.015,
            "reflector_bias_sd": 0.0075,
            "reflector_incidence_bias": 0.015,
            "map_warp_sigma": 0.020,
        },
        "odometry": {"alpha1": 0.2, "alpha2": 0.2, "alpha3": 0.2, "alpha4": 0.2},
        "compliance": {"tilt_full_reach_deg": 0.1},
        "scene_change": {"probability": 0.5, "trans_sigma": 0.005, "rot_sigma_deg": 2.0},
    },
    "ideal": {
        **_NO_V2_SOURCES,
        "kinematics": {
            "dh_length_sigma": 0.0,
            "dh_angle_sigma_deg": 0.0,
            "joint_repeatability_tool": 0.0,
            "hand_eye_trans_sigma": 0.0,
            "hand_eye_rot_sigma_deg": 0.0,
        },
        "camera": {
            **_NO_V2_SOURCES["camera"],
            "subpixel": 0.0,
            "invalid_fraction": 0.0,
            "flying_pixel_fraction": 0.0,
            "depth_scale_sigma": 0.0,
            "color_sigma": 0.0,
        },
        "lidar": {**_NO_V2_SOURCES["lidar"], "range_sigma": 0.0, "reflector_map_sigma": 0.0},
        "odometry": {"alpha1": 0.0, "alpha2": 0.0, "alpha3": 0.0, "alpha4": 0.0},
    },
}


def _merge(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in new.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


class ErrorModelConfig(_Cfg):
    """All error sources. ``seed`` fixes the robot instance (its true DH, hand-eye, lidar
    mount, reflector and map errors); ``profile`` supplies every field not given explicitly
    (see the module docstring)."""

    profile: ProfileName = "realistic"
    seed: int = Field(0, ge=0)  # every random draw flows from it (numpy: >= 0)
    kinematics: KinematicsError = KinematicsError()
    camera: CameraNoise = CameraNoise()
    lidar: LidarNoise = LidarNoise()
    odometry: OdometryNoise = OdometryNoise()
    compliance: BaseCompliance = BaseCompliance()
    scene_change: SceneChange = SceneChange()
    operator: OperatorError = OperatorError()
    parking: ParkingNoise = ParkingNoise()

    @model_validator(mode="before")
    @classmethod
    def _fill_from_profile(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        name = data.get("profile", "realistic")
        if not isinstance(name, str) or name not in PROFILES:
            return data  # the Literal field reports the unknown name (or a mapping, a list)
        given = {k: (v.model_dump() if isinstance(v, BaseModel) else v) for k, v in data.items()}
        return _merge(PROFILES[name], given)

    @classmethod
    def from_profile(cls, profile: ProfileName, seed: int = 0, **fields: Any) -> ErrorModelConfig:
        """The ``profile`` model with ``seed`` and any explicitly given sections/fields."""
        return cls.model_validate({"profile": profile, "seed": seed, **fields})


def _pose_error(rng: np.random.Generator, trans_sigma: float, rot_sigma_deg: float) -> Array:
    """A small pose error (4x4): ``N(0, trans_sigma)`` m per axis, then
    ``N(0, rot_sigma_deg)`` per rotation axis, as ``vec6_to_T([tx, ty, tz, r, p, y])``."""
    t = rng.normal(0.0, trans_sigma, 3)
    r = rng.normal(0.0, np.deg2rad(rot_sigma_deg), 3)
    return vec6_to_T(np.concatenate([t, r]))


@dataclass(frozen=True)
class ErrorModel:
    """A sampled robot instance: the TRUE robot next to the NOMINAL one, and noise settings.

    ``rng(stream)`` derives independent, reproducible generators for each consumer
    (``"camera"``, ``"lidar"``, ...) from the seed, so adding a consumer never shifts the
    draws of another.
    """

    config: ErrorModelConfig
    nominal: RobotDescription
    true: RobotDescription
    joint_noise_sigma: float  # rad, per joint, equivalent to the tool repeatability

    @classmethod
    def sample(
        cls, nominal: RobotDescription, config: ErrorModelConfig | None = None
    ) -> ErrorModel:
        """Draw the true robot from ``nominal`` with the configured errors: DH parameters,
        hand-eye ``T_flange_camera`` and the lidar mount ``T_base_link_laser``."""
        config = config or ErrorModelConfig()
        rng = np.random.default_rng([config.seed, 1])
        k = config.kinematics
        a, d, alpha, off = nominal.arm.dh.as_arrays()
        ang = np.deg2rad(k.dh_angle_sigma_deg)
        true_dh = DHParameters(
            a=tuple(a + rng.normal(0.0, k.dh_length_sigma, 6)),
            d=tuple(d + rng.normal(0.0, k.dh_length_sigma, 6)),
            alpha=tuple(alpha + rng.normal(0.0, ang, 6)),
            theta_offset=tuple(off + rng.normal(0.0, ang, 6)),
        )
        T_true = nominal.camera.T_flange_camera @ _pose_error(
            rng, k.hand_eye_trans_sigma, k.hand_eye_rot_sigma_deg
        )
        true_camera = nominal.camera.model_copy(
            update={"T_flange_camera_vec": tuple(float(x) for x in T_to_vec6(T_true))}
        )
        true_arm = nominal.arm.model_copy(update={"dh": true_dh})
        # the lidar mount from a stream of its own (the draws above stay as they were)
        li = config.lidar
        r_mount = np.random.default_rng([config.seed, zlib.crc32(b"lidar_mount")])
        T_laser = nominal.lidar.T_base_link_laser @ _pose_error(
            r_mount, li.mount_trans_sigma, li.mount_rot_sigma_deg
        )
        true_lidar = nominal.lidar.model_copy(
            update={"T_base_link_laser_vec": tuple(float(x) for x in T_to_vec6(T_laser))}
        )
        true = nominal.with_updates(
            arm=true_arm.model_dump(),
            camera=true_camera.model_dump(),
            lidar=true_lidar.model_dump(),
        )
        # ~0.8 m lever arm from the joints to the tool: sigma_q = sigma_tool / 0.8
        joint_sigma = k.joint_repeatability_tool / 0.8
        return cls(config=config, nominal=nominal, true=true, joint_noise_sigma=joint_sigma)

    def rng(self, stream: str, episode: int = 0) -> np.random.Generator:
        """An independent generator for one consumer (and one episode) of this instance."""
        key = zlib.crc32(stream.encode())
        return np.random.default_rng([self.config.seed, key, episode])

    def session_rng(self, stream: str, session: int) -> np.random.Generator:
        """The generator of one consumer's draws for ``session`` (0: the teaching session,
        k > 0: the k-th repeat): independent of the episode streams and of other sessions."""
        return self.rng(f"session/{stream}", int(session))

    def sample_parking_offset(self, site: str, rng: np.random.Generator) -> Array:
        """Paper 000 Table 2 parking error ``[tx, ty, tz, r, p, y]`` (m, rad) for ``site``."""

        table = self.config.parking.table
        if site not in table:
            raise UnknownNameError("parking site", site, sorted(table))
        mean = np.array(table[site]["mean"], dtype=float)
        sd = np.array(table[site]["sd"], dtype=float)
        v = rng.normal(mean, sd)
        v[3:] = np.deg2rad(v[3:])
        return v

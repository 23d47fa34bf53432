"""The reference error model of DESIGN.md: every error source, named, seeded, configurable.

The simulator builds its TRUE robot and world from the nominal description plus the
perturbations sampled here; software only ever receives the nominal values. A robot
instance is fixed by ``ErrorModelConfig.seed``: the same seed gives the same true robot.

Units: m, rad (configuration fields ending in ``_deg`` are degrees for readability).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from mmpa.geometry import Array, T_to_vec6, vec6_to_T
from mmpa.robot.description import DHParameters, RobotDescription

__all__ = [
    "PARKING_TABLE2",
    "CameraNoise",
    "ErrorModel",
    "ErrorModelConfig",
    "KinematicsError",
    "LidarNoise",
    "OdometryNoise",
    "ParkingNoise",
]


class _Cfg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class KinematicsError(_Cfg):
    """Arm and hand-eye errors (fixed per robot instance)."""

    dh_length_sigma: float = 0.2e-3  # m, on a and d
    dh_angle_sigma_deg: float = 0.02  # on alpha and theta offsets
    joint_repeatability_tool: float = 0.01e-3  # m at the tool (sigma)
    hand_eye_trans_sigma: float = 1.0e-3  # m per axis
    hand_eye_rot_sigma_deg: float = 0.2  # per axis


class CameraNoise(_Cfg):
    """D435-like depth and color noise (DESIGN.md table)."""

    subpixel: float = 0.08  # px, disparity noise; sigma_z = z^2 subpixel / (f baseline)
    invalid_fraction: float = 0.02  # random holes
    flying_pixel_fraction: float = 0.5  # fraction of depth-edge pixels that fly
    edge_threshold: float = 0.05  # m, depth jump that counts as an edge
    depth_scale_sigma: float = 0.001  # per capture, relative
    color_sigma: float = 2.0 / 255.0
    lighting_gain: float = 1.0  # multiplies color (experiment flag)


class LidarNoise(_Cfg):
    """2D lidar noise and reflector map error."""

    range_sigma: float = 0.015  # m
    reflector_map_sigma: float = 0.002  # m, measured (map) vs true reflector positions
    reflector_intensity: float = 3000.0
    surface_intensity: float = 200.0


class OdometryNoise(_Cfg):
    """Differential-drive odometry noise (Thrun et al., Probabilistic Robotics, Table 5.6).

    The odometry increments ``(rot1, trans, rot2)`` are perturbed with variance
    ``alpha1 rot^2 + alpha2 trans^2`` (rotations) and ``alpha3 trans^2 + alpha4 rot^2``
    (translation), as Nav2 AMCL's ``DifferentialMotionModel`` assumes.
    """

    alpha1: float = 0.05
    alpha2: float = 0.05
    alpha3: float = 0.05
    alpha4: float = 0.05


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
    """Sampled-mode parking error: per-site normal with paper 000 Table 2 mean and SD."""

    table: dict[str, dict[str, tuple[float, ...]]] = Field(default_factory=lambda: PARKING_TABLE2)


class ErrorModelConfig(_Cfg):
    """All error sources. ``seed`` fixes the robot instance (its true DH and hand-eye)."""

    seed: int = 0
    kinematics: KinematicsError = KinematicsError()
    camera: CameraNoise = CameraNoise()
    lidar: LidarNoise = LidarNoise()
    odometry: OdometryNoise = OdometryNoise()
    parking: ParkingNoise = ParkingNoise()


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
        """Draw the true robot from ``nominal`` with the configured errors."""
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
        dT = vec6_to_T(
            np.concatenate(
                [
                    rng.normal(0.0, k.hand_eye_trans_sigma, 3),
                    rng.normal(0.0, np.deg2rad(k.hand_eye_rot_sigma_deg), 3),
                ]
            )
        )
        T_true = nominal.camera.T_flange_camera @ dT
        true_camera = nominal.camera.model_copy(
            update={"T_flange_camera_vec": tuple(float(x) for x in T_to_vec6(T_true))}
        )
        true_arm = nominal.arm.model_copy(update={"dh": true_dh})
        true = nominal.with_updates(arm=true_arm.model_dump(), camera=true_camera.model_dump())
        # ~0.8 m lever arm from the joints to the tool: sigma_q = sigma_tool / 0.8
        joint_sigma = k.joint_repeatability_tool / 0.8
        return cls(config=config, nominal=nominal, true=true, joint_noise_sigma=joint_sigma)

    def rng(self, stream: str, episode: int = 0) -> np.random.Generator:
        """An independent generator for one consumer (and one episode) of this instance."""
        key = zlib.crc32(stream.encode())
        return np.random.default_rng([self.config.seed, key, episode])

    def sample_parking_offset(self, site: str, rng: np.random.Generator) -> Array:
        """Paper 000 Table 2 parking error ``[tx, ty, tz, r, p, y]`` (m, rad) for ``site``."""
        from mmpa.errors import UnknownNameError

        table = self.config.parking.table
        if site not in table:
            raise UnknownNameError("parking site", site, sorted(table))
        mean = np.array(table[site]["mean"], dtype=float)
        sd = np.array(table[site]["sd"], dtype=float)
        v = rng.normal(mean, sd)
        v[3:] = np.deg2rad(v[3:])
        return v

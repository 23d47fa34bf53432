"""Pure sensor-noise functions of the reference error model (DESIGN.md, "Truth and belief").

Every function takes the noise-free measurement as a numpy array and a
``numpy.random.Generator``; every random draw goes through that generator, so the same
generator state gives the same noisy measurement. Nothing here touches MuJoCo.

Units: m, rad; colors are uint8 RGB in, uint8 RGB out.
"""

from __future__ import annotations

import numpy as np

from mmpa.errors import InvalidInputError
from mmpa.sim.error_model import CameraNoise, OdometryNoise

__all__ = [
    "angle_diff",
    "axial_depth_sigma",
    "color_noise",
    "depth_edges",
    "depth_noise",
    "odometry_increment_noise",
    "range_noise",
]

_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0))


def axial_depth_sigma(z: np.ndarray | float, cfg: CameraNoise, f_native: float, baseline: float):
    """Stereo axial depth noise ``sigma_z = z^2 subpixel / (f_native baseline)`` (m)."""
    return np.square(z) * (cfg.subpixel / (f_native * baseline))


def depth_edges(depth: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth-discontinuity pixels and, for each, the 4-neighbour across the largest jump.

    Only pairs of valid pixels (finite, > 0) count. Returns ``(edge, other)``: ``edge`` (H, W)
    bool is True where some valid 4-neighbour differs by more than ``threshold`` (m); ``other``
    (H, W) holds that neighbour's depth (the pixel's own depth where it is not an edge).
    """
    z = np.asarray(depth, dtype=np.float64)
    if z.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {z.shape}")
    h, w = z.shape
    valid = np.isfinite(z) & (z > 0)
    zc = np.where(valid, z, 0.0)
    zp = np.pad(zc, 1, mode="edge")
    vp = np.pad(valid, 1, mode="constant", constant_values=False)
    best = np.zeros_like(zc)
    other = zc.copy()
    for dy, dx in _NEIGHBOURS:
        nz = zp[1 + dy : h + 1 + dy, 1 + dx : w + 1 + dx]
        nv = vp[1 + dy : h + 1 + dy, 1 + dx : w + 1 + dx]
        jump = np.where(valid & nv, np.abs(nz - zc), 0.0)
        better = jump > best
        best = np.where(better, jump, best)
        other = np.where(better, nz, other)
    return best > threshold, other


def depth_noise(
    depth: np.ndarray,
    rng: np.random.Generator,
    cfg: CameraNoise,
    f_native: float,
    baseline: float,
    min_range: float,
    max_range: float,
) -> np.ndarray:
    """A D435-like depth measurement from the true depth image.

    ``depth`` (H, W) metres along the optical axis; values that are not finite or ``<= 0`` are
    invalid. In order:

    1. flying pixels: of the pixels at a depth discontinuity (a valid 4-neighbour more than
       ``cfg.edge_threshold`` away, see :func:`depth_edges`), a fraction
       ``cfg.flying_pixel_fraction`` takes a depth drawn uniformly between its own and that
       neighbour's (a point floating between fore- and background);
    2. per-capture scale error: every depth times ``1 + N(0, cfg.depth_scale_sigma)``;
    3. axial noise ``N(0, sigma_z)``, ``sigma_z = z^2 cfg.subpixel / (f_native baseline)``;
    4. random holes: a fraction ``cfg.invalid_fraction`` of the pixels becomes invalid;
    5. measurements outside ``[min_range, max_range]`` become invalid.

    Returns float32 (H, W) metres, 0 where invalid.
    """
    z = np.asarray(depth, dtype=np.float64)
    if z.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {z.shape}")
    if f_native <= 0 or baseline <= 0:
        raise InvalidInputError(f"f_native ({f_native}) and baseline ({baseline}) must be positive")
    valid = np.isfinite(z) & (z > 0)
    z = np.where(valid, z, 0.0)

    scale = 1.0 + rng.normal(0.0, cfg.depth_scale_sigma)

    if cfg.flying_pixel_fraction > 0:
        edge, other = depth_edges(z, cfg.edge_threshold)
        idx = np.flatnonzero(edge)
        fly = idx[rng.random(idx.size) < cfg.flying_pixel_fraction]
        t = rng.random(fly.size)
        zf = z.reshape(-1)  # a view of the fresh array z
        zf[fly] = zf[fly] + t * (other.reshape(-1)[fly] - zf[fly])

    z *= scale
    sigma = axial_depth_sigma(z, cfg, f_native, baseline)
    z += sigma * rng.standard_normal(z.shape)

    holes = rng.random(z.shape) < cfg.invalid_fraction
    keep = valid & ~holes & (z >= min_range) & (z <= max_range)
    return np.where(keep, z, 0.0).astype(np.float32)


def color_noise(rgb: np.ndarray, rng: np.random.Generator, cfg: CameraNoise) -> np.ndarray:
    """Lighting gain then per-pixel Gaussian noise on an RGB image.

    ``rgb`` (H, W, 3) uint8. Intensities in [0, 1] are multiplied by ``cfg.lighting_gain``, get
    ``N(0, cfg.color_sigma)`` per channel, are clipped to [0, 1] and rounded back to uint8.
    """
    c = np.asarray(rgb)
    if c.ndim != 3 or c.shape[2] != 3:
        raise InvalidInputError(f"color must be (H, W, 3), got {c.shape}")
    f = c.astype(np.float32) * np.float32(cfg.lighting_gain / 255.0)
    f += rng.standard_normal(c.shape, dtype=np.float32) * np.float32(cfg.color_sigma)
    np.clip(f, 0.0, 1.0, out=f)
    return np.rint(f * 255.0).astype(np.uint8)


def range_noise(
    ranges: np.ndarray, rng: np.random.Generator, sigma: float, range_max: float
) -> np.ndarray:
    """Lidar ranges with ``N(0, sigma)`` noise; no return (non-finite, ``<= 0`` or beyond
    ``range_max``, before or after the noise) becomes ``inf``. Noisy ranges are clipped at 0."""
    r = np.asarray(ranges, dtype=np.float64)
    hit = np.isfinite(r) & (r > 0) & (r <= range_max)
    noisy = np.where(hit, r, 0.0) + rng.normal(0.0, sigma, r.shape)
    np.maximum(noisy, 0.0, out=noisy)
    return np.where(hit & (noisy <= range_max), noisy, np.inf)


def angle_diff(a: float, b: float) -> float:
    """``a - b`` wrapped to [-pi, pi)."""
    return float((a - b + np.pi) % (2.0 * np.pi) - np.pi)


def odometry_increment_noise(
    rot1: float, trans: float, rot2: float, rng: np.random.Generator, cfg: OdometryNoise
) -> tuple[float, float, float]:
    """Perturb an odometry increment as ``sample_motion_model_odometry`` does.

    Thrun, Burgard, Fox, *Probabilistic Robotics*, Table 5.6, in the variance form and with the
    reverse-driving handling of Nav2 AMCL's ``DifferentialMotionModel``: the rotation terms use
    ``min(|rot|, |pi - rot|)`` so a backward step is not taken for a half turn.

    ``rot1_hat = rot1 - N(0, alpha1 rot1^2 + alpha2 trans^2)``,
    ``trans_hat = trans - N(0, alpha3 trans^2 + alpha4 (rot1^2 + rot2^2))``,
    ``rot2_hat = rot2 - N(0, alpha1 rot2^2 + alpha2 trans^2)`` (variances).
    """
    r1 = min(abs(angle_diff(rot1, 0.0)), abs(angle_diff(rot1, np.pi)))
    r2 = min(abs(angle_diff(rot2, 0.0)), abs(angle_diff(rot2, np.pi)))
    t2 = trans * trans
    s_r1 = np.sqrt(cfg.alpha1 * r1 * r1 + cfg.alpha2 * t2)
    s_t = np.sqrt(cfg.alpha3 * t2 + cfg.alpha4 * (r1 * r1 + r2 * r2))
    s_r2 = np.sqrt(cfg.alpha1 * r2 * r2 + cfg.alpha2 * t2)
    n = rng.standard_normal(3)
    return (
        angle_diff(rot1, s_r1 * n[0]),
        float(trans - s_t * n[1]),
        angle_diff(rot2, s_r2 * n[2]),
    )

"""Pure sensor-noise functions of the error model (DESIGN.md, "Truth and belief", "Error model v2").

Every function takes the noise-free measurement as a numpy array and a
``numpy.random.Generator``; every random draw goes through that generator, so the same
generator state gives the same noisy measurement. Nothing here touches MuJoCo.

Units: m, rad; colors are uint8 RGB in, uint8 RGB out.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from mmpa.backends.twin.error_model import CameraNoise, OdometryNoise
from mmpa.core.errors import InvalidInputError

__all__ = [
    "angle_diff",
    "axial_depth_sigma",
    "bernoulli_indices",
    "color_noise",
    "color_session_gain",
    "correlated_field",
    "depth_bias_pattern",
    "depth_edges",
    "depth_noise",
    "edge_neighbours",
    "odometry_increment_noise",
    "range_noise",
    "resample_to",
    "session_disparity",
    "standard_normal_f32",
]


def axial_depth_sigma(z: np.ndarray | float, cfg: CameraNoise, f_native: float, baseline: float):
    """Stereo axial depth noise ``sigma_z = z^2 subpixel / (f_native baseline)`` (m)."""
    return np.square(z) * (cfg.subpixel / (f_native * baseline))


def standard_normal_f32(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """float32 standard normal draws of ``shape`` by the Box-Muller transform.

    From pairs of the generator's float32 uniforms ``u1, u2`` in [0, 1):
    ``r = sqrt(-2 ln(1 - u1))``, ``(r cos 2 pi u2, r sin 2 pi u2)`` are two independent
    N(0, 1) draws (Box & Muller 1958). About 3x faster than ``rng.standard_normal`` for the
    ~10^6 per-pixel draws of an image; the 24-bit uniforms bound ``|x|`` by
    ``sqrt(48 ln 2) = 5.77`` (a tail mass of 8e-9).
    """
    n = int(np.prod(shape, dtype=np.int64))
    m = (n + 1) // 2
    u = rng.random((2, m), dtype=np.float32)
    r = np.log1p(-u[0])
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)
    t = u[1]
    t *= np.float32(2.0 * np.pi)
    out = np.empty(2 * m, dtype=np.float32)
    np.cos(t, out=out[:m])
    np.sin(t, out=out[m:])
    out[:m] *= r
    out[m:] *= r
    return out[:n].reshape(shape)


def bernoulli_indices(rng: np.random.Generator, n: int, p: float) -> np.ndarray:
    """Sorted indices (int64) of the successes among ``n`` independent Bernoulli(``p``)
    trials, drawn as geometric gaps between successes (``~n p`` draws instead of ``n``;
    the same process: the gaps of a Bernoulli process are iid Geometric(p))."""
    if n <= 0 or p <= 0:
        return np.zeros(0, dtype=np.int64)
    if p >= 1:
        return np.arange(n, dtype=np.int64)
    if p > 0.25:  # dense: gaps are short, one uniform per trial is cheaper
        return np.flatnonzero(rng.random(n) < p)
    parts: list[np.ndarray] = []
    last = -1  # index of the last success so far
    while True:
        left = n - 1 - last
        k = int(left * p + 6.0 * np.sqrt(left * p) + 16)
        idx = last + np.cumsum(rng.geometric(p, k))
        if idx[-1] >= n:
            parts.append(idx[idx < n])
            return np.concatenate(parts)
        parts.append(idx)
        last = int(idx[-1])


def depth_edges(depth: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth-discontinuity pixels and, for each, the 4-neighbour across the largest jump.

    Only pairs of valid pixels (finite, > 0) count. Returns ``(edge, other)``: ``edge`` (H, W)
    bool is True where some valid 4-neighbour differs by more than ``threshold`` (m); ``other``
    (H, W) holds that neighbour's depth (the pixel's own depth where it is not an edge); on
    equal jumps the right, then left, lower, upper neighbour wins. float32 input is kept
    float32, anything else is computed in float64.
    """
    z = np.asarray(depth)
    if z.dtype != np.float32:
        z = z.astype(np.float64)
    if z.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {z.shape}")
    valid = np.isfinite(z) & (z > 0)
    zc = np.where(valid, z, z.dtype.type(0))
    # jumps between horizontal (H, W-1) and vertical (H-1, W) pairs of valid pixels
    jh = np.abs(zc[:, 1:] - zc[:, :-1])
    jh[~(valid[:, 1:] & valid[:, :-1])] = 0
    jv = np.abs(zc[1:] - zc[:-1])
    jv[~(valid[1:] & valid[:-1])] = 0
    best = np.zeros_like(zc)
    other = zc.copy()
    # (pixel slice, neighbour slice, jump) for the right, left, lower, upper neighbour
    for px, nb, jump in (
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None)), jh),
        ((slice(None), slice(1, None)), (slice(None), slice(None, -1)), jh),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None)), jv),
        ((slice(1, None), slice(None)), (slice(None, -1), slice(None)), jv),
    ):
        b = best[px]
        better = jump > b
        np.copyto(b, jump, where=better)
        np.copyto(other[px], zc[nb], where=better)
    return best > threshold, other


def edge_neighbours(z: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`depth_edges` at its edges only: the flat indices (int64, ascending) of the
    depth-discontinuity pixels of ``z`` (H, W) (valid where ``> 0``; invalid pixels must
    already be 0) and, for each, the depth of the 4-neighbour across the largest jump (ties:
    right, left, lower, upper), the values :func:`depth_edges` gives there. The largest jump
    of every pixel is a running maximum; the neighbour is searched at the edges alone."""
    h, w = z.shape
    valid = z > 0
    jh = np.abs(z[:, 1:] - z[:, :-1])
    jh[~(valid[:, 1:] & valid[:, :-1])] = 0
    jv = np.abs(z[1:] - z[:-1])
    jv[~(valid[1:] & valid[:-1])] = 0
    best = np.zeros_like(z)
    best[:, :-1] = jh
    np.maximum(best[:, 1:], jh, out=best[:, 1:])
    np.maximum(best[:-1], jv, out=best[:-1])
    np.maximum(best[1:], jv, out=best[1:])
    idx = np.flatnonzero(best > threshold)
    r, c = np.divmod(idx, w)
    jumps = np.zeros((4, idx.size), dtype=z.dtype)  # right, left, lower, upper
    for k, (ok, jj, rr, cc) in enumerate(
        ((c < w - 1, jh, r, c), (c > 0, jh, r, c - 1), (r < h - 1, jv, r, c), (r > 0, jv, r - 1, c))
    ):
        jumps[k, ok] = jj[rr[ok], cc[ok]]
    k = np.argmax(jumps, axis=0)  # the first of the largest
    return idx, z[r + np.array([0, 0, 1, -1])[k], c + np.array([1, -1, 0, 0])[k]]


def correlated_field(
    rng: np.random.Generator, shape: tuple[int, int], corr_px: float
) -> np.ndarray:
    """A stationary Gaussian random field of unit variance, float32 ``shape``: white noise
    smoothed by a Gaussian kernel of SD ``corr_px`` pixels (so the field's autocorrelation is
    Gaussian with SD ``sqrt(2) corr_px``), normalized by its sample SD. ``corr_px = 0`` gives
    white noise."""

    f = rng.standard_normal(shape).astype(np.float32)
    if corr_px > 0:
        f = gaussian_filter(f, sigma=float(corr_px), mode="reflect")
    sd = float(f.std())
    return f / np.float32(sd) if sd > 0 else f


def _image_coords(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates relative to the image centre, in units of half the image width
    (``u`` in [-1, 1] across the width, ``v`` likewise scaled), float32 (H, W) each."""
    h, w = shape
    half = np.float32(w / 2.0)
    u = (np.arange(w, dtype=np.float32) - np.float32((w - 1) / 2.0)) / half
    v = (np.arange(h, dtype=np.float32) - np.float32((h - 1) / 2.0)) / half
    return np.broadcast_to(u[None, :], shape), np.broadcast_to(v[:, None], shape)


def session_disparity(
    shape: tuple[int, int], rng: np.random.Generator, cfg: CameraNoise
) -> np.ndarray:
    """The disparity error (px, float32 ``shape``) fixed for one session of the depth camera.

    Sum of (DESIGN.md "Error model v2"):

    - the correlated part of the per-pixel noise,
      ``sqrt(correlated_fraction) subpixel F``, ``F`` a unit-variance
      :func:`correlated_field` with ``correlation_px`` (librealsense #1375, #4286: a 10-frame
      average is still wavy);
    - a disparity offset ``N(0, session_offset_px)``;
    - a gradient ``g . (u, v)`` with ``g ~ N(0, session_gradient_px)`` per axis, ``(u, v)``
      the pixel position from the centre in half image widths (``g_x`` is the value at the
      left/right edge);
    - a low-frequency wave ``a sin(2 pi (u cos t + v sin t) / L + phi)``, ``a ~
      N(0, sqrt(2) session_wave_px)`` (its RMS over the image has SD ``session_wave_px``),
      direction ``t`` and phase uniform, wavelength ``L`` uniform in [1, 3] half widths.

    All draws come from ``rng`` in a fixed order.
    """
    out = np.zeros(shape, dtype=np.float32)
    if cfg.correlated_fraction > 0 and cfg.subpixel > 0:
        f = correlated_field(rng, shape, cfg.correlation_px)
        out += f * np.float32(np.sqrt(cfg.correlated_fraction) * cfg.subpixel)
    u, v = _image_coords(shape)
    offset = rng.normal(0.0, cfg.session_offset_px)
    g = rng.normal(0.0, cfg.session_gradient_px, 2)
    a = rng.normal(0.0, np.sqrt(2.0) * cfg.session_wave_px)
    t, phi = rng.uniform(0.0, 2.0 * np.pi, 2)
    wavelength = rng.uniform(1.0, 3.0)
    out += np.float32(offset)
    out += np.float32(g[0]) * u + np.float32(g[1]) * v
    phase = (u * np.float32(np.cos(t)) + v * np.float32(np.sin(t))) * np.float32(
        2.0 * np.pi / wavelength
    )
    out += np.float32(a) * np.sin(phase + np.float32(phi))
    return out


def depth_bias_pattern(
    shape: tuple[int, int], rng: np.random.Generator, sd_px: float
) -> np.ndarray:
    """The fixed ring-shaped disparity bias of one depth camera (px, float32 ``shape``):
    ``sqrt(2) sd_px sin(2 pi r / P + phi)``, ``r`` the distance (px) from a centre drawn
    ``N(0, W / 10)`` around the image centre, period ``P`` uniform in [40, 80] px, phase
    uniform (librealsense #3210, realsense-ros #1534: concentric rings, ~1 % p-p)."""
    h, w = shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) + rng.normal(0.0, w / 10.0, 2)
    period = rng.uniform(40.0, 80.0)
    phi = rng.uniform(0.0, 2.0 * np.pi)
    x = np.arange(w, dtype=np.float32) - np.float32(c[0])
    y = np.arange(h, dtype=np.float32) - np.float32(c[1])
    r = np.sqrt(x[None, :] ** 2 + y[:, None] ** 2)
    amp = np.float32(np.sqrt(2.0) * sd_px)
    return amp * np.sin(r * np.float32(2.0 * np.pi / period) + np.float32(phi))


def color_session_gain(
    shape: tuple[int, int], rng: np.random.Generator, cfg: CameraNoise
) -> np.ndarray:
    """Multiplicative colour gain (float32 (H, W, 3)) fixed for one session: exposure
    ``1 + N(0, exposure_gain_sigma)`` times white balance ``1 + N(0, white_balance_sigma)``
    per channel times a lighting gradient ``1 + g . (u, v)``, ``g ~
    N(0, lighting_gradient_sigma)`` per axis (``(u, v)`` as in :func:`session_disparity`)."""
    exposure = 1.0 + rng.normal(0.0, cfg.exposure_gain_sigma)
    wb = 1.0 + rng.normal(0.0, cfg.white_balance_sigma, 3)
    g = rng.normal(0.0, cfg.lighting_gradient_sigma, 2)
    u, v = _image_coords(shape)
    light = np.float32(1.0) + np.float32(g[0]) * u + np.float32(g[1]) * v
    np.maximum(light, np.float32(0.0), out=light)
    return light[..., None] * (np.float32(exposure) * wb.astype(np.float32))[None, None, :]


def resample_to(field: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A per-pixel field of the native stream (H0, W0[, C]) at another resolution of the same
    field of view (H, W): the native pixel nearest to each pixel's centre."""
    h0, w0 = field.shape[:2]
    h, w = shape
    if (h, w) == (h0, w0):
        return field
    rows = np.clip(np.floor((np.arange(h) + 0.5) * h0 / h).astype(np.int64), 0, h0 - 1)
    cols = np.clip(np.floor((np.arange(w) + 0.5) * w0 / w).astype(np.int64), 0, w0 - 1)
    return np.ascontiguousarray(field[rows][:, cols])


def depth_noise(
    depth: np.ndarray,
    rng: np.random.Generator,
    cfg: CameraNoise,
    f_native: float,
    baseline: float,
    min_range: float,
    max_range: float,
    fixed_disparity: np.ndarray | None = None,
) -> np.ndarray:
    """A D435-like depth measurement from the true depth image.

    ``depth`` (H, W) metres along the optical axis; values that are not finite or ``<= 0`` are
    invalid. In order:

    1. flying pixels: of the pixels at a depth discontinuity (a valid 4-neighbour more than
       ``cfg.edge_threshold`` away, see :func:`depth_edges`), a fraction
       ``cfg.flying_pixel_fraction`` takes a depth drawn uniformly between its own and that
       neighbour's (a point floating between fore- and background);
    2. per-capture scale error: every depth times ``1 + N(0, cfg.depth_scale_sigma)``;
    3. axial noise ``N(0, sigma_z)``, ``sigma_z = z^2 sqrt(1 - correlated_fraction)
       subpixel / (f_native baseline)`` (:func:`standard_normal_f32` draws): the part of the
       per-pixel noise that changes from frame to frame;
       then the disparity error fixed in this session, ``fixed_disparity`` (H, W) px (the
       correlated noise, session drift and bias pattern: :func:`session_disparity`,
       :func:`depth_bias_pattern`): ``z -= z^2 fixed_disparity / (f_native baseline)``
       (a larger disparity is a nearer point; the linearization of ``z = f b / d``);
    4. random holes: each pixel independently invalid with probability
       ``cfg.invalid_fraction`` (:func:`bernoulli_indices`);
    5. measurements outside ``[min_range, max_range]`` become invalid.

    Computed in float32 (the depth resolution of the frame: 1e-6 m at 4 m, against a
    ``sigma_z`` of 0.3 mm at the 0.2 m minimum range). Returns float32 (H, W) metres, 0 where
    invalid.
    """
    z = np.array(depth, dtype=np.float32)  # a fresh copy
    if z.ndim != 2:
        raise InvalidInputError(f"depth must be (H, W), got {z.shape}")
    if f_native <= 0 or baseline <= 0:
        raise InvalidInputError(f"f_native ({f_native}) and baseline ({baseline}) must be positive")
    valid = np.isfinite(z) & (z > 0)
    z[~valid] = 0.0

    scale = 1.0 + rng.normal(0.0, cfg.depth_scale_sigma)

    if cfg.flying_pixel_fraction > 0:
        idx, other = edge_neighbours(z, cfg.edge_threshold)
        pick = rng.random(idx.size) < cfg.flying_pixel_fraction
        fly = idx[pick]
        t = rng.random(fly.size, dtype=np.float32)
        zf = z.reshape(-1)  # a view of the fresh array z
        zf[fly] = zf[fly] + t * (other[pick] - zf[fly])

    z *= np.float32(scale)
    white = cfg.subpixel * np.sqrt(1.0 - cfg.correlated_fraction)
    noise = standard_normal_f32(rng, z.shape)
    if fixed_disparity is not None:
        fd = np.asarray(fixed_disparity, dtype=np.float32)
        if fd.shape != z.shape:
            raise InvalidInputError(
                f"fixed_disparity must be the depth's shape {z.shape}, got {fd.shape}"
            )
        noise *= np.float32(white)
        noise -= fd  # disparity error (px): per frame plus fixed
        noise *= z
        noise *= z
        noise *= np.float32(1.0 / (f_native * baseline))
    else:
        noise *= z
        noise *= z
        noise *= np.float32(white / (f_native * baseline))  # sigma_z N(0, 1)
    z += noise

    keep = valid & (z >= min_range) & (z <= max_range)
    keep.reshape(-1)[bernoulli_indices(rng, z.size, cfg.invalid_fraction)] = False
    z[~keep] = 0.0
    return z


def color_noise(
    rgb: np.ndarray,
    rng: np.random.Generator,
    cfg: CameraNoise,
    gain: np.ndarray | None = None,
) -> np.ndarray:
    """Lighting gain then per-pixel Gaussian noise on an RGB image.

    ``rgb`` (H, W, 3) uint8. Intensities in [0, 1] are multiplied by ``cfg.lighting_gain``
    and by the session's ``gain`` (H, W, 3) when given (:func:`color_session_gain`), get
    ``N(0, cfg.color_sigma)`` per channel (:func:`standard_normal_f32` draws), are clipped to
    [0, 1] and rounded back to uint8 (computed in float32, in units of 1/255).
    """
    c = np.asarray(rgb)
    if c.ndim != 3 or c.shape[2] != 3:
        raise InvalidInputError(f"color must be (H, W, 3), got {c.shape}")
    f = standard_normal_f32(rng, c.shape)
    f *= np.float32(255.0 * cfg.color_sigma)
    lit = c.astype(np.float32) * np.float32(cfg.lighting_gain)
    if gain is not None:
        g = np.asarray(gain, dtype=np.float32)
        if g.shape != c.shape:
            raise InvalidInputError(
                f"colour gain must be the image's shape {c.shape}, got {g.shape}"
            )
        lit *= g
    f += lit
    np.clip(f, 0.0, 255.0, out=f)
    np.rint(f, out=f)
    return f.astype(np.uint8)


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

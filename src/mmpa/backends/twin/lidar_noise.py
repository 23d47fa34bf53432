"""Pure functions of the lidar / localization side of the error model v2 (DESIGN.md).

Nothing here touches MuJoCo; :class:`mmpa.backends.twin.sensors.SimLidar` casts the rays and calls
these.
Every random draw goes through a ``numpy.random.Generator`` passed in.

- **Reflector range bias** (range walk, Sedek et al. 2024): a retroreflective return is off
  by a per-reflector fixed bias ``b_i = mean + N(0, sd)`` (:func:`reflector_biases`) plus
  ``c (1 - cos incidence)`` (:func:`incidence_bias`).
- **Beam width** (SICK NAV350): the beam is a Gaussian spot whose 1/e^2 diameter grows as
  ``D(r) = beam_width + beam_divergence r`` (:func:`footprint_diameter`). It is sampled by
  ``K`` sub-rays of equal power (:func:`beam_subrays`) fanned from the scanner, cast only for
  the beams whose footprint can reach an edge or a reflector (:func:`footprint_beams`). Each
  sub-ray returns a Gaussian pulse of range SD :data:`PULSE_SIGMA` with its power; the
  receiver reports the highest peak of the summed echo (:func:`strongest_echo`): returns
  closer in range than about two pulse SDs merge into one echo at a power-weighted range in
  between (mixed pixels), farther ones stay separate echoes and the stronger one wins; a
  beam half on a reflector returns about half its intensity.
- **Occupancy map warp**: the map the localizer gets is drawn from the world through a smooth
  random displacement field (:class:`SmoothWarp`, SD ``sigma``, Gaussian correlation of
  length ``length``).
- **Operator's rough pose** (:func:`rough_pose`): the truth plus the operator's error.

Units: m, rad.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from mmpa.core.errors import InvalidInputError
from mmpa.core.geometry import Array

__all__ = [
    "EDGE_JUMP",
    "PULSE_SIGMA",
    "SUBRAYS",
    "SmoothWarp",
    "beam_subrays",
    "footprint_beams",
    "footprint_diameter",
    "incidence_bias",
    "reflector_biases",
    "rough_pose",
    "strongest_echo",
]

#: m, range SD of one echo pulse (a Gaussian pulse of ~1.6 ns FWHM: 0.24 m FWHM in range).
#: Returns closer than ~2 PULSE_SIGMA merge into one echo (mixed pixel); farther ones separate.
PULSE_SIGMA = 0.10
#: sub-rays per beam where the footprint is resolved (odd: the middle one is the beam axis)
SUBRAYS = 5
#: m, a range jump between neighbouring beams on the same geom that counts as an edge
EDGE_JUMP = 0.25


def footprint_diameter(r: Array | float, beam_width: float, beam_divergence: float) -> Array:
    """1/e^2 diameter (m) of the beam's spot at range ``r`` (m):
    ``D(r) = beam_width + beam_divergence r`` (``beam_divergence`` in rad, full angle)."""
    return beam_width + beam_divergence * np.asarray(r, float)


def beam_subrays(k: int = SUBRAYS) -> tuple[Array, Array]:
    """Lateral offsets ``u`` (in units of the spot diameter ``D``) and weights of ``k`` sub-rays
    that sample a Gaussian spot of 1/e^2 diameter ``D`` (intensity ``exp(-8 u^2)``, SD
    ``D / 4``) with equal power each: ``u_j = Phi^-1((j + 1/2) / k) / 4``, weight ``1 / k``.
    For ``k = 5``: ``u = 0, +-0.131, +-0.320``. ``k`` must be odd (the middle one is the axis)."""
    if k < 1 or k % 2 == 0:
        raise InvalidInputError(f"the number of sub-rays must be odd and positive, got {k}")
    u = ndtri((np.arange(k) + 0.5) / k) / 4.0
    u[k // 2] = 0.0  # exactly the axis
    return u, np.full(k, 1.0 / k)


def incidence_bias(cos_inc: Array, coefficient: float) -> Array:
    """Range walk with incidence (m): ``coefficient (1 - |cos incidence|)``; 0 head-on,
    ``coefficient`` at grazing incidence."""
    return coefficient * (1.0 - np.abs(np.asarray(cos_inc, float)))


def reflector_biases(
    names: Sequence[str],
    retro: Array,
    rng: np.random.Generator,
    mean: float,
    sd: float,
) -> Array:
    """Fixed range bias (m) of each retroreflector: ``mean + N(0, sd)`` for ``retro[i]``, 0
    for the other geoms. The draw of each reflector is keyed by its name (one integer from
    ``rng``, then a generator per name), so adding a geom never changes another's bias."""
    retro = np.asarray(retro, bool)
    if retro.shape != (len(names),):
        raise InvalidInputError(f"retro must have one flag per name, got {retro.shape}")
    base = int(rng.integers(0, 2**63 - 1))
    out = np.zeros(len(names))
    for i in np.flatnonzero(retro):
        z = np.random.default_rng([base, zlib.crc32(names[i].encode())]).standard_normal()
        out[i] = mean + sd * z
    return out


def _spans(lo: np.ndarray, hi: np.ndarray, n: int, circular: bool) -> tuple[np.ndarray, np.ndarray]:
    """Integer beam indices of the closed intervals ``[lo_s, hi_s]`` (each interval's
    indices) and the interval each belongs to; wrapped modulo ``n`` when ``circular``, else
    clipped to ``[0, n)``."""
    lo = np.asarray(lo, np.int64)
    length = np.maximum(np.asarray(hi, np.int64) - lo + 1, 0)
    owner = np.repeat(np.arange(lo.size), length)
    start = np.cumsum(length) - length
    idx = np.arange(int(length.sum())) - np.repeat(start, length) + np.repeat(lo, length)
    if circular:
        return idx % n, owner
    keep = (idx >= 0) & (idx < n)
    return idx[keep], owner[keep]


def footprint_beams(
    ranges: Array,
    key: Array,
    retro: Array,
    angle_increment: float,
    beam_width: float,
    beam_divergence: float,
    range_max: float,
    circular: bool,
    edge_jump: float = EDGE_JUMP,
) -> tuple[Array, Array]:
    """Which beams' spots can reach an edge or a retroreflector, and the range to size their
    sub-ray fan at.

    From the axis ranges ``ranges`` (inf: no return) and the surface ``key`` of each axis hit
    (geom id; equal keys = the same surface): an *edge* lies between beams ``j`` and ``j+1``
    when their keys differ or their ranges differ by more than ``edge_jump``; it can fall in
    the spot of beam ``i`` when ``|i - j - 1/2| da <= D(r_e) / 2 + da / 2`` (``da`` the angle
    increment, ``r_e`` the nearer range of the two, ``D`` :func:`footprint_diameter`; the
    ``da / 2`` for the edge's unknown place between the beams). A retroreflector hit by beam
    ``j`` can fall in the spot of beam ``i`` when ``|i - j| da <= D(r_j) / 2``. Returns
    ``need`` (bool per beam) and ``r_ref``, per beam the nearest axis range among the beams
    whose hit may lie in its spot (itself included; ``range_max`` for no return): the fan
    ``u D(r_ref) / r_ref`` then has the spot's exact width on the nearest surface around it
    (a farther surface sees it wider by ``D(r_ref) r / (D(r) r_ref)``; the approximation of a
    fan from one point for a beam that leaves a ``beam_width`` aperture).

    ``circular``: beam ``n-1`` neighbours beam 0 (a 360 degree scan).
    """
    r = np.where(np.isfinite(ranges), np.asarray(ranges, float), range_max)
    r = np.maximum(r, 1e-3)
    key = np.asarray(key)
    retro = np.asarray(retro, bool)
    n = r.size
    half = 0.5 * footprint_diameter(r, beam_width, beam_divergence) / r  # rad, spot half-angle
    # edges between j and j+1
    j = np.arange(n if circular else n - 1)
    j1 = (j + 1) % n
    edge = (key[j] != key[j1]) | (np.abs(r[j] - r[j1]) > edge_jump)
    je = j[edge]
    je1 = (je + 1) % n
    near = np.minimum(r[je], r[je1])
    a = np.floor(np.maximum(half[je], half[je1]) / angle_increment).astype(np.int64)
    jr = np.flatnonzero(retro)
    ar = np.floor(half[jr] / angle_increment).astype(np.int64)
    lo = np.concatenate([je - a, jr - ar])
    hi = np.concatenate([je + 1 + a, jr + ar])
    src_r = np.concatenate([near, r[jr]])
    idx, owner = _spans(lo, hi, n, circular)
    need = np.zeros(n, dtype=bool)
    need[idx] = True
    r_ref = r.copy()
    np.minimum.at(r_ref, idx, src_r[owner])
    return need, r_ref


def _mean_shift(
    rr: Array, pp: Array, x: Array, inv2s2: float, iterations: int, tol: float
) -> Array:
    """Mean-shift iterations ``x <- sum_k P_k g_k r_k / sum_k P_k g_k`` of the starts ``x``
    (m, S) on the pulses ``rr``, ``pp`` (m, K), each row until it moves less than ``tol``."""
    x = x.copy()
    active = np.arange(x.shape[0])
    for _ in range(iterations):
        xa, ra, pa = x[active], rr[active], pp[active]
        g = np.exp(-inv2s2 * np.square(xa[:, :, None] - ra[:, None, :])) * pa[:, None, :]
        den = g.sum(axis=2)
        num = (g * ra[:, None, :]).sum(axis=2)
        xn = np.where(den > 0, num / np.where(den > 0, den, 1.0), xa)
        x[active] = xn
        active = active[np.max(np.abs(xn - xa), axis=1) > tol]
        if active.size == 0:
            break
    return x


def strongest_echo(
    ranges: Array,
    power: Array,
    pulse_sigma: float = PULSE_SIGMA,
    iterations: int = 20,
    tol: float = 1e-5,
) -> tuple[Array, Array]:
    """The echo a pulsed receiver reports from ``K`` sub-returns per beam.

    ``ranges``, ``power``: (m, K); a sub-return with a non-finite range or zero power is none.
    Each sub-return ``k`` is a Gaussian pulse ``P_k g(x - r_k)``, ``g(d) = exp(-d^2 / (2
    s^2))``, ``s = pulse_sigma``; the received signal is their sum ``S(x)``. The reported
    range is the position ``x*`` of the highest peak of ``S``, found by fixed-point (mean
    shift) iterations ``x <- sum_k P_k g(x - r_k) r_k / sum_k P_k g(x - r_k)`` (at most
    ``iterations``, until no start moves by more than ``tol`` m): from the power-weighted mean
    where the sub-returns span at most ``s`` (``S`` is then unimodal), else from every
    sub-return. Returns within ~2 s merge (a mixed return between two surfaces, at their
    power-weighted mean when close), separate echoes compete and the strongest wins. Returns
    ``x*`` (inf where there is no sub-return; where two echoes are about to merge the peak is
    flat and 20 iterations leave up to ~0.05 mm, measured) and the gains ``g(x* - r_k)``
    (m, K) (0 for none), so that the echo's amplitude is ``sum_k P_k gain_k``.
    """
    r = np.asarray(ranges, float)
    p = np.asarray(power, float)
    if r.ndim != 2 or r.shape != p.shape:
        raise InvalidInputError(f"ranges and power must be (m, K) alike, got {r.shape}, {p.shape}")
    valid = np.isfinite(r) & (p > 0)
    any_valid = valid.any(axis=1)
    rr = np.where(valid, r, 0.0)
    pp = np.where(valid, p, 0.0)
    inv2s2 = 0.5 / pulse_sigma**2
    hi = np.max(np.where(valid, r, -np.inf), axis=1)
    lo = np.min(np.where(valid, r, np.inf), axis=1)
    uni = any_valid & (hi - lo <= pulse_sigma)
    xs = np.full(r.shape[0], np.inf)
    u = np.flatnonzero(uni)
    if u.size:
        x0 = (pp[u] * rr[u]).sum(axis=1) / pp[u].sum(axis=1)
        xs[u] = _mean_shift(rr[u], pp[u], x0[:, None], inv2s2, iterations, tol)[:, 0]
    mlt = np.flatnonzero(any_valid & ~uni)
    if mlt.size:
        ra, pa = rr[mlt], pp[mlt]
        x = _mean_shift(ra, pa, ra, inv2s2, iterations, tol)
        amp = (np.exp(-inv2s2 * np.square(x[:, :, None] - ra[:, None, :])) * pa[:, None, :]).sum(2)
        amp = np.where(valid[mlt], amp, -1.0)
        xs[mlt] = x[np.arange(mlt.size), np.argmax(amp, axis=1)]
    gain = np.where(
        valid, np.exp(-inv2s2 * np.square(np.where(any_valid, xs, 0.0)[:, None] - rr)), 0.0
    )
    return xs, gain


@dataclass(frozen=True)
class SmoothWarp:
    """A smooth random 2D displacement field ``u(p)`` (m) on the plane.

    Each component is a stationary Gaussian field with SD ``sigma`` and correlation
    ``E[u_c(p) u_c(p + d)] = sigma^2 exp(-|d|^2 / (2 length^2))``, drawn by random Fourier
    features (Rahimi & Recht 2007): ``u_c(p) = sigma sqrt(2 / M) sum_m cos(k_m . p + phi_m)``
    with ``k_m ~ N(0, I / length^2)`` and ``phi_m ~ U(0, 2 pi)`` (``M`` features per
    component), whose covariance is exactly the Gaussian above in expectation and whose
    values are near-Gaussian for ``M`` in the hundreds. The two components are independent.
    """

    sigma: float
    length: float
    wavevectors: Array  # (2, M, 2) rad/m
    phases: Array  # (2, M)

    @classmethod
    def sample(
        cls, rng: np.random.Generator, sigma: float, length: float, features: int = 256
    ) -> SmoothWarp:
        """Draw a field with SD ``sigma`` (m) and correlation length ``length`` (m)."""
        if sigma < 0 or length <= 0 or features < 1:
            raise InvalidInputError(
                f"need sigma >= 0, length > 0, features >= 1; got {sigma}, {length}, {features}"
            )
        k = rng.normal(0.0, 1.0 / length, (2, features, 2))
        phi = rng.uniform(0.0, 2.0 * np.pi, (2, features))
        return cls(float(sigma), float(length), k, phi)

    def __call__(self, xy: Array) -> Array:
        """Displacement (..., 2) m at the points ``xy`` (..., 2) m."""
        xy = np.asarray(xy, float)
        if self.sigma == 0:
            return np.zeros_like(xy)
        m = self.phases.shape[1]
        flat = xy.reshape(-1, 2)
        out = np.empty_like(flat)
        for c in range(2):
            arg = flat @ self.wavevectors[c].T + self.phases[c]
            out[:, c] = self.sigma * np.sqrt(2.0 / m) * np.cos(arg).sum(axis=1)
        return out.reshape(xy.shape)

    def on_grid(self, xs: Array, ys: Array) -> Array:
        """Displacement (H, W, 2) m at the grid points ``(xs[j], ys[i])`` (W,), (H,) m: the
        same values as ``self(meshgrid)``, by the separable sum ``Re(sum_m e^{i phi_m}
        e^{i k_mx x} e^{i k_my y})`` (one (H, M) x (M, W) product per component)."""
        xs, ys = np.asarray(xs, float), np.asarray(ys, float)
        out = np.zeros((ys.size, xs.size, 2))
        if self.sigma == 0:
            return out
        m = self.phases.shape[1]
        for c in range(2):
            k = self.wavevectors[c]
            ex = np.exp(1j * (k[:, 0:1] * xs[None, :] + self.phases[c][:, None]))  # (M, W)
            ey = np.exp(1j * (ys[:, None] * k[None, :, 1]))  # (H, M)
            out[..., c] = self.sigma * np.sqrt(2.0 / m) * (ey @ ex).real
        return out


def rough_pose(truth: Array, rng: np.random.Generator, pos_sigma: float, yaw_sigma: float) -> Array:
    """The operator's rough pose ``[x, y, theta]`` ('2D Pose Estimate'): ``truth`` plus
    ``N(0, pos_sigma)`` (m) per axis and ``N(0, yaw_sigma)`` (rad) on the heading (wrapped)."""
    t = np.asarray(truth, float).reshape(3)
    e = rng.normal(0.0, 1.0, 3) * np.array([pos_sigma, pos_sigma, yaw_sigma])
    out = t + e
    out[2] = (out[2] + np.pi) % (2.0 * np.pi) - np.pi
    return out

"""Error model v2, lidar and localization side (DESIGN.md "Error model v2"): each source acts at
its configured size against the simulator's truth or an independent computation.

- reflector range bias (range walk): per-reflector fixed bias and incidence term;
- beam width: mixed returns at a depth edge, none on a flat wall, partial intensity at a
  reflector's edge;
- lidar mount calibration error: the true laser site vs the nominal one;
- occupancy map warp: size and smoothness of the displacement, the map drawn through it;
- the operator's rough initial pose;
- the reference profile: the single-ray scan, draw for draw.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModel, ErrorModelConfig, LidarNoise
from mmpa.backends.twin.lidar_noise import (
    PULSE_SIGMA,
    SmoothWarp,
    beam_subrays,
    footprint_beams,
    strongest_echo,
)
from mmpa.backends.twin.noise import range_noise
from mmpa.backends.twin.operator import rough_initial_pose
from mmpa.backends.twin.sensors import SimLidar
from mmpa.backends.twin.twin_maps import twin_map
from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import T_to_vec6, inv, make_T
from mmpa.maps.occupancy import Box2D, rasterize
from mmpa.robot.description import LidarDescription, default_robot

REALISTIC = ErrorModelConfig().lidar
REFERENCE = ErrorModelConfig(profile="reference").lidar
NO_WIDTH = REALISTIC.model_copy(update={"beam_width": 0.0, "beam_divergence": 0.0})
LASER_Z = 0.3


def _model(geoms: str) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A world of ``geoms`` with the laser site at (0, 0, LASER_Z), scanning in the x-y plane
    (beam angle = world bearing)."""
    xml = f"""
<mujoco model="lidar_v2">
  <worldbody>
    {geoms}
    <site name="laser" pos="0 0 {LASER_Z}"/>
  </worldbody>
</mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    return m, d


def _box(name: str, cx: float, cy: float, hx: float, hy: float, group: int = 0) -> str:
    return f'<geom name="{name}" type="box" size="{hx} {hy} 1" pos="{cx} {cy} 1" group="{group}"/>'


def _cyl(name: str, x: float, y: float, r: float) -> str:
    return f'<geom name="{name}" type="cylinder" size="{r} 1" pos="{x} {y} 1" group="2"/>'


def _lidar(m, d, noise: LidarNoise, seed: int = 0, bias_seed: int = 1) -> SimLidar:
    return SimLidar(
        m,
        d,
        LidarDescription(),
        noise,
        np.random.default_rng(seed),
        lambda: 0.0,
        bias_rng=np.random.default_rng(bias_seed),
    )


def _mean_scan(lidar: SimLidar, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-beam mean range and intensity over ``n`` scans (NaN where a beam never returned)."""
    r = np.stack([s.ranges for s in (lidar.scan() for _ in range(n))])
    ok = np.isfinite(r)
    count = ok.sum(axis=0)
    mean = np.where(count > 0, np.where(ok, r, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)
    i = np.stack([lidar.scan().intensities for _ in range(min(n, 20))])
    return mean, i.mean(axis=0)


def _cos_cylinder(angles: np.ndarray, cx: float, cy: float, radius: float) -> np.ndarray:
    """|cos incidence| of beams from the origin at ``angles`` on a vertical cylinder: the
    beam passes the axis at ``p = D sin(a - phi)``, ``cos = sqrt(1 - (p / R)^2)``."""
    D, phi = math.hypot(cx, cy), math.atan2(cy, cx)
    p = D * np.sin(angles - phi)
    return np.sqrt(np.clip(1.0 - (p / radius) ** 2, 0.0, 1.0))


# --------------------------------------------------------------------------------------------
# reflector range bias


RING = [(2.5 + 0.06 * i, math.radians(15.0 * i)) for i in range(24)]  # (distance, bearing)
R_REFL = 0.04


def test_reflector_range_bias_per_reflector_at_the_configured_size() -> None:
    geoms = "\n".join(
        _cyl(f"reflector_{i}", D * math.cos(a), D * math.sin(a), R_REFL)
        for i, (D, a) in enumerate(RING)
    )
    m, d = _model(geoms)
    lidar = _lidar(m, d, NO_WIDTH)  # the range walk alone (beam width tested below)
    truth = lidar.scan_truth()
    _, gid, _ = lidar.cast()
    mean, _ = _mean_scan(lidar, 200)
    a = truth.angles
    biases = []
    for i, (D, phi) in enumerate(RING):
        on = gid == mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"reflector_{i}")
        assert on.sum() >= 3
        walk = NO_WIDTH.reflector_incidence_bias * (
            1 - _cos_cylinder(a[on], D * math.cos(phi), D * math.sin(phi), R_REFL)
        )
        b = mean[on] - truth.ranges[on] - walk  # what is left: the reflector's fixed bias
        assert np.ptp(b) < 0.005  # one bias per reflector (200 scans: SE ~1 mm per beam)
        biases.append(float(np.mean(b)))
    biases = np.array(biases)
    # mean -10 mm, SD 5 mm over reflectors (24 draws: SE of the mean 1 mm, of the SD ~15 %)
    assert np.mean(biases) == pytest.approx(NO_WIDTH.reflector_bias_mean, abs=0.003)
    assert 0.6 * NO_WIDTH.reflector_bias_sd < np.std(biases) < 1.5 * NO_WIDTH.reflector_bias_sd
    # fixed per robot instance: the same bias stream gives the same biases, another not
    again = _lidar(m, d, NO_WIDTH, seed=5, bias_seed=1)
    other = _lidar(m, d, NO_WIDTH, seed=5, bias_seed=2)
    np.testing.assert_array_equal(again._bias, lidar._bias)
    assert not np.array_equal(other._bias, lidar._bias)


def test_reflector_range_bias_grows_with_incidence() -> None:
    # one wide retroreflective cylinder: its beams see every incidence from 0 to ~80 degrees
    cx, radius = 4.0, 1.0
    m, d = _model(_cyl("reflector_0", cx, 0.0, radius))
    lidar = _lidar(m, d, NO_WIDTH)
    truth = lidar.scan_truth()
    mean, _ = _mean_scan(lidar, 200)
    on = np.isfinite(truth.ranges)
    cos = _cos_cylinder(truth.angles[on], cx, 0.0, radius)
    keep = cos > 0.15  # not the tangent beams
    x = 1.0 - cos[keep]
    y = (mean[on] - truth.ranges[on])[keep]
    slope, intercept = np.polyfit(x, y, 1)
    assert slope == pytest.approx(NO_WIDTH.reflector_incidence_bias, rel=0.15)
    assert intercept == pytest.approx(float(lidar._bias[lidar.cast()[1][on][0]]), abs=0.0005)
    assert np.std(y - (slope * x + intercept)) < 0.0025  # 200-scan means: ~1 mm each


# --------------------------------------------------------------------------------------------
# beam width


EDGE_SCENE = "\n".join(
    [
        # a plain box whose front face (x = 3.0) ends at y = 0: a depth edge at bearing 0
        _box("block", 3.05, 0.75, 0.05, 0.75),
        # the wall behind it, face at x = 3.1, built of two boxes meeting at y = -2.5
        _box("wall_a", 3.2, -2.75, 0.1, 0.25),
        _box("wall_b", 3.2, 0.25, 0.1, 2.75),
        # a near box in front of a far wall (a 1.7 m gap): an edge at bearing ~118 degrees
        _box("near", -1.4, 1.505, 0.6, 0.005),
        _box("far", 0.0, 3.1, 5.0, 0.1),
    ]
)


def _edge_lidar(noise: LidarNoise, seed: int = 0) -> SimLidar:
    m, d = _model(EDGE_SCENE)
    return _lidar(m, d, noise, seed)


def test_mixed_returns_at_a_depth_edge_not_on_a_flat_wall() -> None:
    lidar = _edge_lidar(REALISTIC)
    truth = lidar.scan_truth()
    a = np.degrees(truth.angles)
    mean, _ = _mean_scan(lidar, 400)  # SE 0.75 mm per beam
    err = mean - truth.ranges
    # the flat wall, its joint (bearing -38.9 deg) included: no mixed returns, no bias
    flat = (a > -40.0) & (a < -5.0)
    assert flat.sum() > 100
    assert np.max(np.abs(err[flat])) < 0.004
    assert abs(np.mean(err[flat])) < 0.0005
    # the 0.1 m depth edge at bearing 0 (one pulse SD): the spot spans both surfaces there
    # and the echo lies in between, a mixed return
    near_edge = np.abs(a) < 3.0
    mixed = near_edge & (err < -0.01) | near_edge & (err > 0.01)
    assert 1 <= mixed.sum() <= 6
    r_edge = mean[mixed] * np.cos(truth.angles[mixed])  # x of the echo's point
    assert np.all((r_edge > 3.0 + 0.01) & (r_edge < 3.1 - 0.01))
    assert np.all(np.abs(err[~near_edge & flat]) < 0.004)
    # the same edge with the single-ray lidar: no point in between
    ref_mean, _ = _mean_scan(_edge_lidar(REFERENCE), 400)
    assert np.max(np.abs((ref_mean - truth.ranges)[near_edge])) < 0.004


def test_separate_echoes_at_a_wide_depth_gap() -> None:
    lidar = _edge_lidar(REALISTIC)
    truth = lidar.scan_truth()
    a = truth.angles
    mean, _ = _mean_scan(lidar, 100)
    around = np.abs(np.degrees(a) - 118.0) < 6.0
    r_near, r_far = 1.5 / np.sin(a[around]), 3.0 / np.sin(a[around])
    # 1.7 m apart: two echoes, the stronger reported, never a point in between (the near
    # box's 10 mm thin end face aside)
    dist = np.minimum(np.abs(mean[around] - r_near), np.abs(mean[around] - r_far))
    assert np.max(dist) < 0.012
    # the spot is wider than a beam: the near box shows at least as wide as it is
    near_scan = np.sum(np.abs(mean[around] - r_near) < 0.006)
    near_truth = np.sum(np.abs(truth.ranges[around] - r_near) < 1e-6)
    assert near_scan >= near_truth


def test_partial_intensity_at_a_reflector_edge() -> None:
    m, d = _model(_cyl("reflector_0", 2.0, 0.0, 0.04) + _box("wall", 6.1, 0.0, 0.1, 3.0))
    lidar = _lidar(m, d, REALISTIC)
    truth = lidar.scan_truth()
    _, inten = _mean_scan(lidar, 40)
    window = np.abs(truth.angles) < math.radians(4.0)
    full = REALISTIC.reflector_intensity
    partial = window & (inten > 0.15 * full) & (inten < 0.85 * full)
    assert partial.sum() >= 2  # both edges
    # the single-ray reference lidar: a beam is on the reflector or not
    ref = _lidar(m, d, REFERENCE)
    _, ref_inten = _mean_scan(ref, 40)
    assert not np.any(window & (ref_inten > 0.15 * full) & (ref_inten < 0.85 * full))


def test_strongest_echo_and_subrays() -> None:
    u, w = beam_subrays(5)
    assert u[2] == 0 and np.allclose(u, -u[::-1]) and np.allclose(w, 0.2)
    # equal-power quantiles of a Gaussian of SD D/4: the second moment is (D/4)^2 (5 samples)
    assert np.sum(w * u**2) == pytest.approx(1 / 16, rel=0.25)
    s = PULSE_SIGMA
    r = np.array(
        [
            [3.0, 3.0 + 0.5 * s, np.inf],  # one echo: the power-weighted mode in between
            [3.0, 3.0 + 10 * s, 3.0 + 10 * s],  # two echoes: the stronger (far) one wins
            [np.inf, np.inf, np.inf],  # nothing
        ]
    )
    p = np.array([[1.0, 1.0, 0.0], [1.0, 0.8, 0.8], [1.0, 1.0, 1.0]])
    echo, gain = strongest_echo(r, p)
    assert echo[0] == pytest.approx(3.0 + 0.25 * s, abs=1e-6)  # symmetric: the midpoint
    assert echo[1] == pytest.approx(3.0 + 10 * s, abs=1e-6)
    assert np.isinf(echo[2]) and np.all(gain[2] == 0)
    assert gain[1, 0] < 1e-10 and gain[1, 1] == pytest.approx(1.0)
    # a flat surface flags nothing; an edge flags the beams whose spot reaches it
    n = 1440  # 0.25 degrees: a spot of 35 mm at 3 m spans 1.3 beams each side
    flat, _ = footprint_beams(
        np.full(n, 3.0), np.zeros(n, int), np.zeros(n, bool), 2 * math.pi / n, 0.02, 0.005, 20, True
    )
    assert not flat.any()
    key = np.zeros(n, int)
    key[720:] = 1  # edges between beams 719|720 and (circular) 1439|0
    ranges = np.full(n, 3.0)
    ranges[720:] = 1.0  # the second surface nearer
    need, r_ref = footprint_beams(
        ranges, key, np.zeros(n, bool), 2 * math.pi / n, 0.02, 0.005, 20, True
    )
    # at 1 m the spot (25 mm) spans 2.9 beams each side of the edge
    assert need[717:723].all() and not need[10:700].any() and need[0] and need[n - 1]
    assert np.all(r_ref[717:723] == 1.0) and np.all(r_ref[10:700] == 3.0)
    assert not footprint_beams(
        ranges, key, np.zeros(n, bool), 2 * math.pi / n, 0.02, 0.005, 20, False
    )[0][0]  # not circular: 1439 and 0 are not neighbours


# --------------------------------------------------------------------------------------------
# lidar mount calibration error


def test_lidar_mount_error_moves_the_true_laser_site() -> None:
    nominal = default_robot()
    cfg = ErrorModelConfig()
    T_nom = nominal.lidar.T_base_link_laser
    v = np.array(
        [
            T_to_vec6(
                inv(T_nom)
                @ ErrorModel.sample(
                    nominal, cfg.model_copy(update={"seed": s})
                ).true.lidar.T_base_link_laser
            )
            for s in range(60)
        ]
    )
    li = cfg.lidar
    rms_t = np.sqrt(np.mean(v[:, :3] ** 2))
    rms_r = np.degrees(np.sqrt(np.mean(v[:, 3:] ** 2)))
    assert rms_t == pytest.approx(li.mount_trans_sigma, rel=0.2)
    assert rms_r == pytest.approx(li.mount_rot_sigma_deg, rel=0.2)
    ref = ErrorModel.sample(nominal, ErrorModelConfig(profile="reference"))
    np.testing.assert_allclose(ref.true.lidar.T_base_link_laser, T_nom, atol=1e-12)
    # the simulated laser site is the TRUE mount; the software's nominal one is off by it
    with SimWorld(errors=ErrorModelConfig(seed=3), site="1") as w:
        sid = mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_SITE, "laser")
        T_site = make_T(w.data.site_xmat[sid].reshape(3, 3), w.data.site_xpos[sid])
        T_base = w.truth.T_map_base_link()
        T_true = T_base @ w.true_robot.lidar.T_base_link_laser
        np.testing.assert_allclose(T_site, T_true, atol=1e-9)
        dT = inv(T_base @ w.nominal.lidar.T_base_link_laser) @ T_site
        off = T_to_vec6(dT)
        expect = T_to_vec6(inv(T_nom) @ w.true_robot.lidar.T_base_link_laser)
        np.testing.assert_allclose(off, expect, atol=1e-9)
        assert np.linalg.norm(off[:3]) > 1e-4  # the mount error is there


# --------------------------------------------------------------------------------------------
# occupancy map warp


def test_warp_field_size_and_correlation() -> None:
    sigma, length = 0.010, 3.0
    p0 = np.array([[1.0, -2.0]])
    lags = np.array([0.05, length, 2 * length])
    u0, uL = [], []
    for s in range(400):
        f = SmoothWarp.sample(np.random.default_rng(s), sigma, length)
        pts = np.vstack([p0, p0 + np.c_[lags, np.zeros(3)]])
        u = f(pts)
        u0.append(u[0])
        uL.append(u[1:])
    u0, uL = np.array(u0), np.array(uL)  # (S, 2), (S, 3, 2)
    assert np.std(u0) == pytest.approx(sigma, rel=0.1)
    rho = [np.mean(u0 * uL[:, k]) / sigma**2 for k in range(3)]
    expect = np.exp(-(lags**2) / (2 * length**2))  # Gaussian correlation, length = its SD
    assert rho[0] > 0.95  # neighbouring map cells move together
    np.testing.assert_allclose(rho, expect, atol=0.12)
    # the tensor-grid evaluation is the same field
    xs, ys = np.linspace(-5, 5, 7), np.linspace(-2, 2, 4)
    X, Y = np.meshgrid(xs, ys)
    np.testing.assert_allclose(f.on_grid(xs, ys), f(np.stack([X, Y], -1)), atol=1e-15)


def test_warped_raster_shows_the_world_displaced_by_the_field() -> None:
    """A long wall rasterized at 2 mm through a warp: its edge in the map is where the true edge
    lies moved by the field (measured per column), about sigma on average, smooth along it."""
    res, sigma = 0.002, 0.010
    wall = [Box2D((0.0, 0.0), (10.0, 0.2))]  # y in [-0.1, 0.1]
    shifts, expected = [], []
    for s in range(6):
        f = SmoothWarp.sample(np.random.default_rng(100 + s), sigma, 3.0)
        g = rasterize(wall, (-5.0, -0.2, 5.0, 0.2), res, warp=f)
        occ = g.occupied  # rows: y from -0.2 up
        top = occ.shape[0] - 1 - np.argmax(occ[::-1], axis=0)  # highest occupied row per column
        y_top = g.origin[1] + (top + 1) * res  # upper edge of that cell
        xs = g.origin[0] + (np.arange(g.width) + 0.5) * res
        inner = np.abs(xs) < 4.9  # the wall's ends move too: away from them
        shifts.append((y_top - 0.1)[inner])
        # a world point q is at q + u(q) in the map: the edge at y = 0.1 moves by u_y there
        expected.append(f(np.c_[xs, np.full_like(xs, 0.1)])[inner, 1])
    shifts, expected = np.array(shifts), np.array(expected)
    assert np.max(np.abs(shifts - expected)) <= res + 1e-3 * sigma  # within one cell
    assert np.sqrt(np.mean(shifts**2)) == pytest.approx(sigma, rel=0.5)  # 6 walls of 3.3 L
    step = np.abs(np.diff(shifts, axis=1))
    assert np.max(step) <= res + 1e-9  # smooth: neighbouring columns at most one cell apart


def test_twin_map_is_warped_under_realistic_only() -> None:
    with SimWorld(errors=ErrorModelConfig(seed=2), site="1") as w:
        warped, true = twin_map(w), twin_map(w, warped=False)
        assert warped.data.shape == true.data.shape
        differ = np.sum(warped.data != true.data)
        # 10 mm against 50 mm cells: some edge cells flip (~sqrt(2/pi) sigma / res of them)
        assert 0 < differ < 0.25 * true.occupied.sum()
    with SimWorld(errors=ErrorModelConfig(profile="reference", seed=2), site="1") as w:
        np.testing.assert_array_equal(twin_map(w).data, twin_map(w, warped=False).data)


# --------------------------------------------------------------------------------------------
# the operator's rough initial pose


def test_initial_pose_is_the_operators_rough_pose() -> None:
    with SimWorld(errors=ErrorModelConfig(seed=1), site="0") as w:
        truth = w.truth.base_pose2d()
        rng = np.random.default_rng(0)
        e = np.array([rough_initial_pose(w, rng) - truth for _ in range(400)])
        e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
        op = w.error_model.config.operator
        assert np.std(e[:, :2]) == pytest.approx(op.initial_pos_sigma, rel=0.1)
        assert np.degrees(np.std(e[:, 2])) == pytest.approx(op.initial_yaw_sigma_deg, rel=0.1)
        assert np.all(np.abs(e.mean(axis=0)) < [0.03, 0.03, 0.03])
        # the default stream: seeded, the same draw each call
        np.testing.assert_array_equal(rough_initial_pose(w), rough_initial_pose(w))
    with SimWorld(errors=ErrorModelConfig(profile="reference", seed=1), site="0") as w:
        np.testing.assert_allclose(rough_initial_pose(w), w.truth.base_pose2d(), atol=1e-12)


# --------------------------------------------------------------------------------------------
# the reference profile


def test_reference_scan_is_the_single_ray_model() -> None:
    """Profile ``reference``: no range walk, no footprint; the scan is the noise-free cast plus
    N(0, range_sigma), with the old draw order (intensity noise, then range noise)."""
    geoms = EDGE_SCENE + _cyl("reflector_0", 2.0, -1.0, 0.04)
    m, d = _model(geoms)
    lidar = _lidar(m, d, REFERENCE, seed=7)
    assert not lidar._biased and not lidar._footprint and not lidar._bias.any()
    ranges, _, _ = lidar.cast()
    rng = np.random.default_rng(7)
    for _ in range(3):
        scan = lidar.scan()
        rng.standard_normal((2, ranges.size))  # the intensity noise
        expect = range_noise(ranges, rng, REFERENCE.range_sigma, LidarDescription().range_max)
        np.testing.assert_array_equal(scan.ranges, expect)
    # scan_truth is noise-free under every profile
    real = _lidar(m, d, REALISTIC)
    np.testing.assert_array_equal(real.scan_truth().ranges, lidar.scan_truth().ranges)


def test_world_wires_the_bias_stream_per_robot() -> None:
    def biases(cfg: ErrorModelConfig) -> np.ndarray:
        with SimWorld(errors=cfg, site="0") as w:
            return w.lidar._bias.copy()

    a, b = biases(ErrorModelConfig(seed=4)), biases(ErrorModelConfig(seed=4, profile="realistic"))
    np.testing.assert_array_equal(a, b)
    assert np.count_nonzero(a) >= 9  # the nine reflectors (and the fiducials)
    assert not np.array_equal(a, biases(ErrorModelConfig(seed=5)))
    assert not biases(ErrorModelConfig(seed=4, profile="reference")).any()

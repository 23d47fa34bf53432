"""Error model v2 (DESIGN.md): profiles, and the camera's session errors acting at their
configured size against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from mmpa.backends.twin.error_model import PROFILES, ErrorModel, ErrorModelConfig
from mmpa.backends.twin.noise import (
    color_session_gain,
    correlated_field,
    depth_bias_pattern,
    depth_edges,
    resample_to,
    session_disparity,
)
from mmpa.core.config import load_config
from mmpa.harness.twin_site import MMPAExperimentConfig

# --------------------------------------------------------------------------------------------
# profiles


def test_realistic_is_the_default_with_the_design_values():
    e = ErrorModelConfig()
    assert e.profile == "realistic"
    # DESIGN.md "Error model v2", realistic column (binding)
    assert e.kinematics.dh_length_sigma == pytest.approx(0.5e-3)
    assert e.kinematics.dh_angle_sigma_deg == pytest.approx(0.05)
    assert e.kinematics.joint_repeatability_tool == pytest.approx(0.03e-3)
    assert e.kinematics.hand_eye_rot_sigma_deg == pytest.approx(0.5)
    assert e.camera.correlated_fraction == pytest.approx(0.75)
    assert e.camera.correlation_px == pytest.approx(3.0)
    assert (e.camera.session_offset_px, e.camera.session_gradient_px) == (0.06, 0.035)
    assert e.camera.session_wave_px == pytest.approx(0.02)
    assert e.camera.bias_pattern_px == pytest.approx(0.05)
    assert e.lidar.reflector_map_sigma == pytest.approx(0.010)
    assert e.lidar.reflector_bias_mean == pytest.approx(-0.010)
    assert e.compliance.tilt_full_reach_deg == pytest.approx(0.05)
    assert e.scene_change.probability == pytest.approx(0.3)
    assert e.operator.initial_pos_sigma == pytest.approx(0.2)


def test_profiles_fill_what_is_not_given():
    ref = ErrorModelConfig(profile="reference")
    assert ref.kinematics.dh_length_sigma == pytest.approx(0.2e-3)
    assert ref.camera.correlated_fraction == 0.0 and ref.lidar.reflector_map_sigma == 0.002
    harsh = ErrorModelConfig(profile="harsh", camera={"subpixel": 0.2})
    assert harsh.camera.subpixel == 0.2  # explicit wins
    assert harsh.camera.correlated_fraction == pytest.approx(0.85)  # the rest: the profile
    ideal = ErrorModelConfig(profile="ideal")
    flat = ideal.model_dump()
    for section in ("kinematics", "odometry", "compliance", "operator"):
        assert all(v == 0 for v in flat[section].values()), section
    assert ideal.camera.subpixel == 0 and ideal.lidar.range_sigma == 0
    for name in PROFILES:  # a dumped config validates back to itself
        c = ErrorModelConfig(profile=name, seed=4)
        assert ErrorModelConfig.model_validate(c.model_dump()) == c
    with pytest.raises(ValidationError):
        ErrorModelConfig(profile="kind")


def test_set_profile_rebases_the_section_and_keeps_the_seed(tmp_path):
    # a saved config lists every field; setting the profile must still switch all of them
    saved = tmp_path / "config.yaml"
    from mmpa.core.config import save_config

    save_config(MMPAExperimentConfig(errors=ErrorModelConfig(seed=5)), saved)
    cfg = load_config(
        MMPAExperimentConfig, saved, ["errors.profile=harsh", "errors.camera.subpixel=0.3"]
    )
    assert cfg.errors.profile == "harsh" and cfg.errors.seed == 5
    assert cfg.errors.kinematics.hand_eye_trans_sigma == pytest.approx(3e-3)
    assert cfg.errors.camera.subpixel == pytest.approx(0.3)


def test_reference_profile_keeps_the_founding_robot_instance():
    """The reference profile draws the same true robot as the founding model (same stream)."""
    from mmpa.robot.description import default_robot

    nominal = default_robot()
    ref = ErrorModel.sample(nominal, ErrorModelConfig(profile="reference", seed=3))
    rng = np.random.default_rng([3, 1])
    a = np.asarray(nominal.arm.dh.a) + rng.normal(0.0, 0.2e-3, 6)
    np.testing.assert_allclose(ref.true.arm.dh.a, a, rtol=0, atol=1e-15)
    # the lidar mount is exact in the reference model, off in the realistic one
    np.testing.assert_allclose(
        ref.true.lidar.T_base_link_laser, nominal.lidar.T_base_link_laser, atol=1e-15
    )
    real = ErrorModel.sample(nominal, ErrorModelConfig(seed=3))
    d = real.true.lidar.T_base_link_laser[:3, 3] - nominal.lidar.T_base_link_laser[:3, 3]
    assert 0 < np.linalg.norm(d) < 5 * 3e-3 * np.sqrt(3)


# --------------------------------------------------------------------------------------------
# the pure session functions


def test_correlated_field_unit_variance_and_gaussian_correlation():
    rng = np.random.default_rng(0)
    s = 3.0
    f = correlated_field(rng, (400, 400), s)
    assert f.dtype == np.float32 and f.std() == pytest.approx(1.0, abs=1e-5)
    # white noise smoothed by a Gaussian of SD s: autocorrelation exp(-d^2 / (4 s^2))
    for lag in (1, 3, 6):
        r = np.mean(f[:, lag:] * f[:, :-lag])
        assert r == pytest.approx(np.exp(-(lag**2) / (4 * s * s)), abs=0.03), lag


def test_session_disparity_statistics_match_the_config():
    cfg = ErrorModelConfig().camera.model_copy(update={"correlated_fraction": 0.0})
    shape = (48, 64)
    h, w = shape
    u = (np.arange(w) - (w - 1) / 2) / (w / 2)
    v = (np.arange(h) - (h - 1) / 2) / (w / 2)
    A = np.column_stack([np.ones(h * w), np.tile(u, h), np.repeat(v, w)])
    fits, waves = [], []
    for k in range(600):
        f = session_disparity(shape, np.random.default_rng([1, k]), cfg).astype(float).ravel()
        coef, *_ = np.linalg.lstsq(A, f, rcond=None)
        fits.append(coef)
        waves.append(np.sqrt(np.mean((f - A @ coef) ** 2)))
    fits = np.array(fits)
    # the wave leaks a little into the plane fit: 15 % slack
    assert fits[:, 0].std() == pytest.approx(cfg.session_offset_px, rel=0.15)
    assert fits[:, 1].std() == pytest.approx(cfg.session_gradient_px, rel=0.15)
    assert fits[:, 2].std() == pytest.approx(cfg.session_gradient_px, rel=0.15)
    assert np.sqrt(np.mean(np.square(waves))) < 1.2 * cfg.session_wave_px
    assert np.sqrt(np.mean(np.square(waves))) > 0.3 * cfg.session_wave_px


def test_bias_pattern_and_colour_gain_sizes():
    shape = (480, 640)
    b = depth_bias_pattern(shape, np.random.default_rng(0), 0.05)
    assert b.std() == pytest.approx(0.05, rel=0.1)
    cfg = ErrorModelConfig().camera
    gains = np.array(
        [color_session_gain((8, 8), np.random.default_rng([2, k]), cfg) for k in range(500)]
    )
    centre = gains[:, 3:5, 3:5, :].mean(axis=(1, 2))  # (500, 3): exposure x white balance
    expo = centre.mean(axis=1)
    assert expo.std() == pytest.approx(cfg.exposure_gain_sigma, rel=0.15)
    wb = centre / expo[:, None]  # 3 channels less their mean: SD sqrt(2/3) sigma
    assert wb.std() == pytest.approx(np.sqrt(2 / 3) * cfg.white_balance_sigma, rel=0.15)


def test_resample_to_picks_the_nearest_native_pixel():
    f = np.arange(480 * 640, dtype=np.float32).reshape(480, 640)
    half = resample_to(f, (240, 320))
    assert half.shape == (240, 320)
    assert half[10, 20] == f[21, 41]  # centre of pixel 10 at half res -> native 21
    assert resample_to(f, (480, 640)) is f


# --------------------------------------------------------------------------------------------
# in the twin, against the truth


def _sixteen_frames(profile: str):
    from mmpa.backends.twin.world import SimWorld

    with SimWorld(site="1", errors=ErrorModelConfig(profile=profile, seed=2)) as w:
        w.set_arm_configuration(np.asarray(w.nominal.arm.view_bench))
        truth = w.camera.capture_truth().depth.astype(float)
        frames = np.array([w.camera.capture().depth for _ in range(16)], dtype=float)
        fixed = w._camera_session[0]
        d = w.true_robot.camera
        fb = d.depth_focal_native * d.baseline
        # session 1 then back to 0: the session's draws come back exactly
        w.begin_session(1)
        other = w._camera_session[0]
        w.begin_session(0)
        again = w._camera_session[0]
    edge, _ = depth_edges(truth, 0.01)
    grown = edge.copy()
    for ax in (0, 1):
        for s in (-2, -1, 1, 2):
            grown |= np.roll(edge, s, axis=ax)
    ok = (truth > 0.25) & np.all(frames > 0, axis=0) & ~grown
    mean = frames[:, ok].mean(axis=0)
    z = truth[ok]
    dd = -(mean - z) * fb / z**2  # the disparity error of the 16-frame mean, px
    return dd, (None if fixed is None else fixed[ok]), other, again, fixed


def test_sixteen_frame_mean_keeps_the_session_part_realistic():
    dd, fixed, other, again, fixed_full = _sixteen_frames("realistic")
    assert fixed is not None and dd.size > 50_000
    # the per-frame part averages down (0.08 sqrt(0.25) / 4 = 0.01 px, plus the per-capture
    # scale 0.1 % of ~38 px / 4): what is left is the session's fixed disparity error
    assert np.std(dd - fixed) < 0.025
    assert np.std(fixed) > 0.06  # >= sqrt(0.75) 0.08 correlated part
    assert np.corrcoef(dd, fixed)[0, 1] > 0.9
    np.testing.assert_array_equal(again, fixed_full)
    assert np.std(other - fixed_full) > 0.05  # a new session: new fixed errors


def test_sixteen_frame_mean_averages_out_in_the_reference_model():
    dd, fixed, *_ = _sixteen_frames("reference")
    assert fixed is None
    # 0.08 px per frame / 4 plus the scale error's mean: no fixed part left
    assert np.std(dd) < 0.03


def test_colour_session_gain_acts_on_the_captured_image():
    from mmpa.backends.twin.world import SimWorld

    cfg = ErrorModelConfig(seed=1, camera={"color_sigma": 0.0, "exposure_gain_sigma": 0.2})
    with SimWorld(site="1", errors=cfg) as w:
        w.set_arm_configuration(np.asarray(w.nominal.arm.view_bench))
        w.begin_session(3)
        truth = w.camera.capture_truth().color.astype(float)
        noisy = w.camera.capture().color.astype(float)
        gain = w._camera_session[1]
    ok = (truth > 30) & (truth < 200) & (noisy < 250)
    ratio = noisy[ok] / truth[ok]
    # the image is the truth times the session gain (up to rounding to uint8)
    np.testing.assert_allclose(ratio, gain[ok], atol=0.5 / 30 + 1e-6)
    assert abs(np.mean(gain) - 1.0) > 1e-3


def test_a_top_level_profile_field_rebases_nothing():
    """Only a section's ``profile`` re-bases that section; a top-level field of that name
    (e.g. the perception data set's) leaves the other fields alone."""
    from mmpa.core.config import apply_overrides

    out = apply_overrides({"n": 3, "profile": "realistic"}, ["profile=ideal"])
    assert out == {"n": 3, "profile": "ideal"}
    out = apply_overrides(
        {"errors": {"seed": 2, "camera": {"subpixel": 0.3}}}, ["errors.profile=harsh"]
    )
    assert out == {"errors": {"seed": 2, "profile": "harsh"}}

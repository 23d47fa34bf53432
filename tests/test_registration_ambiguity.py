"""The competing-pose check (mmpa.registration.ambiguity, issue 34 item 4).

Synthetic hard cases with an exact truth (mmpa.registration.scenes): without the check the
default registration returns the wrong pose of a repeated structure and of a corridor as a
success (measured: 100 mm and 20 mm off); with it they are refused and the good cases are
still accepted within a millimetre. The real desk pair that passed at 24 mm (frames 81 -> 95
of ../shared/real-data/desk) is refused, its good neighbours are not.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from mmpa.core.geometry import apply, inv, make_T
from mmpa.ipe.config import IPEConfig
from mmpa.registration import RegistrationConfig, register
from mmpa.registration.ambiguity import (
    explained,
    rms_displacement,
    translation_modes,
    weak_starts,
)
from mmpa.registration.scenes import look_at, render, scene_cases
from mmpa.robot.interfaces import PointCloud

CFG = RegistrationConfig()
OFF = CFG.model_copy(update={"ambiguity_check": "off"})
DESK = Path("/work/shared/real-data/desk")


def _err_mm(T, truth, points) -> float:
    """Displacement (mm) of the cloud's centroid between ``T`` and the truth."""
    c = points.mean(axis=0)
    return float(np.linalg.norm(apply(T, c) - apply(truth, c)) * 1e3)


@pytest.fixture(scope="module")
def cases():
    out = {}
    for name, (scene, expect) in scene_cases().items():
        src = render(scene, scene.views["source"], seed=0)
        tgt = render(scene, scene.views["target"], seed=1)
        truth = inv(scene.views["target"]) @ scene.views["source"]
        out[name] = (src, tgt, truth, expect)
    return out


def test_rms_displacement_and_explained_closed_forms() -> None:
    pts = np.random.default_rng(0).normal(size=(500, 3))
    t = np.array([0.003, -0.004, 0.0])
    assert rms_displacement(make_T(np.eye(3), t), np.eye(4), pts) == pytest.approx(0.005)
    tree = cKDTree(pts)
    ok, j = explained(tree, pts, np.eye(4), 1e-6)
    assert ok.all() and (j == np.arange(500)).all()
    far = make_T(np.eye(3), [10.0, 0, 0])
    assert not explained(tree, pts, far, 1.0)[0].any()


def test_weak_start_of_a_corridor_is_its_axis() -> None:
    """Two walls (normals +-y) and a floor (normal z) along x: nothing constrains x, so the
    weakest direction is the pure translation along x and the starts move by +-shift there."""
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 2, 3000)
    u = rng.uniform(0, 1, 3000)
    k = np.arange(3000) % 3
    p = np.column_stack([x, np.where(k == 0, -0.5, np.where(k == 1, 0.5, u - 0.5)), u])
    p[k == 2, 2] = 0.0
    n = np.zeros_like(p)
    n[k == 0, 1], n[k == 1, 1], n[k == 2, 2] = 1.0, -1.0, 1.0
    starts = weak_starts(p, n, np.eye(4), 0.03, 1)
    assert [s[0] for s in starts] == ["weak0+", "weak0-"]
    for _, S in starts:
        assert np.allclose(S[:3, :3], np.eye(3), atol=1e-9)
        assert abs(S[0, 3]) == pytest.approx(0.03, abs=1e-9)
        assert np.allclose(S[1:3, 3], 0.0, atol=1e-9)


def test_translation_modes_find_the_copies() -> None:
    """Matches of a row of copies every 0.1 m vote for the true translation and for the
    translation one period off; the modes are the ones away from the given pose."""
    rng = np.random.default_rng(2)
    src = rng.uniform(0, 1, (300, 3))
    t_true = np.array([0.02, 0.0, 0.0])
    shift = np.where(np.arange(300) % 3 == 0, 0.1, 0.0)  # a third matched one copy off
    tgt = src + t_true + np.column_stack([shift, 0 * shift, 0 * shift])
    matches = np.column_stack([np.arange(300), np.arange(300)])
    modes = translation_modes(src, tgt, matches, make_T(np.eye(3), t_true), 0.03, 2)
    assert len(modes) == 1  # only the copy: the true translation is the given pose's
    assert modes[0][1][:3, 3] == pytest.approx(t_true + np.array([0.1, 0.0, 0.0]))
    assert "100 votes" in modes[0][0]


@pytest.mark.parametrize("name", ["repeated", "corridor", "irregular", "desk"])
def test_hard_cases(cases, name: str) -> None:
    """Refuse-cases: without the check the default registration returns a wrong pose as
    success (repeated 100 mm, corridor 20 mm off: far beyond the 1 mm of the good cases);
    with it, refused: the row as ambiguous (a pose one period off explains 642 points the
    accepted one does not, it 403: ratio 0.63, the rival threshold 0.9 of the other way
    round), the corridor as degenerate at 2 cm (information 0.0038 < 0.01; the real desk's
    pairs: >= 0.022). Accept-cases: accepted within 1.5 mm (measured 0.1-0.5)."""
    src, tgt, truth, expect = cases[name]
    r = register(src, tgt, CFG)
    if expect == "refuse":
        before = register(src, tgt, OFF)
        assert before.ok and _err_mm(before.T, truth, src.points) > 15.0
        assert not r.ok, r.reason
        assert r.reason.startswith(("ambiguous pose", "degenerate geometry at the 2 cm")), r.reason
    else:
        assert r.ok, r.reason
        assert _err_mm(r.T, truth, src.points) < 1.5
        # the competitors the check tried: the moved starts lose points, none is a rival
        assert r.stages["ambiguity_rounds"] == 1
        assert len(r.stages["ambiguity_competitors"]) >= 4


def test_with_init_the_check_is_off_by_default(cases) -> None:
    """``ambiguity_check="global"``: a registration from a given ``init`` is not probed."""
    src, tgt, truth, _ = cases["desk"]
    r = register(src, tgt, CFG, init=truth)
    assert r.ok and "ambiguity_s" not in r.stages
    r = register(src, tgt, CFG.model_copy(update={"ambiguity_check": "always"}), init=truth)
    assert r.ok and r.stages["ambiguity_s"] > 0


def test_look_at_is_a_proper_camera_pose() -> None:
    T = look_at((0, -1, 1), (0, 0, 0))
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.linalg.det(T[:3, :3]) > 0
    assert np.allclose(T[:3, 2], np.array([0, 1, -1]) / np.sqrt(2))  # optical axis at target


def _desk_cloud(idx: int) -> tuple[PointCloud, np.ndarray]:
    name = f"frame-{15 + 2 * idx:06d}"
    K = np.loadtxt(DESK / "intrinsics.K.txt")
    depth = np.asarray(Image.open(DESK / f"{name}.depth.png"), dtype=float) / 1000.0
    color = np.asarray(Image.open(DESK / f"{name}.color.png").convert("RGB"))
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    pts = np.column_stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    return PointCloud(pts, color[v, u] / 255.0), np.loadtxt(DESK / f"{name}.pose.txt")


@pytest.mark.skipif(not DESK.exists(), reason=f"no real desk frames at {DESK}")
def test_desk_pair_that_passed_wrong() -> None:
    """Desk frames 33 -> 40 (of 50; files 81 -> 95): FGR starts 40-65 mm off and ICP stops in
    a wrong minimum at fitness 0.52, 24 mm from the given pose (every other accepted pair of
    the set lies within 7.4 mm of it); its reverse is accepted at 3.5 mm. The check refuses
    it (or finds the right pose); the neighbouring pairs stay accepted."""
    clouds = {i: _desk_cloud(i) for i in (33, 34, 39, 40)}
    for a, b in ((33, 40), (34, 39), (33, 39), (34, 40)):
        (ca, Pa), (cb, Pb) = clouds[a], clouds[b]
        truth = inv(Pb) @ Pa
        r = register(ca, cb, CFG)
        if (a, b) == (33, 40):
            before = register(ca, cb, OFF)
            assert before.ok and _err_mm(before.T, truth, ca.points) > 20.0
            assert not r.ok or _err_mm(r.T, truth, ca.points) < 8.0, r.reason
        else:
            assert r.ok, (a, b, r.reason)
            assert _err_mm(r.T, truth, ca.points) < 8.0


def test_defaults_per_caller() -> None:
    """On for ``register`` without ``init`` (``mmpa register``, loop closures); off for the
    paper's registration and for IPE, which registers every later view from its estimate
    (the check would take ~0.35 s of its 0.5 s compute target: docs/registration.md)."""
    assert CFG.ambiguity_check == "global"
    assert RegistrationConfig.paper().ambiguity_check == "off"
    assert IPEConfig().registration.ambiguity_check == "off"

"""Registration on real RGB-D frames (tests/data/desk: a desk, depth with a grid of holes).

The given poses come from TSDF tracking and are only cm-accurate: they judge gross errors
(> 3 cm); mm accuracy is judged by self-consistency (reverse registration, 3-view loop) and by
the agreement of two independent estimators (voxel ICP, projective ICP on the depth image).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from mmpa.core.geometry import apply, inv
from mmpa.registration import (
    Prepared,
    ProjectiveConfig,
    RegistrationConfig,
    prepare,
    refine_projective,
    register,
)
from mmpa.registration.checks import rmse_gate
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import PointCloud

DATA = Path(__file__).parent / "data" / "desk"
NAMES = ("000015", "000017", "000019", "000021", "000113")
CFG = RegistrationConfig()


class Frame:
    def __init__(self, name: str, intr: CameraIntrinsics) -> None:
        self.color = np.asarray(Image.open(DATA / f"frame-{name}.color.png").convert("RGB"))
        raw = np.asarray(Image.open(DATA / f"frame-{name}.depth.png"))
        assert raw.dtype == np.uint16
        self.depth = raw.astype(float) / 1000.0  # mm -> m
        self.pose = np.loadtxt(DATA / f"frame-{name}.pose.txt")
        v, u = np.nonzero(self.depth > 0)
        z = self.depth[v, u]
        pts = np.column_stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z])
        self.cloud = PointCloud(pts, self.color[v, u] / 255.0)
        self.centroid = pts.mean(axis=0)


@pytest.fixture(scope="module")
def desk() -> tuple[CameraIntrinsics, list[Frame], list[Prepared]]:
    K = np.loadtxt(DATA / "intrinsics.K.txt")
    intr = CameraIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    frames = [Frame(n, intr) for n in NAMES]
    return intr, frames, [prepare(f.cloud, CFG) for f in frames]


def _mm(T_a: np.ndarray, T_b: np.ndarray, c: np.ndarray) -> float:
    """Displacement (mm) of the point ``c`` between two poses."""
    return float(np.linalg.norm(apply(T_a, c) - apply(T_b, c)) * 1e3)


def test_depth_has_holes(desk) -> None:
    """The data is what the tests claim: a regular grid of holes, ~1/3 valid pixels."""
    _, frames, _ = desk
    for f in frames:
        assert 0.25 < (f.depth > 0).mean() < 0.45


def test_neighbours_register_consistently(desk) -> None:
    _, frames, prep = desk
    T = {}
    for i, j in ((0, 1), (1, 2), (0, 2), (2, 3)):
        for a, b in ((i, j), (j, i)):
            r = register(prep[a], prep[b], CFG)
            assert r.ok, (a, b, r.reason)
            truth = inv(frames[b].pose) @ frames[a].pose
            assert _mm(r.T, truth, frames[a].centroid) < 30.0  # the poses are cm-level
            T[a, b] = r.T
    for i, j in ((0, 1), (1, 2), (0, 2), (2, 3)):
        # forward and reverse registrations are independent estimates: they agree to a few mm
        assert _mm(T[i, j] @ T[j, i], np.eye(4), frames[j].centroid) < 4.0
    # the 3-view loop 0 -> 1 -> 2 closes on the direct 0 -> 2
    assert _mm(T[1, 2] @ T[0, 1], T[0, 2], frames[0].centroid) < 4.0


def test_rmse_gate_scales_with_the_clouds(desk) -> None:
    """The adaptive gate grows with the measured spacing and depth; "fixed" is max_rmse."""
    _, _, prep = desk
    g = rmse_gate(prep[0], prep[1], CFG)
    s = max(prep[0].stats["spacing"], prep[1].stats["spacing"])
    z = max(prep[0].stats["median_depth"], prep[1].stats["median_depth"])
    sigma = CFG.depth_noise_k * z**2
    expect = CFG.rmse_margin * np.sqrt((CFG.rmse_spacing_factor * s) ** 2 + 2 * sigma**2)
    assert g == pytest.approx(max(CFG.max_rmse, expect))
    assert g > CFG.max_rmse  # sparse real clouds: above the twin-tuned constant
    assert rmse_gate(prep[0], prep[1], CFG.model_copy(update={"rmse_gate": "fixed"})) == 0.006
    noisier = CFG.model_copy(update={"depth_noise_k": 4 * CFG.depth_noise_k})
    assert rmse_gate(prep[0], prep[1], noisier) > g


def test_pair_without_overlap_is_refused(desk) -> None:
    """Frame 0's part that frame 4 (the end of the sequence) does not see, by the poses."""
    _, frames, prep = desk
    a, b = frames[0], frames[4]
    q = apply(inv(b.pose) @ a.pose, a.cloud.points)
    d, _ = cKDTree(b.cloud.points[::3]).query(q, distance_upper_bound=0.05)
    keep = ~np.isfinite(d)
    part = PointCloud(a.cloud.points[keep], a.cloud.colors[keep])
    assert len(part.points) > 20000  # still a large cloud: refused for the overlap, not size
    r = register(part, prep[4], CFG)
    assert not r.ok
    # and the whole of frame 0 against frame 4 registers or is refused, never wrong
    r = register(prep[0], prep[4], CFG)
    if r.ok:
        assert _mm(r.T, inv(b.pose) @ a.pose, a.centroid) < 30.0


def test_projective_refinement_on_depth_with_holes(desk) -> None:
    intr, frames, prep = desk
    for i, j in ((0, 1), (1, 3)):
        icp = register(prep[i], prep[j], CFG)
        assert icp.ok, icp.reason
        pr = refine_projective(frames[i].cloud.points, frames[j].depth, intr, icp.T)
        assert pr.ok, pr.reason
        assert pr.inlier_fraction > 0.4
        assert pr.rmse < 0.0025
        assert _mm(pr.T, icp.T, frames[i].centroid) < 4.0
        # without filling the holes the association falls through them (the former failure)
        no_fill = ProjectiveConfig(hole_fill_px=0)
        bad = refine_projective(frames[i].cloud.points, frames[j].depth, intr, icp.T, no_fill)
        assert not bad.ok and bad.inlier_fraction < 0.2

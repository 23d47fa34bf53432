"""The shipped detector on freshly rendered frames (a seed never used for training)."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import apply, inv
from mmpa.harness.perception_data import DatasetConfig, render_dataset
from mmpa.perception import CLASSES
from mmpa.perception.locate import project
from mmpa.perception.ssd import Detector, default_weights_path
from mmpa.perception.train import evaluate


@pytest.fixture(scope="module")
def det():
    assert default_weights_path().is_file()
    return Detector.load()


def test_shipped_weights_detect_fresh_renders(det):
    data = render_dataset(DatasetConfig(n_images=8, seed=424242, lighting={"normal": 1}))
    res = evaluate(det, data)
    # object-level detection success at the operating point, IoU >= 0.5 with the right class
    assert res.success_all["normal"] >= 0.7
    assert res.precision["normal"] >= 0.6


def test_detection_on_the_wrist_camera_locates_the_true_object(det, tmp_path):
    from mmpa.harness.perception_data import DESK_PARK, random_table_scene
    from mmpa.servo.grasp import look_configuration

    with SimWorld(site="0", episode=5) as w:
        w.reset(pose2d=np.array(DESK_PARK), settle=0.0)
        random_table_scene(
            w, np.random.default_rng(9), ["tennis_ball", "cube"], [], region=(-0.1, 0.1, -0.2, 0.0)
        )
        T_ab = w.nominal.T_base_link_arm_base
        w.set_arm_configuration(
            look_configuration(w.nominal, np.array([0.47, 0.0, 0.35 - T_ab[2, 3]]), 0.45)
        )
        frame = w.camera.capture()  # 640x480: the detector works at 320x240 inside
        dets = det.detect(frame.color)
        K = frame.intrinsics.K
        for name in ("tennis_ball", "cube"):
            hits = [d for d in dets if d.name == name]
            assert hits, f"{name} not detected: {[(d.name, d.score) for d in dets]}"
            u, v = project(apply(inv(w.truth.T_map_camera()), w.truth.T_map_object(name)[:3, 3]), K)
            b = hits[0].box
            assert b[0] <= u <= b[2] and b[1] <= v <= b[3]
    # save / load round trip gives the same detections
    p = tmp_path / "w.pt"
    det.save(p)
    again = Detector.load(p).detect(frame.color)
    assert [d.name for d in again] == [d.name for d in dets]
    assert np.allclose([d.box for d in again], [d.box for d in dets])
    assert len(CLASSES) == len(det.cfg.classes)

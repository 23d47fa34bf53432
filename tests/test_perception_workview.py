"""Working views (the robot's pre-grasp view), crop-and-zoom augmentation and the
target-detection metric; the mobile-manipulation desk search against the twin's truth."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.harness.perception_data import Dataset, DatasetConfig, render_dataset
from mmpa.perception import CLASSES

torch = pytest.importorskip("torch")

from mmpa.perception.ssd import Detection  # noqa: E402
from mmpa.perception.train import EvalResult, _work_view_success, crop_zoom, recall_precision  # noqa: E402


@pytest.fixture(scope="module")
def work():
    return render_dataset(
        DatasetConfig(n_images=4, seed=11, work_view_prob=1.0, work_exact_lighting=True)
    )


def test_working_views_label_the_target_inside_the_image(work):
    assert work.images.shape == (4, 240, 320, 3)
    assert np.all(work.target >= 0)
    for b, lab, t in zip(work.boxes, work.labels, work.target, strict=True):
        assert t in lab  # the target lies in the reachable region, in the first view
        assert np.all((b >= 0) & (b <= [320, 240, 320, 240]))
        assert np.all(b[:, 2] > b[:, 0]) and np.all(b[:, 3] > b[:, 1])
    again = render_dataset(
        DatasetConfig(n_images=2, seed=11, work_view_prob=1.0, work_exact_lighting=True)
    )
    assert np.array_equal(again.images, work.images[:2])
    assert np.array_equal(again.target, work.target[:2])


def test_crop_zoom_moves_boxes_with_the_pixels():
    img = np.zeros((240, 320, 3), np.uint8)
    img[100:140, 150:200] = (255, 0, 0)  # a red object
    boxes = np.array([[150, 100, 200, 140], [0, 0, 20, 20]], np.float32)
    labels = np.array([3, 1])
    rng = np.random.default_rng(4)
    for _ in range(20):
        out, b, lab = crop_zoom(img, boxes, labels, rng)
        assert out.shape == img.shape
        red = np.argwhere(out[..., 0] == 255)
        if 3 in lab:
            bb = b[list(lab).index(3)]
            # the red pixels fill the new box (to the nearest-neighbour resize's pixel)
            assert abs(red[:, 1].min() - bb[0]) <= 2 and abs(red[:, 1].max() + 1 - bb[2]) <= 2
            assert abs(red[:, 0].min() - bb[1]) <= 2 and abs(red[:, 0].max() + 1 - bb[3]) <= 2
        else:  # dropped only when less than a quarter of it stays in view
            assert red.shape[0] < 0.25 * 50 * 40 * (320 * 240) / (0.6 * 320 * 0.6 * 240)


def _det(c: int, box, score: float = 0.9) -> Detection:
    return Detection(c, CLASSES[c], score, np.asarray(box, float))


def test_target_success_and_recall_precision_count_by_hand():
    boxes = [np.array([[10, 10, 50, 50], [100, 100, 140, 160]], np.float32)] * 3
    labels = [np.array([0, 2])] * 3
    data = Dataset(
        np.zeros((3, 240, 320, 3), np.uint8),
        boxes,
        labels,
        np.array([1, 1, 1]),
        np.array([2, 2, 0]),
    )
    low = [
        [_det(2, [101, 99, 141, 158])],  # target hit
        [_det(2, [101, 99, 141, 158], 0.2)],  # below the threshold
        [_det(1, [10, 10, 50, 50]), _det(0, [60, 60, 90, 90])],  # wrong class / wrong place
    ]
    res = EvalResult({}, 0.0, {}, {}, {}, 0.0)
    _work_view_success(res, low, data, 0.5, CLASSES)
    assert res.work_success["normal"]["yida_bottle"] == 0.5
    assert res.work_success["normal"]["cube"] == 0.0
    assert res.work_success_all["normal"] == pytest.approx(1 / 3)
    r, p = recall_precision(low, data, 0.5, len(CLASSES))
    assert r == pytest.approx(1 / 6) and p == pytest.approx(1 / 3)
    r, p = recall_precision(low, data, 0.1, len(CLASSES))
    assert r == pytest.approx(2 / 6) and p == pytest.approx(2 / 4)


def test_desk_search_finds_the_legs_only_where_the_map_puts_them():
    from mmpa.backends.twin.twin_maps import laser_pose2d
    from mmpa.backends.twin.world import SimWorld
    from mmpa.core.geometry import se2_to_T
    from mmpa.experiments.paper001.mobile_manipulation import desk_front_legs
    from mmpa.harness.perception_data import DESK_PARK
    from mmpa.missions.desk_search import desk_in_scan

    with SimWorld(site="0") as w:
        legs = desk_front_legs(w)
        truth = []
        for k in range(4):
            g = w.model.geom(f"desk_{w.scene.grasp_desk.name}_leg{k}").id
            truth.append(w.data.geom_xpos[g][:2].copy())
        truth = np.array(truth)
        for leg in legs:  # the nominal front legs are two of the model's four legs
            assert np.min(np.linalg.norm(truth - leg, axis=1)) < 1e-6
        assert np.all(legs[:, 1] < w.scene.grasp_desk.center[1])  # on the robot's side
        pose = np.array(DESK_PARK) - [0.0, 0.25, 0.0]
        w.reset(pose2d=pose, settle=0.2)
        scan = w.lidar.scan()
        T_bl = se2_to_T(*laser_pose2d(w))
        est = w.truth.base_pose2d()
        assert desk_in_scan(scan, se2_to_T(*est) @ T_bl, legs, 0.05, 2)
        off = est + np.array([0.25, 0.0, 0.0])  # 25 cm off: no legs where expected
        assert not desk_in_scan(scan, se2_to_T(*off) @ T_bl, legs, 0.05, 2)


@pytest.mark.slow
def test_mobile_manipulation_one_run(tmp_path):
    from mmpa.backends.bag import messages as rm
    from mmpa.backends.bag.reader import BagPlayback, bag_topics, read_messages
    from mmpa.harness.runner import run_experiment

    out = run_experiment(
        "mobile-manipulation",
        tmp_path,
        trials=1,
        overrides=["objects=[tennis_ball]"],
        record=tmp_path / "bags",
    )
    row = out.rows[0]
    assert row["object"] == "tennis_ball"
    for k in ("navigation", "detected", "grasped", "desk_found"):
        assert isinstance(row[k], bool)
    assert (tmp_path / "report.md").read_text().count("tennis_ball") >= 1
    # the run's bag (--record): the drive's estimates, the grasp's frames, the arm at 50 Hz;
    # the last estimate against the recorded truth is the row's parking localization error
    bag = tmp_path / "bags" / "object-tennis_ball-site-0-trial-0.mcap"
    counts = {k: v[1] for k, v in bag_topics(bag).items()}
    assert counts["/map"] == 1 and counts["/amcl_pose"] > 50
    assert counts["/camera/color/image_raw"] > 0
    t, pose, _ = rm.from_pose_cov(read_messages(bag, ["/amcl_pose"])["/amcl_pose"][-1])
    truth = BagPlayback.open(bag).truth_at(t)
    assert float(np.hypot(*(pose[:2] - truth[:2]))) == pytest.approx(row["loc_err_m"], abs=2e-3)


def test_servo_views_put_the_tcp_above_the_target_in_the_simulator():
    """Servo views (the tracking grasp's approach): after the arm takes the configuration,
    the simulator's TCP lies ``standoff`` in range above the target's top, within the jitter
    sideways, tool z pointing down; rendered servo views label the target."""
    from mmpa.backends.twin.world import SimWorld
    from mmpa.harness.perception_data import (
        DESK_PARK,
        _footprint,
        random_table_scene,
        servo_view_configuration,
    )

    cfg = DatasetConfig(work_servo_standoff=(0.15, 0.25), work_servo_jitter=0.02)
    rng = np.random.default_rng(7)
    with SimWorld(site="0") as world:
        world.reset(pose2d=np.array(DESK_PARK), settle=0.0)
        for name in ("yida_bottle", "tennis_ball", "cube"):
            random_table_scene(world, rng, [name], [], region=(-0.1, 0.1, -0.15, 0.0))
            q = servo_view_configuration(world, rng, cfg, name)
            world.set_arm_configuration(q)
            T_tcp = world.truth.T_map_tcp()
            p_obj = world.truth.T_map_object(name)[:3, 3]
            top = p_obj[2] + _footprint(world, name)[1]
            d = T_tcp[:3, 3] - np.array([p_obj[0], p_obj[1], top])
            # nominal IK on the true robot: a few mm of kinematic error allowed
            assert 0.15 - 0.005 < d[2] < 0.25 + 0.005
            assert np.all(np.abs(d[:2]) < 0.02 * np.sqrt(2) + 0.005)
            assert T_tcp[:3, 2] @ np.array([0.0, 0.0, -1.0]) > 0.999
    servo = render_dataset(
        DatasetConfig(
            n_images=3, seed=12, work_view_prob=1.0, work_servo_prob=1.0, lighting={"high": 1}
        )
    )
    assert np.all(servo.lighting == 2)
    for lab, t in zip(servo.labels, servo.target, strict=True):
        assert t in lab


def test_turn_to_heading_aligns_the_true_base_on_the_estimate():
    """The mobile-manipulation turn at the entry pose: steering on the enhanced-AMCL estimate
    only, the simulator's true heading ends within 0.01 rad of the goal heading (it starts
    0.35 rad off, about the most the desk search leaves) and the base stays in place."""
    from mmpa.backends.twin.twin_maps import laser_pose2d, twin_map
    from mmpa.backends.twin.world import SimWorld
    from mmpa.core.geometry import wrap_angle
    from mmpa.harness.perception_data import DESK_PARK
    from mmpa.localization.localizer import make_localizer
    from mmpa.missions.desk_search import turn_to_heading

    park = np.array(DESK_PARK)
    start = np.array([park[0], park[1] - 0.25, park[2] - 0.35])
    with SimWorld(site="0") as world:
        world.reset(pose2d=start, settle=0.2)
        loc = make_localizer(
            "enhanced", twin_map(world), laser_pose2d(world), np.random.default_rng(3)
        )
        loc.initialize(start + np.array([0.02, -0.02, 0.02]))
        for _ in range(5):  # converge while standing
            loc.update(world.odometry.odometry().pose, world.lidar.scan(), force=True)
            world.step(0.2)
        aligned, secs = turn_to_heading(world, loc, float(park[2]), 0.003, 10.0)
        truth = world.truth.base_pose2d()
    assert aligned and secs < 10.0
    assert abs(float(wrap_angle(truth[2] - park[2]))) < 0.01
    assert np.hypot(*(truth[:2] - start[:2])) < 0.03

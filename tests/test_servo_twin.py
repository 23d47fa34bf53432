"""The tracking grasp in the twin, judged by the physics (held off the desk for 2 s)."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.errors import UnknownNameError
from mmpa.experiments.grasp import Config, OracleDetector, grasp_trial, make_grasper
from mmpa.servo.grasp import GraspConfig, TrackingGrasp
from mmpa.sim.world import SimWorld


@pytest.fixture(scope="module")
def world():
    with SimWorld(site="0") as w:
        yield w


def test_static_grasp_holds_the_object(world):
    g = make_grasper(Config(weights="oracle"), world)
    row = grasp_trial(world, g, "tennis_ball", "normal", np.random.default_rng(0))
    assert row["detected"] and row["grasped"], row
    # the gripper closed within 1.5 cm of the ball's true center
    assert np.hypot(row["close_dx"], row["close_dy"]) < 0.015
    top = world.scene.grasp_desk.size[2]
    assert world.truth.T_map_object("tennis_ball")[2, 3] > top + 0.05


def test_unknown_object_and_object_out_of_view(world):
    g = TrackingGrasp(OracleDetector(world), world.nominal, GraspConfig(max_time=1.0))
    with pytest.raises(UnknownNameError, match="unicorn"):
        g.run(
            "unicorn",
            world.arm,
            world.gripper,
            world.camera,
            world.base,
            world.step,
            lambda: world.time,
        )
    world.reset(pose2d=np.array([2.7, 0.85, np.pi / 2]), settle=0.1)
    world.place_object("cube", np.array([3.9, -2.9, 0.03]))  # nowhere near the desk
    q0 = world.arm.joint_positions()
    res = g.run(
        "cube", world.arm, world.gripper, world.camera, world.base, world.step, lambda: world.time
    )
    assert res.reason == "not found" and not res.closed_on_object
    # a safe stop: the arm held still
    assert np.abs(world.arm.joint_positions() - q0).max() < 0.01


def test_static_grasp_with_the_shipped_detector(world):
    g = make_grasper(Config(), world)
    row = grasp_trial(world, g, "cube", "normal", np.random.default_rng(3))
    assert row["detected"] and row["grasped"], row


@pytest.mark.slow
def test_tracking_grasp_of_a_moving_ball(world):
    """The operator moves the ball at 0.1 m/s (the paper's limit) with random turns: the
    predictor's tracking grasp holds it in most trials (physics judges)."""
    g = make_grasper(Config(use_predictor=True), world)
    rng = np.random.default_rng([0, 100])
    rows = [
        grasp_trial(world, g, "tennis_ball", "normal", rng, speed=0.1, others=1) for _ in range(5)
    ]
    assert sum(r["grasped"] for r in rows) >= 4, [r["failure"] for r in rows]
    # every attempt got as far as closing the gripper (no lost track, no timeout)
    assert all(r["reason"] in ("grasped", "missed", "dropped") for r in rows), rows

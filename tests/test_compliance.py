"""Base compliance in the physics (DESIGN.md "Error model v2"): the arm sits on a compliant
mount, so moving it from its folded pose to full reach tilts the TRUE arm base by the
configured angle (realistic 0.05 deg, harsh 0.1 deg), the tilt settles, the rigid profiles
keep today's model bit for bit, and the kinematic modes and the ground truth carry the tilt.

Every figure is read from the simulator's truth (body poses, joint states)."""

from __future__ import annotations

import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig
from mmpa.backends.twin.mjcf import (
    MOUNT_JOINTS,
    build_model,
    full_reach_configuration,
    mount_compliance,
)
from mmpa.backends.twin.world import SimWorld
from mmpa.core.geometry import inv
from mmpa.robot.kinematics import fk

TILT_DEG = {"realistic": 0.05, "harsh": 0.1}


def _z_tilt_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) between the z axes of two rotations (a tilt; a yaw does not count)."""
    return float(np.degrees(np.arccos(np.clip(Ra[:, 2] @ Rb[:, 2], -1.0, 1.0))))


def _mount(world: SimWorld) -> tuple[np.ndarray, np.ndarray]:
    """qpos and dof addresses of the mount hinges."""
    m = world.model
    ids = [m.joint(j).id for j in MOUNT_JOINTS]
    return m.jnt_qposadr[ids], m.jnt_dofadr[ids]


@pytest.fixture(scope="module", params=["realistic", "harsh"])
def reached(request: pytest.FixtureRequest) -> tuple[str, SimWorld, dict[str, np.ndarray]]:
    """A world whose arm moved folded -> full reach: truth before, and a 1 s trace after."""
    profile = request.param
    world = SimWorld(errors=ErrorModelConfig(profile=profile))
    qa, da = _mount(world)
    before = world.truth.T_map_arm_base()
    world.arm.move_joints(full_reach_configuration(world.nominal), settle=0.0)
    q, v = [], []
    for _ in range(500):  # 1 s at the 2 ms timestep
        world.step(0.002)
        q.append(world.data.qpos[qa].copy())
        v.append(world.data.qvel[da].copy())
    yield profile, world, {"before": before, "q": np.array(q), "v": np.array(v)}
    world.close()


def test_full_reach_tilts_the_arm_base_by_the_configured_angle(reached) -> None:
    profile, world, rec = reached
    after = world.truth.T_map_arm_base()
    tilt = _z_tilt_deg(rec["before"][:3, :3], after[:3, :3])
    assert tilt == pytest.approx(TILT_DEG[profile], rel=0.10)
    # it is the mount that tilts, not the chassis on its tyres
    T_bl_ab = inv(world.truth.T_map_base_link()) @ after
    nominal_mount = world.true_robot.T_base_link_arm_base[:3, :3]
    assert _z_tilt_deg(nominal_mount, T_bl_ab[:3, :3]) == pytest.approx(tilt, rel=0.02)
    # and it sags toward the load: the arm base's z axis leans the way the arm reaches
    reach = world.truth.T_map_flange()[:3, 3] - after[:3, 3]
    lean = after[:3, 2] - rec["before"][:3, 2]
    assert lean[:2] @ reach[:2] > 0.9 * np.linalg.norm(lean[:2]) * np.linalg.norm(reach[:2])


def test_tilt_settles_after_the_move(reached) -> None:
    _, _, rec = reached
    q, v = rec["q"], rec["v"]
    final = np.linalg.norm(q[-1])
    err = np.linalg.norm(q - q[-1], axis=1)
    outside = np.nonzero(err > 0.05 * final)[0]
    settle = (outside[-1] + 1) * 0.002 if outside.size else 0.0
    assert settle < 0.3  # s, within 5 % of its final tilt (measured ~0.03-0.12 s)
    assert np.abs(v[300:]).max() < 2e-4  # rad/s, from 0.6 s on: at rest, no ringing


def test_stiffness_follows_from_the_models_gravity_torques() -> None:
    """k = |tau_reach - tau_folded| / tilt: the harsh mount is half as stiff, and the
    folded arm rests level (springref = -tau_folded / k)."""
    world = SimWorld(errors=ErrorModelConfig(profile="reference"))
    scene, robot = world.scene, world.true_robot
    realistic = mount_compliance(scene, robot, 0.05)
    harsh = mount_compliance(scene, robot, 0.1)
    assert mount_compliance(scene, robot, 0.0) is None
    assert realistic is not None and harsh is not None
    assert harsh.stiffness == pytest.approx(realistic.stiffness / 2, rel=1e-9)
    # a UR5e-class arm (18.9 kg with the tool) shifting ~0.3 m of its weight: 50-80 kN m/rad
    assert 3e4 < realistic.stiffness < 1.5e5
    # near critical: damping^2 / (4 k I) = 1 for an inertia I of a few kg m^2 (full reach)
    inertia = realistic.damping**2 / (4 * realistic.stiffness)
    assert 1.0 < inertia < 10.0
    world.close()


@pytest.mark.parametrize("profile", ["reference", "ideal"])
def test_rigid_profiles_keep_the_old_model(profile: str) -> None:
    errors = ErrorModelConfig(profile=profile)
    world = SimWorld(errors=errors)
    assert not {world.model.joint(i).name for i in range(world.model.njnt)} & set(MOUNT_JOINTS)
    pose = world.scene.site("0").pose2d
    old = build_model(world.scene, world.true_robot, pose)
    assert build_model(world.scene, world.true_robot, pose, errors.compliance).xml == old.xml
    world.arm.move_joints(full_reach_configuration(world.nominal), settle=0.5)
    T_bl_ab = inv(world.truth.T_map_base_link()) @ world.truth.T_map_arm_base()
    np.testing.assert_allclose(T_bl_ab, world.true_robot.T_base_link_arm_base, atol=1e-12)
    world.close()


def test_kinematic_modes_and_truth_carry_the_tilt(reached) -> None:
    profile, world, rec = reached
    qa, da = _mount(world)
    settled = rec["q"][-1]
    q_reach = world.arm.joint_positions()
    world.set_arm_configuration(np.asarray(world.nominal.arm.home))
    assert np.degrees(np.abs(world.data.qpos[qa])).max() < 1e-3  # folded: level
    world.set_arm_configuration(q_reach)
    np.testing.assert_allclose(world.data.qpos[qa], settled, rtol=0.02, atol=1e-6)
    assert np.all(world.data.qvel[da] == 0.0)
    np.testing.assert_allclose(world.arm.joint_positions(), q_reach)  # indexing by name
    # the truth includes the tilt: flange and camera ride on the tilted arm base
    t = world.truth
    T_ab = t.T_map_arm_base()
    T_bl_ab = inv(t.T_map_base_link()) @ T_ab
    tilt = _z_tilt_deg(world.true_robot.T_base_link_arm_base[:3, :3], T_bl_ab[:3, :3])
    assert tilt == pytest.approx(TILT_DEG[profile], rel=0.10)
    T_flange = T_ab @ fk(world.true_robot.arm.dh, q_reach)
    np.testing.assert_allclose(t.T_map_flange(), T_flange, atol=1e-9)
    T_cam = T_flange @ world.true_robot.camera.T_flange_camera
    np.testing.assert_allclose(t.T_map_camera(), T_cam, atol=1e-9)
    # kinematic mode (mj_kinematics and mj_camlight: bodies, sites and cameras)
    pose = world.truth.base_pose2d()
    world.set_kinematic_state(pose, np.asarray(world.nominal.arm.home))
    assert np.degrees(np.abs(world.data.qpos[qa])).max() < 1e-3
    world.set_kinematic_state(pose, q_reach)
    np.testing.assert_allclose(world.data.qpos[qa], settled, rtol=0.02, atol=1e-6)
    np.testing.assert_allclose(world.arm.joint_positions(), q_reach)
    T_ab = t.T_map_arm_base()
    T_flange = T_ab @ fk(world.true_robot.arm.dh, q_reach)
    np.testing.assert_allclose(t.T_map_flange(), T_flange, atol=1e-9)
    # the camera follows too (mj_camlight): what the wrist camera renders is this pose
    T_cam = T_flange @ world.true_robot.camera.T_flange_camera
    np.testing.assert_allclose(t.T_map_camera(), T_cam, atol=1e-9)
    T_bl_ab = inv(t.T_map_base_link()) @ T_ab
    tilt = _z_tilt_deg(world.true_robot.T_base_link_arm_base[:3, :3], T_bl_ab[:3, :3])
    assert tilt == pytest.approx(TILT_DEG[profile], rel=0.10)
    world.reset("0")  # a reset rests the mount again (folded arm: level)
    assert np.degrees(np.abs(world.data.qpos[qa])).max() < 1e-3


def test_mount_stays_stable_while_the_base_drives() -> None:
    """Accelerating, turning and braking at the base's limits: the mount deflects (the arm's
    inertia) but stays bounded and comes to rest."""
    world = SimWorld(errors=ErrorModelConfig(profile="harsh"))
    qa, da = _mount(world)
    peak = 0.0
    for v, w, T in [(0.5, 0.0, 1.0), (0.5, 0.8, 1.0), (-0.5, -0.8, 1.0), (0.0, 0.0, 1.0)]:
        world.base.set_velocity(v, w)
        for _ in range(round(T / 0.02)):
            world.step(0.02)
            peak = max(peak, float(np.degrees(np.abs(world.data.qpos[qa])).max()))
    assert 0.0 < peak < 3 * TILT_DEG["harsh"]
    assert np.abs(world.data.qvel[da]).max() < 1e-3
    assert np.degrees(np.abs(world.data.qpos[qa])).max() < 0.01 * TILT_DEG["harsh"] + 1e-3
    world.close()

"""Scene change between teaching and repeating (error model v2): loose desk items are nudged
with the configured probability and size, the change is in the simulator's truth and
survives a reset, the teaching session restores the scene, and fixtures, backboards and the
task's target never move."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from mmpa.backends.twin.error_model import ErrorModelConfig, SceneChange
from mmpa.backends.twin.mjcf import build_model
from mmpa.backends.twin.scene import DeskItem, SceneConfig, load_scene, parse_scene
from mmpa.backends.twin.scene_change import apply_scene_change, draw_scene_change, loose_items
from mmpa.backends.twin.world import SimWorld
from mmpa.core.errors import ConfigError
from mmpa.robot.description import default_robot

LOOSE = {
    "site1_bench": {
        "cup_1",
        "cup_2",
        "site1_bench_small_bottle_5",
        "site1_bench_small_bottle_6",
        "site1_bench_small_bottle_7",
    },
    "site2_bench": {
        "naoh",
        "hcl",
        "phenolphthalein",
        "ferrum",
        "site2_bench_dropper_5",
        "site2_bench_dropper_6",
    },
}


# --- helpers --------------------------------------------------------------------------------
def _truth(world: SimWorld, name: str) -> np.ndarray:
    """TRUE ``T_map_body`` of body ``name`` from the simulator (4x4)."""
    b = world.data.body(name)
    T = np.eye(4)
    T[:3, :3] = b.xmat.reshape(3, 3)
    T[:3, 3] = b.xpos
    return T


def _planar_offset(T_taught: np.ndarray, T_now: np.ndarray) -> np.ndarray:
    """``(dx, dy, dyaw)`` (m, m, rad) that take the taught pose to the current one in map."""
    dR = T_now[:3, :3] @ T_taught[:3, :3].T
    return np.array([*(T_now[:2, 3] - T_taught[:2, 3]), math.atan2(dR[1, 0], dR[0, 0])])


def _taught(world: SimWorld) -> dict[str, np.ndarray]:
    return {it.name: it.T_map for b in loose_items(world.scene).values() for it in b}


def _model_poses(world: SimWorld) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = world.model
    return m.body_pos.copy(), m.body_quat.copy(), m.qpos0.copy()


def _strip_loose(scene: SceneConfig) -> SceneConfig:
    benches = [
        b.model_copy(update={"items": [it.model_copy(update={"loose": False}) for it in b.items]})
        for b in scene.workbenches
    ]
    return scene.model_copy(update={"workbenches": benches})


@pytest.fixture(scope="module")
def scene() -> SceneConfig:
    return load_scene()


@pytest.fixture(scope="module")
def world() -> SimWorld:
    """A realistic-profile world at Site 1 (session 0 drawn at construction)."""
    return SimWorld(errors=ErrorModelConfig(profile="realistic", seed=3), site="1")


# --- the scene file and the model -----------------------------------------------------------
def test_loose_items_per_site(scene):
    got = {b: {it.name for it in items} for b, items in loose_items(scene).items()}
    assert got == LOOSE
    for bench in scene.workbenches:
        for it in bench.items:
            if it.kind in ("backboard", "dot", "valve_container", "logo_tape", "letter_tape"):
                assert not it.loose, (bench.name, it.kind)
            if it.kind in ("waste_container", "test_tube_stand"):
                assert not it.loose  # fixtures of Site 2


@pytest.mark.parametrize("kind", ["dot", "backboard"])
def test_target_and_backboard_cannot_be_loose(kind):
    with pytest.raises(ValueError, match="never moves"):
        DeskItem(kind=kind, xy=(0.0, 0.0), loose=True)
    raw = load_scene().model_dump()
    raw["workbenches"][0]["items"].append({"kind": kind, "xy": [0.0, 0.0], "loose": True})
    with pytest.raises(ConfigError, match="loose"):
        parse_scene(raw)


def test_loose_flags_leave_the_rendered_scene_where_it_was(scene):
    """Loose static items become their own bodies; every geom keeps its place and looks."""
    robot = default_robot()
    before = build_model(_strip_loose(scene), robot).compile()
    after = build_model(scene, robot).compile()
    db, da = mujoco.MjData(before), mujoco.MjData(after)
    mujoco.mj_forward(before, db)
    mujoco.mj_forward(after, da)
    assert after.ngeom == before.ngeom
    for g in range(before.ngeom):
        name = before.geom(g).name
        ga = after.geom(name).id
        assert da.geom_xpos[ga] == pytest.approx(db.geom_xpos[g], abs=1e-8), name
        assert da.geom_xmat[ga] == pytest.approx(db.geom_xmat[g], abs=1e-8), name
        for attr in ("geom_size", "geom_rgba", "geom_matid", "geom_group", "geom_contype"):
            assert np.array_equal(getattr(after, attr)[ga], getattr(before, attr)[g]), (name, attr)
    for names in LOOSE.values():
        for n in names:
            body = after.body(n)
            assert body.parentid[0] == 0
            if n.startswith("cup"):
                assert after.joint(f"{n}_free").type[0] == mujoco.mjtJoint.mjJNT_FREE
            else:
                assert body.jntnum[0] == 0  # static: moved only by the scene change
                assert after.geom_group[after.body_geomadr[body.id]] == 0


def test_loose_static_items_are_their_own_bodies(scene):
    n_static = sum(it.loose and not it.free for b in scene.workbenches for it in b.items)
    assert n_static == 9  # 3 small bottles, 4 reagent bottles, 2 droppers
    model = build_model(scene, default_robot()).compile()
    assert model.nbody == build_model(_strip_loose(scene), default_robot()).compile().nbody + 9


# --- the pure draw --------------------------------------------------------------------------
@pytest.mark.parametrize("profile", ["realistic", "harsh"])
def test_draw_has_the_configured_probability_count_and_size(profile):
    cfg = ErrorModelConfig(profile=profile).scene_change
    names = [f"item{i}" for i in range(5)]
    rng = np.random.default_rng(1)
    n = 20000
    draws = [draw_scene_change(names, rng, cfg) for _ in range(n)]
    changed = [d for d in draws if d]
    # binomial SD sqrt(p (1 - p) / n) ~ 0.0035: 5 SD
    assert len(changed) / n == pytest.approx(cfg.probability, abs=0.018)
    counts = np.bincount([len(d) for d in changed], minlength=cfg.max_objects + 1)
    assert counts[0] == 0 and len(counts) == cfg.max_objects + 1
    assert counts[1:] / len(changed) == pytest.approx(1 / cfg.max_objects, abs=0.03)
    v = np.array([x for d in changed for x in d.values()])
    picked = np.unique([k for d in changed for k in d], return_counts=True)[1]
    assert len(picked) == len(names) and picked.min() > 0.8 * picked.mean()  # uniform pick
    assert np.all(np.abs(v.mean(axis=0)) < 4 * v.std(axis=0) / math.sqrt(len(v)))  # zero mean
    sd = v.std(axis=0)
    assert sd[0] == pytest.approx(cfg.trans_sigma, rel=0.04)
    assert sd[1] == pytest.approx(cfg.trans_sigma, rel=0.04)
    assert np.rad2deg(sd[2]) == pytest.approx(cfg.rot_sigma_deg, rel=0.04)


def test_draw_limits_and_consumption():
    names = ["a", "b"]
    always = SceneChange(probability=1.0, max_objects=5)
    counts = {len(draw_scene_change(names, np.random.default_rng(s), always)) for s in range(200)}
    assert counts == {1, 2}  # never more than there are loose items, never none
    assert draw_scene_change([], np.random.default_rng(0), always) == {}
    # the same draws are consumed whatever the outcome: benches drawn in turn are independent
    ra, rb = np.random.default_rng(7), np.random.default_rng(7)
    draw_scene_change(names, ra, always)
    draw_scene_change(names, rb, SceneChange(probability=0.0, max_objects=5))
    assert ra.random() == rb.random()


# --- in the simulator -----------------------------------------------------------------------
def test_fraction_of_repeats_with_a_change_per_bench(world):
    cfg = world.error_model.config.scene_change
    n = 400
    hits = {b: 0 for b in LOOSE}
    for k in range(1, n + 1):
        moved = apply_scene_change(world, k)
        for b, names in LOOSE.items():
            mb = set(moved) & names
            hits[b] += bool(mb)
            assert len(mb) <= cfg.max_objects
    apply_scene_change(world, 0)
    for b in LOOSE:  # binomial SD ~ 0.023: 3.5 SD
        assert hits[b] / n == pytest.approx(cfg.probability, abs=0.08), b


def _session_moving(world: SimWorld) -> tuple[int, dict]:
    """The first repeat session that nudges a free cup and a static item (deterministic)."""
    for k in range(1, 200):
        moved = apply_scene_change(world, k)
        if any(n.startswith("cup") for n in moved) and any(not n.startswith("cup") for n in moved):
            return k, moved
    raise AssertionError("no session moved both a cup and a static item")


def test_truth_moves_by_exactly_the_returned_offset_and_survives_reset(world):
    taught = _taught(world)
    k, moved = _session_moving(world)
    assert apply_scene_change(world, k) == moved  # a session's change is reproducible

    def check(tol_xy: float, tol_yaw: float) -> None:
        for name, T0 in taught.items():
            off = _planar_offset(T0, _truth(world, name))
            want = np.array(moved.get(name, (0.0, 0.0, 0.0)))
            assert off[:2] == pytest.approx(want[:2], abs=tol_xy), name
            assert off[2] == pytest.approx(want[2], abs=tol_yaw), name

    check(1e-9, 1e-9)
    world.reset("1", settle=0.0)  # mj_resetData: qpos <- model.qpos0
    check(1e-9, 1e-9)
    world.reset("1")  # and the physics settles: a cup resting on the desk does not creep
    check(2e-6, 1e-5)
    # the nudges are the configured size: mm and degrees, not metres
    for dx, dy, dyaw in moved.values():
        assert math.hypot(dx, dy) < 0.02 and abs(dyaw) < math.radians(10)
    apply_scene_change(world, 0)


def test_teaching_session_restores_the_scene_exactly(world, scene):
    fresh = SimWorld(errors=ErrorModelConfig(profile="realistic", seed=3), site="1")
    _, moved = _session_moving(world)
    assert moved
    assert apply_scene_change(world, 0) == {}
    taught = _taught(world)
    for name, T0 in taught.items():
        assert _truth(world, name) == pytest.approx(T0, abs=1e-12), name
    for a, b in zip(_model_poses(world), _model_poses(fresh), strict=True):
        assert np.array_equal(a, b)
    # ... which is the model the scene file builds (its XML keeps 9 significant digits)
    built = build_model(scene, default_robot()).compile()
    for names in LOOSE.values():
        for n in names:
            b = built.body(n).id
            if built.body_jntnum[b]:
                qa = built.jnt_qposadr[built.body_jntadr[b]]
                assert world.model.qpos0[qa : qa + 7] == pytest.approx(
                    built.qpos0[qa : qa + 7], abs=1e-8
                )
            else:
                assert world.model.body_pos[b] == pytest.approx(built.body_pos[b], abs=1e-8)
                assert world.model.body_quat[b] == pytest.approx(built.body_quat[b], abs=1e-8)
    world.reset("1", settle=0.0)
    fresh.reset("1", settle=0.0)
    assert world.data.qpos == pytest.approx(fresh.data.qpos, abs=1e-8)


def test_fixtures_backboards_and_the_target_never_move():
    """Every item is nudged in every session (p = 1, no limit on the count, harsh sizes):
    still every geom outside the loose items' bodies stays exactly where it was."""
    errors = ErrorModelConfig(profile="harsh", scene_change={"probability": 1.0, "max_objects": 20})
    w = SimWorld(errors=errors, site="1")
    loose_bodies = {w.model.body(n).id for names in LOOSE.values() for n in names}
    fixed = [g for g in range(w.model.ngeom) if w.model.geom_bodyid[g] not in loose_bodies]
    for name in ("site1_dot_disc", "site2_dot_disc"):
        assert w.model.geom(name).id in fixed
    for bench in ("site1_bench", "site2_bench"):
        assert w.model.geom(f"{bench}_backboard_0_board").id in fixed
    xpos, xmat = w.data.geom_xpos[fixed].copy(), w.data.geom_xmat[fixed].copy()
    seen: set[str] = set()
    for k in range(1, 6):
        moved = apply_scene_change(w, k)
        seen |= set(moved)
        assert np.array_equal(w.data.geom_xpos[fixed], xpos)
        assert np.array_equal(w.data.geom_xmat[fixed], xmat)
        for name, T0 in _taught(w).items():
            if name in moved:
                assert not np.allclose(_truth(w, name), T0, atol=1e-6), name
    assert seen == set().union(*LOOSE.values())


@pytest.mark.parametrize("profile", ["reference", "ideal"])
def test_reference_and_ideal_never_change_the_scene(profile):
    w = SimWorld(errors=ErrorModelConfig(profile=profile), site="2")
    assert apply_scene_change(w, 0) == {}  # the cups back from resting 0.1 mm into the desk
    poses = _model_poses(w)
    xpos = w.data.xpos.copy()
    for k in range(1, 60):
        assert apply_scene_change(w, k) == {}
        for a, b in zip(_model_poses(w), poses, strict=True):
            assert np.array_equal(a, b)
        assert np.array_equal(w.data.xpos, xpos)

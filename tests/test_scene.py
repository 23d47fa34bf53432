"""The scene file and the MJCF generator: the default world matches the papers, malformed
files fail naming the field, and the generated model honours the naming contract of
``mmpa.backends.twin.mjcf``."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import mujoco
import numpy as np
import pytest
import yaml

from mmpa.backends.twin.mjcf import GROUP, build_model, desk_item_pose
from mmpa.backends.twin.scene import default_scene_path, load_scene
from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.robot.description import default_robot

# paper 000 §4.2: park poses as position and unit quaternion (x, y, z, w)
PAPER_SITES = {
    "0": ((-0.3498, 0.9449, 0.0), (0.0, 0.0, -0.5367, 0.8437)),
    "1": ((2.0415, -1.375, 0.0), (0.0, 0.0, -0.2970, 0.9548)),
    "2": ((0.1251, -0.7638, 0.0), (0.0, 0.0, -0.8785, 0.4776)),
}
# paper 002 Table 1: fiducial arrangement (m)
PAPER_FIDUCIALS = [
    (0.94, 0.34),
    (1.14, 0.32),
    (1.37, 0.37),
    (1.57, 0.32),
    (1.82, 0.34),
    (2.00, 0.32),
]


def _quat_yaw(q: tuple[float, float, float, float]) -> float:
    """Heading of a z-rotation quaternion (x, y, z, w), computed independently of mmpa."""
    return 2.0 * math.atan2(q[2], q[3])


@pytest.fixture(scope="module")
def scene():
    return load_scene()


@pytest.fixture(scope="module")
def raw() -> dict:
    return yaml.safe_load(default_scene_path().read_text())


@pytest.fixture(scope="module")
def built(scene):
    return build_model(scene, default_robot())


@pytest.fixture(scope="module")
def compiled(built):
    model = built.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


# --- the default scene ----------------------------------------------------------------------


def test_default_scene_loads(scene):
    assert scene.name == "default"
    assert set(scene.sites) == {"0", "1", "2", "2'"}
    assert scene.site("1").workbench == "site1_bench"
    assert scene.workbench("site1_bench").name == "site1_bench"
    assert scene.site(1) is scene.site("1")  # ints are accepted as site names


@pytest.mark.parametrize("name", ["0", "1", "2"])
def test_site_poses_equal_paper_000(scene, name):
    (x, y, z), q = PAPER_SITES[name]
    site = scene.site(name)
    assert site.position == pytest.approx((x, y, z), abs=1e-12)
    pose = site.pose2d
    assert pose[:2] == pytest.approx((x, y), abs=1e-12)
    assert pose[2] == pytest.approx(_quat_yaw(q), abs=1e-6)


def test_site1_heading_is_minus_34_56_deg(scene):
    assert math.degrees(scene.site("1").yaw) == pytest.approx(-34.56, abs=0.01)


def test_site2_prime_is_site2_with_the_speed_bump(scene):
    s2, s2p = scene.site("2"), scene.site("2'")
    assert np.array_equal(s2.pose2d, s2p.pose2d)
    assert s2p.speed_bump and not s2.speed_bump
    sb = scene.speed_bump
    assert (sb.length, sb.width, sb.height) == pytest.approx((1.0, 0.35, 0.05))  # DESIGN.md
    # the bump lies under Site 2's footprint: its center within 0.3 m of the park position
    assert np.hypot(*(np.array(sb.center) - s2.pose2d[:2])) < 0.3


def test_nine_reflectors(scene):
    P = scene.reflector_positions()
    assert P.shape == (9, 2)
    # all distinct (pairwise > 0.5 m apart), so triangle matching has something to match
    d = np.linalg.norm(P[:, None] - P[None], axis=-1) + np.eye(9) * 1e9
    assert d.min() > 0.5


def test_fiducials_equal_paper_002_table_1(scene):
    fa = scene.fiducial_artifact
    assert fa is not None
    assert np.array(fa.fiducials) == pytest.approx(np.array(PAPER_FIDUCIALS), abs=1e-12)
    assert fa.tube_inner_diameter == pytest.approx(0.0127)
    assert fa.tube_height == pytest.approx(0.0667)


def test_unknown_site_lists_the_valid_names(scene):
    with pytest.raises(UnknownNameError) as e:
        scene.site("9")
    msg = str(e.value)
    assert "'9'" in msg
    for valid in ("0", "1", "2", "2'"):
        assert valid in e.value.valid
    assert "0, 1, 2, 2'" in msg
    with pytest.raises(UnknownNameError, match="site1_bench"):
        scene.workbench("nope")


# --- malformed scene files ------------------------------------------------------------------


def _write(tmp_path: Path, data: object) -> Path:
    p = tmp_path / "scene.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def _drop_reflectors(d: dict) -> None:
    del d["reflectors"]


def _string_wall_coordinate(d: dict) -> None:
    d["walls"][0]["start"] = ["left", 1.0]


def _quaternion_norm_two(d: dict) -> None:
    d["sites"]["1"]["orientation_xyzw"] = [0.0, 0.0, 0.0, 2.0]


def _item_off_desk(d: dict) -> None:
    d["workbenches"][0]["items"][3]["xy"] = [2.0, 0.0]


def _missing_workbench(d: dict) -> None:
    d["sites"]["1"]["workbench"] = "no_such_bench"


def _two_reflectors(d: dict) -> None:
    d["reflectors"]["positions"] = d["reflectors"]["positions"][:2]


def _unknown_field(d: dict) -> None:
    d["reflector"] = {"positions": []}


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (_drop_reflectors, ["reflectors", "Field required"]),
        (_string_wall_coordinate, ["walls.0.start"]),
        (_quaternion_norm_two, ["sites.1.orientation_xyzw", "unit length", "2.000"]),
        (_item_off_desk, ["workbenches.0", "item 3", "off"]),
        (_missing_workbench, ["no_such_bench", "site '1'", "workbench"]),
        (_two_reflectors, ["reflectors.positions", "at least 3"]),
        (_unknown_field, ["reflector", "Extra inputs"]),
    ],
)
def test_malformed_scene_names_the_field(tmp_path, raw, mutate, expected):
    data = copy.deepcopy(raw)
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as e:
        load_scene(path)
    msg = str(e.value)
    assert str(path) in msg
    for part in expected:
        assert part in msg, f"{part!r} not in {msg!r}"


# issue 22: bad numbers that reached MuJoCo (a crash inside it, or a body silently at NaN)
# before; each is refused naming the field
def _set(path: str, value: object):
    def mutate(d: dict) -> None:
        *head, last = path.split(".")
        node = d
        for k in head:
            node = node[int(k)] if isinstance(node, list) else node[k]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value

    mutate.__name__ = f"{path}={value!r}"
    return mutate


def _same_reflector_twice(d: dict) -> None:
    d["reflectors"]["positions"].append(list(d["reflectors"]["positions"][4]))


def _overlapping_reflectors(d: dict) -> None:
    x, y = d["reflectors"]["positions"][0]
    d["reflectors"]["positions"].append([x + 0.05, y])  # radius 0.04: centres need 0.08 m


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (_set("walls.0.start", [float("nan"), 1.0]), ["walls.0.start.0", "finite"]),
        (_set("walls.2.end", [1.0, float("inf")]), ["walls.2.end.1", "finite"]),
        (_set("walls.1.thickness", 0.0), ["walls.1.thickness", "greater than 0"]),
        (_set("walls.1.height", -1.0), ["walls.1.height", "greater than 0"]),
        (_set("floor_size", [0.0, 8.0]), ["floor_size", "> 0 m"]),
        (_set("reflectors.positions.3", [float("nan"), 0.0]), ["reflectors.positions.3.0"]),
        (_set("reflectors.radius", float("nan")), ["reflectors.radius", "finite"]),
        (_set("reflectors.radius", 0.0), ["reflectors.radius", "greater than 0"]),
        (_same_reflector_twice, ["reflectors", "reflector 9", "same position as reflector 4"]),
        (_overlapping_reflectors, ["reflectors", "reflector 9", "overlapping reflector 0"]),
        (_set("workbenches.0.size", [1.2, -0.6, 0.72]), ["workbenches.0.size", "> 0 m"]),
        (_set("workbenches.0.top_color", [1.2, 0.5, 0.5]), ["workbenches.0.top_color", "[0, 1]"]),
        (_set("workbenches.0.items.0.color", [0.5, -0.1, 0.5]), ["items.0.color", "[0, 1]"]),
        (_set("workbenches.0.items.0.size", [0.0, 0.1]), ["items.0.size", "> 0 m"]),
        (_set("workbenches.0.items.0.xy", [float("nan"), 0.0]), ["items.0.xy.0", "finite"]),
        (_set("grasp_objects.0.color", [0.2, 0.2, 255.0]), ["grasp_objects.0.color", "[0, 1]"]),
        (_set("grasp_objects.0.size", [-0.02]), ["grasp_objects.0.size", "> 0 m"]),
        (_set("grasp_objects.0.position", [0.0, float("nan"), 0.8]), ["grasp_objects.0.position"]),
        (_set("sites.1.position", [float("nan"), 0.0, 0.0]), ["sites.1.position.0", "finite"]),
    ],
    ids=lambda v: getattr(v, "__name__", None) if callable(v) else "",
)
def test_bad_numbers_are_refused_before_mujoco(tmp_path, raw, mutate, expected):
    data = copy.deepcopy(raw)
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as e:
        load_scene(path)
    msg = str(e.value)
    assert str(path) in msg
    for part in expected:
        assert part in msg, f"{part!r} not in {msg!r}"


def test_grasp_object_size_must_fit_its_kind(tmp_path, raw):
    data = copy.deepcopy(raw)
    obj = data["grasp_objects"][0]
    obj["size"] = [0.02] if obj["kind"] in ("bottle", "cup", "stick") else [0.02, 0.05]
    with pytest.raises(ConfigError, match=r"grasp_objects\.0: .*size is"):
        load_scene(_write(tmp_path, data))


def test_scene_alias_bomb_is_refused(tmp_path):
    lines = ["a: &a [1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]"]
    for k in "bcdefghij":
        prev = chr(ord(k) - 1)
        lines.append(f"{k}: &{k} [*{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}]")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\nname: bomb\n")
    with pytest.raises(ConfigError, match=r"alias \*a is not accepted") as e:
        load_scene(p)
    assert str(p) in str(e.value)


def test_unmodified_copy_loads(tmp_path, raw):
    """Control for the malformed cases: the dumped default document itself is fine."""
    scene = load_scene(_write(tmp_path, raw))
    assert scene == load_scene()


def test_invalid_yaml_syntax(tmp_path):
    p = tmp_path / "broken.yaml"
    p.write_text("name: broken\nwalls: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_scene(p)


@pytest.mark.parametrize("text", ["- a\n- b\n", "just a string\n", ""])
def test_non_mapping_document(tmp_path, text):
    p = tmp_path / "list.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match="must be a YAML mapping"):
        load_scene(p)


def test_missing_file(tmp_path):
    p = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=r"cannot read scene file .*nope\.yaml"):
        load_scene(p)


# --- MJCF generation ------------------------------------------------------------------------

CONTRACT = {
    mujoco.mjtObj.mjOBJ_BODY: [
        "base_link",
        "wheel_left",
        "wheel_right",
        "arm_base",
        *[f"link{i}" for i in range(1, 7)],
        "flange",
        "finger_left",
        "finger_right",
        "speed_bump",
        "cube",
        "cup_1",
        "cup_2",
    ],
    mujoco.mjtObj.mjOBJ_ACTUATOR: [
        "wheel_left_vel",
        "wheel_right_vel",
        *[f"arm{i}" for i in range(1, 7)],
        "gripper",
    ],
    mujoco.mjtObj.mjOBJ_CAMERA: ["wrist_camera"],
    mujoco.mjtObj.mjOBJ_SITE: ["laser", "photosensor", "tcp"],
}
JOINTS = {
    "base_free": mujoco.mjtJoint.mjJNT_FREE,
    "wheel_left_joint": mujoco.mjtJoint.mjJNT_HINGE,
    "wheel_right_joint": mujoco.mjtJoint.mjJNT_HINGE,
    **{f"joint{i}": mujoco.mjtJoint.mjJNT_HINGE for i in range(1, 7)},
    "finger_left_joint": mujoco.mjtJoint.mjJNT_SLIDE,
    "finger_right_joint": mujoco.mjtJoint.mjJNT_SLIDE,
    "cube_free": mujoco.mjtJoint.mjJNT_FREE,
}


def test_model_compiles_with_the_contract_names(compiled):
    model, _ = compiled
    for obj, names in CONTRACT.items():
        for name in names:
            assert mujoco.mj_name2id(model, obj, name) >= 0, f"{obj.name} {name!r} missing"
    for name, jtype in JOINTS.items():
        jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)
        assert jid >= 0, f"joint {name!r} missing"
        assert model.jnt_type[jid] == jtype, name
    # actuators drive the joints their names say
    for i in range(1, 7):
        assert model.actuator(f"arm{i}").trnid[0] == model.joint(f"joint{i}").id
    assert model.actuator("gripper").trnid[0] == model.joint("finger_left_joint").id
    assert model.actuator("wheel_left_vel").trnid[0] == model.joint("wheel_left_joint").id
    # the kinematic chain: link{i} parent is the previous DH frame, flange ends it
    assert model.body(model.body("flange").parentid[0]).name == "link6"
    assert model.body(model.body("arm_base").parentid[0]).name == "base_link"
    assert model.body(model.body("finger_left").parentid[0]).name == "flange"


def test_reflector_geoms_sit_at_the_scene_positions(scene, compiled):
    model, data = compiled
    P = scene.reflector_positions()
    for i, (x, y) in enumerate(P):
        g = data.geom(f"reflector_{i}")
        assert g.xpos == pytest.approx((x, y, scene.reflectors.height / 2), abs=1e-9)
        assert model.geom(f"reflector_{i}").group[0] == GROUP["reflectors"]
    with pytest.raises(KeyError):
        model.geom(f"reflector_{len(P)}")


def test_fiducials_sit_at_table_1_in_the_artifact_frame(scene, compiled):
    model, data = compiled
    fa = scene.fiducial_artifact
    c, s = math.cos(math.radians(fa.yaw_deg)), math.sin(math.radians(fa.yaw_deg))
    for i, (fx, fy) in enumerate(PAPER_FIDUCIALS):
        want = (fa.origin[0] + c * fx - s * fy, fa.origin[1] + s * fx + c * fy)
        assert data.geom(f"fiducial_{i}_reflector").xpos[:2] == pytest.approx(want, abs=1e-9)
        assert model.geom(f"fiducial_{i}_wall_23").group[0] == GROUP["reflectors"]


def test_robot_geoms_never_collide_with_each_other(compiled):
    model, _ = compiled
    root = model.body("base_link").id
    robot = [g for g in range(model.ngeom) if model.body_rootid[model.geom_bodyid[g]] == root]
    assert len(robot) > 10
    ct, ca = model.geom_contype[robot], model.geom_conaffinity[robot]
    pair = (ct[:, None] & ca[None, :]) | (ct[None, :] & ca[:, None])
    assert not pair.any()
    # ... but the robot's collision geoms do collide with the world (floor is group 0)
    floor = model.geom("floor").id
    coll = [g for g in robot if model.geom_group[g] == GROUP["robot"]]
    assert coll
    for g in coll:
        assert (model.geom_contype[g] & model.geom_conaffinity[floor]) or (
            model.geom_contype[floor] & model.geom_conaffinity[g]
        )


def test_free_desk_items_and_grasp_objects(scene, compiled):
    model, data = compiled
    bench = scene.workbench("site1_bench")
    for item in bench.items:
        if item.free:
            assert data.body(item.name).xpos == pytest.approx(
                desk_item_pose(bench, item)[:3, 3], abs=1e-6
            )
            assert model.joint(f"{item.name}_free").type[0] == mujoco.mjtJoint.mjJNT_FREE
    for obj in scene.grasp_objects:
        assert data.body(obj.name).xpos == pytest.approx(obj.position, abs=1e-9)
        assert model.geom(f"{obj.name}_geom").group[0] == GROUP["objects"]
    # the cube is the 50 mm cube of paper 001 (half size 25 mm)
    assert model.geom("cube_geom").size == pytest.approx((0.025, 0.025, 0.025))


def test_speed_bump_is_parked_below_the_floor(scene, compiled):
    _, data = compiled
    sb = scene.speed_bump
    assert data.body("speed_bump").xpos == pytest.approx((*sb.center, -1.0), abs=1e-9)


def test_robot_starts_where_asked(scene):
    model = build_model(scene, default_robot(), np.array([1.0, -0.5, 0.7])).compile()
    assert model.body("base_link").pos[:2] == pytest.approx((1.0, -0.5))
    quat = model.body("base_link").quat
    assert 2 * math.atan2(quat[3], quat[0]) == pytest.approx(0.7, abs=1e-9)


def test_generation_is_deterministic_per_seed(scene, built):
    again = build_model(scene, default_robot())
    assert again.xml == built.xml
    assert again.assets.keys() == built.assets.keys()
    assert len(built.assets) >= 5
    for name, png in built.assets.items():
        assert png.startswith(b"\x89PNG"), name
        assert again.assets[name] == png, name
    other = build_model(scene.model_copy(update={"seed": scene.seed + 1}), default_robot())
    assert other.assets.keys() == built.assets.keys()
    differ = [n for n in built.assets if other.assets[n] != built.assets[n]]
    assert "floor.png" in differ
    assert len(differ) >= len(built.assets) // 2

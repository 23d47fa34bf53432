"""Reflector map files: round trip, strict validation (file + entry index in every error),
alias bombs refused, the same entries embedded in / referenced by a map_server map YAML."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.maps.map_server import load_map, save_map, write_pgm
from mmpa.maps.occupancy import OccupancyGrid
from mmpa.maps.reflector_map import (
    ReflectorMap,
    load_reflector_map,
    save_reflector_map,
)


def _rm() -> ReflectorMap:
    rng = np.random.default_rng(3)
    xy = rng.uniform(-20, 20, (7, 2))  # full-precision floats: must come back bit for bit
    return ReflectorMap(np.array([4, 0, 9, 1, 2, 3, 77]), xy, rng.uniform(0.02, 0.06, 7))


def test_round_trip_is_exact(tmp_path: Path) -> None:
    rm = _rm()
    p = save_reflector_map(rm, tmp_path / "sub" / "site.reflectors.yaml")
    doc = yaml.safe_load(p.read_text())
    assert doc["frame_id"] == "map" and len(doc["reflectors"]) == 7
    assert doc["reflectors"][6] == {
        "id": 77,
        "x": float(rm.xy[6, 0]),
        "y": float(rm.xy[6, 1]),
        "radius": float(rm.radius[6]),
    }
    rm2 = load_reflector_map(p)
    np.testing.assert_array_equal(rm2.ids, rm.ids)
    np.testing.assert_array_equal(rm2.xy, rm.xy)
    np.testing.assert_array_equal(rm2.radius, rm.radius)
    assert rm2.ids.dtype == np.int64 and rm2.xy.shape == (7, 2) and len(rm2) == 7
    with pytest.raises(ValueError, match="read-only"):
        rm2.xy[0, 0] = 1.0


def test_hand_written_file(tmp_path: Path) -> None:
    p = tmp_path / "r.yaml"
    p.write_text(
        "# surveyed 2026-11-24\nreflectors:\n"
        "  - {id: 1, x: 1.25, y: -0.4, radius: 0.04}\n"
        "  - id: 2\n    x: 3\n    y: 2.1\n    radius: 0.05\n"
    )
    rm = load_reflector_map(p)
    assert rm.ids.tolist() == [1, 2] and rm.frame_id == "map"
    np.testing.assert_array_equal(rm.xy, [[1.25, -0.4], [3.0, 2.1]])
    np.testing.assert_array_equal(rm.radius, [0.04, 0.05])


_OK = "{id: 0, x: 0.0, y: 0.0, radius: 0.04}"


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("reflectors: []", "at least one reflector"),
        ("frame_id: map\n", "lacks the required field 'reflectors'"),
        ("- 1\n- 2\n", "must be a mapping with a 'reflectors' list"),
        ("reflectors: [1.0, 2.0, 3.0, 4.0]", r"reflectors\[0\]: must be a mapping"),
        ("reflectors: {x: 1}", "must be a list of"),
        (f"reflectors: [{_OK}, {{id: 1, x: .nan, y: 0, radius: 0.04}}]", r"\[1\].x: must be fin"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: .inf, radius: 0.04}}]", r"\[1\].y: must be fin"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: 0, radius: -0.04}}]", r"\[1\].radius: must be >"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: 0, radius: 0}}]", r"\[1\].radius: must be >"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: 0, radius: .nan}}]", r"\[1\].radius: must be f"),
        (f"reflectors: [{_OK}, {{id: 1, x: '1', y: 0, radius: 0.04}}]", r"\[1\].x: must be a num"),
        (f"reflectors: [{_OK}, {{id: 1.5, x: 1, y: 0, radius: 0.04}}]", r"\[1\].id: must be an in"),
        (f"reflectors: [{_OK}, {{id: true, x: 1, y: 0, radius: 0.04}}]", r"\[1\].id: must be an i"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: 0}}]", r"\[1\]: .*missing radius"),
        (f"reflectors: [{_OK}, {{id: 1, x: 1, y: 0, r: 1, radius: 1}}]", r"\[1\]: .*unknown r"),
        (f"reflectors: [{_OK}, {{id: 0, x: 1, y: 0, radius: 0.04}}]", r"\[1\]: id 0 is taken"),
        (f"reflectors: [{_OK}, {{id: 1, x: 0.0000001, y: 0, radius: 0.04}}]", r"\[1\]: .*duplic"),
        (f"frame_id: odom\nreflectors: [{_OK}]", "frame_id: reflector maps are in frame 'map'"),
        (f"reflector: [{_OK}]", "unknown key"),
        ("reflectors: [{id: 0, x: 0, y: 0, radius: 0.04}", "not valid YAML"),
    ],
)
def test_bad_reflector_maps_name_file_and_entry(tmp_path: Path, body: str, match: str) -> None:
    p = tmp_path / "bad.reflectors.yaml"
    p.write_text(body + "\n")
    with pytest.raises(ConfigError, match=match) as e:
        load_reflector_map(p)
    assert str(p) in str(e.value)


def test_alias_bomb_in_reflector_list_is_refused(tmp_path: Path) -> None:
    lines = ["a: &a {id: 0, x: 0.0, y: 0.0, radius: 0.04}"]
    for k in "bcdefghi":
        prev = chr(ord(k) - 1)
        lines.append(f"{k}: &{k} [*{prev}, *{prev}, *{prev}, *{prev}, *{prev}, *{prev}]")
    lines.append("reflectors: *i")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=r"alias \*a is not accepted") as e:
        load_reflector_map(p)
    assert str(p) in str(e.value)


def test_constructor_checks() -> None:
    with pytest.raises(InvalidInputError, match="disagree"):
        ReflectorMap(np.array([0, 1]), np.zeros((4,)), np.full(2, 0.04))
    with pytest.raises(InvalidInputError, match="entry 1: id 0 is taken"):
        ReflectorMap(np.array([0, 0]), np.array([[0.0, 0], [1, 1]]), np.full(2, 0.04))
    with pytest.raises(InvalidInputError, match="entry 0: radius"):
        ReflectorMap(np.array([0]), np.array([[0.0, 0]]), np.array([-1.0]))
    with pytest.raises(InvalidInputError, match="at least one"):
        ReflectorMap(np.zeros(0, int), np.zeros((0, 2)), np.zeros(0))
    with pytest.raises(InvalidInputError, match="integer"):
        ReflectorMap(np.array([0.5]), np.array([[0.0, 0]]), np.array([0.04]))


def _map_yaml(tmp_path: Path, reflectors: str) -> Path:
    write_pgm(tmp_path / "m.pgm", np.full((2, 2), 254, np.uint8))
    p = tmp_path / "m.yaml"
    p.write_text(
        "image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
        f"occupied_thresh: 0.65\nfree_thresh: 0.196\nreflectors: {reflectors}\n"
    )
    return p


def test_map_yaml_embeds_or_references_reflector_entries(tmp_path: Path) -> None:
    rm = ReflectorMap(
        np.array([5, 6, 7]), np.array([[1.0, 2.0], [3.0, -4.0], [0.5, 0.25]]), [0.04] * 3
    )
    save_reflector_map(rm, tmp_path / "site.reflectors.yaml")
    g = load_map(_map_yaml(tmp_path, "site.reflectors.yaml"))  # a file next to the map YAML
    np.testing.assert_array_equal(g.reflectors, rm.xy)
    assert g.reflector_radius == 0.04
    g = load_map(_map_yaml(tmp_path, yaml.safe_dump(rm.entries(), default_flow_style=True)))
    np.testing.assert_array_equal(g.reflectors, rm.xy)
    assert g.reflector_radius == 0.04
    assert len(load_map(_map_yaml(tmp_path, "[]")).reflectors) == 0  # a map may have none
    # the localizers use one radius: differing radii are refused, naming the entries' source
    mixed = "[{id: 0, x: 0, y: 0, radius: 0.04}, {id: 1, x: 1, y: 0, radius: 0.05}]"
    with pytest.raises(ConfigError, match=r"one reflector radius; the entries give 0\.04, 0\.05"):
        load_map(_map_yaml(tmp_path, mixed))
    with pytest.raises(ConfigError, match=r"cannot read .*nothere.yaml"):
        load_map(_map_yaml(tmp_path, "nothere.yaml"))
    (tmp_path / "bad.yaml").write_text("reflectors: [{id: 0, x: 0, y: 0, radius: -1}]\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: reflectors\[0\].radius"):
        load_map(_map_yaml(tmp_path, "bad.yaml"))


def test_save_map_writes_reflector_entries(tmp_path: Path) -> None:
    refl = np.array([[0.1, 0.2], [0.3, 0.4]])
    g = OccupancyGrid(np.zeros((2, 3)), 0.1, (0.0, 0.0, 0.0), refl, 0.04)
    meta = yaml.safe_load(save_map(g, tmp_path / "m.yaml").read_text())
    assert meta["reflectors"] == [
        {"id": 0, "x": 0.1, "y": 0.2, "radius": 0.04},
        {"id": 1, "x": 0.3, "y": 0.4, "radius": 0.04},
    ]
    g2 = load_map(tmp_path / "m.yaml")
    np.testing.assert_array_equal(g2.reflectors, refl)
    assert g2.reflector_radius == 0.04
    # radius not known (0): the earlier {positions, radius} form, which still loads
    g0 = OccupancyGrid(np.zeros((2, 3)), 0.1, (0.0, 0.0, 0.0), refl, 0.0)
    meta = yaml.safe_load(save_map(g0, tmp_path / "z.yaml").read_text())
    assert meta["reflectors"] == {"radius": 0.0, "positions": [[0.1, 0.2], [0.3, 0.4]]}
    g3 = load_map(tmp_path / "z.yaml")
    np.testing.assert_array_equal(g3.reflectors, refl)
    assert g3.reflector_radius == 0.0

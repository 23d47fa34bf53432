"""Maps: map_server YAML + PGM round trip, ROS row order, bad input, twin map vs lidar truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mmpa.errors import ConfigError, InvalidInputError
from mmpa.localization.maps import Box2D, OccupancyGrid, load_map, rasterize, save_map, write_pgm


def _grid() -> OccupancyGrid:
    data = np.zeros((4, 6), dtype=np.int8)
    data[0, 0] = 100  # bottom-left cell (ROS row 0 = smallest y)
    data[3, 5] = -1
    return OccupancyGrid(data, 0.1, (-1.0, 2.0, 0.0), np.array([[0.1, 0.2], [0.3, 0.4]]), 0.04)


def test_round_trip_and_row_flip(tmp_path: Path) -> None:
    g = _grid()
    y = save_map(g, tmp_path / "m.yaml")
    img = (tmp_path / "m.pgm").read_bytes()
    assert img.startswith(b"P5\n6 4\n255\n")
    pix = np.frombuffer(img[-24:], dtype=np.uint8).reshape(4, 6)
    # image row 0 is the TOP of the map: the occupied bottom-left cell is the last image row
    assert pix[3, 0] == 0 and pix[0, 5] == 205 and pix[1, 1] == 254
    g2 = load_map(y)
    np.testing.assert_array_equal(g2.data, g.data)
    assert g2.resolution == 0.1 and g2.origin == (-1.0, 2.0, 0.0)
    np.testing.assert_allclose(g2.reflectors, g.reflectors)
    assert g2.reflector_radius == 0.04


def test_gmapping_style_map_loads(tmp_path: Path) -> None:
    # as map_saver writes it: no reflectors key, ASCII header comment, scale mode values
    img = np.full((3, 3), 254, dtype=np.uint8)
    img[0, 0] = 0
    img[1, 1] = 205
    write_pgm(tmp_path / "g.pgm", img)
    raw = (tmp_path / "g.pgm").read_bytes().replace(b"P5\n", b"P5\n# CREATOR: map_saver\n", 1)
    (tmp_path / "g.pgm").write_bytes(raw)
    (tmp_path / "g.yaml").write_text(
        "image: g.pgm\nresolution: 0.050000\norigin: [-10.0, -10.0, 0.0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    g = load_map(tmp_path / "g.yaml")
    assert g.data[2, 0] == 100 and g.data[1, 1] == -1 and g.data[0, 2] == 0
    assert len(g.reflectors) == 0


def test_bad_maps(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("image: a.pgm\nresolution: 0.05\n")
    with pytest.raises(ConfigError, match="origin"):
        load_map(tmp_path / "a.yaml")
    (tmp_path / "b.yaml").write_text(
        "image: nothere.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    with pytest.raises(ConfigError, match="cannot read map image"):
        load_map(tmp_path / "b.yaml")
    (tmp_path / "c.pgm").write_bytes(b"JUNK")
    (tmp_path / "c.yaml").write_text(
        "image: c.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    with pytest.raises(ConfigError, match="not a PGM"):
        load_map(tmp_path / "c.yaml")
    with pytest.raises(InvalidInputError):
        OccupancyGrid(np.zeros((2, 2)), -0.1)


def test_rasterize_and_distance_field() -> None:
    g = rasterize(
        [Box2D((0.0, 0.0), (1.0, 0.1)), Box2D((2.0, 0.0), radius=0.2)], (-1, -1, 3, 1), 0.05
    )
    c, r = g.world_to_cell(np.array([[0.0, 0.0], [2.0, 0.1], [0.0, 0.5], [1.0, 0.0]]))
    assert list(g.occupied[r, c]) == [True, True, False, False]
    d = g.distance_field(2.0)
    # 0.5 m above the box (top edge at 0.05): ~0.45 m to the nearest occupied center
    assert abs(d[r[2], c[2]] - 0.45) < 0.06


@pytest.mark.parametrize("shift", [0.0, 0.0125])
def test_signed_distance_field_is_the_distance_to_the_box_surface(shift: float) -> None:
    """Signed field vs the exact signed distance to an axis-aligned box (independent formula),
    at cell centers in front of or behind one face (not near a corner): exact when the faces
    lie on cell edges (cells occupied by their center), within half a cell otherwise; negative
    inside, where the unsigned field is 0."""
    res = 0.05
    lo, hi = np.array([-0.5 + shift, -0.3 + shift]), np.array([0.5 + shift, 0.3 + shift])
    box = Box2D(tuple((lo + hi) / 2), tuple(hi - lo))
    g = rasterize([box], (-1.5, -1.5, 1.5, 1.5), res)
    phi = g.signed_distance_field(2.0, 0.5)
    cols, rows = np.meshgrid(np.arange(g.width), np.arange(g.height))
    xy = g.cell_to_world(cols, rows)
    q = np.abs(xy - (lo + hi) / 2) - (hi - lo) / 2  # box signed distance (Quilez)
    exact = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(axis=-1), 0)
    face = (np.sort(q, axis=-1)[..., 0] < -0.05) & (np.abs(exact) < 0.3)  # off the corners
    err = np.abs(phi[face] - exact[face])
    assert face.sum() > 100
    assert err.max() <= (1e-9 if shift == 0 else res / 2 + 1e-9)
    assert (phi[g.occupied] < 0).all() and (phi[~g.occupied] > 0).all()
    assert (g.distance_field(2.0)[g.occupied] == 0).all()

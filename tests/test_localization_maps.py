"""Maps: map_server YAML + PGM round trip, ROS row order, bad input, twin map vs lidar truth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from mmpa.core.errors import ConfigError, InvalidInputError
from mmpa.maps.map_server import load_map, read_map_image, read_pgm_maxval, save_map, write_pgm
from mmpa.maps.occupancy import Box2D, OccupancyGrid, rasterize


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
    with pytest.raises(ConfigError, match=r"c.yaml: image: .*c.pgm: not a map image"):
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


# --- Nav2 map_server parity ------------------------------------------------------------------
# The reference below is a per-pixel transcription of Nav2's nav2_map_server/src/map_io.cpp
# (loadMapFromFile) over GraphicsMagick Q16 quanta (MaxRGB 65535; an 8-bit value v is
# v * 257, a PGM value v of maxval m is round(v * 65535 / m)): plain Python scalars written
# from the C++ text, not from mmpa's vectorized code; spot values computed by hand pin it.
MAXRGB = 65535


def _nav2_cell(
    rgb: tuple[int, int, int],
    alpha: int | None,
    mode: str,
    negate: bool,
    occ_t: float,
    free_t: float,
) -> int:
    channels = [int(c) for c in rgb]
    if mode == "trinary" and alpha is not None:
        channels.append(int(alpha))  # "average in alpha with color channels in Trinary mode"
    total = 0.0
    for c in channels:
        total += c
    shade = (total / len(channels)) / MAXRGB  # scaleQuantumToDouble(sum / channels.size())
    occ = shade if negate else 1.0 - shade
    if mode == "trinary":
        return 100 if occ_t < occ else (0 if occ < free_t else -1)
    if mode == "scale":
        if alpha is not None and alpha != MAXRGB:  # alphaQuantum() != OpaqueOpacity
            return -1
        if occ_t < occ:
            return 100
        if occ < free_t:
            return 0
        return round((occ - free_t) / (occ_t - free_t) * 100.0)  # rint: half to even
    v = math.floor(shade * 255 + 0.5)  # std::round of a non-negative value
    return v if 0 <= v <= 100 else -1


def _write_yaml(path: Path, image: str, mode: str, negate: int = 0, thr=(0.65, 0.196)) -> Path:
    path.write_text(
        f"image: {image}\nmode: {mode}\nresolution: 0.05\norigin: [-1.0, 2.0, 0.0]\n"
        f"negate: {negate}\noccupied_thresh: {thr[0]}\nfree_thresh: {thr[1]}\n"
    )
    return path


def _ramp_images(tmp_path: Path) -> dict[str, tuple[Path, np.ndarray, np.ndarray | None]]:
    """Each 16 x 16 test image: (file, (H, W, 3) R, G, B quanta, alpha quanta or None)."""
    rng = np.random.default_rng(0)
    v = np.arange(256, dtype=np.uint8).reshape(16, 16)  # every 8-bit grey once
    rgb = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
    a = rng.choice(np.array([0, 128, 254, 255], np.uint8), (16, 16))
    out: dict[str, tuple[Path, np.ndarray, np.ndarray | None]] = {}
    grey = np.repeat(v[..., None].astype(int), 3, axis=-1) * 257
    write_pgm(tmp_path / "p5.pgm", v)
    out["pgm8"] = (tmp_path / "p5.pgm", grey, None)
    Image.fromarray(v, "L").save(tmp_path / "l.png")
    out["png_L"] = (tmp_path / "l.png", grey, None)
    Image.fromarray(np.stack([v, a], -1), "LA").save(tmp_path / "la.png")
    out["png_LA"] = (tmp_path / "la.png", grey, a.astype(int) * 257)
    Image.fromarray(rgb, "RGB").save(tmp_path / "rgb.bmp")
    out["bmp_RGB"] = (tmp_path / "rgb.bmp", rgb.astype(int) * 257, None)
    Image.fromarray(np.concatenate([rgb, a[..., None]], -1), "RGBA").save(tmp_path / "rgba.png")
    out["png_RGBA"] = (tmp_path / "rgba.png", rgb.astype(int) * 257, a.astype(int) * 257)
    # 16-bit PGM, maxval 1000 (GraphicsMagick scales by maxval: shade = value / maxval)
    w16 = (np.arange(256).reshape(16, 16) * 1000 // 255).astype(">u2")
    (tmp_path / "p16.pgm").write_bytes(b"P5\n16 16\n1000\n" + w16.tobytes())
    q16 = np.array([[int(x * MAXRGB / 1000 + 0.5) for x in r] for r in w16.tolist()])
    out["pgm16_maxval1000"] = (tmp_path / "p16.pgm", np.repeat(q16[..., None], 3, -1), None)
    # ASCII PGM with maxval 100 and a comment
    p2 = (np.arange(256).reshape(16, 16) * 100 // 255).astype(int)
    text = "P2\n# CREATOR: test\n16 16\n100\n" + "\n".join(" ".join(map(str, r)) for r in p2)
    (tmp_path / "p2.pgm").write_text(text + "\n")
    q2 = np.array([[int(x * MAXRGB / 100 + 0.5) for x in r] for r in p2.tolist()])
    out["pgm2_maxval100"] = (tmp_path / "p2.pgm", np.repeat(q2[..., None], 3, -1), None)
    return out


@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
@pytest.mark.parametrize("negate", [0, 1])
def test_load_map_matches_nav2_cell_by_cell(tmp_path: Path, mode: str, negate: int) -> None:
    for name, (img, chans, alpha) in _ramp_images(tmp_path).items():
        for thr in [(0.65, 0.196), (0.9, 0.1)]:
            g = load_map(_write_yaml(tmp_path / f"{name}.yaml", img.name, mode, negate, thr))
            assert g.data.shape == (16, 16)
            want = np.array(
                [
                    [
                        _nav2_cell(
                            tuple(chans[y, x]),
                            None if alpha is None else int(alpha[y, x]),
                            mode,
                            bool(negate),
                            *thr,
                        )
                        for x in range(16)
                    ]
                    for y in range(16)
                ]
            )
            # ROS row 0 is the bottom: image row y is grid row 15 - y
            np.testing.assert_array_equal(g.data, want[::-1], err_msg=f"{name} {mode} {thr}")


def test_nav2_spot_values(tmp_path: Path) -> None:
    """Hand-computed values (thresholds 0.65 / 0.196) for single grey pixels."""
    pix = np.array([[0, 89, 90, 150, 205, 206, 255, 50, 100, 101]], np.uint8)
    write_pgm(tmp_path / "s.pgm", pix)
    tri = load_map(_write_yaml(tmp_path / "t.yaml", "s.pgm", "trinary")).data[0]
    # occ = 1 - p/255: 1.0, .651, .647, .412, .196078 (> .196), .192, 0, .804, .608, .604
    assert tri.tolist() == [100, 100, -1, -1, -1, 0, 0, 100, -1, -1]
    sc = load_map(_write_yaml(tmp_path / "s.yaml", "s.pgm", "scale")).data[0]
    # (occ - .196) / .454 * 100: p=90 -> 99.3 -> 99; p=150 -> 47.5 -> 48 (mmpa's old 99-based
    # formula gave 47); p=205 -> 0.017 -> 0; p=100 -> 90.8 -> 91; p=101 -> 89.9 -> 90
    assert sc.tolist() == [100, 100, 99, 48, 0, 0, 0, 100, 91, 90]
    raw = load_map(_write_yaml(tmp_path / "r.yaml", "s.pgm", "raw")).data[0]
    # the pixel is the value; above 100 (205, 255, ...) is unknown, never clipped to occupied
    assert raw.tolist() == [0, 89, 90, -1, -1, -1, -1, 50, 100, -1]
    neg = load_map(_write_yaml(tmp_path / "n.yaml", "s.pgm", "raw", negate=1)).data[0]
    np.testing.assert_array_equal(neg, raw)  # raw ignores negate (as Nav2)


def test_scale_mode_png_transparency_is_unknown(tmp_path: Path) -> None:
    rgba = np.zeros((1, 3, 4), np.uint8)
    rgba[..., 3] = [255, 254, 0]  # opaque black, nearly opaque black, transparent black
    Image.fromarray(rgba, "RGBA").save(tmp_path / "a.png")
    assert load_map(_write_yaml(tmp_path / "a.yaml", "a.png", "scale")).data[0].tolist() == [
        100,
        -1,
        -1,
    ]
    # trinary averages alpha with R, G, B: black opaque (0,0,0,1) -> shade .25 -> occ .75 -> 100;
    # black transparent -> shade 0 -> 100 as well
    tri = load_map(_write_yaml(tmp_path / "b.yaml", "a.png", "trinary")).data[0]
    assert tri.tolist() == [100, 100, 100]


def test_pgm_reader_agrees_with_pillow(tmp_path: Path) -> None:
    """mmpa reads PGM itself (exact to the header maxval); Pillow rescales other maxvals to
    8/16 bits, truncating: the shades agree to one step of Pillow's scale."""
    for maxval, dt in [(255, "u1"), (100, "u1"), (1000, ">u2"), (65535, ">u2")]:
        v = (np.arange(60).reshape(6, 10) * maxval // 59).astype(dt)
        p = tmp_path / f"m{maxval}.pgm"
        p.write_bytes(f"P5\n10 6\n{maxval}\n".encode() + v.tobytes())
        rgb_sum, alpha = read_map_image(p)
        assert alpha is None
        shade = rgb_sum / 3 / MAXRGB
        np.testing.assert_array_equal(read_pgm_maxval(p)[0], v.astype(int))
        with Image.open(p) as im:
            full = 255.0 if im.mode == "L" else 65535.0
            ref = np.asarray(im).astype(float) / full
        np.testing.assert_allclose(shade, ref, atol=1 / full)  # Pillow truncates
        if maxval in (255, 65535):
            np.testing.assert_array_equal(shade, ref)


@pytest.mark.parametrize("mode", ["trinary", "scale", "raw"])
def test_save_map_writes_what_map_saver_writes(tmp_path: Path, mode: str) -> None:
    data = np.arange(-1, 101, dtype=np.int8)  # every cell value once, as one row
    data = np.stack([data, data[::-1]])  # two rows: checks the row flip too
    g = OccupancyGrid(data, 0.05, (0.0, 0.0, 0.0), occupied_thresh=0.65, free_thresh=0.196)
    y = save_map(g, tmp_path / "m.yaml", mode=mode)
    meta = yaml.safe_load(y.read_text())
    assert meta["mode"] == mode and meta["negate"] == 0 and "reflectors" not in meta
    img_path = tmp_path / meta["image"]
    assert img_path.suffix == (".png" if mode == "scale" else ".pgm")
    with Image.open(img_path) as im:
        img = np.asarray(im)
    top = img[0]  # image row 0 = the grid's top row = data[1]
    for c, px in zip(data[1].tolist(), top, strict=True):
        # map_io.cpp tryWriteMapToFile, per cell (free 20, occupied 65 after rint(* 100))
        if mode == "trinary":
            want = 205 if c < 0 else (254 if c <= 20 else (0 if c >= 65 else 205))
            assert px == want, c
        elif mode == "raw":
            assert px == (255 if c < 0 else c), c
        else:
            if c < 0:
                assert px[3] == 0, c
            else:
                grey = math.floor((100 - c) / 100 * 255 + 0.5)
                assert tuple(px) == (grey, grey, grey, 255), c
    g2 = load_map(y)
    if mode == "raw":
        np.testing.assert_array_equal(g2.data, g.data)  # raw is lossless
    elif mode == "trinary":
        # (with free_thresh 0.25, map_saver's default, the unknown grey 205 would read back
        # as free: occ = 1 - 205/255 = 0.196 < 0.25; mmpa's default 0.196 keeps it unknown)
        want = np.where(data < 0, -1, np.where(data <= 20, 0, np.where(data >= 65, 100, -1)))
        np.testing.assert_array_equal(g2.data, want)
    else:  # scale: the 8-bit grey quantization moves a cell by at most one step
        known = data >= 0
        assert (g2.data[~known] == -1).all()
        occ = 1 - np.floor((100 - data[known].astype(float)) / 100 * 255 + 0.5) / 255
        want = np.where(
            occ > 0.65, 100, np.where(occ < 0.196, 0, np.rint((occ - 0.196) / 0.454 * 100))
        )
        np.testing.assert_array_equal(g2.data[known], want)


def _bad_map(tmp_path: Path, **fields: str) -> Path:
    base = {
        "image": "ok.pgm",
        "resolution": "0.05",
        "origin": "[0.0, 0.0, 0.0]",
        "negate": "0",
        "occupied_thresh": "0.65",
        "free_thresh": "0.196",
    }
    base.update(fields)
    write_pgm(tmp_path / "ok.pgm", np.full((2, 3), 254, np.uint8))
    p = tmp_path / "bad.yaml"
    p.write_text("".join(f"{k}: {v}\n" for k, v in base.items()))
    return p


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"occupied_thresh": ".nan"}, "occupied_thresh: must be finite"),
        ({"free_thresh": ".inf"}, "free_thresh: must be finite"),
        ({"occupied_thresh": "1.5"}, r"occupied_thresh: must be in \[0, 1\]"),
        ({"free_thresh": "-0.1"}, r"free_thresh: must be in \[0, 1\]"),
        ({"free_thresh": "0.7"}, "free_thresh .* must be smaller than occupied_thresh"),
        ({"origin": "[.nan, 0, 0]"}, "origin: must be finite"),
        ({"origin": "[0, 0, .nan]"}, "origin: must be finite"),
        ({"origin": '"120"'}, r"origin: must be a list \[x, y, yaw\], got '120'"),
        ({"origin": "[0, 0]"}, r"origin: must be a list \[x, y, yaw\]"),
        ({"origin": "[0, 0, 0.5]"}, "origin: yaw 0.5 rad; rotated map origins are not"),
        ({"origin": "[true, 0, 0]"}, "origin: must be a number"),
        ({"resolution": "0"}, "resolution: must be > 0"),
        ({"resolution": "-0.05"}, "resolution: must be > 0"),
        ({"resolution": ".nan"}, "resolution: must be finite"),
        ({"resolution": "fine"}, "resolution: must be a number"),
        ({"negate": "maybe"}, "negate: must be 0, 1 or a boolean"),
        ({"mode": "fancy"}, "mode: must be trinary, scale or raw"),
        ({"image": '""'}, "image: must be a file name"),
        ({"reflectors": "{positions: [[.nan, 0.0]]}"}, r"reflectors.positions\[0\]: must be"),
        ({"reflectors": "{positions: [1, 2, 3, 4]}"}, r"reflectors.positions\[0\]: must be a pair"),
        ({"reflectors": "{positions: [[0, 0]], radius: -0.04}"}, "reflectors.radius: must be >="),
        ({"reflectors": "{positions: [[0, 0]], radius: .nan}"}, "radius: must be finite"),
        ({"reflectors": "{positions: [[1, 1], [1, 1]]}"}, r"positions\[1\]: .*duplicate"),
        ({"reflectors": "{position: [[1, 1]]}"}, "reflectors: unknown key"),
        ({"reflectors": "[{id: 0, x: 0, y: 0}]"}, r"reflectors\[0\]: .*missing radius"),
        ({"reflectors": "[{id: 0, x: 0, y: 0, radius: .nan}]"}, r"reflectors\[0\].radius"),
        ({"reflectors": "[{id: 0, x: 0, y: 0, radius: -1}]"}, r"reflectors\[0\].radius"),
        ({"reflectors": "[1.0, 2.0, 3.0, 4.0]"}, r"reflectors\[0\]: must be a mapping"),
        ({"reflectors": "7"}, "reflectors: must be a reflector map file name"),
        ({"reflectors": "[&a [1, 2], *a]"}, "alias"),
    ],
)
def test_bad_map_yaml_names_file_and_field(tmp_path: Path, fields: dict, match: str) -> None:
    p = _bad_map(tmp_path, **fields)
    with pytest.raises(ConfigError, match=match) as e:
        load_map(p)
    assert str(p) in str(e.value)


@pytest.mark.parametrize(
    ("pgm", "match"),
    [
        (b"P5\n-3 2\n255\n" + bytes(6), "PGM width must be a positive integer, got b'-3'"),
        (b"P5\n3 2\n0\n" + bytes(6), "PGM maxval must be in 1..65535, got 0"),
        (b"P5\n3 2\n70000\n" + bytes(12), "PGM maxval must be in 1..65535"),
        (b"P5\n0 0\n255\n", "PGM image is 0 x 0"),
        (b"P5\n3 2\n255\n" + bytes(4), "PGM pixel data truncated"),
        (b"P5\n3 2", "PGM header truncated before maxval"),
        (b"P2\n2 1\n100\n50 101\n", "PGM pixel value 101 exceeds maxval 100"),
        (b"P2\n2 1\n100\n50\n", "PGM holds 1 pixel values"),
    ],
)
def test_bad_pgm_names_image_and_yaml(tmp_path: Path, pgm: bytes, match: str) -> None:
    p = _bad_map(tmp_path)
    (tmp_path / "ok.pgm").write_bytes(pgm)
    with pytest.raises(ConfigError, match=match) as e:
        load_map(p)
    assert str(p) in str(e.value) and "ok.pgm" in str(e.value)


def test_map_yaml_alias_bomb_in_reflectors_is_refused(tmp_path: Path) -> None:
    bomb = ["a: &a [[0.0, 0.0], [0.0, 0.0]]"]
    for k in "bcdefgh":
        prev = chr(ord(k) - 1)
        bomb.append(f"{k}: &{k} [*{prev}, *{prev}, *{prev}, *{prev}, *{prev}]")
    p = _bad_map(tmp_path)
    p.write_text(p.read_text() + "\n".join(bomb) + "\nreflectors: {positions: *h}\n")
    with pytest.raises(ConfigError, match=r"alias \*a is not accepted") as e:
        load_map(p)
    assert str(p) in str(e.value)


def test_grid_refuses_flat_or_nan_reflectors() -> None:
    with pytest.raises(InvalidInputError, match=r"\(N, 2\)"):
        OccupancyGrid(np.zeros((2, 2)), 0.1, reflectors=np.array([1.0, 2.0, 3.0, 4.0]))
    with pytest.raises(InvalidInputError, match=r"\(N, 2\)"):
        OccupancyGrid(np.zeros((2, 2)), 0.1, reflectors=np.array([[np.nan, 0.0]]))
    with pytest.raises(InvalidInputError, match="reflector radius"):
        OccupancyGrid(np.zeros((2, 2)), 0.1, reflector_radius=-0.04)
    with pytest.raises(InvalidInputError, match="thresholds"):
        OccupancyGrid(np.zeros((2, 2)), 0.1, occupied_thresh=0.1, free_thresh=0.2)

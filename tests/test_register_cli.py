"""``mmpa register`` on recorded frames: PNG pairs of tests/data/desk and a bag written here."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import typer
from PIL import Image
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from mmpa.apps.register import load_intrinsics, load_png_frame
from mmpa.backends.bag import BagWriter
from mmpa.backends.bag import messages as rm
from mmpa.cli.register import register
from mmpa.core.geometry import apply, inv

DATA = Path(__file__).parent / "data" / "desk"
K_FILE = DATA / "intrinsics.K.txt"

app = typer.Typer()


@app.callback()
def _root() -> None:
    """The root app (main.py wires ``register`` the same way)."""


register(app)
runner = CliRunner()


def _png_args(a: str, b: str, k: Path = K_FILE) -> list[str]:
    return [
        "register",
        "--color1",
        str(DATA / f"frame-{a}.color.png"),
        "--depth1",
        str(DATA / f"frame-{a}.depth.png"),
        "--color2",
        str(DATA / f"frame-{b}.color.png"),
        "--depth2",
        str(DATA / f"frame-{b}.depth.png"),
        "--intrinsics",
        str(k),
    ]


def _run(args: list[str], out: Path) -> dict:
    res = runner.invoke(app, [*args, "--out", str(out)])
    assert res.exit_code == 0, res.output
    s = json.loads((out / "summary.json").read_text())
    assert np.allclose(np.loadtxt(out / "T.csv", delimiter=","), s["T_2_1"], atol=1e-8)
    return s


def _centroid(name: str) -> np.ndarray:
    f = load_png_frame(DATA / f"frame-{name}.color.png", DATA / f"frame-{name}.depth.png", K_FILE)
    return f.to_point_cloud().points.mean(axis=0)


def _pose(name: str) -> np.ndarray:
    return np.loadtxt(DATA / f"frame-{name}.pose.txt")


def _mm(T_a: np.ndarray, T_b: np.ndarray, c: np.ndarray) -> float:
    return float(np.linalg.norm(apply(T_a, c) - apply(T_b, c)) * 1e3)


@pytest.fixture(scope="module")
def forward(tmp_path_factory) -> dict:
    return _run(_png_args("000015", "000017"), tmp_path_factory.mktemp("fwd"))


def test_intrinsics_file_forms(tmp_path) -> None:
    K = np.loadtxt(K_FILE)
    tum = tmp_path / "tum.txt"
    tum.write_text(f"# fx fy cx cy\n{K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}\n")
    a, b = load_intrinsics(K_FILE, 640, 480), load_intrinsics(tum, 640, 480)
    assert a == b
    assert np.allclose(a.K, K)


def test_neighbours_register_and_agree_with_the_reverse(forward, tmp_path) -> None:
    s = forward
    assert s["ok"] and s["icp"]["ok"], s["reason"]
    assert s["pose_from"] == "projective" and s["projective"]["ok"]
    assert 0.5 < s["icp"]["fitness"] <= 1.0 and 0 < s["icp"]["rmse"] < 0.008
    T = np.asarray(s["T_2_1"])
    c15, c17 = _centroid("000015"), _centroid("000017")
    # the printed motion is the pose's
    assert s["translation_mm"] == pytest.approx(np.linalg.norm(T[:3, 3]) * 1e3)
    # against the (cm-level) TSDF tracking poses
    assert _mm(T, inv(_pose("000017")) @ _pose("000015"), c15) < 30.0
    rev = _run(_png_args("000017", "000015"), tmp_path)
    assert rev["ok"], rev["reason"]
    # forward and reverse are independent estimates: they compose to identity within a few mm
    assert _mm(T @ np.asarray(rev["T_2_1"]), np.eye(4), c17) < 4.0
    # the projective refinement moved the pose by little; --no-refine reports the ICP pose
    T_icp = np.asarray(s["icp"]["T"])
    assert 0.0 < _mm(T, T_icp, c15) < 4.0
    raw = _run([*_png_args("000015", "000017"), "--no-refine"], tmp_path / "raw")
    assert raw["pose_from"] == "icp" and raw["projective"] is None and raw["ok"]
    assert np.allclose(raw["T_2_1"], T_icp, atol=1e-9)


def test_pair_without_overlap_is_refused(tmp_path) -> None:
    """Frame 15's part that frame 113 (the sequence's end) does not see, by the poses, written
    as a depth PNG with the rest masked out: refused, not registered wrongly."""
    f1 = load_png_frame(DATA / "frame-000015.color.png", DATA / "frame-000015.depth.png", K_FILE)
    f2 = load_png_frame(DATA / "frame-000113.color.png", DATA / "frame-000113.depth.png", K_FILE)
    k = f1.intrinsics
    v, u = np.nonzero(f1.depth > 0)
    z = f1.depth[v, u].astype(float)
    pts = np.column_stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])
    q = apply(inv(_pose("000113")) @ _pose("000015"), pts)
    d, _ = cKDTree(f2.to_point_cloud().points[::3]).query(q, distance_upper_bound=0.05)
    seen = np.isfinite(d)
    raw = np.asarray(Image.open(DATA / "frame-000015.depth.png")).copy()
    raw[v[seen], u[seen]] = 0
    assert (raw > 0).sum() > 20000  # a large cloud: refused for the overlap, not its size
    Image.fromarray(raw).save(tmp_path / "part.png")
    args = _png_args("000015", "000113")
    args[args.index("--depth1") + 1] = str(tmp_path / "part.png")
    s = _run(args, tmp_path / "out")
    assert not s["ok"] and s["reason"]
    assert s["projective"] is None  # a refused pose is not refined


def _write_bag(path: Path, names: list[str], t0: float, dt: float) -> None:
    with BagWriter(path) as bag:
        for i, n in enumerate(names):
            f = load_png_frame(
                DATA / f"frame-{n}.color.png",
                DATA / f"frame-{n}.depth.png",
                K_FILE,
                stamp=t0 + i * dt,
            )
            bag.write("/cam/rgb", rm.rgb_image(f))
            bag.write("/cam/depth", rm.depth_image(f))
            bag.write("/cam/info", rm.camera_info(f.intrinsics, f.stamp))


def test_bag_frames_register_like_the_pngs(forward, tmp_path) -> None:
    bag = tmp_path / "cam.mcap"
    _write_bag(bag, ["000019", "000015", "000017"], t0=100.0, dt=0.5)
    topics = ["--color-topic", "/cam/rgb", "--depth-topic", "/cam/depth", "--info-topic"]
    args = ["register", "--bag", str(bag), "--from", "0.45", "--to", "1.1", *topics, "/cam/info"]
    s = _run(args, tmp_path / "out")
    assert s["stamps"] == [100.5, 101.0]  # frames 15 and 17, the nearest to 0.45 s and 1.1 s
    assert s["ok"], s["reason"]
    # the same pixels through the bag (16UC1 mm) as through the PNGs: the same pose
    T, T_png = np.asarray(s["T_2_1"]), np.asarray(forward["T_2_1"])
    assert np.abs(T - T_png).max() < 1e-6
    assert s["icp"]["fitness"] == pytest.approx(forward["icp"]["fitness"], abs=1e-6)
    # a time past the last frame (1.0 s) is refused with exit code 2
    bad = runner.invoke(app, [*args[:6], "5", *topics, "/cam/info"])
    assert bad.exit_code == 2
    assert "beyond the bag's camera frames" in bad.output and "5 s" in bad.output
    same = runner.invoke(app, [*args[:6], "0.55", *topics, "/cam/info"])
    assert same.exit_code == 2 and "pick the same frame" in same.output
    no_topic = runner.invoke(app, args[:7])  # the default topics are not in this bag
    assert no_topic.exit_code == 2 and "no topic /camera/color/image_raw" in " ".join(
        no_topic.output.split()
    )


def test_bad_inputs_exit_2_with_clear_messages(tmp_path) -> None:
    def fails(args: list[str], *words: str) -> None:
        res = runner.invoke(app, args)
        assert res.exit_code == 2, res.output
        flat = " ".join(res.output.split())
        for w in words:
            assert w in flat, (w, flat)

    args = _png_args("000015", "000017")
    # a missing file
    missing = list(args)
    missing[missing.index("--color2") + 1] = str(tmp_path / "nope.png")
    fails(missing, "colour image", "nope.png", "does not exist")
    # not a PNG
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    bad_png = list(args)
    bad_png[bad_png.index("--depth1") + 1] = str(junk)
    fails(bad_png, "depth image", "junk.png", "cannot be read")
    # a colour image given as depth
    rgb_depth = list(args)
    rgb_depth[rgb_depth.index("--depth1") + 1] = str(DATA / "frame-000015.color.png")
    fails(rgb_depth, "single-channel integer depth")
    # depth of another size than its colour image
    small = tmp_path / "small.png"
    raw = np.asarray(Image.open(DATA / "frame-000017.depth.png"))
    Image.fromarray(np.ascontiguousarray(raw[::2, ::2])).save(small)
    sizes = list(args)
    sizes[sizes.index("--depth2") + 1] = str(small)
    fails(sizes, "320x240", "640x480", "same size")
    # a malformed intrinsics file
    k5 = tmp_path / "k5.txt"
    k5.write_text("600 600 320 240 1\n")
    fails(_png_args("000015", "000017", k5), "k5.txt", "got 5 numbers")
    # a depth scale that leaves no depth in range
    fails([*args, "--depth-scale", "1.0"], "valid depth pixels", "wrong depth scale")
    # mixing the two input forms, or neither
    fails([*args, "--bag", str(tmp_path / "x.mcap")], "--bag excludes")
    fails(["register", "--color1", str(junk)], "missing --depth1")
    fails(
        ["register", "--bag", str(tmp_path / "x.mcap"), "--from", "0", "--to", "1"],
        "does not exist",
    )

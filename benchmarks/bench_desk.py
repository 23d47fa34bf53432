"""mmpa.registration on real RGB-D frames: acceptance, wrong poses and self-consistency.

Run on purpose: ``python benchmarks/bench_desk.py [--data DIR] [--step 1] [--far 50]
[--projective 40] [--json OUT] [--set key=value ...]`` (``--set`` overrides a
:class:`RegistrationConfig` field, JSON values).

Data: a folder of ``frame-NNNNNN.{color,depth,pose}.png/txt`` and ``intrinsics.K.txt`` (the desk
set of andyzeng/tsdf-fusion, BSD-2-Clause: 640x480, depth uint16 mm aligned to colour with a
regular grid of holes, ~34 % valid pixels; camera-to-world poses from TSDF tracking, cm-level).
Default: ``/work/shared/real-data/desk``, else ``tests/data/desk``.

Cases (source ``i``, target ``j``; the reference ``T_j_i = inv(P_j) P_i`` from the given poses):

- neighbours: ``(i, i + k)`` for ``k = 1..3`` (frames taken every other frame of the sequence);
- reverse: ``(i + k, i)`` for the same pairs; the reverse error is the displacement (mm) of the
  source cloud's centroid under ``T_ij T_ji`` when both are accepted;
- loops: ``(i, i + 1, i + 2)``; the closure error is the centroid displacement (mm) of
  ``inv(T_{i+2,i}) T_{i+2,i+1} T_{i+1,i}`` when the three are accepted;
- wide: ``(i, i + k)`` for ``k = 5, 8`` (informational: wider baselines, no reverse);
- far: no real pair of the set is without overlap (the camera circles the desk: every pair
  shares 30-60 % of its pixels), so ``--far`` pairs ``(i, j)`` with ``j - i >= n / 3`` are
  made so: the source is the part of frame ``i`` farther than 5 cm from every point of frame
  ``j`` by the given poses (kept when at least 5000 points remain); all must be refused;
- projective: ``refine_projective`` of the full-resolution source points on the target depth
  image, from the ICP pose of ``--projective`` accepted neighbour pairs (ok, and its
  disagreement with the ICP pose in mm);
- projective loops: the 3-view loop closure of the projective refinement (``k = 1, 2``
  pairs, from their ICP poses), depth only and depth + colour (the photometric term).

A pose is wrong when accepted and more than 30 mm (centroid displacement) from the given pose,
or (for neighbours) more than 5 mm from the inverse of its accepted reverse. Prints one table
and exits 0.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from PIL import Image

from mmpa.core.geometry import Array, apply, inv
from mmpa.registration import (
    ProjectiveConfig,
    RegistrationConfig,
    prepare,
    refine_projective,
    register,
)
from mmpa.robot.description import CameraIntrinsics
from mmpa.robot.interfaces import PointCloud

_DEFAULT = Path("/work/shared/real-data/desk")
_FALLBACK = Path(__file__).resolve().parents[1] / "tests" / "data" / "desk"


def load_frames(folder: Path) -> tuple[CameraIntrinsics, list[dict]]:
    """Intrinsics and the frames (sorted by name): ``depth`` (H, W) m (0 = invalid), ``color``
    (H, W, 3) uint8, ``pose`` (4, 4) camera-to-world, ``cloud`` the valid pixels as a
    :class:`PointCloud` in the camera optical frame (m, colours in [0, 1])."""
    K = np.loadtxt(folder / "intrinsics.K.txt")
    frames = []
    for p in sorted(folder.glob("frame-*.color.png")):
        stem = p.name[: -len(".color.png")]
        color = np.asarray(Image.open(p).convert("RGB"))
        depth = np.asarray(Image.open(folder / f"{stem}.depth.png"), dtype=np.float64) / 1000.0
        pose = np.loadtxt(folder / f"{stem}.pose.txt")
        frames.append({"name": stem, "color": color, "depth": depth, "pose": pose})
    h, w = frames[0]["depth"].shape
    intr = CameraIntrinsics(width=w, height=h, fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    for f in frames:
        f["cloud"] = to_cloud(f["depth"], f["color"], intr)
    return intr, frames


def to_cloud(depth: Array, color: Array, intr: CameraIntrinsics) -> PointCloud:
    """The valid pixels (depth > 0) of an RGB-D frame as a camera-frame :class:`PointCloud`."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    pts = np.column_stack([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z])
    return PointCloud(pts, color[v, u].astype(float) / 255.0)


def motion_mm(T_a: Array, T_b: Array, c: Array) -> float:
    """Displacement (mm) of the point ``c`` between the poses ``T_a`` and ``T_b``."""
    return float(np.linalg.norm(apply(T_a, c) - apply(T_b, c)) * 1e3)


def without_overlap(src: dict, tgt: dict, margin: float = 0.05) -> PointCloud:
    """The points of ``src`` farther than ``margin`` m from every point of ``tgt`` (by the
    given poses), in the source camera frame."""
    from scipy.spatial import cKDTree

    q = apply(inv(tgt["pose"]) @ src["pose"], src["cloud"].points)
    d, _ = cKDTree(tgt["cloud"].points[::3]).query(q, distance_upper_bound=margin)
    keep = ~np.isfinite(d)
    return PointCloud(src["cloud"].points[keep], src["cloud"].colors[keep])


def _stats(x: list[float]) -> str:
    if not x:
        return "-"
    return f"{np.median(x):.2f} / {np.max(x):.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=_DEFAULT if _DEFAULT.exists() else _FALLBACK)
    ap.add_argument("--step", type=int, default=1, help="use every step-th frame")
    ap.add_argument("--far", type=int, default=50)
    ap.add_argument("--projective", type=int, default=40)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="key=value")
    a = ap.parse_args()
    over = {k: json.loads(v) for k, v in (s.split("=", 1) for s in a.set)}
    cfg = RegistrationConfig(**over)
    pcfg = ProjectiveConfig()
    t0 = time.perf_counter()
    intr, frames = load_frames(a.data)
    frames = frames[:: a.step]
    n = len(frames)
    prep = [prepare(f["cloud"], cfg) for f in frames]
    cents = [f["cloud"].points.mean(axis=0) for f in frames]
    print(f"{n} frames from {a.data}, prepared in {time.perf_counter() - t0:.1f} s")

    def gt(i: int, j: int) -> Array:
        return inv(frames[j]["pose"]) @ frames[i]["pose"]

    reg: dict[tuple[int, int], object] = {}

    def run(i: int, j: int):
        if (i, j) not in reg:
            reg[i, j] = register(prep[i], prep[j], cfg)
        return reg[i, j]

    rows: dict[str, dict] = {}
    reasons: dict[str, int] = {}

    def tally(case: str, i: int, j: int, check_reverse: bool) -> None:
        r = run(i, j)
        row = rows.setdefault(case, {"n": 0, "ok": 0, "wrong": 0, "err": [], "rmse": []})
        row["n"] += 1
        if not r.ok:
            key = r.reason.split(":")[0].split(" (")[0][:40]
            key = "".join(ch for ch in key if not ch.isdigit()).strip()
            reasons[key] = reasons.get(key, 0) + 1
            return
        row["ok"] += 1
        row["rmse"].append(r.rmse * 1e3)
        e = motion_mm(r.T, gt(i, j), cents[i])
        row["err"].append(e)
        wrong = e > 30.0
        if check_reverse and reg.get((j, i)) is not None and reg[j, i].ok:
            wrong |= motion_mm(r.T, inv(reg[j, i].T), cents[i]) > 5.0
        row["wrong"] += int(wrong)

    t1 = time.perf_counter()
    pairs = [(i, i + k) for k in (1, 2, 3) for i in range(n - k)]
    for i, j in pairs:
        run(i, j)
        run(j, i)
    for i, j in pairs:
        tally(f"neighbours k={j - i}", i, j, True)
        tally(f"reverse k={j - i}", j, i, True)
    rev = [
        motion_mm(reg[i, j].T @ reg[j, i].T, np.eye(4), cents[j])
        for i, j in pairs
        if reg[i, j].ok and reg[j, i].ok
    ]
    loops, n_loops = [], 0
    for i in range(n - 2):
        n_loops += 1
        a01, a12, a02 = reg[i, i + 1], reg[i + 1, i + 2], reg[i, i + 2]
        if a01.ok and a12.ok and a02.ok:
            loops.append(motion_mm(a12.T @ a01.T, a02.T, cents[i]))
    t_pairs = time.perf_counter() - t1
    for k in (5, 8):
        for i in range(0, n - k):
            tally(f"wide k={k}", i, i + k, False)
    far = [(i, j) for i in range(n) for j in range(i + max(1, n // 3), n)]
    rng = np.random.default_rng(0)
    for q in rng.permutation(len(far)):
        if rows.get("far (no overlap)", {}).get("n", 0) >= a.far:
            break
        i, j = far[q]
        part = without_overlap(frames[i], frames[j])
        if len(part) < 5000:
            continue
        r = register(part, prep[j], cfg)
        row = rows.setdefault(
            "far (no overlap)", {"n": 0, "ok": 0, "wrong": 0, "err": [], "rmse": []}
        )
        row["n"] += 1
        if r.ok:
            row["ok"] += 1
            row["wrong"] += 1
            row["rmse"].append(r.rmse * 1e3)
    # projective refinement from the accepted ICP poses of neighbour pairs
    proj_ok, proj_dev, proj_n, proj_reasons, proj_fail = 0, [], 0, {}, []
    acc = [(i, j) for i, j in pairs if reg[i, j].ok][: a.projective]
    for i, j in acc:
        proj_n += 1
        pr = refine_projective(
            frames[i]["cloud"].points, frames[j]["depth"], intr, reg[i, j].T, pcfg
        )
        if pr.ok:
            proj_ok += 1
            proj_dev.append(motion_mm(pr.T, reg[i, j].T, cents[i]))
        else:
            k = pr.reason.split(":")[0][:40]
            proj_fail.append(pr.inlier_fraction)
            proj_reasons[k] = proj_reasons.get(k, 0) + 1

    # 3-view loops of the projective refinement, depth only and depth + colour (the
    # photometric term), each from the accepted ICP pose of its pair
    pcfgs = {"depth": pcfg.model_copy(update={"photometric_sigma": None}), "depth+colour": pcfg}
    pj: dict[str, dict] = {name: {} for name in pcfgs}
    pj_s: dict[str, list[float]] = {name: [] for name in pcfgs}
    for i, j in pairs:
        if j - i > 2 or not reg[i, j].ok:
            continue
        for name, c in pcfgs.items():
            colour = (
                {"source_colors": frames[i]["cloud"].colors, "target_color": frames[j]["color"]}
                if c.photometric_sigma is not None
                else {}
            )
            pr = refine_projective(
                frames[i]["cloud"].points, frames[j]["depth"], intr, reg[i, j].T, c, **colour
            )
            pj[name][i, j] = pr
            pj_s[name].append(pr.seconds)
    proj_loops: dict[str, list[float]] = {}
    for name, d in pj.items():
        proj_loops[name] = [
            motion_mm(d[i + 1, i + 2].T @ d[i, i + 1].T, d[i, i + 2].T, cents[i])
            for i in range(n - 2)
            if all((a, b) in d and d[a, b].ok for a, b in ((i, i + 1), (i + 1, i + 2), (i, i + 2)))
        ]

    print(f"registrations: {len(reg)} in {t_pairs:.1f} s (+ far)")
    print(
        f"{'case':<20}{'pairs':>6}{'ok':>6}{'refused':>8}{'wrong':>6}"
        f"  {'E vs poses mm med/max':>22}  {'RMSE mm med/max':>16}"
    )
    out: dict = {"cases": {}}
    for case, row in rows.items():
        print(
            f"{case:<20}{row['n']:>6}{row['ok']:>6}{row['n'] - row['ok']:>8}{row['wrong']:>6}"
            f"  {_stats(row['err']):>22}  {_stats(row['rmse']):>16}"
        )
        out["cases"][case] = {k: row[k] for k in ("n", "ok", "wrong")}
    print(
        f"reverse consistency (both accepted: {len(rev)}/{len(pairs)}): "
        f"median / max {_stats(rev)} mm"
    )
    print(
        f"3-view loops (all accepted: {len(loops)}/{n_loops}): closure median / max "
        f"{_stats(loops)} mm; > 5 mm: {sum(x > 5 for x in loops)}"
    )
    print(
        f"projective from ICP: {proj_ok}/{proj_n} ok; |proj - ICP| median / max "
        f"{_stats(proj_dev)} mm; refusals {proj_reasons}"
        + (f" (inlier fraction of the refused {_stats(proj_fail)})" if proj_fail else "")
    )
    for name, lp in proj_loops.items():
        n_ok = sum(r.ok for r in pj[name].values())
        print(
            f"projective {name}: {n_ok}/{len(pj[name])} ok; 3-view loops ({len(lp)}): closure "
            f"median / max {_stats(lp)} mm; median {np.median(pj_s[name]):.2f} s per pair"
        )
    print("refusal reasons:", dict(sorted(reasons.items(), key=lambda kv: -kv[1])))
    out.update(
        reverse_mm=rev,
        loops_mm=loops,
        n_loops=n_loops,
        projective_ok=proj_ok,
        projective_n=proj_n,
        projective_dev_mm=proj_dev,
        reasons=reasons,
        projective_loops_mm=proj_loops,
    )
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()

"""Speed and accuracy of mmpa.registration against Open3D's documented pipeline, same pairs.

Run on purpose: ``python benchmarks/bench_registration.py [--pairs 8] [--seed 0]
[--set key=value ...]`` (``--set`` overrides a :class:`RegistrationConfig` field, JSON values).

Pairs come from the digital twin at Site 1 looking at the bench (``view_bench``): the taught
capture at the site's park pose, the current one after a parking error drawn like paper 000
Table 2 (a few cm, 1-3 degrees). The truth is ``inv(T_map_cam_current) T_map_cam_taught``.

Reference (measured in the same run on the same clouds): Open3D's documented pipeline from
the raw ``PointCloud`` (conversion included): voxel 2 cm, normals (r 4 cm, 30 nn), FPFH
(r 10 cm, 100 nn), FGR (``maximum_correspondence_distance`` 1 cm), then colored ICP at
4/2/1 cm with 50/30/14 iterations (voxel, normals r = 2 voxel, gate = voxel).

Ours:
  (a) cold: ``register(PointCloud, PointCloud)`` (both clouds prepared inside);
  (b) IPE first iteration: taught cloud ``prepare``-d once (as IPE does: X_i(O) is fixed per
      task), current raw, global stage (the IPE's path without a localization prior);
  (c) IPE later iterations: current capture 1-3 mm / 0.1-0.3 deg from the taught viewpoint,
      ``init=I`` (global stage skipped);
  (d) (c) then the projective point-to-plane refinement on the current depth image
      (``refine_projective``, full resolution, depth scale estimated): the IPE's compute per
      view after the first;
  (e) IPE compute estimate: (b) + its projective refinement + (d) (two views, as the IPE
      experiment converges); the real loop is timed by ``mmpa experiment ipe`` (compute_s).
Every timed call is repeated ``--repeat`` times, interleaved with the reference on the same
pair, and the fastest kept (wall and CPU seconds, both pipelines alike): on a shared machine
the best of a few calls is the least disturbed. Prints mean/max E_t (mm), E_R (paper eq.
12-13), median seconds, speedup ratios (wall, and CPU time of all threads) and one VERDICT
line per case against the issue's target (>= 5x at equal or better accuracy). Exits 0.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import argparse
import json
import platform
import time
from collections.abc import Callable

import numpy as np
import open3d as o3d

from mmpa.core.geometry import Array, inv, rotation_error, translation_error
from mmpa.registration import RegistrationConfig, prepare, refine_projective, register
from mmpa.robot.interfaces import PointCloud

_reg = o3d.pipelines.registration
_KD = o3d.geometry.KDTreeSearchParamHybrid


def open3d_reference(src: PointCloud, tgt: PointCloud, seed: int = 0) -> Array:
    """Open3D's documented FPFH + FGR (2 cm) then colored ICP 4/2/1 cm x 50/30/14."""

    def o3c(pc: PointCloud) -> o3d.geometry.PointCloud:
        x = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pc.points))
        x.colors = o3d.utility.Vector3dVector(pc.colors)
        return x

    s, t = o3c(src), o3c(tgt)
    v = 0.02

    def feat(x: o3d.geometry.PointCloud) -> tuple:
        y = x.voxel_down_sample(v)
        y.estimate_normals(_KD(2 * v, 30))
        return y, _reg.compute_fpfh_feature(y, _KD(5 * v, 100))

    (sd, sf), (td, tf) = feat(s), feat(t)
    o3d.utility.random.seed(seed)
    opt = _reg.FastGlobalRegistrationOption(maximum_correspondence_distance=0.5 * v)
    T = _reg.registration_fgr_based_on_feature_matching(sd, td, sf, tf, opt).transformation
    for r, it in zip((0.04, 0.02, 0.01), (50, 30, 14), strict=True):
        a, b = s.voxel_down_sample(r), t.voxel_down_sample(r)
        a.estimate_normals(_KD(2 * r, 30))
        b.estimate_normals(_KD(2 * r, 30))
        T = _reg.registration_colored_icp(
            a,
            b,
            r,
            T,
            _reg.TransformationEstimationForColoredICP(),
            _reg.ICPConvergenceCriteria(1e-6, 1e-6, it),
        ).transformation
    return np.asarray(T)


def make_pairs(n: int, seed: int, near: bool) -> tuple[PointCloud, list[tuple[PointCloud, Array]]]:
    """Taught cloud at Site 1 and ``n`` current clouds with their true ``T_current_taught``;
    the current depth frames are kept in ``FRAMES`` (same order)."""
    from mmpa.backends.twin.world import SimWorld

    rng = np.random.default_rng(seed)
    with SimWorld(site="1") as w:
        q = np.array(w.nominal.arm.view_bench)
        site = w.scene.site("1").pose2d
        w.reset(site="1", q_arm=q)
        taught = w.camera.capture().to_point_cloud(min_depth=0.2, max_depth=3.0)
        T0 = w.truth.T_map_camera()
        out = []
        for _ in range(n):
            if near:  # camera already back near its taught viewpoint (IPE k >= 2)
                d = rng.uniform(1e-3, 3e-3) * rng.choice([-1, 1], 2)
                off = np.array([d[0], d[1], np.deg2rad(rng.uniform(0.1, 0.3))])
            else:  # a parking error like paper 000 Table 2
                off = np.array([*rng.normal(0, 0.025, 2), np.deg2rad(rng.normal(0, 1.5))])
            w.reset(pose2d=np.asarray(site) + off, q_arm=q)
            frame = w.camera.capture()
            FRAMES.append(frame)
            cur = frame.to_point_cloud(min_depth=0.2, max_depth=3.0)
            out.append((cur, inv(w.truth.T_map_camera()) @ T0))
    return taught, out


FRAMES: list = []


def timed(f: Callable[[], Array]) -> tuple[Array, float]:
    t0 = time.perf_counter()
    T = f()
    return T, time.perf_counter() - t0


def best_of(f: Callable[[], object], repeat: int) -> tuple[object, float, float]:
    """``f()``'s result and the smallest wall and CPU (all threads) seconds of ``repeat``
    calls (the least disturbed by other processes)."""
    out, wall, cpu = None, np.inf, np.inf
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = f()
        wall = min(wall, time.perf_counter() - w0)
        cpu = min(cpu, time.process_time() - c0)
    return out, wall, cpu


def errs(T_true: Array, T: Array) -> tuple[float, float]:
    return translation_error(T_true, T) * 1e3, rotation_error(T_true, T)


#: (case, label, reference case)
CASES = (
    ("reference", "Open3D documented (parking pairs)", "reference"),
    ("cold", "ours, both raw", "reference"),
    ("ipe_first", "ours, taught prepared (IPE k=1)", "reference"),
    ("ref_near", "Open3D documented (near pairs)", "ref_near"),
    ("ipe_init", "ours, init=I (IPE k>=2)", "ref_near"),
    ("ipe_proj", "ours, init=I + projective", "ref_near"),
)
TARGET = 5.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per pair (best kept)")
    ap.add_argument("--set", action="append", default=[], help="RegistrationConfig key=value")
    a = ap.parse_args()
    over = {k: json.loads(v) for k, v in (s.split("=", 1) for s in a.set)}
    cfg = RegistrationConfig(**over)
    print(
        f"mmpa registration benchmark  {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cpus, open3d {o3d.__version__}, config overrides {over}, "
        f"best of {a.repeat} calls per pair, load average {os.getloadavg()[0]:.2f}"
    )
    taught, far = make_pairs(a.pairs, a.seed, near=False)
    FRAMES.clear()
    _, near = make_pairs(a.pairs, a.seed + 1, near=True)
    near_frames = list(FRAMES)
    open3d_reference(taught, far[0][0])  # warm up Open3D
    register(taught, far[0][0], cfg)

    # case -> per pair (E_t mm, E_R, wall s, cpu s, ok)
    rows: dict[str, list[tuple[float, float, float, float, bool]]] = {c[0]: [] for c in CASES}
    t_prep = []
    shifts: list[tuple[float, float]] = []
    stage_t: dict[str, dict[str, list[float]]] = {"ipe_first": {}, "ipe_init": {}}

    def keep_stages(case: str, st: dict) -> None:
        for k, v in st.items():
            if k.endswith("_s"):
                stage_t[case].setdefault(k, []).append(v)

    def run(case: str, f: Callable[[], object], T_true: Array) -> object:
        out, wall, cpu = best_of(f, a.repeat)
        T, ok = (out, True) if isinstance(out, np.ndarray) else (out.T, out.ok)
        rows[case].append((*errs(T_true, T), wall, cpu, ok))
        if not ok:
            print(f"  {case} failed: {out.reason}")
        return out

    for cur, T_true in far:
        run("reference", lambda cur=cur: open3d_reference(taught, cur, cfg.seed), T_true)
        run("cold", lambda cur=cur: register(taught, cur, cfg), T_true)
        P, wall, _ = best_of(lambda: prepare(taught, cfg), a.repeat)
        t_prep.append(wall)
        r = run("ipe_first", lambda cur=cur, P=P: register(P, cur, cfg), T_true)
        keep_stages("ipe_first", r.stages)
        shifts.append(
            (r.stages.get("fine_shift_m", np.nan), r.stages.get("fine_rotation_deg", np.nan))
        )
    P = prepare(taught, cfg)
    t_proj = []
    for (cur, T_true), fr in zip(near, near_frames, strict=True):
        run("ref_near", lambda cur=cur: open3d_reference(taught, cur, cfg.seed), T_true)
        r = run("ipe_init", lambda cur=cur: register(P, cur, cfg, init=np.eye(4)), T_true)
        keep_stages("ipe_init", r.stages)

        def both(cur=cur, fr=fr):  # the IPE's per-view compute: registration + projective
            r = register(P, cur, cfg, init=np.eye(4))
            return refine_projective(taught.points, fr.depth, fr.intrinsics, r.T)

        pr = run("ipe_proj", both, T_true)
        t_proj.append(pr.seconds)

    def summary(k: str) -> dict[str, float]:
        x = np.array(rows[k], float)
        return {
            "E_t": x[:, 0].mean(),
            "E_t_max": x[:, 0].max(),
            "E_R": x[:, 1].mean(),
            "E_R_max": x[:, 1].max(),
            "wall": float(np.median(x[:, 2])),
            "cpu": float(np.median(x[:, 3])),
            "ok": x[:, 4].mean(),
        }

    S = {k: summary(k) for k, _, _ in CASES}
    print(
        f"\n{'case':<34}{'E_t mean':>9}{'E_t max':>9}{'E_R mean':>10}{'E_R max':>9}"
        f"{'median s':>10}{'ok':>6}{'speedup':>9}{'CPU x':>7}"
    )
    for k, label, base in CASES:
        x, b = S[k], S[base]
        print(
            f"{label:<34}{x['E_t']:9.3f}{x['E_t_max']:9.3f}{x['E_R']:10.5f}{x['E_R_max']:9.5f}"
            f"{x['wall']:10.4f}{x['ok']:6.2f}{b['wall'] / x['wall']:9.2f}{b['cpu'] / x['cpu']:7.2f}"
        )
    ipe = S["ipe_first"]["wall"] + float(np.median(t_proj)) + S["ipe_proj"]["wall"]
    print(
        f"\nprepare(taught) median {np.median(t_prep):.4f} s (once per task); IPE compute "
        f"estimate without a localization prior, 2 views as in `mmpa experiment ipe` "
        f"(global k=1 + projective, then init + projective) {ipe:.3f} s (target <= 0.5 s; "
        f"the experiment measures the real loop: compute_s)"
    )
    sh = np.array(shifts)
    print(
        f"fine stage moved from the FGR pose by up to {1e3 * sh[:, 0].max():.1f} mm / "
        f"{sh[:, 1].max():.2f} deg (limits {1e3 * cfg.max_fine_shift:.0f} mm / "
        f"{cfg.max_fine_rotation_deg} deg)"
    )
    for case, st in stage_t.items():
        print(
            f"stages {case} (median ms): "
            + ", ".join(f"{k[:-2]} {1e3 * np.median(v):.1f}" for k, v in st.items())
        )
    print(
        f"\ntarget: speedup >= {TARGET:g}x over Open3D's documented pipeline, same pairs, same "
        "run, at equal or better accuracy (mean E_t and mean E_R against the truth); the IPE "
        "registers a taught cloud prepared once per task (IPE k=1, k>=2 rows), 'both raw' "
        "prepares both clouds inside every call; 'info': the IPE's whole per-view compute"
    )
    for k, label, base in CASES:
        if k == base:
            continue
        x, b = S[k], S[base]
        ratio = b["wall"] / x["wall"]
        acc = x["E_t"] <= b["E_t"] and x["E_R"] <= b["E_R"] and x["ok"] == 1.0
        verdict = "PASS" if ratio >= TARGET and acc else "FAIL"
        if k == "ipe_proj":  # registration + a refinement Open3D's pipeline does not do
            verdict = "info"
        print(
            f"VERDICT {verdict}  {label}: {ratio:.2f}x wall (CPU {b['cpu'] / x['cpu']:.2f}x) vs "
            f"{TARGET:g}x; E_t {x['E_t']:.3f} vs {b['E_t']:.3f} mm, E_R {x['E_R']:.5f} vs "
            f"{b['E_R']:.5f}: accuracy {'equal or better' if acc else 'WORSE'}"
        )


if __name__ == "__main__":
    main()

"""Issue 23's calibration targets in the twin under ``realistic``, over robot instances.

Run on purpose: ``python benchmarks/bench_calibration.py [--seeds 0-9] [--survey-seeds 0-4]
[--workers 2] [--out DIR]``. Each seed is one robot instance of the error model (its true DH,
hand-eye, lidar mount, reflector biases). Per seed it runs

- ``mmpa calibrate hand-eye`` at its defaults (joint DH + hand-eye fit, 40 views) and prints
  the error against the TRUE hand-eye, against its identifiable part ``E6 X`` (the last DH
  link's error ``E6`` is indistinguishable from the hand-eye for any flange-mounted sensor),
  ``|E6|`` itself and OpenCV's best method against ``E6 X``;
- ``mmpa calibrate reflectors`` at its defaults and, for comparison, with the paper's
  mean-angle reflector bearings and 10 scans per stop (the defaults before stop 23);

then one line per target (0.5 mm / 0.1 deg; 3 mm mean) with how many seeds meet it. With
``--out``: ``calibration.json`` (every figure) and ``calibration.png`` (the two panels).
Always exits 0.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "osmesa")
if os.environ["MUJOCO_GL"] == "osmesa":
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

HAND_EYE_MM, HAND_EYE_DEG, SURVEY_MM = 0.5, 0.1, 3.0
PAPER_SETTING = "mean-angle bearing, 10 scans (before)"
DEFAULT_SETTING = "intensity bearing, 30 scans (default)"


def _seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def hand_eye(seed: int) -> dict:
    from mmpa.apps.calibrate import HandEyeConfig, run_hand_eye

    s = run_hand_eye(HandEyeConfig(seed=seed), None, log=lambda m: None)
    cv = s["by_method"]["opencv"]
    return {
        "seed": seed,
        "true_mm": s["error_trans_mm"],
        "true_deg": s["error_rot_deg"],
        "identifiable_mm": s["error_identifiable_trans_mm"],
        "identifiable_deg": s["error_identifiable_rot_deg"],
        "e6_mm": s["diagnostic"]["last_link_dh_error_trans_mm"],
        "e6_deg": s["diagnostic"]["last_link_dh_error_rot_deg"],
        "opencv_identifiable_mm": cv["error_vs_effective_trans_mm"],
        "opencv_identifiable_deg": cv["error_vs_effective_rot_deg"],
        "nominal_mm": s["nominal_error_trans_mm"],
        "wall_s": s["wall_s"],
    }


def survey(seed: int, paper: bool) -> dict:
    from mmpa.apps.calibrate import ReflectorSurveyConfig, run_reflector_survey

    extra = {"scans": 10, "detection": {"bearing": "mean"}} if paper else {}
    s = run_reflector_survey(ReflectorSurveyConfig(seed=seed, **extra), None, log=lambda m: None)
    return {
        "seed": seed,
        "setting": PAPER_SETTING if paper else DEFAULT_SETTING,
        "mean_mm": s["error_mean_mm"],
        "max_mm": s["error_max_mm"],
        "found": s["found"],
        "missed": s["missed"],
        "spurious": s["spurious"],
        "marked_map_mm": s["diagnostic"]["marked_map"]["error_mean_mm"],
        "wall_s": s["wall_s"],
    }


def _plot(he: list[dict], sv: list[dict], path: Path) -> None:
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.2))
    FigureCanvasAgg(fig)
    ax1, ax2 = fig.subplots(1, 2)
    x = np.array([r["seed"] for r in he])
    w = 0.2
    for k, (key, label) in enumerate(
        [
            ("true_mm", "joint vs the true hand-eye"),
            ("identifiable_mm", "joint vs E6 X (identifiable)"),
            ("opencv_identifiable_mm", "OpenCV vs E6 X"),
            ("e6_mm", "|E6| (last DH link, unobservable)"),
        ]
    ):
        ax1.bar(x + (k - 1.5) * w, [r[key] for r in he], w, label=label)
    ax1.axhline(HAND_EYE_MM, color="k", ls="--", lw=1, label="target 0.5 mm")
    ax1.set(xlabel="robot instance (seed)", ylabel="translation error (mm)", xticks=x)
    ax1.set_title("hand-eye, realistic, 40 views")
    ax1.legend(fontsize=7)
    seeds = sorted({r["seed"] for r in sv})
    for k, setting in enumerate([PAPER_SETTING, DEFAULT_SETTING]):
        rows = {r["seed"]: r for r in sv if r["setting"] == setting}
        xs = np.array([s for s in seeds if s in rows])
        ax2.bar(xs + (k - 0.5) * 0.35, [rows[s]["mean_mm"] for s in xs], 0.35, label=setting)
    ax2.axhline(SURVEY_MM, color="k", ls="--", lw=1, label="target 3 mm")
    ax2.set(xlabel="robot instance (seed)", ylabel="mean error (mm)", xticks=seeds)
    marked = [r["marked_map_mm"] for r in sv]
    ax2.set_title(
        f"reflector survey, realistic (the marked map: {min(marked):.0f}-{max(marked):.0f} mm)"
    )
    ax2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-9", help="hand-eye robot instances, e.g. 0-9 or 0,3")
    ap.add_argument("--survey-seeds", default="0-4", help="reflector survey robot instances")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None, help="only redraw a calibration.json")
    a = ap.parse_args()
    if a.plot is not None:
        d = json.loads(a.plot.read_text())
        _plot(d["hand_eye"], d["survey"], a.plot.with_suffix(".png"))
        return 0
    ctx = multiprocessing.get_context("spawn")  # MuJoCo / OSMesa are not fork-safe
    with ProcessPoolExecutor(max_workers=a.workers, mp_context=ctx) as pool:
        he_f = [pool.submit(hand_eye, s) for s in _seeds(a.seeds)]
        sv_f = [pool.submit(survey, s, p) for s in _seeds(a.survey_seeds) for p in (False, True)]
        he = [f.result() for f in he_f]
        sv = [f.result() for f in sv_f]
    print("hand-eye (mm / deg): seed, true, identifiable E6 X, |E6|, OpenCV vs E6 X")
    for r in he:
        print(
            f"  {r['seed']}: {r['true_mm']:.2f} / {r['true_deg']:.3f}   "
            f"{r['identifiable_mm']:.2f} / {r['identifiable_deg']:.3f}   "
            f"{r['e6_mm']:.2f} / {r['e6_deg']:.3f}   "
            f"{r['opencv_identifiable_mm']:.2f} / {r['opencv_identifiable_deg']:.3f}"
        )
    print("reflector survey (mm): seed, setting, mean, max, found/missed/spurious")
    for r in sv:
        print(
            f"  {r['seed']}: {r['setting']:38s} {r['mean_mm']:.2f} {r['max_mm']:.2f} "
            f"{r['found']}/{r['missed']}/{r['spurious']}"
        )

    def met(rows: list[dict], key_mm: str, key_deg: str) -> int:
        return sum(r[key_mm] <= HAND_EYE_MM and r[key_deg] <= HAND_EYE_DEG for r in rows)

    n = len(he)
    print(f"TARGET hand-eye vs true within 0.5 mm / 0.1 deg: {met(he, 'true_mm', 'true_deg')}/{n}")
    print(
        f"TARGET hand-eye vs E6 X within 0.5 mm / 0.1 deg: "
        f"{met(he, 'identifiable_mm', 'identifiable_deg')}/{n}"
    )
    dflt = [r for r in sv if r["setting"] == DEFAULT_SETTING]
    ok = sum(r["mean_mm"] <= SURVEY_MM and r["missed"] == 0 for r in dflt)
    print(f"TARGET reflector survey mean within 3 mm: {ok}/{len(dflt)}")
    if a.out is not None:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "calibration.json").write_text(
            json.dumps({"hand_eye": he, "survey": sv}, indent=2) + "\n"
        )
        _plot(he, sv, a.out / "calibration.png")
        print(f"wrote {a.out}/calibration.json and {a.out}/calibration.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

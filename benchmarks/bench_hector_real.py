"""Hector on the real CARMEN logs (issue 34 item 3): tracking from the true pose and the
fit from the true pose, per log.

For each log in ``/work/shared/real-data/laser`` (or ``--root``): the map is built from all
its scans at the corrected poses (:func:`~mmpa.maps.from_scans.occupancy_from_scans`, 5 cm,
lidar at the base origin: the logs' ``robot_frontlaser_offset`` is 0), then

- ``track``: ``make_localizer("hector")`` (health monitor included, as ``mmpa localize``
  runs it) from the first corrected pose, fed every scan with the wheel odometry; the
  position error against the corrected pose (median, p95, max, mm), the matcher's refusals
  (``ok=False`` of its own, with the first reasons) and the monitor's ``ok=False`` count,
  the time per update;
- ``one step``: every ``--every``-th scan matched from its true pose: the displacement of a
  single step on the finest level (``levels=1, iterations=1``, no search) and of the full
  fit (no search), and the score at the truth and after the fit (medians).

The corrected trajectory is itself a SLAM estimate (a few cm), so errors of 1-3 cm are what
the map and the trajectory agree to, not the matcher's alone.

Run::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_hector_real.py [--paper] \\
        [--set search_xy=0 --set levels=2] [--logs intel,csail,freiburg-079] [--every 5]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from mmpa.backends.bag.carmen import CarmenLog, read_carmen
from mmpa.localization.hector import HectorConfig, HectorMatcher
from mmpa.localization.localizer import make_localizer
from mmpa.maps.from_scans import occupancy_from_scans
from mmpa.maps.occupancy import OccupancyGrid

REAL = Path("/work/shared/real-data/laser")
LOGS = ("intel", "csail", "freiburg-079")


def _stats(e_mm: np.ndarray) -> dict[str, float]:
    return {
        "median_mm": round(float(np.median(e_mm)), 1),
        "p95_mm": round(float(np.percentile(e_mm, 95)), 1),
        "max_mm": round(float(e_mm.max()), 1),
    }


def track(log: CarmenLog, grid: OccupancyGrid, cfg: HectorConfig) -> dict[str, Any]:
    """Hector (monitored) over the whole log from the first corrected pose."""
    loc = make_localizer("hector", grid, np.zeros(3), np.random.default_rng(0), hector=cfg)
    loc.initialize(log.poses[0])
    err, not_ok, reasons = [], 0, []
    before = 0
    t0 = time.perf_counter()
    for k in range(len(log)):
        est = loc.update(log.odometry[k], log.scans[k])
        err.append(np.hypot(*(loc.pose_at(log.odometry[k])[:2] - log.poses[k][:2])))
        not_ok += not est.ok
        if loc.refusals > before:
            reasons.append(loc.last_refusal)
            before = loc.refusals
    dt = (time.perf_counter() - t0) / len(log)
    out: dict[str, Any] = _stats(np.array(err) * 1e3)
    out["over_0.5m"] = int(np.sum(np.array(err) > 0.5))
    out["refusals"] = int(loc.refusals)
    kinds = (re.sub(r"-?\d+(\.\d+)?", "#", r) for r in reasons)  # one per kind of reason
    out["refusal_reasons"] = list(dict.fromkeys(kinds))[:3]
    out["monitor_not_ok"] = int(not_ok)
    out["ms_per_update"] = round(dt * 1e3, 2)
    return out


def one_step(log: CarmenLog, grid: OccupancyGrid, cfg: HectorConfig, every: int) -> dict:
    """Moves of one finest-level step and of the whole fit from the true pose."""
    no_search = {"search_xy": 0.0, "search_theta": 0.0}
    single = HectorMatcher(
        grid, np.zeros(3), cfg.model_copy(update={**no_search, "levels": 1, "iterations": 1})
    )
    full = HectorMatcher(grid, np.zeros(3), cfg.model_copy(update=no_search))
    m1, mf, s0, sf = [], [], [], []
    for k in range(0, len(log), every):
        pts = full._endpoints_base(log.scans[k])
        truth = log.poses[k]
        m1.append(np.hypot(*(single.fit(truth, pts).pose[:2] - truth[:2])))
        f = full.fit(truth, pts)
        mf.append(np.hypot(*(f.pose[:2] - truth[:2])))
        s0.append(full.score(truth, pts))
        sf.append(f.score)
    return {
        "one_step_median_mm": round(float(np.median(m1)) * 1e3, 1),
        "fit_from_truth": _stats(np.array(mf) * 1e3),
        "score_truth": round(float(np.median(s0)), 3),
        "score_fit": round(float(np.median(sf)), 3),
    }


def _config(args: argparse.Namespace) -> HectorConfig:
    base = HectorConfig.paper() if args.paper else HectorConfig()
    upd: dict[str, Any] = {}
    for kv in args.set:
        key, val = kv.split("=", 1)
        upd[key] = json.loads(val) if val[:1] in "-0123456789[{tf" else val
    return HectorConfig.model_validate({**base.model_dump(), **upd})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", type=Path, default=REAL)
    ap.add_argument("--logs", default=",".join(LOGS))
    ap.add_argument("--paper", action="store_true", help="HectorConfig.paper()")
    ap.add_argument("--set", action="append", default=[], help="HectorConfig field=value")
    ap.add_argument("--every", type=int, default=5, help="one-step check: every n-th scan")
    ap.add_argument("--no-track", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="JSON results")
    args = ap.parse_args(argv)
    cfg = _config(args)
    print("config:", cfg.model_dump(), flush=True)
    results: dict[str, Any] = {"config": cfg.model_dump()}
    for name in args.logs.split(","):
        path = args.root / f"{name}-corrected.log.gz"
        if not path.exists():
            print(f"{name}: no {path}, skipped")
            continue
        log = read_carmen(path)
        grid = occupancy_from_scans(log.poses, log.scans, 0.05)
        row: dict[str, Any] = {"scans": len(log)}
        row.update(one_step(log, grid, cfg, args.every))
        if not args.no_track:
            row["track"] = track(log, grid, cfg)
        results[name] = row
        print(f"{name}: {json.dumps(row)}", flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

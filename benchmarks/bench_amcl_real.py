"""AMCL on the real CARMEN logs (issue 34 item 3): the figures of docs/localization.md
"Real logs" (table "AMCL at its defaults").

For each log in ``/work/shared/real-data/laser`` (or ``--root``), through the pipeline of
``mmpa benchmark localization`` (:func:`~mmpa.apps.benchmark.run_pipeline`: the map built
from the log at 5 cm, the health monitor included, seed 0), one line per run:

- ``true``: from the first corrected pose, every scan (``--max-scans`` to cut);
- ``offset``: from 1 m / 30 deg off, in three directions (``--offsets``), the first 60 scans:
  the first scan within 10 cm and whether the error stays under 0.5 m from scan 30 on;
- ``global``: started without a pose (``global_localization``: the whole-map search of
  the first scan, ``mmpa.localization.global_search``), 60 scans, per laser model
  (``likelihood_field_prob``, ``beam``) and seed (``--seeds``, default 0-4), from scan 0 and
  from ``--starts`` scans spread evenly over the log (seed 0); each line also gives
  ``converged``: the first scan within 10 cm after which the error stays under 0.5 m
  (None: not converged), the median error from there, and the first update's time (s: the
  search, Hector's matches and the laser model on the seeded cloud).

Each line: median / p95 / max position error (mm), heading median (deg), the share within
10 cm, the first scan over 0.5 m after scan 30 (``diverged``), the median time per update
(ms, this machine). ``--set key=value`` changes the AMCL settings (``--set
scan_refine=false`` ...; ``--paper`` starts from Nav2's defaults).

Run::

    OMP_NUM_THREADS=1 nice -n 5 .venv/bin/python benchmarks/bench_amcl_real.py \\
        [--logs intel,csail,freiburg-079] [--runs true,offset,global] [--paper] [--set k=v] \\
        [--seeds 0,1,2,3,4] [--starts 10]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mmpa.apps.benchmark import BenchmarkConfig, run_pipeline
from mmpa.apps.benchmark_data import CarmenDataset
from mmpa.localization.config import AMCLConfig
from mmpa.localization.evaluation import error_statistics, trajectory_errors

REAL = Path("/work/shared/real-data/laser")
LOGS = ("intel", "csail", "freiburg-079")
OFFSETS = ((1.0, 0.0, 0.5236), (0.0, 1.0, -0.5236), (-0.7071, -0.7071, 0.5236))


def converged_at(pos: np.ndarray, within: float = 0.10, lost: float = 0.5) -> int | None:
    """The first scan within ``within`` m after which the error stays under ``lost`` m."""
    bad = np.flatnonzero(pos >= lost)
    first = int(bad[-1]) + 1 if bad.size else 0
    ok = np.flatnonzero(pos[first:] <= within)
    return first + int(ok[0]) if ok.size else None


def _line(ds: CarmenDataset, cfg: BenchmarkConfig) -> dict[str, Any]:
    run = run_pipeline(ds, cfg)
    s = error_statistics(run.estimate, run.truth, run.t, run.update_s)
    pos, _ = trajectory_errors(run.estimate, run.truth)
    near = np.flatnonzero(pos <= 0.10)
    conv = converged_at(pos)
    return {
        "converged": conv,
        "median_after_mm": None if conv is None else float(np.median(pos[conv:]) * 1e3),
        "first_update_s": float(run.update_s[0]),
        "scans": s["scans"],
        "median_mm": s["error_median_mm"],
        "p95_mm": s["error_p95_mm"],
        "max_mm": s["error_max_mm"],
        "heading_median_deg": s["heading_error_median_deg"],
        "within_10cm": s["within_10cm"],
        "first_within_10cm": int(near[0]) if near.size else None,
        "diverged": s["diverged_at_scan"],
        "ms_per_update": s["update_median_ms"],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", type=Path, default=REAL)
    ap.add_argument("--logs", default=",".join(LOGS))
    ap.add_argument("--runs", default="true,offset,global")
    ap.add_argument("--max-scans", type=int, default=None)
    ap.add_argument("--paper", action="store_true", help="Nav2's defaults (AMCLConfig.paper())")
    ap.add_argument("--set", action="append", default=[], help="an AMCL setting, key=value")
    ap.add_argument("--seeds", default="0,1,2,3,4", help="global: the seeds from scan 0")
    ap.add_argument("--starts", type=int, default=10, help="global: start scans over the log")
    a = ap.parse_args(argv)
    base = AMCLConfig.paper() if a.paper else AMCLConfig()
    sets = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in a.set)}
    amcl = AMCLConfig.model_validate(base.model_dump() | sets)
    runs = a.runs.split(",")
    for name in a.logs.split(","):
        path = a.root / f"{name}-corrected.log.gz"
        if not path.exists():
            print(f"{path}: missing", file=sys.stderr)
            return 2
        ds = CarmenDataset(path)
        jobs: list[tuple[str, dict[str, Any]]] = []
        if "true" in runs:
            jobs.append(("true", {"max_scans": a.max_scans}))
        if "offset" in runs:
            jobs += [(f"offset {o}", {"max_scans": 60, "initial_offset": o}) for o in OFFSETS]
        if "global" in runs:
            jobs += _global_jobs(len(ds), [int(v) for v in a.seeds.split(",")], a.starts)
        for label, kw in jobs:
            model = kw.pop("laser_model_type", None)
            cfg_amcl = (
                amcl if model is None else amcl.model_copy(update={"laser_model_type": model})
            )
            cfg = BenchmarkConfig(method="amcl", amcl=cfg_amcl, **kw)
            print(json.dumps({"log": name, "run": label, **_line(ds, cfg)}), flush=True)
    return 0


def _global_jobs(n: int, seeds: list[int], starts: int) -> list[tuple[str, dict[str, Any]]]:
    """The global runs: per laser model, every seed from scan 0, then seed 0 from ``starts``
    scans spread over the log (the first, 0, already run)."""
    jobs = []
    spread = np.linspace(0, n - 61, starts).astype(int)[1:] if starts > 1 else []
    for model in ("likelihood_field_prob", "beam"):
        kw = {"max_scans": 60, "global_localization": True, "laser_model_type": model}
        jobs += [(f"global {model} seed {sd}", kw | {"seed": sd}) for sd in seeds]
        jobs += [(f"global {model} start {int(st)}", kw | {"start": int(st)}) for st in spread]
    return jobs


if __name__ == "__main__":
    raise SystemExit(main())

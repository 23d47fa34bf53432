"""Trials in parallel (issue 21): wall time of ``mmpa experiment ipe --trials N`` with
``--workers 1`` and ``--workers W`` (run on purpose: ``python benchmarks/bench_workers.py
[--trials 4] [--workers 2] [--executor local|ray]``).

Each run is a separate ``mmpa`` process (start-up, teaching and the trials all counted; with
``--executor ray``, starting and stopping its local Ray too, unless ``--ray-address`` names a
running cluster), on the same configuration; the script prints both wall times, the speedup
(target >= 1.6x with two workers on two free cores), the peak memory per worker from the
rows, and whether the two ``results.csv`` agree but for the time and memory columns (they
must). The machine's load average is printed with the figures: other work on the cores
lowers the speedup.
Always exits 0 unless the rows differ.
"""

from __future__ import annotations

import argparse
import csv
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mmpa.harness.twin_trials import TIMING_COLUMNS

TARGET_SPEEDUP = 1.6
VARYING = TIMING_COLUMNS


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def run(
    trials: int, workers: int, executor: str, out: Path, extra: list[str]
) -> tuple[float, float]:
    """Wall time and CPU time (s, the command and its worker processes) of one run."""
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
    cmd = [sys.executable, "-m", "mmpa.cli.main", "experiment", "ipe", "--trials", str(trials)]
    cmd += ["--workers", str(workers), "--executor", executor, "--out", str(out), *extra]
    t0, c0 = time.perf_counter(), _children_cpu()
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0, _children_cpu() - c0


def rows(folder: Path) -> tuple[list[dict], list[float]]:
    with open(folder / "results.csv") as f:
        r = list(csv.DictReader(f))
    return [{k: v for k, v in x.items() if k not in VARYING} for x in r], [
        float(x["worker_rss_mb"]) for x in r
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--executor", default="local", choices=["local", "ray"])
    ap.add_argument("--set", action="append", default=[], help="an override, as mmpa --set")
    ap.add_argument(
        "--ray-address",
        help="a running Ray cluster (e.g. `ray start --head --num-cpus 2` here): the run "
        "connects to it instead of starting and stopping a local Ray of its own",
    )
    a = ap.parse_args()
    extra = [x for s in a.set for x in ("--set", s)]
    if a.ray_address:
        if a.executor != "ray":
            ap.error("--ray-address needs --executor ray")
    print(f"cores: {os.cpu_count()}, load average before: {os.getloadavg()}")
    with tempfile.TemporaryDirectory() as d:
        one = Path(d) / "w1"
        many = Path(d) / f"w{a.workers}"
        t1, c1 = run(a.trials, 1, "local", one, extra)
        print(f"--workers 1: {t1:.1f} s wall, {c1:.1f} s CPU (load {os.getloadavg()[0]:.2f})")
        at = ["--ray-address", a.ray_address] if a.ray_address else []
        tn, cn = run(a.trials, a.workers, a.executor, many, [*extra, *at])
        print(
            f"--workers {a.workers} --executor {a.executor}: {tn:.1f} s wall, {cn:.1f} s CPU "
            f"(load {os.getloadavg()[0]:.2f})"
        )
        # on free cores and with perfect balance the wall time is the CPU time over the
        # workers: the most the speedup can be (Ray's processes are not counted here)
        if a.executor == "local":
            bound = c1 / (cn / a.workers)
            print(f"speedup bound on {a.workers} free cores, from the CPU times: {bound:.2f}x")
        r1, _ = rows(one)
        rn, mem = rows(many)
        ok = r1 == rn
        speedup = t1 / tn
        verdict = "meets" if speedup >= TARGET_SPEEDUP else "below"
        print(f"speedup: {speedup:.2f}x ({verdict} the {TARGET_SPEEDUP}x target)")
        print(f"trials: {len(r1)} rows; peak worker memory {max(mem):.0f} MB")
        print(f"rows identical but for time/memory columns: {ok}")
        diff = [
            (x.get("method"), x["site"], x["trial"], k, x[k], y.get(k))
            for x, y in zip(r1, rn, strict=False)
            for k in x
            if x[k] != y.get(k)
        ]
        for d in diff[:10]:
            print("  differs (method, site, trial, column, workers 1, workers N):", d)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

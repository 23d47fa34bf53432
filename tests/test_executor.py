"""Trials on executors (issue 21): each trial seeded on its own, the same rows whatever the
executor and worker count, streamed to a journal, resumable."""

from __future__ import annotations

import csv
import json
import os
import shutil
import time

import pytest

from mmpa.core.errors import ConfigError, MMPAError
from mmpa.harness import executor as ex
from mmpa.harness.twin_trials import TIMING_COLUMNS

# ---------------------------------------------------------------------------------------
# the executors on toy jobs (no simulator)


def slow_square(x: int, delay: float) -> dict:
    """A job that finishes later the larger ``delay``: the early jobs finish last."""
    time.sleep(delay)
    return {"x": x, "sq": x * x, "pid": os.getpid(), "omp": os.environ.get("OMP_NUM_THREADS")}


def failing(x: int) -> int:
    raise ValueError(f"bad input {x}")


def _jobs(n: int):
    return [({"site": "1", "trial": i}, slow_square, (i, 0.05 * (n - i))) for i in range(n)]


def test_serial_journal_and_order(tmp_path):
    seen = []
    with ex.SerialExecutor(tmp_path) as e:
        recs = e.run(_jobs(3), lambda done, total, rec: seen.append((done, total, rec["key"])))
    assert [r["result"]["sq"] for r in recs] == [0, 1, 4]
    assert [s[:2] for s in seen] == [(1, 3), (2, 3), (3, 3)]
    lines = (tmp_path / ex.JOURNAL).read_text().splitlines()
    assert [json.loads(x)["key"]["trial"] for x in lines] == [0, 1, 2]
    assert all(r["worker_rss_mb"] > 10 and r["trial_s"] >= 0 for r in recs)


def test_process_executor_returns_job_order_from_other_processes(tmp_path, monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    order = []
    with ex.ProcessExecutor(2, tmp_path) as e:
        recs = e.run(_jobs(4), lambda done, total, rec: order.append(rec["key"]["trial"]))
    assert [r["result"]["x"] for r in recs] == [0, 1, 2, 3]  # job order, not finish order
    assert sorted(order) == [0, 1, 2, 3]
    pids = {r["result"]["pid"] for r in recs}
    assert os.getpid() not in pids and len(pids) == 2
    # the workers run single-threaded; this process's environment is left as it was
    assert {r["result"]["omp"] for r in recs} == {"1"}
    assert "OMP_NUM_THREADS" not in os.environ


def test_prestarted_workers_are_taken_over_or_stopped(tmp_path):
    """``prestart`` starts the workers (they import the heavy modules) before the executor
    exists; the next ProcessExecutor of that size runs its jobs on them. Workers that no
    executor takes are stopped by ``discard_prestarted``."""
    ex.prestart("local", 2, "json")  # a light module: the mechanism, not MuJoCo's import
    pool = ex._PRESTARTED[2]
    warm = {p.pid for p in pool._processes.values()}  # spawned at prestart
    with ex.ProcessExecutor(2, tmp_path) as e:
        recs = e.run(_jobs(2))
        assert e._pool is pool and 2 not in ex._PRESTARTED
    assert len(warm) == 2 and {r["result"]["pid"] for r in recs} <= warm
    ex.prestart("local", 3, "json")
    procs = list(ex._PRESTARTED[3]._processes.values())
    ex.prestart("ray", 2)  # nothing for Ray
    assert set(ex._PRESTARTED) == {3}
    ex.discard_prestarted()
    assert not ex._PRESTARTED and procs
    assert all(not p.is_alive() for p in procs)


def test_ray_workers_run_single_threaded_and_leave_the_environment(tmp_path, monkeypatch):
    pytest.importorskip("ray")  # the dev extra has it
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    # a job Ray's workers can import: the variable as the worker sees it
    jobs = [({"trial": i}, os.getenv, ("OMP_NUM_THREADS",)) for i in range(2)]
    with ex.RayExecutor(2, tmp_path) as e:
        recs = e.run(jobs, lambda *a: None)
    assert [r["result"] for r in recs] == ["1", "1"]
    assert "OMP_NUM_THREADS" not in os.environ


def test_worker_thread_counts_set_in_the_environment_win(tmp_path, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert "OMP_NUM_THREADS" not in ex.worker_env()
    with ex.ProcessExecutor(2, tmp_path) as e:
        recs = e.run(_jobs(2), lambda *a: None)
    assert {r["result"]["omp"] for r in recs} == {"3"}
    assert os.environ["OMP_NUM_THREADS"] == "3"


def test_resume_skips_journaled_trials_and_ignores_a_torn_last_line(tmp_path):
    with ex.SerialExecutor(tmp_path) as e:
        first = e.run(_jobs(2))
    with open(tmp_path / ex.JOURNAL, "a") as f:
        f.write('{"key": {"site": "1", "tri')  # killed while writing
    calls = []
    with ex.SerialExecutor(tmp_path, resume=True) as e:
        recs = e.run(_jobs(3), lambda done, total, rec: calls.append(rec["key"]["trial"]))
    assert calls == [2]  # only the missing trial ran
    assert recs[:2] == first and recs[2]["result"]["sq"] == 4
    # without resume the journal starts over
    with ex.SerialExecutor(tmp_path) as e:
        e.run(_jobs(1))
    assert len((tmp_path / ex.JOURNAL).read_text().splitlines()) == 1


def test_worker_errors_name_the_trial(tmp_path):
    with ex.ProcessExecutor(2, tmp_path) as e, pytest.raises(MMPAError, match="bad input 7"):
        e.run([({"site": "2", "trial": 7}, failing, (7,))])
    with pytest.raises(ConfigError, match="workers"):
        ex.make_executor("local", 0)
    with pytest.raises(ConfigError, match="valid: local, ray"):
        ex.make_executor("slurm", 2)
    with pytest.raises(ConfigError, match="--executor ray"):
        ex.make_executor("local", 2, address="127.0.0.1:6379")


def test_plain_keeps_nan_and_drops_numpy_types():
    import math

    import numpy as np

    v = ex.plain({"a": np.float64(math.nan), "b": [np.int64(3), np.array([1.5])], "c": True})
    assert math.isnan(v["a"]) and type(v["a"]) is float
    assert v["b"] == [3, [1.5]] and type(v["b"][0]) is int


# ---------------------------------------------------------------------------------------
# the ipe experiment in the twin (one site, no paper method, 2 trials)

SIM = {"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}
OVERRIDES = ["sites=[1]", "paper_method=false"]
VARYING = TIMING_COLUMNS  # time and memory


def _rows(folder) -> list[dict]:
    with open(folder / "results.csv") as f:
        return [{k: v for k, v in r.items() if k not in VARYING} for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    from mmpa.harness.runner import run_experiment

    for k, v in SIM.items():
        os.environ.setdefault(k, v)
    out = tmp_path_factory.mktemp("serial")
    run_experiment("ipe", out, trials=2, overrides=OVERRIDES)
    return out


# slow (10 s: IPE taught anew); the default run keeps per-trial seeding of a real experiment
# (test_servo_twin.py: test_a_grasp_cell_run_alone_repeats_its_trials_in_the_full_table,
# test_localization_experiments.py: test_kidnap_trial_does_not_depend_on_what_ran_before)
@pytest.mark.slow
def test_a_trial_alone_gives_its_row_of_the_full_run(serial_run):
    from mmpa.experiments.paper000 import ipe as mmpa_ipe
    from mmpa.harness.runner import _jsonable
    from mmpa.harness.twin_trials import TrialGroup, run_trial_groups

    cfg = mmpa_ipe.Config(trials=2, sites=["1"], paper_method=False)
    # a fresh twin: taught anew, trial 1 only (nothing ran before it in that world)
    ((rows, _),) = run_trial_groups(
        cfg, lambda s, f: None, [TrialGroup({"method": "mmpa"}, trials=[1])]
    )
    alone = {k: _jsonable(v) for k, v in rows[0].items() if k not in VARYING}
    full = _rows(serial_run)
    assert [r["trial"] for r in full] == ["0", "1"]
    assert full[0]["park_tx"] != full[1]["park_tx"]  # the trials differ
    assert {k: ("" if v is None else str(v)) for k, v in alone.items()} == full[1]


def test_two_workers_give_the_rows_of_one(serial_run, tmp_path):
    """The two trials on two worker processes, from the serial run's taught task (its
    ``taught/``, as a resumed run takes it: the suite's budget), give the serial rows."""
    from mmpa.harness.runner import run_experiment

    shutil.copytree(serial_run / "taught", tmp_path / "taught")
    out = run_experiment("ipe", tmp_path, trials=2, overrides=OVERRIDES, workers=2, resume=True)
    assert out.summary["executor"] == "local x2"
    assert _rows(tmp_path) == _rows(serial_run)
    with open(tmp_path / "results.csv") as f:
        mem = [float(r["worker_rss_mb"]) for r in csv.DictReader(f)]
    assert all(100 < m < 8000 for m in mem)


class InterruptError(Exception):
    pass


# slow (25 s: the suite budget); the default run keeps the journal's resume
# (test_resume_skips_journaled_trials_and_ignores_a_torn_last_line) and two workers' rows
@pytest.mark.slow
def test_an_interrupted_run_resumed_gives_the_rows_of_a_whole_one(serial_run, tmp_path):
    from mmpa.harness.runner import run_experiment

    def stop_after_first(stage: str, frac: float) -> None:
        if "done" in stage and "trial 1/2" in stage:
            raise InterruptError(stage)

    with pytest.raises(InterruptError):
        run_experiment("ipe", tmp_path, trials=2, overrides=OVERRIDES, progress=stop_after_first)
    assert not (tmp_path / "results.csv").exists()
    kept = [json.loads(x) for x in (tmp_path / ex.JOURNAL).read_text().splitlines()]
    assert [r["key"]["trial"] for r in kept] == [0]
    stages = []
    run_experiment(
        "ipe",
        tmp_path,
        trials=2,
        overrides=OVERRIDES,
        resume=True,
        progress=lambda s, f: stages.append(s),
    )
    assert not any("teaching" in s for s in stages)  # the taught bundle was reused
    assert _rows(tmp_path) == _rows(serial_run)
    with open(tmp_path / "results.csv") as f:
        first = next(csv.DictReader(f))
    assert float(first["trial_s"]) == pytest.approx(kept[0]["trial_s"])  # not run again


def test_resume_refuses_another_configuration(tmp_path):
    from mmpa.harness.runner import run_experiment

    (tmp_path / "config.yaml").write_text("seed: 5\n")
    with pytest.raises(ConfigError, match=r"config\.yaml.*seed"):
        run_experiment("ipe", tmp_path, trials=1, overrides=OVERRIDES, resume=True)


# slow (28 s on an idle machine, 480 s beside a busy core: Ray's start-up); the default run
# keeps Ray executing jobs (test_ray_workers_run_single_threaded_and_leave_the_environment)
# and the rows being the same on worker processes (test_two_workers_give_the_rows_of_one)
@pytest.mark.slow
def test_ray_gives_the_rows_of_one_process(serial_run, tmp_path):
    pytest.importorskip("ray")  # the dev extra has it
    from mmpa.harness.runner import run_experiment

    out = run_experiment("ipe", tmp_path, trials=2, overrides=OVERRIDES, workers=2, executor="ray")
    assert out.summary["executor"] == "ray x2"
    assert _rows(tmp_path) == _rows(serial_run)

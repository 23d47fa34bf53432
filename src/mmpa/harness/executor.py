"""Where an experiment's trials run: in this process, in local worker processes, or on Ray.

An experiment hands the executor a list of *jobs*, each a module-level function and its
arguments (plain, picklable values: JSON strings, dicts, paths), under a key that names the
trial in its run (``{"label": ..., "site": ..., "trial": ...}``). The executor

- runs them (:class:`SerialExecutor` here; :class:`ProcessExecutor` in ``N`` spawned
  processes, as MuJoCo, OSMesa and Open3D are not fork-safe; :class:`RayExecutor` as Ray
  tasks of ``num_cpus=1`` and :data:`TRIAL_MEMORY_BYTES` each, on a local Ray started with
  ``num_cpus=N`` or on the cluster at ``address``);
- streams each result back as it finishes: it is appended to the run folder's
  :data:`JOURNAL` (one JSON line per trial, flushed) and reported through ``on_result``, so
  an interrupted run keeps its finished trials, and a ``resume`` run skips them;
- returns the results in the order of the jobs, whatever order they finished in, so the
  run's files are the same for every executor and worker count.

Each worker runs its numerical libraries on one thread (:data:`WORKER_THREAD_ENV`, unless the
environment sets them): ``N`` workers each running a multi-threaded BLAS or OpenMP pool on
``N`` cores oversubscribe them (measured on 2 cores: ``mmpa experiment ipe --trials 4
--workers 2`` 35.0 -> 31.3 s wall).

Every result carries the job's wall time (``trial_s``) and the peak resident memory of the
process that ran it (``worker_rss_mb``, ``getrusage`` ``ru_maxrss``), the only figures
that differ between executors. A worker keeps what its jobs cache (a taught site's world)
between jobs.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import multiprocessing
import os
import resource
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import numpy as np

from mmpa.core.errors import ConfigError, MMPAError

__all__ = [
    "EXECUTORS",
    "JOURNAL",
    "TRIAL_MEMORY_BYTES",
    "Executor",
    "Job",
    "ProcessExecutor",
    "RayExecutor",
    "SerialExecutor",
    "discard_prestarted",
    "make_executor",
    "plain",
    "prestart",
    "read_journal",
]

#: the run folder's journal of finished trials (one JSON object a line)
JOURNAL = "rows.jsonl"
#: the memory a twin trial declares to Ray (bytes): one SimWorld with its renderer and clouds
TRIAL_MEMORY_BYTES = int(0.8e9)
#: executor kinds of ``mmpa experiment --executor``
EXECUTORS = ("local", "ray")
#: the thread counts a worker process starts with (those the environment sets win)
WORKER_THREAD_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
}


def worker_env() -> dict[str, str]:
    """The variables of :data:`WORKER_THREAD_ENV` this process's environment does not set."""
    return {k: v for k, v in WORKER_THREAD_ENV.items() if k not in os.environ}


@contextlib.contextmanager
def _spawn_env(env: dict[str, str]) -> Iterator[None]:
    """``env`` in ``os.environ`` while worker processes are spawned (they copy it)."""
    os.environ.update(env)
    try:
        yield
    finally:
        for k in env:
            os.environ.pop(k, None)


#: (key, function, args): ``key`` a JSON-able dict naming the trial in its run
Job = tuple[dict[str, Any], Callable[..., Any], tuple[Any, ...]]
OnResult = Callable[[int, int, dict[str, Any]], None]


def plain(v: Any) -> Any:
    """``v`` with numpy scalars and arrays turned into Python values (NaN and inf kept), so
    a result is the same value whether it was computed here or came back through JSON."""
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return plain(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    return v


def key_text(key: dict[str, Any]) -> str:
    """The canonical text of a job key (sorted JSON), used to match journal lines."""
    return json.dumps(plain(key), sort_keys=True)


def _call(fn: Callable[..., Any], args: tuple[Any, ...]) -> dict[str, Any]:
    """Run one job where it lands; never raises (an exception's text travels back)."""
    t0 = time.perf_counter()
    try:
        out = {"result": plain(fn(*args))}
    except Exception as e:  # reported by the driver, with the trial's key
        out = {"error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc()}
    out["trial_s"] = time.perf_counter() - t0
    out["worker_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return out


def _call_star(fn: Callable[..., Any], *args: Any) -> dict[str, Any]:
    """:func:`_call` with the arguments spread: Ray resolves object references given as
    top-level arguments only (a task bundle put in its store)."""
    return _call(fn, args)


def read_journal(path: Path) -> dict[str, dict[str, Any]]:
    """The finished trials of a run folder's journal: key text -> record. A torn last line
    (the run was killed while writing it) is ignored; a torn line elsewhere is an error."""
    if not path.exists():
        return {}
    lines = path.read_text().splitlines()
    done: dict[str, dict[str, Any]] = {}
    for i, line in enumerate(lines):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            done[key_text(rec["key"])] = rec
        except (ValueError, KeyError, TypeError):
            if i == len(lines) - 1:
                break
            raise ConfigError(f"{path}: line {i + 1} is not a trial record") from None
    return done


class Executor:
    """Runs jobs and journals their results (see the module docstring). ``out``: the run
    folder (None: nothing journaled); ``resume``: reuse the journal's finished trials."""

    kind = "serial"
    workers = 1

    def __init__(self, out: str | Path | None = None, resume: bool = False) -> None:
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        if out is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="mmpa-run-")
            self.out = Path(self._tmp.name)
            self.journaled = False
        else:
            self.out = Path(out)
            self.journaled = True
        self.out.mkdir(parents=True, exist_ok=True)
        self.resume = bool(resume)
        self._journal = self.out / JOURNAL
        if self.journaled and not self.resume and self._journal.exists():
            self._journal.unlink()  # a fresh run: the old trials are not this run's
        self._done = read_journal(self._journal) if self.resume else {}

    # --- what a subclass provides ----------------------------------------------------------
    def _imap(self, calls: Sequence[tuple[Callable[..., Any], tuple[Any, ...]]]) -> Iterator:
        """Yield ``(index, _call result)`` of ``calls`` as each finishes."""
        for i, (fn, args) in enumerate(calls):
            yield i, _call(fn, args)

    def bundle_handle(self, directory: Path) -> Any:
        """What a job is given to read the task bundle in ``directory``: its path here."""
        return str(directory)

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def describe(self) -> str:
        return f"{self.kind} x{self.workers}"

    # --- shared ----------------------------------------------------------------------------
    def map(self, fn: Callable[..., Any], args: Sequence[tuple[Any, ...]]) -> list[Any]:
        """``fn(*a)`` for each ``a`` (in parallel where the executor can), in order; nothing
        journaled. A failed call raises :class:`MMPAError` with the worker's message."""
        out: list[Any] = [None] * len(args)
        for i, res in self._imap([(fn, a) for a in args]):
            out[i] = _unwrap(res, f"{getattr(fn, '__name__', fn)}{args[i]!r:.120}")
        return out

    def run(
        self,
        jobs: Sequence[Job],
        on_result: OnResult | None = None,
        order: Sequence[int] | None = None,
    ) -> list[dict]:
        """Run ``jobs``; returns their records ``{"key", "result", "trial_s",
        "worker_rss_mb"}`` in job order. Trials already in the journal (``resume``) are not
        run again; every new one is appended to the journal as it finishes and reported as
        ``on_result(done, total, record)``. ``order``: the job indices in the order to hand
        them out (e.g. the trials of one site together, so a worker reuses its world);
        default the job order."""
        keys = [key_text(k) for k, _, _ in jobs]
        if len(set(keys)) != len(keys):
            raise MMPAError("two trials of the run share a key: their rows would collide")
        records: list[dict | None] = [self._done.get(k) for k in keys]
        order = list(range(len(jobs))) if order is None else [int(i) for i in order]
        if sorted(order) != list(range(len(jobs))):
            raise MMPAError("order must be a permutation of the job indices")
        todo = [i for i in order if records[i] is None]
        total, done = len(jobs), len(jobs) - len(todo)
        calls = [(jobs[i][1], jobs[i][2]) for i in todo]
        with open(self._journal, "a") if self.journaled else _NullFile() as journal:
            for j, res in self._imap(calls):
                i = todo[j]
                rec = {
                    "key": plain(jobs[i][0]),
                    "result": _unwrap(res, f"trial {keys[i]}"),
                    "trial_s": res["trial_s"],
                    "worker_rss_mb": res["worker_rss_mb"],
                }
                journal.write(json.dumps(rec) + "\n")
                journal.flush()
                self._done[keys[i]] = rec
                records[i] = rec
                done += 1
                if on_result is not None:
                    on_result(done, total, rec)
        return [r for r in records if r is not None]


class _NullFile:
    def write(self, s: str) -> int:
        return len(s)

    def flush(self) -> None:
        pass

    def __enter__(self) -> _NullFile:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def _unwrap(res: dict[str, Any], what: str) -> Any:
    if "error" in res:
        raise MMPAError(f"{what} failed in a worker: {res['error']}\n{res.get('traceback', '')}")
    return res["result"]


class SerialExecutor(Executor):
    """Every job in this process, one after the other (``--workers 1``)."""


class ProcessExecutor(Executor):
    """Jobs in ``workers`` local processes started with ``spawn`` (MuJoCo, OSMesa and
    Open3D are not fork-safe); a process keeps its caches between jobs."""

    kind = "local"

    def __init__(self, workers: int, out: str | Path | None = None, resume: bool = False):
        if workers < 1:
            raise ConfigError(f"--workers must be at least 1, got {workers}")
        super().__init__(out, resume)
        self.workers = int(workers)
        self._pool: ProcessPoolExecutor | None = None

    def _get_pool(self) -> ProcessPoolExecutor:
        if self._pool is None:  # the workers :func:`prestart` started, else new ones
            self._pool = _PRESTARTED.pop(self.workers, None) or _new_pool(self.workers)
        return self._pool

    def _imap(self, calls):
        if not calls:
            return
        pool = self._get_pool()
        with _spawn_env(worker_env()):  # the pool spawns its processes in submit()
            futures: dict[Future, int] = {
                pool.submit(_call, fn, a): i for i, (fn, a) in enumerate(calls)
            }
        try:
            pending = set(futures)
            while pending:
                finished, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in sorted(finished, key=futures.__getitem__):
                    yield futures[f], f.result()
        finally:
            for f in futures:
                f.cancel()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        super().close()


def _new_pool(workers: int) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))


#: worker pools started ahead of their executor (:func:`prestart`), by worker count
_PRESTARTED: dict[int, ProcessPoolExecutor] = {}


def _warm_up(module: str) -> int:
    """A prestarted worker's first job: import ``module`` (the experiment's, with what its
    trials need: MuJoCo, Open3D, ...; ~2 s); returns the worker's process id."""
    importlib.import_module(module)
    return os.getpid()


def prestart(kind: str, workers: int, module: str = "mmpa.harness.twin_trials") -> None:
    """Start the local worker processes of ``--executor kind --workers N`` now, each
    importing ``module``, while this process goes on (e.g. importing the experiment): the
    :class:`ProcessExecutor` made next with ``workers`` takes them over. Nothing for Ray or
    one worker. :func:`discard_prestarted` stops workers no executor took."""
    if kind != "local" or workers < 2 or workers in _PRESTARTED:
        return
    pool = _new_pool(workers)
    with _spawn_env(worker_env()):  # the pool spawns its processes in submit()
        for _ in range(workers):
            pool.submit(_warm_up, module)
    _PRESTARTED[workers] = pool


def discard_prestarted() -> None:
    """Stop the prestarted workers that no executor took over (once their imports are done:
    a pool shut down without waiting can leave its workers running)."""
    while _PRESTARTED:
        _PRESTARTED.popitem()[1].shutdown(wait=True, cancel_futures=True)


class RayExecutor(Executor):
    """Jobs as Ray tasks (``num_cpus=1``, ``memory`` :data:`TRIAL_MEMORY_BYTES`): on a local
    Ray started here with ``num_cpus=workers`` (no dashboard), or on the running cluster at
    ``address`` (its workers need mmpa installed, and read task bundles from Ray's object
    store, not from this machine's disk)."""

    kind = "ray"

    def __init__(
        self,
        workers: int,
        out: str | Path | None = None,
        resume: bool = False,
        address: str | None = None,
        memory: int = TRIAL_MEMORY_BYTES,
    ):
        if workers < 1:
            raise ConfigError(f"--workers must be at least 1, got {workers}")
        try:
            import ray
        except ModuleNotFoundError:
            raise ConfigError(
                "--executor ray needs the Python package 'ray', which is not installed"
            ) from None
        super().__init__(out, resume)
        self.workers = int(workers)
        self.address = address
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            if address:  # the cluster's workers: through the job's runtime environment
                env = {"env_vars": worker_env()}
                ray.init(address=address, log_to_driver=False, runtime_env=env)
            else:
                with _spawn_env(worker_env()):  # the local Ray's processes copy it
                    ray.init(num_cpus=self.workers, include_dashboard=False, log_to_driver=False)
            self._started = True
        self._remote = ray.remote(num_cpus=1, memory=int(memory), max_retries=0)(_call_star)
        self._handles: dict[str, Any] = {}

    def bundle_handle(self, directory: Path) -> Any:
        """The bundle's files as an object in Ray's store (workers may be on other hosts)."""
        key = str(directory)
        if key not in self._handles:
            files = {p.name: p.read_bytes() for p in sorted(Path(directory).iterdir())}
            self._handles[key] = self._ray.put(files)
        return self._handles[key]

    def _imap(self, calls):
        ray = self._ray
        refs = {self._remote.remote(fn, *a): i for i, (fn, a) in enumerate(calls)}
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                for r in ready:
                    yield refs[r], ray.get(r)
        finally:
            for r in pending:
                ray.cancel(r)

    def close(self) -> None:
        self._handles.clear()
        if self._started:
            self._ray.shutdown()
            self._started = False
        super().close()


def make_executor(
    kind: str = "local",
    workers: int = 1,
    out: str | Path | None = None,
    resume: bool = False,
    address: str | None = None,
) -> Executor:
    """The executor of ``--executor kind --workers N [--ray-address ADDR]``: ``local`` with
    one worker runs in this process."""
    if kind not in EXECUTORS:
        raise ConfigError(f"unknown executor {kind!r}; valid: {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    if kind == "ray":
        return RayExecutor(workers, out, resume, address)
    if address:
        raise ConfigError("--ray-address needs --executor ray")
    if workers == 1:
        return SerialExecutor(out, resume)
    return ProcessExecutor(workers, out, resume)

"""The experiment runner: one registry, one output layout for every paper table and figure.

``mmpa experiment NAME --trials N --seed S --out DIR`` resolves ``NAME`` in :data:`EXPERIMENTS`
(module paths, imported lazily so that a missing optional dependency of one experiment never
breaks another), builds the experiment's config from defaults, an optional YAML file,
``--seed``/``--trials`` and ``--set key=value`` overrides, and writes to ``DIR``:

- ``config.yaml``: the final configuration;
- ``results.csv``: one row per trial (the union of the rows' keys as columns);
- ``rows.jsonl`` and ``taught/``: the finished trials as they arrive and the taught task
  bundles (experiments that run their trials on an executor, below);
- ``summary.json``: the headline figures (also printed by the CLI);
- ``report.md``: our figures next to the paper's;
- any PNG plots the experiment writes into ``ctx.out``.

An experiment module provides

- ``Config``: a pydantic model with at least ``seed: int`` and ``trials: int | None``
  (``None`` means the paper's count);
- ``PAPER``: a one-line citation of the reproduced table/figure;
- ``run(cfg: Config, ctx: Context) -> Outcome``;
- optionally ``RECORDS_TRIALS = True``: each trial can record itself to a ROS 2 bag of its
  own (``--record DIR``, :func:`mmpa.harness.recording.record_trials`);
- optionally ``PARALLEL_TRIALS = True``: its trials run on ``ctx.executor``
  (:mod:`mmpa.harness.executor`): ``workers`` local processes or Ray tasks, each trial
  seeded on its own so that ``results.csv`` is the same whatever the executor and worker
  count (but for the ``trial_s`` and ``worker_rss_mb`` columns); ``resume`` completes an
  interrupted run from its journal.
"""

from __future__ import annotations

import csv
import importlib
import json
import math
import time
from collections.abc import Callable, Iterable, Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel

from mmpa.core.config import load_config, save_config
from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.core.yamlio import load_yaml
from mmpa.harness import executor as _executor
from mmpa.harness.executor import SerialExecutor, make_executor
from mmpa.harness.recording import record_trials

__all__ = [
    "EXPERIMENTS",
    "Context",
    "Outcome",
    "experiment_module",
    "markdown_table",
    "run_experiment",
    "run_trials",
    "stats",
]

Progress = Callable[[str, float], None]

#: name -> module path; modules are imported on use.
EXPERIMENTS: dict[str, str] = {
    # paper 000 (MMPA / IPE)
    "parking": "mmpa.experiments.paper000.parking",
    "ipe": "mmpa.experiments.paper000.ipe",
    "path-accuracy": "mmpa.experiments.paper000.path_accuracy",
    "ablation-alpha": "mmpa.experiments.paper000.ablation",
    "ablation-beta": "mmpa.experiments.paper000.ablation",
    "scenes": "mmpa.experiments.paper000.scenes",
    # paper 001 (localization, detection, servoing)
    "localization": "mmpa.experiments.paper001.localization",
    "reflector-dropout": "mmpa.experiments.paper001.reflector_dropout",
    "grasp": "mmpa.experiments.paper001.grasp",
    "tracking": "mmpa.experiments.paper001.tracking",
    "mobile-manipulation": "mmpa.experiments.paper001.mobile_manipulation",
    # paper 002 (fiducial search)
    "planning-convergence": "mmpa.experiments.paper002.planning_convergence",
    "fiducial-search": "mmpa.experiments.paper002.fiducial_search",
}


@dataclass
class Context:
    """What the runner hands an experiment: where to write and how to report progress."""

    name: str
    out: Path
    progress: Progress = field(default=lambda stage, frac: None)
    executor: Any = None  # an mmpa.harness.executor.Executor (None: in this process)


@dataclass
class Outcome:
    """What an experiment returns.

    ``rows``: one dict per trial (scalars; becomes ``results.csv``). ``summary``: headline
    figures (JSON-serializable). ``report``: the Markdown body of ``report.md`` (our figures
    next to the paper's). ``figures``: file names of plots written into ``ctx.out``.
    """

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    report: str
    figures: list[str] = field(default_factory=list)


def experiment_module(name: str) -> Any:
    """Import the module of experiment ``name``; clear errors for unknown/unavailable ones."""
    if name not in EXPERIMENTS:
        raise UnknownNameError("experiment", name, sorted(EXPERIMENTS))
    path = EXPERIMENTS[name]
    try:
        return importlib.import_module(path)
    except ModuleNotFoundError as e:
        if e.name == path:
            raise ConfigError(
                f"experiment {name!r} is registered but not implemented yet ({path})"
            ) from None
        raise ConfigError(
            f"experiment {name!r} needs the Python package {e.name!r}, which is not installed"
        ) from None


def run_experiment(
    name: str,
    out: str | Path,
    *,
    seed: int | None = None,
    trials: int | None = None,
    profile: str | None = None,
    config: str | Path | None = None,
    overrides: Sequence[str] = (),
    progress: Progress | None = None,
    workers: int = 1,
    executor: str = "local",
    ray_address: str | None = None,
    resume: bool = False,
    compare: Sequence[str] = (),
    record: str | Path | None = None,
) -> Outcome:
    """Run experiment ``name`` and write its run folder (see the module docstring).

    ``profile`` picks the twin's error model profile (``errors.profile``; later ``--set
    errors....`` overrides apply on top); the summary and the report record the profile.
    ``workers``, ``executor`` (``local``/``ray``), ``ray_address``: where the trials run
    (experiments with ``PARALLEL_TRIALS``); ``resume``: keep the trials already finished in
    ``out`` (same configuration but for ``trials``) and run the rest. ``compare``: error
    model profiles to run the same experiment under as well (same seed, trials and
    overrides), each into ``out/profile-NAME``; the report then ends with their summary
    figures beside this run's (:func:`compare_profiles`). ``record``: a folder where every
    trial records its own ROS 2 bag (``<label>site-<site>-trial-<n>.mcap``;
    :func:`mmpa.harness.recording.record_trials`; a ``compare`` profile's trials go to
    ``record/profile-NAME``); only the experiments whose trials run on the executor
    (``PARALLEL_TRIALS``: the paper 000 twin experiments) can record, the others raise a
    :class:`ConfigError` naming the experiment."""

    # local workers start now and import what the trials need while this process imports
    # the experiment (~1 s of a 30 s two-worker run on two cores)
    if name in EXPERIMENTS:
        _executor.prestart(executor, workers, EXPERIMENTS[name])
    try:
        return _run_experiment(
            name, out, seed=seed, trials=trials, profile=profile, config=config,
            overrides=overrides, progress=progress, workers=workers, executor=executor,
            ray_address=ray_address, resume=resume, compare=compare, record=record,
        )  # fmt: skip
    finally:
        _executor.discard_prestarted()  # workers no executor took over (an error before)


def _check_options(
    name: str,
    mod: Any,
    *,
    workers: int,
    executor: str,
    ray_address: str | None,
    resume: bool,
    compare: Sequence[str],
    record: str | Path | None,
) -> bool:
    """Refuse the run options experiment ``name`` (its module ``mod``) cannot honour; returns
    whether it runs its trials on an executor (``PARALLEL_TRIALS``)."""
    parallel = getattr(mod, "PARALLEL_TRIALS", False)
    if record is not None and not getattr(mod, "RECORDS_TRIALS", False):
        raise ConfigError(
            f"experiment {name!r} cannot record its trials (--record): only the experiments "
            "whose trials run one by one in a twin site record, one bag per trial: "
            + ", ".join(k for k, v in EXPERIMENTS.items() if _parallel(v, "RECORDS_TRIALS"))
        )
    if not parallel and (workers != 1 or executor != "local" or ray_address or resume):
        raise ConfigError(
            f"experiment {name!r} runs its trials in one process: --workers, --executor, "
            "--ray-address and --resume apply to "
            + ", ".join(k for k, v in EXPERIMENTS.items() if _parallel(v))
        )
    if compare and "errors" not in mod.Config.model_fields:
        raise ConfigError(
            f"experiment {name!r} runs no twin error model: --compare-profile is moot"
        )
    return bool(parallel)


def _settings(
    name: str, mod: Any, seed: int | None, trials: int | None, profile: str | None
) -> list[str]:
    """The ``key=value`` settings the command line's options stand for."""
    sets = []
    if profile is not None:
        if "errors" not in mod.Config.model_fields:
            raise ConfigError(f"experiment {name!r} runs no twin error model: --profile is moot")
        sets.append(f"errors.profile={profile}")
    if seed is not None:
        sets.append(f"seed={seed}")
    if trials is not None:
        if trials < 1:
            raise ConfigError(f"--trials must be at least 1, got {trials}")
        sets.append(f"trials={trials}")
    fields = mod.Config.model_fields
    if "experiment" in fields:  # one module serving several names (e.g. ablation-alpha/-beta)
        sets.append(f"experiment={name}")
    return sets


def _run_on_executor(
    name: str,
    mod: Any,
    cfg: BaseModel,
    ctx: Context,
    executor: str,
    workers: int,
    resume: bool,
    ray_address: str | None,
    record: str | Path | None,
) -> Outcome:
    """``mod.run`` with its trials on the executor (and recording them to ``record``)."""
    with (
        make_executor(executor, workers, ctx.out, resume, ray_address) as ex,
        record_trials(record) if record is not None else nullcontext() as target,
    ):
        ctx.executor = ex
        outcome: Outcome = mod.run(cfg, ctx)
    outcome.summary.setdefault("executor", ex.describe())
    if target is not None:
        if not target.used:  # no silent ignore: it ran trials that did not record
            raise ConfigError(
                f"experiment {name!r} ran no trials that can record (--record): "
                f"nothing was recorded to {record}"
            )
        outcome.summary.setdefault("bags", str(target.folder))
    return outcome


def _write_outputs(name: str, mod: Any, cfg: BaseModel, outcome: Outcome, out: Path) -> str:
    """results.csv, summary.json and report.md of a run; returns the report's text."""
    errors = getattr(cfg, "errors", None)
    if errors is not None:
        outcome.summary.setdefault("profile", errors.profile)
    write_csv(out / "results.csv", outcome.rows)
    (out / "summary.json").write_text(json.dumps(_jsonable(outcome.summary), indent=2) + "\n")
    head = f"# mmpa experiment {name}\n\nReproduces {mod.PAPER}.\n\n"
    if errors is not None:
        head += f"Twin error model: profile `{errors.profile}` (seed {errors.seed}).\n\n"
    report = head + outcome.report.rstrip() + "\n"
    (out / "report.md").write_text(report)
    return report


def _run_experiment(
    name: str,
    out: str | Path,
    *,
    seed: int | None,
    trials: int | None,
    profile: str | None,
    config: str | Path | None,
    overrides: Sequence[str],
    progress: Progress | None,
    workers: int,
    executor: str,
    ray_address: str | None,
    resume: bool,
    compare: Sequence[str],
    record: str | Path | None,
) -> Outcome:
    mod = experiment_module(name)
    parallel = _check_options(
        name, mod, workers=workers, executor=executor, ray_address=ray_address,
        resume=resume, compare=compare, record=record,
    )  # fmt: skip
    sets = _settings(name, mod, seed, trials, profile)
    cfg: BaseModel = load_config(mod.Config, config, [*sets, *overrides])
    out = Path(out)
    if resume:
        _check_resumable(cfg, out / "config.yaml")
    out.mkdir(parents=True, exist_ok=True)
    save_config(cfg, out / "config.yaml")
    ctx = Context(name=name, out=out, progress=progress or (lambda stage, frac: None))
    t0 = time.perf_counter()
    if parallel:
        outcome = _run_on_executor(
            name, mod, cfg, ctx, executor, workers, resume, ray_address, record
        )
    else:
        outcome = mod.run(cfg, ctx)
    wall = time.perf_counter() - t0
    outcome.summary.setdefault("wall_seconds", round(wall, 2))
    report = _write_outputs(name, mod, cfg, outcome, out)
    if compare:
        errors = getattr(cfg, "errors", None)
        others = {}
        # the other runs' profile is theirs: an ``errors.profile`` override would win over it
        keep = [o for o in overrides if o.split("=", 1)[0].strip() != "errors.profile"]
        for p in compare:
            sub = run_experiment(
                name, out / f"profile-{p}", seed=seed, trials=trials, profile=p,
                config=config, overrides=keep, workers=workers, executor=executor,
                ray_address=ray_address, resume=resume,
                record=None if record is None else Path(record) / f"profile-{p}",
            )  # fmt: skip
            others[p] = sub.summary
        table = compare_profiles(errors.profile, outcome.summary, others)
        (out / "report.md").write_text(report + table)
    return outcome


def run_trials(ctx: Context, jobs: Sequence[Any], stage: str) -> list[dict[str, Any]]:
    """``jobs`` (:data:`mmpa.harness.executor.Job`) on ``ctx.executor`` (None: in this
    process, one after the other), progress reported as ``stage``: their records
    (``result``, ``trial_s``, ``worker_rss_mb``) in job order."""

    ex = ctx.executor if ctx.executor is not None else SerialExecutor()
    try:
        return ex.run(jobs, lambda done, total, rec: ctx.progress(stage, done / total))
    finally:
        if ctx.executor is None:
            ex.close()


def flatten(d: Any, prefix: str = "") -> dict[str, float]:
    """The numeric leaves of a nested summary as dotted names (``None``: NaN)."""
    out: dict[str, float] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    elif d is None:
        out[prefix[:-1]] = math.nan
    elif isinstance(d, int | float) and not isinstance(d, bool):
        out[prefix[:-1]] = float(d)
    return out


def compare_profiles(profile: str, summary: dict, others: dict[str, dict]) -> str:
    """A Markdown section: every numeric summary figure of this run (under ``profile``)
    beside the same figure of the runs under the ``others`` profiles (name -> summary);
    the run's wall time left out."""
    mine = flatten(_jsonable(summary))
    theirs = {p: flatten(_jsonable(s)) for p, s in others.items()}
    keys = [k for k in mine if k != "wall_seconds"]
    rows = [[k, mine[k], *(t.get(k, math.nan) for t in theirs.values())] for k in keys]
    cols = [f"`{profile}` (this run)", *(f"`{p}`" for p in theirs)]
    folders = ", ".join(f"`profile-{p}/`" for p in theirs)
    return (
        f"\n## Under other error model profiles\n\nThe same experiment (seed, trials, "
        f"overrides) under each profile, in {folders}:\n\n"
        + markdown_table(["figure", *cols], rows, digits=4)
    )


def _parallel(module_path: str, flag: str = "PARALLEL_TRIALS") -> bool:
    """Whether the experiment module at ``module_path`` sets ``flag`` (False when it does
    not import)."""
    try:
        return bool(getattr(importlib.import_module(module_path), flag, False))
    except ImportError:
        return False


def _check_resumable(cfg: BaseModel, path: Path) -> None:
    """A run folder can be resumed with ``cfg`` if its ``config.yaml`` differs at most in
    ``trials`` (a trial's row does not depend on how many there are)."""

    if not path.exists():
        return  # nothing to resume: a fresh run
    old = load_yaml(path)
    new = cfg.model_dump(mode="json")  # as save_config writes it
    old_d = old if isinstance(old, dict) else {}
    diff = sorted(k for k in set(old_d) | set(new) if k != "trials" and old_d.get(k) != new.get(k))
    if diff:
        raise ConfigError(
            f"{path}: --resume needs the run's configuration (but for trials); "
            f"these fields differ: {', '.join(diff)}"
        )


def write_csv(path: Path, rows: Iterable[dict[str, Any]]) -> None:
    """Rows (dicts) to CSV; columns are the union of keys in first-seen order."""
    rows = list(rows)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: _jsonable(v) for k, v in r.items()})


def stats(values: Iterable[float]) -> dict[str, float]:
    """Mean, SD (ddof=1), median, max and count of the finite values."""
    a = np.asarray([v for v in values if v is not None], dtype=float)
    a = a[np.isfinite(a)]
    if len(a) == 0:
        return {"mean": math.nan, "sd": math.nan, "median": math.nan, "max": math.nan, "n": 0}
    return {
        "mean": float(a.mean()),
        "sd": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
        "median": float(np.median(a)),
        "max": float(a.max()),
        "n": len(a),
    }


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[Any]], digits: int = 3) -> str:
    """A GitHub Markdown table; floats rounded to ``digits`` significant decimals, a ``|``
    inside a cell escaped (it would start another column)."""

    def fmt(v: Any) -> str:
        if isinstance(v, float | np.floating):
            return "–" if not math.isfinite(v) else f"{v:.{digits}f}"
        return str(v).replace("|", "\\|")

    lines = ["| " + " | ".join(fmt(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(fmt(v) for v in r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None if math.isnan(v) else v
    return v

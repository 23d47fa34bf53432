"""Parameter sweeps: a grid over config fields, across experiments, through the runner.

``mmpa sweep FILE.yaml --out DIR`` reads a sweep file (:class:`SweepSpec`)::

    experiments: [ipe]            # names of mmpa.harness.runner.EXPERIMENTS
    trials: 2                     # per point (leave out: each experiment's default)
    seeds: [0]                    # every point runs once per seed
    set: ["sites=[2]"]            # base overrides (``--set key=value``) of every point
    sweep:                        # field -> the values it takes
      errors.profile: [ideal, reference, realistic]
      errors.camera.correlated_fraction: [0.0, 0.75]
    grid: ofat                    # ofat (the default) or full
    metrics: [success, E_t_mm]    # optional: summary figures to tabulate and plot

``grid: ofat`` (one factor at a time) varies each swept field alone around the base
configuration (``set``): the example gives 3 + 2 = 5 points per experiment and seed;
``grid: full`` runs the cartesian product (3 x 2 = 6). Each point is one
:func:`~mmpa.harness.runner.run_experiment` call into its own run folder
``DIR/EXPERIMENT/seedS/FIELD=VALUE[__FIELD=VALUE...]``, so ``resume`` completes an
interrupted sweep point by point (a finished point whose ``config.yaml`` is the one it would
write is kept as it is; the others resume their trials, see ``--resume``).

A point's overrides are the base ``set`` followed by its swept values, but a ``...profile``
override (which re-bases its section, see :mod:`mmpa.core.config`) goes first, so that sweeping
``errors.profile`` keeps a base ``errors.camera....`` override on top of every profile.

The sweep writes, next to the point folders,

- ``sweep.csv``: one row per point: ``experiment``, ``field``, ``value``, ``seed``, (full
  grid: one column per swept field), ``dir`` and the point's metrics, the numeric leaves of
  its ``summary.json`` as dotted names (``1.E_t_mm`` is site 1's mean E_t in mm for ``ipe``);
- ``sweep.md``: one Markdown table per swept field;
- ``sweep_FIELD.png``: per swept field, each metric against the field's value (one line per
  experiment, seed and, for a full grid, setting of the other fields).

Every point's configuration is built and validated before the first one runs, so a typo in
the file costs nothing.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import re
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from mmpa.core.config import load_config
from mmpa.core.errors import ConfigError, MMPAError
from mmpa.core.yamlio import load_yaml
from mmpa.harness.executor import EXECUTORS
from mmpa.harness.runner import (
    EXPERIMENTS,
    experiment_module,
    flatten,
    markdown_table,
    run_experiment,
    write_csv,
)

__all__ = [
    "DEFAULT_METRICS",
    "SweepPoint",
    "SweepResult",
    "SweepSpec",
    "check_run_options",
    "load_sweep",
    "plan_points",
    "point_metrics",
    "run_sweep",
]

Progress = Callable[[str, float], None]

#: per experiment, the summary leaves tabulated and plotted by default (others: every
#: numeric leaf of ``summary.json`` but the run's wall time)
DEFAULT_METRICS: dict[str, tuple[str, ...]] = {
    "ipe": ("success", "E_t_mm", "E_R"),
}
#: at most this many metrics are plotted per swept field (the CSV keeps them all)
MAX_PLOTTED = 9
#: fields with a key of their own in the sweep file
_RESERVED = {"seed": "seeds", "trials": "trials", "experiment": "experiments"}


class SweepSpec(BaseModel):
    """A sweep file (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    experiments: list[str] = Field(min_length=1)
    trials: int | None = Field(None, ge=1)
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1)
    set: list[str] = Field(default_factory=list)
    sweep: dict[str, list[Any]] = Field(min_length=1)
    grid: Literal["ofat", "full"] = "ofat"
    metrics: list[str] | None = None

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int]) -> list[int]:
        if any(s < 0 for s in v):
            raise ValueError("seeds must be >= 0")
        if len(set(v)) != len(v):
            raise ValueError("seeds repeat")
        return v

    @field_validator("sweep")
    @classmethod
    def _values(cls, v: dict[str, list[Any]]) -> dict[str, list[Any]]:
        for name, values in v.items():
            if not values:
                raise ValueError(f"{name}: no values to sweep (give at least one)")
            keys = [json.dumps(x, sort_keys=True) for x in values]
            if len(set(keys)) != len(keys):
                raise ValueError(f"{name}: a value repeats")
        return v


@dataclass(frozen=True)
class SweepPoint:
    """One run of the sweep: ``experiment`` at ``seed`` with the swept ``assign``ments
    (field -> value; one field for ``ofat``), its ``overrides`` and run folder ``rel``
    (relative to the sweep's folder)."""

    experiment: str
    seed: int
    assign: dict[str, Any]
    overrides: tuple[str, ...]
    rel: str

    @property
    def label(self) -> str:
        return f"{self.experiment} seed {self.seed} " + ", ".join(
            f"{k}={_text(v)}" for k, v in self.assign.items()
        )


@dataclass
class SweepResult:
    """What :func:`run_sweep` returns: the ``rows`` of ``sweep.csv``, the ``points`` and the
    written ``files`` (relative to the sweep's folder)."""

    rows: list[dict[str, Any]]
    points: list[SweepPoint]
    files: list[str] = field(default_factory=list)


def load_sweep(path: str | Path) -> SweepSpec:
    """Read and check the sweep file ``path``: its schema, its experiments, its fields and
    every point's configuration. Raises :class:`~mmpa.core.errors.ConfigError` naming the file
    and the field."""
    data = load_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a sweep file must be a YAML mapping")
    spec = parse_sweep(data, str(path))
    plan_points(spec, str(path))  # builds and validates every point's configuration
    return spec


def parse_sweep(data: dict[str, Any], what: str = "sweep") -> SweepSpec:
    """The :class:`SweepSpec` of ``data``; errors name ``what`` (the file) and the field."""
    try:
        spec = SweepSpec.model_validate(data)
    except ValidationError as e:
        lines = [
            f"  {'.'.join(map(str, err['loc'])) or '(top)'}: {err['msg']}" for err in e.errors()
        ]
        raise ConfigError(f"{what}: invalid sweep file\n" + "\n".join(lines)) from None
    for name in spec.experiments:
        if name not in EXPERIMENTS:
            raise ConfigError(
                f"{what}: experiments: unknown experiment {name!r}; valid: "
                + ", ".join(sorted(EXPERIMENTS))
            )
    for name in spec.sweep:
        top = name.split(".")[0]
        if top in _RESERVED:
            raise ConfigError(
                f"{what}: sweep: {name!r} is set by the file's {_RESERVED[top]!r} key, not swept"
            )
    return spec


def plan_points(spec: SweepSpec, what: str = "sweep") -> list[SweepPoint]:
    """Every point of ``spec`` in run order (experiment, seed, then the grid), each
    configuration built and validated (nothing runs)."""
    fields = list(spec.sweep)
    if spec.grid == "full":
        combos = [
            dict(zip(fields, vals, strict=True))
            for vals in itertools.product(*(spec.sweep[f] for f in fields))
        ]
    else:
        combos = [{f: v} for f in fields for v in spec.sweep[f]]
    points = []
    for name in spec.experiments:
        try:
            mod = experiment_module(name)
        except MMPAError as e:
            raise ConfigError(f"{what}: experiments: {e}") from None
        for f in fields:
            _check_field(mod.Config, f, name, what)
        for seed in spec.seeds:
            for assign in combos:
                sets = [*spec.set, *(f"{f}={json.dumps(v)}" for f, v in assign.items())]
                sets.sort(key=lambda s: 0 if _is_profile(s) else 1)  # stable: order kept
                try:
                    _validate(mod, name, seed, spec.trials, sets)
                except ConfigError as e:
                    where = ", ".join(f"{f}={_text(v)}" for f, v in assign.items())
                    raise ConfigError(
                        f"{what}: experiment {name!r}, seed {seed}, {where}: {e}"
                    ) from None
                rel = f"{name}/seed{seed}/" + "__".join(
                    f"{_slug(f)}={_slug(_text(v))}" for f, v in assign.items()
                )
                points.append(SweepPoint(name, seed, dict(assign), tuple(sets), rel))
    return points


def run_sweep(
    spec: SweepSpec,
    out: str | Path,
    *,
    workers: int = 1,
    executor: str = "local",
    ray_address: str | None = None,
    resume: bool = False,
    progress: Progress | None = None,
) -> SweepResult:
    """Run every point of ``spec`` into ``out`` and write ``sweep.csv``, ``sweep.md`` and one
    plot per swept field (module docstring).

    ``workers``/``executor``/``ray_address`` apply to the experiments that run their trials
    on an executor (``PARALLEL_TRIALS``); the others run each point in this process.
    ``progress(stage, fraction)``: ``stage`` names the point (``i/n``) and its own stage,
    ``fraction`` is the sweep's (0..1)."""
    check_run_options(workers, executor)
    points = plan_points(spec)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report = progress or (lambda stage, frac: None)
    rows: list[dict[str, Any]] = []
    firsts: dict[str, dict[str, Any]] = {}  # experiment -> the summary of its first point
    n = len(points)
    for i, p in enumerate(points):
        mod = experiment_module(p.experiment)
        parallel = bool(getattr(mod, "PARALLEL_TRIALS", False))
        folder = out / p.rel
        head = f"{i + 1}/{n} {p.label}"

        def step(stage: str, frac: float, head: str = head, i: int = i) -> None:
            report(f"{head}: {stage}", (i + max(0.0, min(frac, 1.0))) / n)

        step("starting", 0.0)
        if not (resume and _finished(mod, p, spec.trials, folder)):
            run_experiment(
                p.experiment,
                folder,
                seed=p.seed,
                trials=spec.trials,
                overrides=list(p.overrides),
                progress=step,
                workers=workers if parallel else 1,
                executor=executor if parallel else "local",
                ray_address=ray_address if parallel else None,
                resume=resume and parallel,
            )
        summary = json.loads((folder / "summary.json").read_text())
        if p.experiment not in firsts:
            firsts[p.experiment] = summary
            _check_metrics(spec, firsts)  # a typo stops the sweep after one point per experiment
        rows.append(_row(spec, p, summary))
        step("done", 1.0)
    files = write_summary(spec, rows, out)
    report("sweep written", 1.0)
    return SweepResult(rows, points, files)


def check_run_options(workers: int, executor: str) -> None:
    """Refuse a worker count below 1 or an unknown executor (before anything runs)."""

    if executor not in EXECUTORS:
        raise ConfigError(f"unknown executor {executor!r}; valid: {', '.join(EXECUTORS)}")
    if workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")


def point_metrics(experiment: str, summary: dict[str, Any], wanted: Sequence[str] | None = None):
    """The metrics of one point: the numeric leaves of its ``summary`` (dotted names), those
    named in ``wanted`` (a dotted name or its last parts: ``enhanced.err_pos_cm`` names
    ``methods.enhanced.err_pos_cm``), else :data:`DEFAULT_METRICS` of the experiment, else
    all but ``wall_seconds``. NaN stays NaN (JSON ``null`` reads as NaN)."""
    flat = flatten(summary)
    names = wanted if wanted is not None else DEFAULT_METRICS.get(experiment)
    if names is None:
        return {k: v for k, v in flat.items() if k != "wall_seconds"}
    return {k: v for k, v in flat.items() if any(_names(k, n) for n in names)}


def _names(key: str, name: str) -> bool:
    """Whether the metric ``name`` names the dotted summary leaf ``key``."""
    return key == name or key.endswith("." + name)


def _check_metrics(spec: SweepSpec, summaries: dict[str, dict[str, Any]]) -> None:
    """Refuse metric names that name no numeric leaf in any experiment's summary, once every
    experiment of ``spec`` has a finished point (``summaries``: experiment -> its first)."""
    if not spec.metrics or set(summaries) != set(spec.experiments):
        return
    leaves = sorted({k for s in summaries.values() for k in flatten(s)})
    missing = [m for m in spec.metrics if not any(_names(k, m) for k in leaves)]
    if missing:
        raise ConfigError(
            f"sweep metrics {missing} name nothing in the summaries of "
            f"{', '.join(summaries)}; their numeric figures are: {', '.join(leaves)}"
        )


def write_summary(spec: SweepSpec, rows: list[dict[str, Any]], out: Path) -> list[str]:
    """``sweep.csv``, ``sweep.md`` and the plots of ``rows``; the written file names."""
    fixed = {"experiment", "field", "value", "seed", "dir", "wall_seconds", *spec.sweep}
    md = [
        "# mmpa sweep\n\n",
        f"Experiments {', '.join(spec.experiments)}; grid `{spec.grid}`; seeds "
        f"{', '.join(map(str, spec.seeds))}; trials per point "
        f"{spec.trials if spec.trials is not None else 'the experiment default'}; base "
        f"overrides: {', '.join(f'`{s}`' for s in spec.set) or 'none'}.\n",
    ]
    files = ["sweep.csv"]
    for f in spec.sweep:
        mine = [r for r in rows if f in r["_assign"]]
        others = [g for g in spec.sweep if g != f] if spec.grid == "full" else []
        metrics: list[str] = []
        for r in mine:
            metrics += [
                k for k in r if k not in fixed and not k.startswith("_") and k not in metrics
            ]
        header = ["experiment", "seed", *others, f, *metrics]
        table = [
            [
                r["experiment"],
                r["seed"],
                *(_text(r["_assign"][g]) for g in others),
                _text(r["_assign"][f]),
                *(r.get(m, math.nan) for m in metrics),
            ]
            for r in mine
        ]
        png = f"sweep_{_slug(f)}.png"
        _plot(f, spec.sweep[f], mine, others, metrics[:MAX_PLOTTED], out / png)
        files.append(png)
        md.append(f"\n## {f}\n\n" + markdown_table(header, table, digits=4))
        if len(metrics) > MAX_PLOTTED:
            md.append(f"\nThe plot shows the first {MAX_PLOTTED} of {len(metrics)} metrics.\n")
        md.append(f"\n![{f}]({png})\n")
    (out / "sweep.md").write_text("".join(md))
    files.append("sweep.md")
    write_csv(
        out / "sweep.csv", [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    )
    return files


def _row(spec: SweepSpec, p: SweepPoint, summary: dict[str, Any]) -> dict[str, Any]:
    if spec.grid == "full":
        fld = "+".join(p.assign)
        value: Any = "; ".join(f"{f}={_text(v)}" for f, v in p.assign.items())
    else:
        ((fld, value),) = p.assign.items()
        value = _cell(value)
    row: dict[str, Any] = {"experiment": p.experiment, "field": fld, "value": value}
    row["seed"] = p.seed
    if spec.grid == "full":
        row.update({f: _cell(v) for f, v in p.assign.items()})
    row["dir"] = p.rel
    row["wall_seconds"] = summary.get("wall_seconds", math.nan)
    row.update(point_metrics(p.experiment, summary, spec.metrics))
    row["_assign"] = p.assign
    return row


def _plot(
    f: str,
    values: list[Any],
    rows: list[dict[str, Any]],
    others: list[str],
    metrics: list[str],
    path: Path,
) -> None:
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
    order = {json.dumps(v, sort_keys=True): i for i, v in enumerate(values)}

    def x_of(v: Any) -> float:
        return float(v) if numeric else float(order[json.dumps(v, sort_keys=True)])

    n = max(1, len(metrics))
    cols = min(3, n)
    nrows = math.ceil(n / cols)
    fig = Figure(figsize=(4.2 * cols, 3.4 * nrows))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, cols, squeeze=False)
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        key = f"{r['experiment']} s{r['seed']}" + "".join(
            f" {g}={_text(r['_assign'][g])}" for g in others
        )
        groups.setdefault(key, []).append(r)
    for k, m in enumerate(metrics):
        ax = axes.ravel()[k]
        for key, rs in groups.items():
            pts = sorted((x_of(r["_assign"][f]), r.get(m, math.nan)) for r in rs if m in r)
            if pts:
                ax.plot([a for a, _ in pts], [b for _, b in pts], "o-", label=key)
        ax.set_title(m, fontsize=9)
        ax.set_xlabel(f)
        if not numeric:
            ax.set_xticks(range(len(values)), [_text(v) for v in values])
        ax.grid(alpha=0.3)
    if not metrics:
        axes[0, 0].text(0.5, 0.5, "no numeric metrics", ha="center", va="center")
    for ax in axes.ravel()[len(metrics) :]:
        if metrics:
            ax.set_visible(False)
    if metrics and len(groups) > 1:
        axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"mmpa sweep: {f}")
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def _finished(mod: Any, p: SweepPoint, trials: int | None, folder: Path) -> bool:
    """Whether ``folder`` holds the finished run of ``p`` (its summary, and the config.yaml
    this point would write)."""
    if not (folder / "summary.json").exists() or not (folder / "config.yaml").exists():
        return False
    cfg = _validate(mod, p.experiment, p.seed, trials, list(p.overrides))
    return load_yaml(folder / "config.yaml") == cfg.model_dump(mode="json")


def _validate(mod: Any, name: str, seed: int, trials: int | None, sets: list[str]) -> BaseModel:
    """The configuration :func:`run_experiment` builds for these arguments (its order of
    overrides)."""
    pre = [f"seed={seed}"] + ([f"trials={trials}"] if trials is not None else [])
    if "experiment" in mod.Config.model_fields:
        pre.append(f"experiment={name}")
    return load_config(mod.Config, None, [*pre, *sets])


def _check_field(model: type[BaseModel], dotted: str, name: str, what: str) -> None:
    """``dotted`` must name a field of ``model`` (descending into nested models; a field
    holding a dict accepts any key below it)."""
    node: Any = model
    parts = dotted.split(".")
    for i, part in enumerate(parts):
        if node is None:
            return  # below a dict (or untyped) field: the config's own validation decides
        fields = node.model_fields
        if part not in fields:
            where = ".".join(parts[:i]) or "the config"
            raise ConfigError(
                f"{what}: sweep: experiment {name!r} has no field {dotted!r} "
                f"({where} has: {', '.join(fields)})"
            )
        sub = _model_of(fields[part].annotation)
        if sub is None and i < len(parts) - 1 and not _is_mapping(fields[part].annotation):
            raise ConfigError(
                f"{what}: sweep: {'.'.join(parts[: i + 1])!r} of experiment {name!r} is a "
                f"value, not a section: {dotted!r} does not exist"
            )
        node = sub


def _model_of(ann: Any) -> type[BaseModel] | None:
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return ann
    if typing.get_origin(ann) in (typing.Union, types.UnionType):
        for a in typing.get_args(ann):
            m = _model_of(a)
            if m is not None:
                return m
    return None


def _is_mapping(ann: Any) -> bool:
    origin = typing.get_origin(ann) or ann
    if origin in (typing.Union, types.UnionType):
        return any(_is_mapping(a) for a in typing.get_args(ann))
    return origin is dict or ann is Any


def _is_profile(override: str) -> bool:
    return override.split("=", 1)[0].strip().split(".")[-1] == "profile"


def _text(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v)


def _cell(v: Any) -> Any:
    return v if isinstance(v, str | int | float | bool) else json.dumps(v)


def _slug(s: str) -> str:
    """A file-name-safe form of ``s``; a short hash is added where characters were replaced
    (so that ``2'`` and ``2_`` stay apart)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", s)[:60]
    if safe != s:
        safe += "-" + hashlib.sha1(s.encode()).hexdigest()[:6]
    return safe

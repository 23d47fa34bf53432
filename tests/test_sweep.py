"""``mmpa sweep``: points of a one-factor-at-a-time or full grid, each a run folder of the
runner, summarized in sweep.csv / sweep.md / one plot per swept field; bad files fail
clearly before anything runs."""

from __future__ import annotations

import csv
import os
import sys
import types

# offscreen rendering (the IPE test's twin); set before mujoco is first imported
os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import pytest
import typer
import yaml
from matplotlib.image import imread
from pydantic import BaseModel
from typer.testing import CliRunner

from mmpa.cli.sweep import register
from mmpa.core.errors import ConfigError
from mmpa.harness import runner as rn
from mmpa.harness.sweep import load_sweep, parse_sweep, plan_points, run_sweep


class _Inner(BaseModel):
    profile: str = "plain"
    gain: float = 1.0


@pytest.fixture
def toy(monkeypatch):
    """An instant experiment: ``trials`` rows of ``scale * gain * (i + seed) + offset``; the
    summary's ``mean`` is that mean, nested ``site.a.mean`` twice it; counts its runs."""
    mod = types.ModuleType("mmpa_sweep_toy")
    calls: list[dict] = []

    class Config(BaseModel):
        seed: int = 0
        trials: int | None = None
        scale: float = 1.0
        offset: float = 0.0
        inner: _Inner = _Inner()

    def run(cfg, ctx):
        calls.append(cfg.model_dump())
        n = cfg.trials or 3
        vals = [cfg.scale * cfg.inner.gain * (i + cfg.seed) + cfg.offset for i in range(n)]
        mean = sum(vals) / n
        ctx.progress("toy", 1.0)
        rows = [{"trial": i, "value": v} for i, v in enumerate(vals)]
        summary = {"mean": mean, "site": {"a": {"mean": 2 * mean}}, "label": cfg.inner.profile}
        return rn.Outcome(rows, summary, "toy report")

    mod.Config, mod.run, mod.PAPER, mod.calls = Config, run, "a toy table", calls
    monkeypatch.setitem(sys.modules, "mmpa_sweep_toy", mod)
    monkeypatch.setitem(rn.EXPERIMENTS, "toy", "mmpa_sweep_toy")
    return mod


def _csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def _expected_mean(scale=1.0, gain=1.0, offset=0.0, seed=0, trials=2):
    return sum(scale * gain * (i + seed) + offset for i in range(trials)) / trials


def test_ofat_sweep_rows_tables_plots_and_resume(toy, tmp_path):
    spec = parse_sweep(
        {
            "experiments": ["toy"],
            "trials": 2,
            "seeds": [0, 3],
            "set": ["offset=10"],
            "sweep": {"scale": [1.0, 2.0, 4.0], "inner.gain": [0.5, 3.0]},
        }
    )
    seen: list[tuple[str, float]] = []
    res = run_sweep(spec, tmp_path, progress=lambda s, f: seen.append((s, f)))
    assert len(res.points) == 2 * (3 + 2) == len(toy.calls)
    rows = _csv(tmp_path / "sweep.csv")
    assert len(rows) == 10
    assert list(rows[0])[:4] == ["experiment", "field", "value", "seed"]
    for r in rows:
        seed = int(r["seed"])
        kw = {"scale" if r["field"] == "scale" else "gain": float(r["value"])}
        want = _expected_mean(offset=10.0, seed=seed, **kw)
        assert float(r["mean"]) == pytest.approx(want)
        assert float(r["site.a.mean"]) == pytest.approx(2 * want)
        assert "label" not in r  # a string, not a metric
        # the point's own run folder holds the runner's files, with the point's config
        cfg = yaml.safe_load((tmp_path / r["dir"] / "config.yaml").read_text())
        assert cfg["seed"] == seed and cfg["offset"] == 10.0 and cfg["trials"] == 2
    # the values do move the metric: scale 1 -> 4 at seed 3
    by = {(r["field"], r["value"], r["seed"]): float(r["mean"]) for r in rows}
    assert by[("scale", "4.0", "3")] - by[("scale", "1.0", "3")] == pytest.approx(3 * 3.5)
    # progress: monotone fractions ending at 1, stages name the point
    fr = [f for _, f in seen]
    assert fr == sorted(fr) and fr[-1] == 1.0 and 0.0 <= fr[0] < 0.1
    assert any(s.startswith("1/10 toy seed 0 scale=1.0") for s, _ in seen)
    md = (tmp_path / "sweep.md").read_text()
    assert md.count("\n## ") == 2 and "## scale" in md and "## inner.gain" in md
    for name in ("sweep_scale.png", "sweep_inner.gain.png"):
        img = imread(tmp_path / name)
        assert img.shape[0] > 100 and img.std() > 0  # a drawn picture, not a blank
    assert sorted(res.files) == sorted(
        ["sweep.csv", "sweep.md", "sweep_scale.png", "sweep_inner.gain.png"]
    )
    # resume: finished points are kept (no run), a removed one runs again
    (tmp_path / res.points[4].rel / "summary.json").unlink()
    n = len(toy.calls)
    run_sweep(spec, tmp_path, resume=True)
    assert len(toy.calls) == n + 1 and toy.calls[-1]["inner"]["gain"] == 3.0
    assert _csv(tmp_path / "sweep.csv") == rows


def test_full_grid_and_profile_goes_first(toy, tmp_path):
    spec = parse_sweep(
        {
            "experiments": ["toy"],
            "trials": 1,
            "seeds": [2],
            "set": ["inner.gain=2"],
            "sweep": {"inner.profile": ["p", "q"], "scale": [1, 3]},
            "grid": "full",
            "metrics": ["site.a.mean"],
        }
    )
    pts = plan_points(spec)
    assert len(pts) == 4
    # the profile override (which re-bases its section) goes before the base inner.gain
    assert pts[0].overrides == ('inner.profile="p"', "inner.gain=2", "scale=1")
    run_sweep(spec, tmp_path)
    rows = _csv(tmp_path / "sweep.csv")
    assert [(r["inner.profile"], r["scale"]) for r in rows] == [
        ("p", "1"),
        ("p", "3"),
        ("q", "1"),
        ("q", "3"),
    ]
    assert rows[0]["field"] == "inner.profile+scale"
    # only the named metric; seed 2, one trial: mean = scale * gain * 2, site.a.mean twice it
    assert "mean" not in rows[0]
    assert [float(r["site.a.mean"]) for r in rows] == [8.0, 24.0, 8.0, 24.0]
    assert [c["inner"]["gain"] for c in toy.calls] == [2.0] * 4
    md = (tmp_path / "sweep.md").read_text()
    assert "| experiment | seed | scale | inner.profile | site.a.mean |" in md


def test_cheapest_real_experiment(tmp_path):
    """planning-convergence (about 0.5 s a point): the points are the runner's runs."""
    spec = parse_sweep(
        {
            "experiments": ["planning-convergence"],
            "trials": 1,
            "set": ["speeds_cm_s=[3.0]"],
            "sweep": {"points": [5, 20]},
        }
    )
    run_sweep(spec, tmp_path / "sw")
    rows = _csv(tmp_path / "sw" / "sweep.csv")
    assert [r["value"] for r in rows] == ["5", "20"]
    for r in rows:  # the same figures as the experiment run on its own
        alone = rn.run_experiment(
            "planning-convergence",
            tmp_path / f"alone{r['value']}",
            seed=0,
            trials=1,
            overrides=["speeds_cm_s=[3.0]", f"points={r['value']}"],
        ).summary
        assert float(r["mean_iterations_to_converge"]) == alone["mean_iterations_to_converge"]
        assert float(r["spiral_3cm_s_iterations"]) == alone["spiral_3cm_s_iterations"]
    # fewer tool points fit the pose sooner: the spiral search needs fewer iterations
    assert float(rows[0]["spiral_3cm_s_iterations"]) < float(rows[1]["spiral_3cm_s_iterations"])
    assert (tmp_path / "sw" / "sweep_points.png").stat().st_size > 5_000


def test_metrics_by_their_last_parts_and_a_typo_stops_after_one_point(toy, tmp_path):
    spec = parse_sweep(
        {"experiments": ["toy"], "trials": 2, "sweep": {"scale": [1.0, 2.0]},
         "metrics": ["a.mean"]}
    )  # fmt: skip
    run_sweep(spec, tmp_path / "ok")
    rows = _csv(tmp_path / "ok" / "sweep.csv")
    assert [float(r["site.a.mean"]) for r in rows] == pytest.approx(
        [2 * _expected_mean(scale=1.0), 2 * _expected_mean(scale=2.0)]
    )
    assert "mean" not in rows[0]  # "a.mean" names site.a.mean only
    bad = spec.model_copy(update={"metrics": ["a.mean", "b.mean"]})
    n = len(toy.calls)
    with pytest.raises(ConfigError, match=r"\['b.mean'\] name nothing.*site.a.mean"):
        run_sweep(bad, tmp_path / "bad")
    assert len(toy.calls) == n + 1  # stopped after the first point, not at the end


def test_docs_sensitivity_files_are_valid():
    for name, n in (("ipe", 26), ("path", 26), ("localization", 28)):
        assert len(plan_points(load_sweep(f"docs/sensitivity_{name}.yaml"))) == n


def test_docs_example_is_valid():
    spec = load_sweep("docs/sweep_example.yaml")
    pts = plan_points(spec)
    assert len(pts) == 5 and {p.experiment for p in pts} == {"ipe"}
    full = plan_points(spec.model_copy(update={"grid": "full"}))
    assert len(full) == 6


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("- a\n- b\n", "must be a YAML mapping"),
        ("experiments: [nope]\nsweep: {seed: [1]}\n", r"experiments: unknown experiment 'nope'"),
        ("experiments: [toy]\nsweep: {scale: []}\n", r"sweep.*scale: no values"),
        ("experiments: [toy]\nsweep: {}\n", r"sweep"),
        ("experiments: [toy]\nsweep: {scael: [1]}\n", r"no field 'scael'"),
        ("experiments: [toy]\nsweep: {inner.gian: [1]}\n", r"no field 'inner.gian'.*gain"),
        ("experiments: [toy]\nsweep: {scale.x: [1]}\n", r"'scale' .* is a value, not a section"),
        (
            "experiments: [toy]\nsweep: {scale: [1, abc]}\n",
            r"(?s)scale=abc: invalid configuration.*scale: Input should be a valid number",
        ),
        ("experiments: [toy]\nsweep: {seed: [1, 2]}\n", r"'seeds' key"),
        ("experiments: [toy]\nsweep: {scale: [1, 1]}\n", r"repeats"),
        ("experiments: [toy]\ntrials: 0\nsweep: {scale: [1]}\n", r"trials"),
        ("experiments: [toy]\nsweeps: {scale: [1]}\n", r"sweeps"),
        ("experiments: [toy]\nsweep: {scale: &a [1]}\nset: *a\n", r"alias"),
    ],
)
def test_bad_files_name_the_file_and_field(toy, tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as e:
        load_sweep(path)
    assert str(path) in str(e.value)


def test_cli_runs_and_fails_clearly(toy, tmp_path):
    app = typer.Typer()
    register(app)
    app.command("other")(lambda: None)  # two commands: `sweep` stays a subcommand
    good = tmp_path / "s.yaml"
    good.write_text("experiments: [toy]\ntrials: 1\nsweep: {offset: [1.5, 2.5]}\n")
    res = CliRunner().invoke(app, ["sweep", str(good), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert "2 points" in res.output
    assert [float(r["mean"]) for r in _csv(tmp_path / "o" / "sweep.csv")] == [1.5, 2.5]
    bad = tmp_path / "b.yaml"
    bad.write_text("experiments: [toy]\nsweep: {offset: []}\n")
    res = CliRunner().invoke(app, ["sweep", str(bad), "--out", str(tmp_path / "p")])
    assert res.exit_code == 2 and "no values" in res.output and not (tmp_path / "p").exists()
    res = CliRunner().invoke(
        app, ["sweep", str(good), "--executor", "dask", "--out", str(tmp_path / "q")]
    )
    assert res.exit_code == 2 and "unknown executor 'dask'" in res.output
    assert not (tmp_path / "q").exists()


@pytest.mark.slow
def test_ipe_profiles_one_trial(tmp_path):
    """The headline use: IPE against the error profile (one trial at Site 1 per point, about
    10 s each; slow: the toy sweeps test the grid, the tables and the plots, and
    ``test_cheapest_real_experiment`` a real experiment's figures). Measured: E_t 0.025 mm
    (ideal) and 0.113 mm (reference), both successes."""
    spec = parse_sweep(
        {
            "experiments": ["ipe"],
            "trials": 1,
            "set": ["sites=[1]", "paper_method=false"],
            "sweep": {"errors.profile": ["ideal", "reference"]},
        }
    )
    run_sweep(spec, tmp_path)
    rows = _csv(tmp_path / "sweep.csv")
    assert [r["value"] for r in rows] == ["ideal", "reference"]
    metrics = [k for k in rows[0] if k not in ("experiment", "field", "value", "seed", "dir")]
    assert metrics == ["wall_seconds", "1.success", "1.E_t_mm", "1.E_R"]
    for r in rows:
        cfg = yaml.safe_load((tmp_path / r["dir"] / "config.yaml").read_text())
        assert cfg["errors"]["profile"] == r["value"] and cfg["sites"] == ["1"]
        summary = yaml.safe_load((tmp_path / r["dir"] / "summary.json").read_text())
        assert float(r["1.E_t_mm"]) == summary["1"]["E_t_mm"]
        assert float(r["1.success"]) == 1.0
    # the reference profile's sensor noise costs accuracy against the noiseless twin
    ideal, ref = (float(r["1.E_t_mm"]) for r in rows)
    assert 0 <= ideal < ref < 5.0
    assert (tmp_path / "sweep_errors.profile.png").stat().st_size > 5_000

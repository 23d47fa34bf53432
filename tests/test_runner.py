"""The experiment runner: registry, config layering and the run-folder layout."""

from __future__ import annotations

import csv
import json
import sys
import types

import pytest
import yaml
from pydantic import BaseModel
from typer.testing import CliRunner

from mmpa.cli.main import app
from mmpa.core.errors import ConfigError, UnknownNameError
from mmpa.harness import runner as rn


@pytest.fixture
def toy(monkeypatch):
    mod = types.ModuleType("mmpa_toy_experiment")

    class Config(BaseModel):
        seed: int = 0
        trials: int | None = None
        scale: float = 1.0

    def run(cfg, ctx):
        n = cfg.trials or 4  # "the paper's count" is 4
        rows = [{"trial": i, "value": cfg.scale * (i + cfg.seed)} for i in range(n)]
        rows[-1]["extra"] = "late column"
        s = rn.stats(r["value"] for r in rows)
        (ctx.out / "plot.png").write_bytes(b"\x89PNG")
        return rn.Outcome(rows, {"mean": s["mean"]}, rn.markdown_table(["mean"], [[s["mean"]]]))

    mod.Config, mod.run, mod.PAPER = Config, run, "a toy table"
    monkeypatch.setitem(sys.modules, "mmpa_toy_experiment", mod)
    monkeypatch.setitem(rn.EXPERIMENTS, "toy", "mmpa_toy_experiment")
    return mod


def test_run_folder_layout_and_config_layering(toy, tmp_path):
    (tmp_path / "c.yaml").write_text("scale: 2.0\n")
    out = rn.run_experiment(
        "toy", tmp_path / "run", seed=1, trials=3, config=tmp_path / "c.yaml", overrides=[]
    )
    # values: 2*(0+1), 2*(1+1), 2*(2+1) -> mean 4
    assert out.summary["mean"] == pytest.approx(4.0)
    cfg = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert cfg == {"seed": 1, "trials": 3, "scale": 2.0}
    with open(tmp_path / "run" / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["value"]) for r in rows] == [2.0, 4.0, 6.0]
    assert rows[-1]["extra"] == "late column" and rows[0]["extra"] == ""
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["mean"] == pytest.approx(4.0) and summary["wall_seconds"] >= 0
    report = (tmp_path / "run" / "report.md").read_text()
    assert "a toy table" in report and "4.000" in report


def test_set_override_beats_file_and_default_trials(toy, tmp_path):
    out = rn.run_experiment("toy", tmp_path, overrides=["scale=0.5"])
    assert len(out.rows) == 4
    assert out.summary["mean"] == pytest.approx(0.5 * 1.5)


def test_bad_names_and_values(toy, tmp_path):
    with pytest.raises(UnknownNameError, match="toy"):
        rn.run_experiment("nope", tmp_path)
    with pytest.raises(ConfigError, match="trials"):
        rn.run_experiment("toy", tmp_path, trials=0)
    with pytest.raises(ConfigError, match="scale"):
        rn.run_experiment("toy", tmp_path, overrides=["scale=abc"])


def test_stats_against_numpy():
    import numpy as np

    v = [1.0, 2.0, 4.0, float("nan")]
    s = rn.stats(v)
    assert s["n"] == 3
    assert s["mean"] == pytest.approx(7 / 3)
    assert s["sd"] == pytest.approx(np.std([1, 2, 4], ddof=1))
    assert s["median"] == 2.0 and s["max"] == 4.0
    assert rn.stats([])["n"] == 0


def test_cli_lists_and_runs(toy, tmp_path):
    cli = CliRunner()
    res = cli.invoke(app, ["experiment"])
    assert res.exit_code == 0 and "fiducial-search" in res.output
    res = cli.invoke(app, ["experiment", "toy", "--out", str(tmp_path), "--trials", "2"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "report.md").exists()
    res = cli.invoke(app, ["experiment", "nope", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "toy" in res.output


def test_markdown_table_escapes_pipes_in_cells():
    """A ``|`` in a header or cell is escaped: every line splits into the same number of
    columns (the mobile-manipulation header 'grasping | detected' broke its table)."""
    import re

    from mmpa.harness.runner import markdown_table

    text = markdown_table(["object", "grasping | detected"], [["a|b", 0.5], ["c", float("nan")]])
    lines = text.strip().splitlines()
    cols = [len(re.split(r"(?<!\\)\|", line)) for line in lines]
    assert len(set(cols)) == 1 and cols[0] == 4  # "", two cells, ""
    assert "grasping \\| detected" in lines[0] and "0.500" in lines[2] and "–" in lines[3]


def test_executor_options_only_for_experiments_that_run_trials_on_one(toy, tmp_path):
    """--workers/--executor/--resume on an experiment that runs in one process is refused
    (it would silently run sequentially), naming the experiments that take them."""
    with pytest.raises(ConfigError, match=r"--workers.*\bipe\b"):
        rn.run_experiment("toy", tmp_path, workers=2)
    with pytest.raises(ConfigError, match="--resume"):
        rn.run_experiment("toy", tmp_path, resume=True)
    res = CliRunner().invoke(
        app, ["experiment", "toy", "--out", str(tmp_path), "--workers", "2", "--trials", "1"]
    )
    assert res.exit_code == 2 and "one process" in res.output
    res = CliRunner().invoke(app, ["experiment", "toy", "--out", str(tmp_path), "--workers", "0"])
    assert res.exit_code == 2  # typer's min=1


def test_compare_profile_runs_each_profile_and_tabulates_them(monkeypatch, tmp_path):
    from mmpa.backends.twin.error_model import ErrorModelConfig

    mod = types.ModuleType("mmpa_toy_twin")

    class Config(BaseModel):
        seed: int = 0
        trials: int | None = None
        errors: ErrorModelConfig = ErrorModelConfig()

    def run(cfg, ctx):  # a figure that follows the profile: the depth noise it models
        sub = cfg.errors.camera.subpixel
        rows = [{"trial": i, "v": sub * (i + 1)} for i in range(cfg.trials or 2)]
        return rn.Outcome(rows, {"site": {"noise_px": sub}, "n": len(rows)}, "toy")

    mod.Config, mod.run, mod.PAPER = Config, run, "a toy twin table"
    monkeypatch.setitem(sys.modules, "mmpa_toy_twin", mod)
    monkeypatch.setitem(rn.EXPERIMENTS, "toytwin", "mmpa_toy_twin")
    out = rn.run_experiment(
        "toytwin", tmp_path / "run", trials=3, overrides=["errors.profile=realistic"],
        compare=["reference", "harsh"],
    )  # fmt: skip
    assert out.summary["profile"] == "realistic"
    for p, sub in (("reference", 0.08), ("harsh", 0.10)):  # DESIGN.md's subpixel per profile
        s = json.loads((tmp_path / "run" / f"profile-{p}" / "summary.json").read_text())
        assert s["profile"] == p and s["site"]["noise_px"] == pytest.approx(sub)
        cfg = yaml.safe_load((tmp_path / "run" / f"profile-{p}" / "config.yaml").read_text())
        assert cfg["trials"] == 3 and cfg["errors"]["profile"] == p
    report = (tmp_path / "run" / "report.md").read_text()
    assert "## Under other error model profiles" in report
    line = next(x for x in report.splitlines() if x.startswith("| site.noise_px"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells == ["site.noise_px", "0.0800", "0.0800", "0.1000"]
    assert "wall_seconds" not in report
    # an experiment without a twin error model has nothing to compare: refused before it runs
    plain = types.ModuleType("mmpa_toy_plain")

    class Plain(BaseModel):
        seed: int = 0
        trials: int | None = None

    plain.Config, plain.run, plain.PAPER = Plain, run, "plain"
    monkeypatch.setitem(sys.modules, "mmpa_toy_plain", plain)
    monkeypatch.setitem(rn.EXPERIMENTS, "toyplain", "mmpa_toy_plain")
    with pytest.raises(ConfigError, match="no twin error model"):
        rn.run_experiment("toyplain", tmp_path / "x", compare=["reference"])
    assert not (tmp_path / "x").exists()

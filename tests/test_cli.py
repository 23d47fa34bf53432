"""End-to-end: the CLI runs the twin and writes real files; bad input fails clearly."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import numpy as np
import pytest
import yaml
from matplotlib.image import imread
from typer.testing import CliRunner

from mmpa.apps.demo import DemoConfig
from mmpa.backends.twin.scene import load_scene
from mmpa.cli.main import app
from mmpa.core.config import apply_overrides, load_config
from mmpa.core.errors import ConfigError

runner = CliRunner()


def test_snapshot_writes_pictures_cloud_and_summary(tmp_path):
    res = runner.invoke(app, ["sim", "snapshot", "--site", "1", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    for name in (
        "color.png",
        "depth.png",
        "topdown.png",
        "cloud.ply",
        "summary.json",
        "config.yaml",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    color = imread(tmp_path / "color.png")
    assert color.shape[:2] == (480, 640)
    assert color[..., :3].std() > 0.05  # a textured bench, not a blank frame
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["profile"] == "realistic"  # the default twin
    site = load_scene().site("1")
    assert np.hypot(*(np.array(summary["base_pose_6d"][:2]) - site.position[:2])) < 0.01
    assert summary["cloud_points"] > 100_000
    assert 0.01 < summary["depth_invalid_fraction"] < 0.2
    assert summary["scan_reflective_beams"] > 0
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    assert len(pc.points) == summary["cloud_points"]
    z = np.asarray(pc.points)[:, 2]
    assert 0.2 <= z.min() and z.max() <= 3.0  # the depth crop of the capture
    saved = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert saved["errors"]["seed"] == 0


def test_unknown_site_lists_valid_names(tmp_path):
    res = runner.invoke(app, ["sim", "snapshot", "--site", "7", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "unknown site '7'" in res.output
    for name in ("0", "1", "2", "2'"):
        assert name in res.output


def test_set_overrides_reach_the_config():
    cfg = load_config(DemoConfig, None, ["goal_site=2", "controller.max_v=0.25", "errors.seed=4"])
    assert cfg.goal_site == "2"
    assert cfg.controller.max_v == pytest.approx(0.25)
    assert cfg.errors.seed == 4
    assert cfg.start_site == "0"  # untouched defaults stay


def test_bad_overrides_name_the_problem():
    with pytest.raises(ConfigError, match="key=value"):
        apply_overrides({}, ["seed"])
    with pytest.raises(ConfigError, match=r"controller\.max_v"):
        load_config(DemoConfig, None, ["controller.max_v=fast"])
    with pytest.raises(ConfigError, match="nonsense"):
        load_config(DemoConfig, None, ["nonsense=1"])


def test_demo_main_job_end_to_end(tmp_path):
    """`mmpa demo`: teach at Site 1, drive 0 -> 1 on the localization estimate, then MMPA;
    every figure is checked against the simulator's truth it reports."""
    res = runner.invoke(app, ["demo", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["reached"] and s["parking_error_xy_m"] < 0.02
    assert s["mmpa_ipe_ok"] and s["mmpa_ipe_E_t_mm"] < 3.0
    assert s["mmpa_tool_error_mm"] < 1.5
    from mmpa.tasks import read_bundle

    task = read_bundle(tmp_path / "task")
    assert task.name == "needle_site1" and len(task.cloud) > 100_000
    for name in ("color.png", "depth.png", "topdown.png", "cloud.ply", "config.yaml"):
        assert (tmp_path / name).stat().st_size > 0


def test_profile_option_picks_the_error_model(tmp_path):
    """--profile reaches the world and the summary; a --set on top still applies; an unknown
    profile is a clear error."""
    args = ["sim", "snapshot", "--site", "1", "--out", str(tmp_path), "--profile", "ideal"]
    res = runner.invoke(app, [*args, "--set", "errors.camera.invalid_fraction=0.1"])
    assert res.exit_code == 0, res.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["profile"] == "ideal"
    cfg = yaml.safe_load((tmp_path / "config.yaml").read_text())
    assert cfg["errors"]["profile"] == "ideal"
    assert cfg["errors"]["camera"]["subpixel"] == 0.0  # the ideal camera ...
    assert cfg["errors"]["camera"]["invalid_fraction"] == 0.1  # ... with the --set on top
    assert 0.08 < summary["depth_invalid_fraction"] < 0.3
    res = runner.invoke(app, ["sim", "snapshot", "--out", str(tmp_path), "--profile", "kind"])
    assert res.exit_code == 2 and "profile" in res.output

"""The wheel: built from this tree, installed in a clean virtual environment (no mmpa
checkout on the path, nothing but the wheel's own dependencies), it runs ``mmpa --help``,
``mmpa --version`` and reads its packaged data (worlds, the robot template)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _run(cmd: list[str], cwd: Path, timeout: int = 300) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    res = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert res.returncode == 0, f"{' '.join(cmd)}\n{res.stdout[-2000:]}\n{res.stderr[-2000:]}"
    return res.stdout


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dist")
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "-q",
            "--no-deps",
            "-w",
            str(out),
            str(ROOT),
        ],
        cwd=out,
    )
    (whl,) = out.glob("mmpa-*.whl")
    return whl


def test_wheel_carries_the_licence_and_the_data(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    assert any(n.endswith("licenses/LICENSE") for n in names)
    assert "mmpa/backends/twin/worlds/default.yaml" in names
    assert "mmpa/py.typed" in names
    assert not any(n.startswith("tests/") for n in names)


# slow (30 s: a venv and a pip install of every dependency); the default run keeps
# test_wheel_carries_the_licence_and_the_data (the same wheel, its files and metadata)
@pytest.mark.slow
def test_wheel_installs_and_runs_in_a_clean_venv(wheel: Path, tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], cwd=tmp_path)
    py, mmpa = venv / "bin" / "python", venv / "bin" / "mmpa"
    _run(
        [str(py), "-m", "pip", "install", "-q", "-c", str(ROOT / "constraints.txt"), str(wheel)],
        cwd=tmp_path,
        timeout=600,
    )
    from mmpa import __version__

    assert _run([str(mmpa), "--version"], cwd=tmp_path).strip() == __version__
    assert "teach" in _run([str(mmpa), "--help"], cwd=tmp_path)
    shown = _run([str(mmpa), "robot", "show"], cwd=tmp_path)
    assert "name: mmpa-ur5e-diffdrive" in shown
    # the installed package, not this checkout, answered
    where = _run([str(py), "-c", "import mmpa; print(mmpa.__file__)"], cwd=tmp_path)
    assert str(venv) in where and str(ROOT / "src") not in where

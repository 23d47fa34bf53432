"""Layering: the capabilities and missions never import the simulator (they run on the robot
protocols; the twin is one backend among bag and hardware ones). Checked on the source: every
``import`` / ``from ... import`` in those packages, at any depth (lazy imports included)."""

from __future__ import annotations

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "mmpa"
CAPABILITIES = [
    "calibration",
    "fiducial_search",
    "ipe",
    "localization",
    "missions",
    "navigation",
    "perception",
    "planning",
    "registration",
    "robot",
    "servo",
    "tasks",
]
#: modules allowed to import the simulator (none)
KNOWN: set[str] = set()


def _sim_imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("mmpa.sim")]
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("mmpa.sim"):
            found.append(node.module or "")
    return found


def test_capabilities_and_missions_do_not_import_the_simulator() -> None:
    offenders = {}
    for pkg in CAPABILITIES:
        for path in sorted((SRC / pkg).rglob("*.py")):
            module = "mmpa." + ".".join(path.relative_to(SRC).with_suffix("").parts)
            hits = _sim_imports(path)
            if hits and module not in KNOWN:
                offenders[module] = hits
    assert not offenders, offenders
    # the checker itself sees an import (it can fail)
    assert _sim_imports(SRC / "experiments" / "perception_data.py")

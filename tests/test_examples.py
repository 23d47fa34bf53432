"""The examples run as shipped (a broken example is a broken promise)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bring_your_own_arm() -> None:
    res = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "bring_your_own_arm.py")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    assert "tool moved 100.0 mm" in res.stdout  # the fake arm ended where the path ends
    assert "refused: joint path: joint 1 velocity" in res.stdout

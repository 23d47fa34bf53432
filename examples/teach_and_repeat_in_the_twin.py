"""Teach and repeat in the twin (the default backend: no robot file, or ``backend.kind:
twin``). The same as ``mmpa teach 1 needle_site1`` then ``mmpa run needle_site1``, in
Python: the twin's scripted operator shows the needle task at site 1, then the robot parks
roughly (a paper Table 2 offset) and repeats it; the twin knows the truth, so the run reports
its errors.

Run ``python examples/teach_and_repeat_in_the_twin.py [TASKS.db]`` (default: a temporary
store). On a robot: ``teach_and_repeat_on_your_robot.py`` (direct) or
``teach_and_repeat_over_ros2.py`` (ros2).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from mmpa.apps.teach_run import run_task, teach_task


def main(db: str) -> dict:
    print("taught:", teach_task("1", "needle_site1", db=db, overwrite=True))
    out = run_task("needle_site1", db=db)  # park with an offset, IPE, the adapted path
    print("run:", out)
    return out


if __name__ == "__main__":
    with tempfile.TemporaryDirectory(prefix="mmpa_twin_") as tmp:
        out = main(sys.argv[1] if len(sys.argv) > 1 else str(Path(tmp) / "tasks.db"))
    sys.exit(0 if out.get("executed") else 1)

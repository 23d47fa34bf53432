"""Test-run order: the files with the longest runs first.

``make test`` spreads whole files over the cores (pytest-xdist ``--dist loadfile``) in the
order collected. A file of a minute collected last runs alone on one core while the other
idles; collected first, the short files fill in around it (longest-first scheduling). The
order of the tests inside a file is kept. Costs from ``--durations`` on 2 cores (s).
"""

from __future__ import annotations

import pytest

# file -> seconds of its tests (issue 32, measured with `pytest --durations=0`, 2 cores)
_HEAVY = {
    "test_mmpa_twin.py": 75,
    "test_servo_twin.py": 70,
    "test_executor.py": 70,
    "test_localization_experiments.py": 45,
    "test_protocols_only.py": 40,
    "test_record_run.py": 30,
    "test_calibration_hand_eye.py": 30,
    "test_cli.py": 25,
    "test_navigation.py": 20,
    "test_record_experiment.py": 20,
    "test_fiducial_experiments.py": 17,
    "test_calibrate_reflectors.py": 12,
    "test_backend_realsense.py": 12,
    "test_navigation_cli.py": 12,
    # issues 34-36 (2 cores, this session's --durations): DDS tests wait on other processes
    "test_ros2_localization.py": 20,
    "test_examples.py": 45,
    "test_ros2_devices.py": 13,
    "test_ros2_drive.py": 12,
    "test_ros2_twin.py": 12,
    "test_localization_real.py": 12,
    "test_run_hardware.py": 10,
    "test_ros2_play.py": 9,
    "test_teach_person.py": 7,
    "test_grasp_cli.py": 6,
    "test_sim_camera_render.py": 6,
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Stable sort of ``items`` by their file's cost, longest first."""
    items.sort(key=lambda it: -_HEAVY.get(it.path.name, 0))

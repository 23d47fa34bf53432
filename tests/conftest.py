"""Test-run order: the files with the longest runs first.

``make test`` spreads whole files over the cores (pytest-xdist ``--dist loadfile``) in the
order collected (``--no-loadscope-reorder``: by default xdist hands out the files with the
most tests first, whatever their cost). A file of a minute collected last runs alone on one
core while the other idles; collected first, the short files fill in around it
(longest-first scheduling). The order of the tests inside a file is kept.
"""

from __future__ import annotations

import pytest

# file -> seconds of its tests on one of 2 busy cores (a pytest-xdist worker's time from the
# previous test's end to each of its tests' ends, summed per file; this session's make test)
_HEAVY = {
    "test_examples.py": 42,
    "test_mmpa_twin.py": 41,
    "test_executor.py": 40,
    "test_servo_twin.py": 38,
    "test_protocols_only.py": 29,
    "test_localization_experiments.py": 28,
    "test_record_run.py": 18,
    "test_cli.py": 18,
    "test_ros2_devices.py": 14,
    "test_ros2_drive.py": 12,
    "test_ros2_localization.py": 12,
    "test_calibration_hand_eye.py": 11,
    "test_localization_amcl.py": 10,
    "test_ros2_twin.py": 10,
    "test_localization_real.py": 10,
    "test_record_experiment.py": 10,
    "test_navigation_cli.py": 9,
    "test_sim_world.py": 9,
    "test_fuzz.py": 9,
    "test_ros2_play.py": 8,
    "test_run_hardware.py": 8,
    "test_layers.py": 8,
    "test_backend_realsense.py": 7,
    "test_navigation.py": 7,
    "test_localization_benchmark.py": 7,
    "test_localization_honest.py": 7,
    "test_calibrate_reflectors.py": 5,
    "test_perception_workview.py": 5,
    "test_teach_person.py": 5,
    "test_sensors.py": 5,
    "test_register_cli.py": 4,
    "test_bags.py": 4,
    "test_grasp_cli.py": 4,
    "test_tasks_hostile.py": 4,
    "test_sim_camera_render.py": 4,
    "test_joint_limits.py": 4,
    "test_sweep.py": 4,
    "test_error_model_v2.py": 4,
    "test_registration.py": 4,
    "test_fiducial_experiments.py": 3,
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Stable sort of ``items`` by their file's cost, longest first."""
    items.sort(key=lambda it: -_HEAVY.get(it.path.name, 0))

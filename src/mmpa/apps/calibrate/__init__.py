"""The calibrations in the twin, each judged against the twin's truth:

- ``mmpa calibrate hand-eye`` (:mod:`~mmpa.apps.calibrate.hand_eye`, the evaluation in
  :mod:`~mmpa.apps.calibrate.hand_eye_truth`): a ChArUco board in front of a site, the
  procedure over the robot interfaces (:mod:`mmpa.missions.hand_eye`), OpenCV's five
  methods and the joint DH + hand-eye fit; on a hardware robot
  (:mod:`~mmpa.apps.calibrate.hand_eye_robot`): the board in the camera's view, the views
  planned around it after the user's confirmation, no truth (the residuals);
- ``mmpa calibrate lidar-mount`` (:mod:`~mmpa.apps.calibrate.lidar_mount`): a turn on the
  spot and a circle fit;
- ``mmpa calibrate reflectors`` (:mod:`~mmpa.apps.calibrate.reflectors`): the reflector map
  surveyed from a drive; on a hardware robot (:mod:`~mmpa.apps.calibrate.reflectors_robot`):
  the user's map, rough pose and route, the drive after the user's confirmation, no truth.

The files they write (``hand_eye.yaml``, ``calibration.conf``, ``robot.yaml``,
``summary.json``) in :mod:`~mmpa.apps.calibrate.files`. Figures: docs/calibration.md.
"""

from __future__ import annotations

from mmpa.apps.calibrate.files import hand_eye_yaml, ur_calibration_conf, write_robot_file
from mmpa.apps.calibrate.hand_eye import HandEyeConfig, run_hand_eye
from mmpa.apps.calibrate.hand_eye_robot import run_hand_eye_on_robot
from mmpa.apps.calibrate.hand_eye_truth import last_link_error
from mmpa.apps.calibrate.lidar_mount import run_lidar_mount
from mmpa.apps.calibrate.reflectors import ReflectorSurveyConfig, run_reflector_survey
from mmpa.apps.calibrate.reflectors_robot import RobotSurveyConfig, run_reflector_survey_on_robot

__all__ = [
    "HandEyeConfig",
    "ReflectorSurveyConfig",
    "RobotSurveyConfig",
    "hand_eye_yaml",
    "last_link_error",
    "run_hand_eye",
    "run_hand_eye_on_robot",
    "run_lidar_mount",
    "run_reflector_survey",
    "run_reflector_survey_on_robot",
    "ur_calibration_conf",
    "write_robot_file",
]

"""The robot file: a YAML description of a user's robot, read into a
:class:`~mmpa.robot.description.RobotDescription`.

A robot file holds any field of ``RobotDescription`` (missing fields keep mmpa's defaults),
plus two shortcuts under ``arm``:

- ``model: ur3e | ur5e | ur10e | ur16e`` takes the published DH parameters, joint speed
  limits, link masses and reach of that Universal Robots e-Series arm (Universal Robots,
  "DH parameters for calculations of kinematics and dynamics"; e-Series datasheets);
- ``calibration: FILE`` applies the arm's factory kinematic calibration: the
  ``calibration.conf`` the controller keeps (``[mounting]`` with ``delta_theta``,
  ``delta_a``, ``delta_d``, ``delta_alpha``), added to the nominal DH as the controller does
  (``theta_offset += delta_theta``, ``a += delta_a``, ``d += delta_d``,
  ``alpha += delta_alpha``). A relative path is read beside the robot file.

``reflector_map: FILE`` (optional, default none) names the site's surveyed reflector map
(:mod:`mmpa.maps.reflector_map`; written by ``mmpa calibrate reflectors``); a
relative path is read beside the robot file (:func:`robot_reflector_map`). It is not part
of the :class:`RobotDescription`: :func:`load_robot` accepts and skips it.

``localization:`` (optional) holds the robot's localization settings: ``method``, ``amcl``
(Nav2's ``amcl`` parameter names), ``enhanced``, ``hector``, ``initial_cov`` (the model is
:class:`mmpa.localization.settings.LocalizationConfig`, checked by the commands that localize;
:func:`robot_localization` returns the section as written). Like ``reflector_map`` it is not
part of the :class:`RobotDescription`.

``backend:`` (optional, default ``kind: twin``) says which robot the mission commands drive:
the twin, a ROS 2 robot or the arm and camera directly
(:class:`mmpa.robot.backend_config.BackendConfig`; :func:`robot_backend`, checked when the
robot file is loaded; a relative ``direct.realsense_playback`` is read beside the robot file).

``frames`` names mmpa's frames as a ROS system does (REP-105 for the base, ur_description
for the arm), with optional prefixes; :func:`frame_names` maps mmpa's names to them.

Example::

    name: my-ur10e-on-agv
    arm: {model: ur10e, calibration: calibration.conf}
    camera: {T_flange_camera_vec: [0.0, -0.09, 0.04, 0.0, 0.0, 0.0]}
    lidar: {T_base_link_laser_vec: [0.3, 0.0, 0.2, 0.0, 0.0, 0.0], num_beams: 720,
            angle_increment: 0.008726646}
    frames: {prefix: "", arm_prefix: "ur_"}
    localization: {method: amcl, amcl: {laser_model_type: beam, alpha1: 0.05}}
    backend: {kind: direct, direct: {ur_host: 192.168.1.10}, safety: {speed_scale: 0.25}}
"""

from __future__ import annotations

import configparser
import math
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from mmpa.core.errors import ConfigError
from mmpa.core.yamlio import load_yaml
from mmpa.robot.backend_config import BackendConfig
from mmpa.robot.description import RobotDescription

__all__ = [
    "UR_MODELS",
    "FrameNames",
    "frame_names",
    "load_robot",
    "read_ur_calibration",
    "robot_backend",
    "robot_localization",
    "robot_reflector_map",
    "robot_to_yaml",
    "save_robot",
]

_D = math.pi / 180.0

#: Published UR e-Series values: DH ``a``, ``d`` (m; ``alpha`` is pi/2, 0, 0, pi/2, -pi/2, 0
#: for all four), link masses (kg), maximum joint speeds (rad/s) and reach (m).
UR_MODELS: dict[str, dict[str, Any]] = {
    "ur3e": {
        "a": (0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
        "d": (0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921),
        "link_masses": (1.98, 3.4445, 1.437, 0.871, 0.805, 0.261),
        "qd_max": (180 * _D, 180 * _D, 180 * _D, 360 * _D, 360 * _D, 360 * _D),
        "reach": 0.5,
    },
    "ur5e": {
        "a": (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
        "d": (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
        "link_masses": (3.761, 8.058, 2.846, 1.37, 1.3, 0.365),
        "qd_max": (180 * _D,) * 6,
        "reach": 0.85,
    },
    "ur10e": {
        "a": (0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0),
        "d": (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        "link_masses": (7.369, 13.051, 3.989, 2.1, 1.98, 0.615),
        "qd_max": (120 * _D, 120 * _D, 180 * _D, 180 * _D, 180 * _D, 180 * _D),
        "reach": 1.3,
    },
    "ur16e": {
        "a": (0.0, -0.4784, -0.36, 0.0, 0.0, 0.0),
        "d": (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655),
        "link_masses": (7.369, 10.45, 4.321, 2.18, 2.033, 0.907),
        "qd_max": (120 * _D, 120 * _D, 180 * _D, 180 * _D, 180 * _D, 180 * _D),
        "reach": 0.9,
    },
}


class FrameNames(BaseModel):
    """ROS frame names of mmpa's frames. Base frames follow REP-105 (``map``, ``odom``,
    ``base_link``, ``laser``) with ``prefix``; the arm's follow ur_description with
    ``arm_prefix``: mmpa's ``arm_base`` is UR's ``base`` (REP-103, x backward: 180 deg in
    yaw from ur_description's ``base_link``, which is not mmpa's mobile ``base_link``), and
    mmpa's ``flange`` is UR's ``tool0``."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    prefix: str = ""
    arm_prefix: str = ""
    map: str = "map"
    odom: str = "odom"
    base_link: str = "base_link"
    laser: str = "laser"
    arm_base: str = "base"
    flange: str = "tool0"
    tcp: str = "tcp"
    camera_optical: str = "camera_color_optical_frame"


def frame_names(frames: FrameNames | None = None) -> dict[str, str]:
    """mmpa frame name -> ROS frame name (prefixes applied; ``map`` and ``odom`` are
    shared by every robot of a site and get no prefix)."""
    f = frames or FrameNames()
    arm = f.prefix + f.arm_prefix
    return {
        "map": f.map,
        "odom": f.prefix + f.odom,
        "base_link": f.prefix + f.base_link,
        "laser": f.prefix + f.laser,
        "arm_base": arm + f.arm_base,
        "flange": arm + f.flange,
        "tcp": arm + f.tcp,
        "camera_optical": f.prefix + f.camera_optical,
    }


def _floats(text: str, what: str) -> tuple[float, ...]:
    body = text.strip().strip("[]")
    try:
        values = tuple(float(x) for x in body.replace(",", " ").split())
    except ValueError:
        raise ConfigError(f"{what}: not a list of numbers: {text.strip()[:80]!r}") from None
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"{what}: need 6 finite numbers, got {len(values)}")
    return values


def read_ur_calibration(path: str | Path) -> dict[str, tuple[float, ...]]:
    """The DH deltas of a UR controller's ``calibration.conf`` (``[mounting]`` section):
    ``{"delta_theta", "delta_a", "delta_d", "delta_alpha"}`` -> 6 values each (rad, m)."""
    p = Path(path)
    parser = configparser.ConfigParser()
    try:
        if p.stat().st_size > 1_000_000:
            raise ConfigError(f"{p}: too large for a UR calibration file")
        parser.read_string(p.read_text(encoding="utf-8"), source=str(p))
    except OSError as e:
        raise ConfigError(f"cannot read UR calibration {p}: {e.strerror or e}") from e
    except (configparser.Error, UnicodeDecodeError) as e:
        raise ConfigError(f"{p}: not a UR calibration file: {e}") from e
    if "mounting" not in parser:
        raise ConfigError(f"{p}: no [mounting] section (a UR controller's calibration.conf)")
    sec = parser["mounting"]
    out = {}
    for key in ("delta_theta", "delta_a", "delta_d", "delta_alpha"):
        if key not in sec:
            raise ConfigError(f"{p}: [mounting] lacks {key}")
        out[key] = _floats(sec[key], f"{p}: [mounting] {key}")
    return out


def _apply_shortcuts(doc: dict[str, Any], where: Path) -> dict[str, Any]:
    arm = doc.get("arm")
    if arm is None:
        return doc
    if not isinstance(arm, dict):
        raise ConfigError(f"{where}: arm must be a mapping")
    arm = dict(arm)
    model = arm.pop("model", None)
    calibration = arm.pop("calibration", None)
    dh = arm.get("dh") or {}
    if not isinstance(dh, dict):
        raise ConfigError(f"{where}: arm.dh must be a mapping (a, d, alpha, theta_offset)")
    dh = dict(dh)
    if model is not None:
        key = str(model).lower()
        if key not in UR_MODELS:
            raise ConfigError(
                f"{where}: arm.model {model!r} is not known; valid: {', '.join(UR_MODELS)}"
            )
        spec = UR_MODELS[key]
        dh = {"a": spec["a"], "d": spec["d"], **dh}
        arm.setdefault("name", key)
        for k in ("link_masses", "qd_max", "reach"):
            arm.setdefault(k, spec[k])
    if calibration is not None:
        cal_path = Path(str(calibration))
        if not cal_path.is_absolute():
            cal_path = where.parent / cal_path
        try:
            deltas = read_ur_calibration(cal_path)
        except ConfigError as e:
            raise ConfigError(f"{where}: arm.calibration: {e}") from None
        base = RobotDescription().arm.dh.model_copy(update=dh) if dh else RobotDescription().arm.dh
        a, d, alpha, theta = base.as_arrays()
        dh = {
            "a": tuple((a + deltas["delta_a"]).tolist()),
            "d": tuple((d + deltas["delta_d"]).tolist()),
            "alpha": tuple((alpha + deltas["delta_alpha"]).tolist()),
            "theta_offset": tuple((theta + deltas["delta_theta"]).tolist()),
        }
    if dh:
        arm["dh"] = dh
    return {**doc, "arm": arm}


def load_robot(path: str | Path) -> tuple[RobotDescription, FrameNames]:
    """Read a robot file (module docstring): the description and its frame names.
    Errors (:class:`ConfigError`) name the file and the field."""
    p = Path(path)
    doc = load_yaml(p)
    if doc is None:
        doc = {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: a robot file must be a YAML mapping")
    doc = dict(doc)
    _reflector_map_entry(doc.pop("reflector_map", None), p)
    _localization_entry(doc.pop("localization", None), p)
    _backend_entry(doc.pop("backend", None), p)
    try:
        frames = FrameNames.model_validate(doc.pop("frames", None) or {})
    except ValidationError as e:
        raise ConfigError(f"{p}: frames: {_first_error(e)}") from None
    doc = _apply_shortcuts(doc, p)
    try:
        return RobotDescription.model_validate(doc), frames
    except ValidationError as e:
        raise ConfigError(f"{p}: {_first_error(e)}") from None


def _reflector_map_entry(value: Any, where: Path) -> Path | None:
    """The ``reflector_map`` entry of robot file ``where``: None, or the path (a relative one
    resolved beside the robot file)."""
    if value is None:
        return None
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(
            f"{where}: reflector_map: must be the path of a reflector map file, got {value!r}"
        )
    path = Path(value)
    return path if path.is_absolute() else where.parent / path


def _localization_entry(value: Any, where: Path) -> dict[str, Any] | None:
    """The ``localization`` section of robot file ``where``: None or a mapping."""
    if value is None:
        return None
    if not isinstance(value, dict):
        raise ConfigError(
            f"{where}: localization: must be a mapping (method, amcl, enhanced, hector, "
            f"initial_cov), got {type(value).__name__}"
        )
    return dict(value)


def robot_localization(path: str | Path) -> dict[str, Any] | None:
    """The ``localization`` section of robot file ``path`` as written (a mapping), or None;
    its values are checked by the command that uses them
    (:class:`mmpa.localization.settings.LocalizationConfig`)."""
    p = Path(path)
    doc = load_yaml(p)
    if doc is None:
        return None
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: a robot file must be a YAML mapping")
    return _localization_entry(doc.get("localization"), p)


def _backend_entry(value: Any, where: Path) -> BackendConfig:
    """The ``backend`` section of robot file ``where``, checked (default: the twin)."""
    if value is None:
        return BackendConfig()
    if not isinstance(value, dict):
        raise ConfigError(
            f"{where}: backend: must be a mapping (kind, ros2, direct, safety), "
            f"got {type(value).__name__}"
        )
    try:
        cfg = BackendConfig.model_validate(value)
    except ValidationError as e:
        raise ConfigError(f"{where}: backend.{_first_error(e)}") from None
    playback = cfg.direct.realsense_playback
    if playback is not None and not playback.is_absolute():
        direct = cfg.direct.model_copy(update={"realsense_playback": where.parent / playback})
        cfg = cfg.model_copy(update={"direct": direct})
    return cfg


def robot_backend(path: str | Path | None) -> BackendConfig:
    """The ``backend`` section of robot file ``path`` (None: no robot file, the twin)."""
    if path is None:
        return BackendConfig()
    p = Path(path)
    doc = load_yaml(p)
    if doc is None:
        return BackendConfig()
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: a robot file must be a YAML mapping")
    return _backend_entry(doc.get("backend"), p)


def robot_reflector_map(path: str | Path) -> Path | None:
    """The reflector map file named by robot file ``path`` (its optional ``reflector_map``
    entry, resolved beside the robot file), or None. The map itself is not read here."""
    p = Path(path)
    doc = load_yaml(p)
    if doc is None:
        return None
    if not isinstance(doc, dict):
        raise ConfigError(f"{p}: a robot file must be a YAML mapping")
    return _reflector_map_entry(doc.get("reflector_map"), p)


def _first_error(e: ValidationError) -> str:
    err = e.errors()[0]
    loc = ".".join(str(x) for x in err["loc"])
    return f"{loc}: {err['msg']}" if loc else str(err["msg"])


class _Dumper(yaml.SafeDumper):
    """Block mappings, flow lists (a 6-vector on one line)."""


_Dumper.add_representer(
    list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True)
)


def robot_to_yaml(
    robot: RobotDescription,
    frames: FrameNames | None = None,
    reflector_map: str | Path | None = None,
    backend: BackendConfig | None = None,
) -> str:
    """The robot file text of ``robot`` (every field, so it is a complete template), with
    the optional ``reflector_map`` entry and ``backend`` section when given."""
    doc = robot.model_dump(mode="json")
    doc["frames"] = (frames or FrameNames()).model_dump(mode="json")
    if reflector_map is not None:
        doc["reflector_map"] = str(reflector_map)
    if backend is not None:
        doc["backend"] = backend.model_dump(mode="json")
    return yaml.dump(doc, Dumper=_Dumper, sort_keys=False, width=100)


def save_robot(
    robot: RobotDescription,
    path: str | Path,
    frames: FrameNames | None = None,
    reflector_map: str | Path | None = None,
) -> Path:
    """Write ``robot`` as a robot file (written to a temporary file, then renamed);
    ``reflector_map``: the optional entry (a relative path is read beside the file)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(robot_to_yaml(robot, frames, reflector_map), encoding="utf-8")
    tmp.replace(p)
    return p

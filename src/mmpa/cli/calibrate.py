"""``mmpa calibrate``: calibrations in the twin (``hand-eye``: the wrist camera on the flange
from a ChArUco board; ``lidar-mount``; ``reflectors``: the reflector map surveyed from a
drive; see :mod:`mmpa.apps.calibrate`); ``hand-eye`` and ``reflectors`` also on the robot of
``mmpa --robot R`` (a ``ros2`` or ``direct`` backend), asking before it moves."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import console, fail
from mmpa.cli.hardware import YesOpt, backend_in_use, confirmer, open_hardware
from mmpa.core.errors import MMPAError

__all__ = ["calibrate_app", "register"]

calibrate_app = typer.Typer(
    help="Calibrations in the twin: hand-eye (ChArUco board), lidar mount (a turn on the spot), "
    "reflectors (a survey drive); hand-eye and reflectors on any backend (mmpa --robot R)."
)

_PROFILES = ("ideal", "reference", "realistic", "harsh")


def _choice(what: str, value: str, allowed: tuple[str, ...]) -> None:
    """A usage error (exit 2) naming ``value`` unless it is one of ``allowed``."""
    if value not in allowed:
        raise typer.BadParameter(f"unknown {what} {value!r}; one of {list(allowed)}")


def _twin_env() -> None:
    """Off-screen rendering for the twin (unless the user chose a backend)."""
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")


_BoardSquaresOpt = Annotated[
    str | None,
    typer.Option(help="ChArUco board: squares across x down, e.g. 7x5 (default 7x5)."),
]


def _board(squares: str | None, square: float | None, marker: float | None, dictionary: str | None):
    """The board fields given on the command line (None: the default board)."""
    board: dict[str, object] = {}
    if squares is not None:
        try:
            nx, ny = (int(v) for v in squares.lower().split("x"))
        except ValueError:
            raise typer.BadParameter(f"--board-squares {squares!r}: use NxM, e.g. 7x5") from None
        board |= {"squares_x": nx, "squares_y": ny}
    given = {"square": square, "marker": marker, "dictionary": dictionary}
    board |= {k: v for k, v in given.items() if v is not None}
    return board or None


def _hand_eye_config(stations: int, method: str, board: dict | None, **twin):
    """The twin run's / the procedure's settings; a bad board is a usage error."""
    from pydantic import ValidationError

    from mmpa.apps.calibrate import HandEyeConfig

    extra = {} if board is None else {"board": board}
    try:
        return HandEyeConfig(stations=stations, method=method, **extra, **twin)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(map(str, err["loc"]))
        raise typer.BadParameter(f"{where}: {err['msg']}") from None


def _hand_eye_hardware(cfg, out: Path, path: Path, backend, yes: bool) -> None:
    """The calibration on the robot of ``path`` (no truth: the residuals)."""
    from mmpa.apps.calibrate import run_hand_eye_on_robot

    try:
        with open_hardware(path, ("clock", "arm", "camera")) as robot:
            s = run_hand_eye_on_robot(
                robot,
                cfg,
                out,
                kind=backend.kind,
                confirm=confirmer(yes, backend),
                log=lambda m: console.print(m, highlight=False),
                robot_file=path,
            )
    except MMPAError as e:
        fail(e)
    if not s["ok"]:
        console.print(f"[yellow]not calibrated: {s['reason']}[/]", highlight=False)
        raise typer.Exit(1)
    r, k = s["residuals"], s["kinematics"]
    console.print(
        f"hand-eye ({s['method']}, {s['stations_used']} of {s['stations_planned']} views): "
        f"board corner spread {r['point_rms_mm']:.3f} mm RMS, AX=XB {r['axxb_trans_mm']:.3f} mm "
        f"{r['axxb_rot_deg']:.4f} deg; joint fit {k['rms_px_start']:.3f} -> {k['rms_px']:.3f} px "
        f"RMS; {s['change_from_nominal_trans_mm']:.2f} mm, "
        f"{s['change_from_nominal_rot_deg']:.3f} deg from the nominal hand-eye; wrote "
        f"{out}/summary.json, {out}/hand_eye.yaml and {out}/robot.yaml (use it: mmpa --robot "
        f"{out}/robot.yaml ...)",
        highlight=False,
    )


@calibrate_app.command("hand-eye")
def hand_eye_cmd(
    out: Annotated[Path, typer.Option(help="output folder (summary.json, hand_eye.yaml)")],
    site: Annotated[
        str, typer.Option(help="twin: site of the scene the board stands in front of")
    ] = "0",
    stations: Annotated[
        int, typer.Option(help="number of views of the board", min=3, max=100)
    ] = 40,
    seed: Annotated[
        int, typer.Option(help="twin: robot instance of the twin's error model", min=0)
    ] = 0,
    profile: Annotated[
        str, typer.Option(help="twin: error model profile: ideal, reference, realistic, harsh")
    ] = "realistic",
    method: Annotated[
        str,
        typer.Option(
            help="joint: the arm's DH corrections with the hand-eye (MAP over the board "
            "corners); opencv: cv2.calibrateHandEye with the nominal kinematics"
        ),
    ] = "joint",
    board_squares: _BoardSquaresOpt = None,
    board_square: Annotated[
        float | None, typer.Option(help="board square side, m (default 0.04)", min=0.001)
    ] = None,
    board_marker: Annotated[
        float | None, typer.Option(help="board marker side, m (default 0.03)", min=0.001)
    ] = None,
    board_dict: Annotated[
        str | None, typer.Option(help="ArUco dictionary (default DICT_5X5_100)")
    ] = None,
    yes: YesOpt = False,
) -> None:
    """Calibrate the wrist camera's pose on the flange (eye-in-hand). In the twin: a ChArUco
    board in front of SITE, STATIONS planned views, cv2.calibrateHandEye with all five
    methods (the one with the smallest residuals picked), then the joint kinematic +
    hand-eye calibration from it; both compared with the TRUE hand-eye, METHOD's written.
    With `mmpa --robot R` on a ros2 / direct robot: point the camera at your board (its
    geometry: --board-*), the views are planned around it from where the arm stands and
    visited after a question (--yes skips it); no truth: the residuals."""
    _choice("profile", profile, _PROFILES)
    _choice("method", method, ("joint", "opencv"))
    board = _board(board_squares, board_square, board_marker, board_dict)
    path, backend = backend_in_use()
    if backend.hardware:
        cfg = _hand_eye_config(stations, method, board)
        _hand_eye_hardware(cfg, out, path, backend, yes)
        return
    _twin_env()
    try:
        from mmpa.apps.calibrate import run_hand_eye

        cfg = _hand_eye_config(stations, method, board, site=site, seed=seed, profile=profile)
        s = run_hand_eye(cfg, out, log=lambda m: console.print(m, highlight=False))
    except MMPAError as e:
        fail(e)
    console.print(
        f"hand-eye ({s['method']}, {s['stations_used']} stations): error "
        f"{s['error_trans_mm']:.3f} mm, {s['error_rot_deg']:.4f} deg against the true hand-eye, "
        f"{s['error_identifiable_trans_mm']:.3f} mm, {s['error_identifiable_rot_deg']:.4f} deg "
        f"against its identifiable part E6 X (the last DH link's error "
        f"{s['diagnostic']['last_link_dh_error_trans_mm']:.2f} mm is not observable); opencv "
        f"{s['by_method']['opencv']['error_vs_effective_trans_mm']:.3f} mm, joint "
        f"{s['by_method']['joint']['error_vs_effective_trans_mm']:.3f} mm against E6 X; "
        f"tool-point FK error "
        f"{s['kinematics']['fk_error']['tcp']['nominal']['rms_mm']:.2f} -> "
        f"{s['kinematics']['fk_error']['tcp']['calibrated']['rms_mm']:.2f} mm RMS; wrote "
        f"{out}/summary.json, {out}/hand_eye.yaml and {out}/robot.yaml (use it: mmpa --robot "
        f"{out}/robot.yaml ...)",
        highlight=False,
    )


@calibrate_app.command("lidar-mount")
def lidar_mount_cmd(
    out: Annotated[Path, typer.Option(help="output folder (summary.json, robot.yaml)")],
    site: Annotated[str, typer.Option(help="site where the robot turns on the spot")] = "0",
    seed: Annotated[int, typer.Option(help="robot instance of the twin's error model", min=0)] = 0,
    profile: Annotated[
        str, typer.Option(help="error model profile: ideal, reference, realistic, harsh")
    ] = "realistic",
) -> None:
    """Calibrate the lidar mount translation in the twin: one turn on the spot, every scan
    matched against the map, a circle fit; compared with the TRUE mount; robot.yaml for
    --robot."""
    _choice("profile", profile, _PROFILES)
    _twin_env()
    try:
        from mmpa.apps.calibrate import run_lidar_mount

        with console.status("turning on the spot"):
            s = run_lidar_mount(site, seed, profile, out)  # type: ignore[arg-type]
    except MMPAError as e:
        fail(e)
    console.print(
        f"lidar mount: error {s['error_mm']:.2f} mm against the true mount (nominal "
        f"{s['nominal_error_mm']:.2f} mm; fit RMS {s['fit_rms_mm']:.2f} mm, {s['scans']} scans); "
        f"wrote {out}/summary.json and {out}/robot.yaml (use it: mmpa --robot {out}/robot.yaml)",
        highlight=False,
    )


_BearingOpt = Annotated[
    str,
    typer.Option(
        help="reflector bearing: intensity (centroid of the intensity profile, sub-beam) "
        "or mean (the cluster's mean beam angle, paper 001)"
    ),
]
_AnchorOpt = Annotated[
    str,
    typer.Option(
        help="placement of the surveyed layout: poses (the laser-only localization's "
        "frame) or reflector-map (rigidly onto the site's existing reflector map)"
    ),
]
_MapMatchOpt = Annotated[
    bool,
    typer.Option(
        "--map-match/--no-map-match",
        help="refine each stop's pose by matching its mean scan onto the map",
    ),
]
_RefineOpt = Annotated[
    bool | None,
    typer.Option(
        "--refine/--no-refine",
        help="joint pose/reflector refinement (default: only without --map-match)",
    ),
]


def _poses(text: str, what: str) -> list[tuple[float, ...]]:
    """``x,y,theta`` poses separated by ``;`` (a usage error otherwise)."""
    try:
        poses = [tuple(float(v) for v in p.split(",")) for p in text.split(";") if p.strip()]
    except ValueError:
        poses = []
    if not poses or any(len(p) != 3 for p in poses):
        raise typer.BadParameter(f"{what} {text!r}: use x,y,theta (m, m, rad), ';' between poses")
    return poses


def _reflectors_hardware(common: dict, hw: dict, out: Path, path: Path, backend, yes: bool) -> None:
    """The survey on the robot of ``path`` (no truth: the fit's residuals)."""
    from pydantic import ValidationError

    from mmpa.apps.calibrate import RobotSurveyConfig, run_reflector_survey_on_robot

    needed = (("--map", "map"), ("--initial-pose", "initial_pose"), ("--route-poses", "route"))
    for opt, key in needed:
        if hw[key] is None:
            raise typer.BadParameter(f"{opt} is needed on a {backend.kind} robot")
    start = _poses(hw["initial_pose"], "--initial-pose")
    if len(start) != 1:
        raise typer.BadParameter("--initial-pose takes one pose x,y,theta")
    route = _poses(hw["route"], "--route-poses")
    try:
        cfg = RobotSurveyConfig(
            map=hw["map"], initial_pose=start[0], route=route, radius=hw["radius"], **common
        )
    except ValidationError as e:
        err = e.errors()[0]
        raise typer.BadParameter(f"{'.'.join(map(str, err['loc']))}: {err['msg']}") from None
    try:
        with open_hardware(path, ("clock", "odometry", "base", "lidar")) as robot:
            s = run_reflector_survey_on_robot(
                robot,
                cfg,
                out,
                kind=backend.kind,
                confirm=confirmer(yes, backend),
                log=lambda m: console.log(m, highlight=False),
                robot_file=path,
            )
    except MMPAError as e:
        fail(e)
    if not s["ok"]:
        console.print(f"[yellow]not surveyed: {s['reason']}[/]", highlight=False)
        raise typer.Exit(1)
    console.print(
        f"reflectors: {s['found']} found, fit RMS {s['residual_rms_mm']:.2f} mm, "
        f"{s['stations']} stops ({len(s['skipped'])} skipped); wrote {out}/reflectors.yaml, "
        f"{out}/summary.json and {out}/robot.yaml (use it: mmpa --robot {out}/robot.yaml)",
        highlight=False,
    )


@calibrate_app.command("reflectors")
def reflectors_cmd(
    out: Annotated[
        Path, typer.Option(help="output folder (reflectors.yaml, summary.json, robot.yaml)")
    ],
    site: Annotated[str, typer.Option(help="site the survey drive starts from")] = "0",
    route: Annotated[
        str, typer.Option(help="sites driven to, in order, comma-separated (e.g. 1,2,0)")
    ] = "1,2,0",
    spacing: Annotated[
        float, typer.Option(help="m between survey stops along the path", min=0.1, max=100.0)
    ] = 1.0,
    scans: Annotated[int, typer.Option(help="scans per survey stop", min=1, max=1000)] = 30,
    method: Annotated[str, typer.Option(help="laser-only localizer: hector or amcl")] = "hector",
    bearing: _BearingOpt = "intensity",
    anchor: _AnchorOpt = "poses",
    map_match: _MapMatchOpt = True,
    refine: _RefineOpt = None,
    seed: Annotated[int, typer.Option(help="robot instance of the twin's error model", min=0)] = 0,
    profile: Annotated[
        str, typer.Option(help="error model profile: ideal, reference, realistic, harsh")
    ] = "realistic",
    map_yaml: Annotated[
        Path | None, typer.Option("--map", help="hardware: the occupancy map (map_server YAML)")
    ] = None,
    initial_pose: Annotated[
        str | None, typer.Option(help="hardware: the robot's rough pose x,y,theta in the map")
    ] = None,
    route_poses: Annotated[
        str | None,
        typer.Option(help="hardware: poses x,y,theta in the map, ';'-separated, in order"),
    ] = None,
    radius: Annotated[
        float | None,
        typer.Option(help="hardware: reflector radius, m (default: the map's)", min=0.001),
    ] = None,
    yes: YesOpt = False,
) -> None:
    """Survey the laser reflectors in the twin: drive ROUTE from SITE, stopping every
    SPACING m; at each stop localize with the laser-only METHOD (no reflectors; the stop's
    mean scan then matched onto the map) and detect the reflectors; cluster, fit (with the
    scanner's range bias), optionally refine the poses and reflectors jointly; placed by
    the poses or (ANCHOR reflector-map) onto the site's existing reflector map; compared
    with the TRUE reflector positions; writes reflectors.yaml and robot.yaml. With
    `mmpa --robot R` on a ros2 / direct robot: --map, --initial-pose and --route-poses (in the
    map) instead of the sites, a question before the base moves (--yes skips it); no
    truth: the fit's residuals."""
    _choice("profile", profile, _PROFILES)
    _choice("laser-only localizer", method, ("hector", "amcl"))
    _choice("anchor", anchor, ("poses", "reflector-map"))
    _choice("bearing", bearing, ("intensity", "mean"))
    common = {
        "station_spacing": spacing,
        "scans": scans,
        "method": method,
        "anchor": anchor.replace("-", "_"),
        "seed": seed,
        "map_match": map_match,
        "survey": {} if refine is None else {"refine_poses": refine},
        "detection": {"bearing": bearing},
    }
    path, backend = backend_in_use()
    if backend.hardware:
        hw = {"map": map_yaml, "initial_pose": initial_pose, "route": route_poses, "radius": radius}
        _reflectors_hardware(common, hw, out, path, backend, yes)
        return
    stops = tuple(s.strip() for s in route.split(",") if s.strip())
    if not stops:
        raise typer.BadParameter("--route needs at least one site")
    _reflectors_twin(common, site, stops, profile, out)


def _reflectors_twin(
    common: dict, site: str, stops: tuple[str, ...], profile: str, out: Path
) -> None:
    """The survey in the twin, judged against the TRUE reflector positions."""
    _twin_env()
    try:
        from mmpa.apps.calibrate import ReflectorSurveyConfig, run_reflector_survey

        cfg = ReflectorSurveyConfig(site=site, route=stops, profile=profile, **common)
        with console.status("surveying the reflectors"):
            s = run_reflector_survey(cfg, out, log=lambda m: console.log(m, highlight=False))
    except MMPAError as e:
        fail(e)
    d = s["diagnostic"]
    console.print(
        f"reflectors: {s['found']} found, {s['missed']} missed, {s['spurious']} spurious; "
        f"error {s['error_mean_mm']:.2f} mm mean, {s['error_max_mm']:.2f} mm max against the "
        f"true positions (the marked map: {d['marked_map']['error_mean_mm']:.2f} mm; fit RMS "
        f"{s['residual_rms_mm']:.2f} mm, {s['stations']} stops); wrote {out}/reflectors.yaml, "
        f"{out}/summary.json and {out}/robot.yaml (use it: mmpa --robot {out}/robot.yaml)",
        highlight=False,
    )


def register(app: typer.Typer) -> None:
    """Add ``calibrate`` to the main app."""
    app.add_typer(calibrate_app, name="calibrate")

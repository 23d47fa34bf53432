"""``mmpa register``: register two recorded RGB-D frames (PNG pairs or a bag), print the pose
and the verdict (runner: :mod:`mmpa.apps.register`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mmpa.cli.common import console, fail, in_range, out_dir
from mmpa.core.errors import MMPAError

__all__ = ["register"]


def register_cmd(
    color1: Annotated[Path | None, typer.Option(help="Colour image of frame 1 (source).")] = None,
    depth1: Annotated[
        Path | None, typer.Option(help="Depth image of frame 1 (16-bit PNG, aligned).")
    ] = None,
    color2: Annotated[Path | None, typer.Option(help="Colour image of frame 2 (target).")] = None,
    depth2: Annotated[Path | None, typer.Option(help="Depth image of frame 2.")] = None,
    intrinsics: Annotated[
        Path | None, typer.Option(help="3x3 camera matrix file, or one line 'fx fy cx cy'.")
    ] = None,
    depth_scale: Annotated[
        float,
        typer.Option(help="Metres per depth-PNG unit.", callback=in_range(0.0, 1e3)),
    ] = 0.001,
    bag: Annotated[
        Path | None, typer.Option(help="ROS 1 .bag, rosbag2 folder, .mcap or .db3.")
    ] = None,
    t_from: Annotated[
        float | None, typer.Option("--from", help="Frame 1: time (s) after the first frame.")
    ] = None,
    t_to: Annotated[
        float | None, typer.Option("--to", help="Frame 2: time (s) after the first frame.")
    ] = None,
    color_topic: Annotated[str, typer.Option(help="Colour image topic.")] = (
        "/camera/color/image_raw"
    ),
    depth_topic: Annotated[str, typer.Option(help="Aligned depth image topic.")] = (
        "/camera/aligned_depth_to_color/image_raw"
    ),
    info_topic: Annotated[str, typer.Option(help="CameraInfo topic.")] = (
        "/camera/color/camera_info"
    ),
    refine: Annotated[
        bool, typer.Option(help="Refine an accepted pose on frame 2's depth image.")
    ] = True,
    out: Annotated[
        Path | None, typer.Option(help="Folder for summary.json and T.csv (4x4 T_2_1).")
    ] = None,
) -> None:
    """Register frame 1 onto frame 2 (T_2_1: p2 = T p1) with FPFH + FGR and colored ICP
    (and projective ICP with --refine); print the pose, the metrics and the verdict. Either
    --color1/--depth1/--color2/--depth2/--intrinsics, or --bag with --from/--to."""
    from mmpa.apps import register as rr

    pngs = {
        "--color1": color1,
        "--depth1": depth1,
        "--color2": color2,
        "--depth2": depth2,
        "--intrinsics": intrinsics,
    }
    try:
        dest = out_dir(out) if out is not None else None  # fail early on a bad folder
        if bag is not None:
            topics = (color_topic, depth_topic, info_topic)
            f1, f2 = _bag_frames(bag, t_from, t_to, topics, pngs)
        else:
            f1, f2 = _png_frames(pngs, depth_scale, t_from is not None or t_to is not None)
        with console.status("registering"):
            r = rr.register_frames(f1, f2, refine=refine)
        s = rr.write_outputs(dest, r) if dest is not None else rr.summary(r)
    except MMPAError as e:
        fail(e)
    _print(s, out)


def _bag_frames(
    bag: Path,
    t_from: float | None,
    t_to: float | None,
    topics: tuple[str, str, str],
    pngs: dict[str, Path | None],
) -> tuple:
    """The two RGB-D frames of ``bag`` nearest to ``t_from`` / ``t_to`` s after its first
    frame, on the ``(colour, depth, camera info)`` topics; the image options refused."""
    from mmpa.apps import register as rr
    from mmpa.apps.register import BagTopics
    from mmpa.core.errors import InvalidInputError

    given = [k for k, v in pngs.items() if v is not None]
    if given:
        raise InvalidInputError(f"--bag excludes the image options ({', '.join(given)})")
    if t_from is None or t_to is None:
        raise InvalidInputError("--bag needs --from and --to (s after the first frame)")
    tp = BagTopics(color=topics[0], depth=topics[1], camera_info=topics[2])
    with console.status(f"reading camera frames of {bag}"):
        return rr.frames_from_bag(bag, t_from, t_to, tp)


def _png_frames(pngs: dict[str, Path | None], depth_scale: float, times_given: bool) -> tuple:
    """The two RGB-D frames of the colour / depth PNGs with the intrinsics file; all five
    options needed (and no --from/--to: ``times_given``), one image size."""
    from mmpa.apps import register as rr
    from mmpa.core.errors import InvalidInputError

    missing = [k for k, v in pngs.items() if v is None]
    if missing:
        raise InvalidInputError(
            f"give --bag BAG --from T1 --to T2, or all of --color1 --depth1 --color2 "
            f"--depth2 --intrinsics (missing {', '.join(missing)})"
        )
    if times_given:
        raise InvalidInputError("--from/--to need --bag")
    color1, depth1, color2, depth2, intrinsics = pngs.values()
    assert color1 and depth1 and color2 and depth2 and intrinsics
    f1 = rr.load_png_frame(color1, depth1, intrinsics, depth_scale)
    f2 = rr.load_png_frame(color2, depth2, intrinsics, depth_scale, stamp=1.0)
    if f1.depth.shape != f2.depth.shape:
        raise InvalidInputError(
            f"frame 1 ({color1}) is {f1.depth.shape[1]}x{f1.depth.shape[0]}, frame 2 "
            f"({color2}) is {f2.depth.shape[1]}x{f2.depth.shape[0]}: one camera "
            f"(--intrinsics) needs one image size"
        )
    return f1, f2


def _print(s: dict, out: Path | None) -> None:
    import numpy as np
    from rich.table import Table

    T = np.asarray(s["T_2_1"])
    t = Table(title="mmpa register (T_2_1: p2 = T p1)", show_header=False)
    t.add_row("T", "\n".join(" ".join(f"{v:+.6f}" for v in row) for row in T))
    t.add_row("pose from", s["pose_from"])
    t.add_row(
        "translation / rotation", f"{s['translation_mm']:.1f} mm / {s['rotation_deg']:.2f} deg"
    )
    icp = s["icp"]
    t.add_row("fitness", f"{icp['fitness']:.3f}")
    t.add_row("rmse", f"{icp['rmse'] * 1e3:.2f} mm")
    t.add_row("ok", "[green]yes[/]" if s["ok"] else "[red]no[/]")
    t.add_row("reason", s["reason"] or "-")
    p = s["projective"]
    if p is None:
        t.add_row("projective", "not run")
    else:
        t.add_row(
            "projective",
            f"ok={p['ok']} rmse {p['rmse'] * 1e3:.2f} mm, inliers {p['inlier_fraction']:.2f}, "
            f"scale {p['scale']:.5f}" + (f" ({p['reason']})" if p["reason"] else ""),
        )
    if out is not None:
        t.add_row("written", f"{out / 'summary.json'}, {out / 'T.csv'}")
    console.print(t)


def register(app: typer.Typer) -> None:
    """Add ``register`` to the root app."""
    app.command("register")(register_cmd)

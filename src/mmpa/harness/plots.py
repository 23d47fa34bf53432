"""Pictures: camera images, depth colormaps and a top-down map of the world.

Functions take numpy arrays and the scene description and write PNG files; they know
nothing about the simulator. matplotlib runs with the non-interactive Agg backend.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import imsave
from matplotlib.patches import Circle, Polygon, Rectangle
from matplotlib.transforms import Affine2D

from mmpa.backends.twin.scene import SceneConfig
from mmpa.core.geometry import Array
from mmpa.robot.description import RobotDescription

__all__ = ["save_color", "save_depth", "save_topdown"]


def save_color(path: str | Path, color: np.ndarray) -> None:
    """Write an RGB uint8 image ``(H, W, 3)``."""
    imsave(path, color)


def save_depth(path: str | Path, depth: np.ndarray, max_depth: float | None = None) -> None:
    """Write a depth image (m, 0 = invalid) as a turbo colormap with a colorbar."""
    valid = depth > 0
    vmax = max_depth or (float(np.percentile(depth[valid], 99)) if valid.any() else 1.0)
    vmin = float(np.percentile(depth[valid], 1)) if valid.any() else 0.0
    fig = Figure(figsize=(7.2, 4.8), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    shown = np.ma.masked_where(~valid, depth)
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="black")
    im = ax.imshow(shown, cmap=cmap, vmin=vmin, vmax=vmax)
    ax.set_title(f"depth (m), {100 * (1 - valid.mean()):.1f} % invalid (black)")
    ax.axis("off")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="m")
    fig.tight_layout()
    fig.savefig(path)


def _rect(ax, center, size, yaw_deg, **kw) -> None:
    w, h = size
    r = Rectangle((-w / 2, -h / 2), w, h, **kw)
    r.set_transform(Affine2D().rotate_deg(yaw_deg).translate(*center) + ax.transData)
    ax.add_patch(r)


def _draw_room(ax, scene: SceneConfig) -> None:
    """Walls, desks, the speed bump's outline and the fiducials."""
    for w in scene.walls:
        a, b = np.array(w.start), np.array(w.end)
        c, d = (a + b) / 2, b - a
        _rect(
            ax,
            c,
            (np.linalg.norm(d) + w.thickness, w.thickness),
            np.rad2deg(np.arctan2(d[1], d[0])),
            color="0.25",
        )
    for bench in [*scene.workbenches, *([scene.grasp_desk] if scene.grasp_desk else [])]:
        _rect(ax, bench.center, bench.size[:2], bench.yaw_deg, color="#c8a878", alpha=0.8)
        ax.text(*bench.center, bench.name, fontsize=7, ha="center", va="center")
    if scene.speed_bump is not None:
        sb = scene.speed_bump
        _rect(
            ax,
            sb.center,
            (sb.length, sb.width),
            sb.yaw_deg,
            fill=False,
            ec="orange",
            ls="--",
            lw=1,
            label="speed bump (Site 2')",
        )
    if scene.fiducial_artifact is not None:
        fa = scene.fiducial_artifact
        c, s = np.cos(np.deg2rad(fa.yaw_deg)), np.sin(np.deg2rad(fa.yaw_deg))
        f = np.array(fa.fiducials)
        fx = fa.origin[0] + c * f[:, 0] - s * f[:, 1]
        fy = fa.origin[1] + s * f[:, 0] + c * f[:, 1]
        ax.plot(fx, fy, "m+", ms=6, label="fiducials (paper 002)")


def _draw_reflectors_and_sites(ax, scene: SceneConfig, map_reflectors: Array | None) -> None:
    """The true reflectors (numbered), the map's, and the sites' park poses."""
    refl = scene.reflector_positions()
    for i, (x, y) in enumerate(refl):
        ax.add_patch(Circle((x, y), scene.reflectors.radius * 2, color="crimson", zorder=4))
        ax.text(x + 0.08, y + 0.08, str(i), color="crimson", fontsize=8)
    ax.plot([], [], "o", color="crimson", label="reflectors (true)")
    if map_reflectors is not None:
        ax.plot(map_reflectors[:, 0], map_reflectors[:, 1], "kx", ms=5, label="reflectors (map)")
    for name, site in scene.sites.items():
        x, y, th = site.pose2d
        ax.annotate(
            "",
            xy=(x + 0.25 * np.cos(th), y + 0.25 * np.sin(th)),
            xytext=(x, y),
            arrowprops={"arrowstyle": "->", "color": "tab:green"},
        )
        ax.text(x - 0.15, y + 0.1, f"site {name}", color="tab:green", fontsize=8)


def _draw_path_and_scan(
    ax,
    path_xy: Array | None,
    scan_points_map: Array | None,
    scan_reflective: Array | None,
    goal_pose2d: Array | None,
) -> None:
    """The base's path, the lidar scan (reflective returns ringed) and the goal."""
    if path_xy is not None and len(path_xy):
        ax.plot(path_xy[:, 0], path_xy[:, 1], "-", color="tab:blue", lw=1, label="base path (true)")
    if scan_points_map is not None and len(scan_points_map):
        ax.plot(
            scan_points_map[:, 0],
            scan_points_map[:, 1],
            ".",
            ms=1.5,
            color="tab:red",
            label="lidar scan",
        )
        if scan_reflective is not None and scan_reflective.any():
            p = scan_points_map[scan_reflective]
            ax.plot(
                p[:, 0],
                p[:, 1],
                "o",
                ms=4,
                mfc="none",
                color="gold",
                label="high-intensity returns",
            )
    if goal_pose2d is not None:
        ax.plot(goal_pose2d[0], goal_pose2d[1], "g*", ms=12, label="goal")


def _draw_robot(ax, robot: RobotDescription, base_pose2d: Array) -> None:
    """The base's footprint at ``base_pose2d`` and its heading."""
    x, y, th = base_pose2d
    b = robot.base
    c, s = np.cos(th), np.sin(th)
    lx, ly = b.body_size[0] / 2, b.body_size[1] / 2
    corners = np.array([[lx, ly], [-lx, ly], [-lx, -ly], [lx, -ly]]) + np.array(
        [b.body_offset_x, 0]
    )
    R = np.array([[c, -s], [s, c]])
    ax.add_patch(
        Polygon(
            corners @ R.T + [x, y], closed=True, fc="tab:blue", alpha=0.35, ec="tab:blue", zorder=5
        )
    )
    ax.annotate(
        "",
        xy=(x + 0.4 * c, y + 0.4 * s),
        xytext=(x, y),
        arrowprops={"arrowstyle": "-|>", "color": "navy"},
        zorder=6,
    )


def save_topdown(
    path: str | Path,
    scene: SceneConfig,
    robot: RobotDescription,
    base_pose2d: Array,
    scan_points_map: Array | None = None,
    scan_reflective: Array | None = None,
    map_reflectors: Array | None = None,
    path_xy: Array | None = None,
    goal_pose2d: Array | None = None,
    title: str = "",
    bounds: tuple[float, float, float, float] | None = None,
) -> None:
    """Top-down map: walls, desks, reflectors (true and surveyed), sites, the robot footprint,
    its path and a lidar scan (points in ``map``; reflective returns highlighted).

    ``bounds`` = ``(x_min, x_max, y_min, y_max)``; default: the lobby and the corridor mouth.
    """
    fig = Figure(figsize=(10, 8), dpi=110)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_aspect("equal")
    _draw_room(ax, scene)
    _draw_reflectors_and_sites(ax, scene, map_reflectors)
    _draw_path_and_scan(ax, path_xy, scan_points_map, scan_reflective, goal_pose2d)
    _draw_robot(ax, robot, base_pose2d)
    x, y, th = base_pose2d
    x0, x1, y0, y1 = bounds or (-4.0, 4.6, -3.6, 3.0)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("map x (m)")
    ax.set_ylabel("map y (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=7, framealpha=0.85)
    ax.set_title(title or f"{scene.name}: robot at ({x:.3f}, {y:.3f}, {np.rad2deg(th):.1f} deg)")
    fig.tight_layout()
    fig.savefig(path)

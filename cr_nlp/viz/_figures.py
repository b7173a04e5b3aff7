"""Matplotlib 3-D figures: the robot as a tube, its tendons, obstacles, trajectories and
target frames. Figures are rendered with the Agg backend (no display needed); pass
your own 3-D ``ax`` to draw into an interactive figure instead. Lengths in metres.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from .._files import atomic_open
from ..model.robot import Robot
from ..world.scene import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    Scene,
    SpherePart,
    rotation_z_to,
)
from ._geometry import backbone_frames, box_faces, tendon_paths, tube_grid

__all__ = [
    "backbone_frames",
    "draw",
    "follow_figure",
    "plot_error_boxes",
    "plot_tendon_lengths",
    "save_figure",
    "trajectory_figure",
]

ROBOT_COLOR = "#d95f02"
OBSTACLE_COLOR = "#7f8fa6"
MESH_COLOR = "#c8a77e"


# ================================================================ obstacle geometry


def _sphere_surface(center: np.ndarray, radius: float, n: int = 18) -> tuple[np.ndarray, ...]:
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n), np.linspace(0, np.pi, n // 2 + 1))
    return (
        center[0] + radius * np.cos(u) * np.sin(v),
        center[1] + radius * np.sin(u) * np.sin(v),
        center[2] + radius * np.cos(v),
    )


def _cylinder_surface(
    a: np.ndarray, b: np.ndarray, radius: float, n: int = 18
) -> tuple[np.ndarray, ...]:
    rot = rotation_z_to(b - a)
    angle = np.linspace(0, 2 * np.pi, n)
    ring = radius * (np.cos(angle)[:, None] * rot[:, 0] + np.sin(angle)[:, None] * rot[:, 1])
    pts = np.stack([a + ring, b + ring], axis=1)  # (n, 2, 3)
    return pts[..., 0], pts[..., 1], pts[..., 2]


def _draw_part(ax: Axes, part: Any, color: str, alpha: float, points: list[np.ndarray]) -> None:
    if isinstance(part, SpherePart):
        x, y, z = _sphere_surface(part.center, part.radius)
        ax.plot_surface(x, y, z, color=color, alpha=alpha, linewidth=0, shade=True)
        points.append(np.c_[x.ravel(), y.ravel(), z.ravel()])
    elif isinstance(part, BoxPart):
        faces = box_faces(part)
        ax.add_collection3d(
            Poly3DCollection(
                list(faces),
                facecolors=color,
                alpha=alpha,
                edgecolors="k",
                linewidths=0.3,
                shade=True,
            )
        )
        points.append(faces.reshape(-1, 3))
    elif isinstance(part, CapsulePart | CylinderPart):
        x, y, z = _cylinder_surface(part.a, part.b, part.radius)
        ax.plot_surface(x, y, z, color=color, alpha=alpha, linewidth=0, shade=True)
        points.append(np.c_[x.ravel(), y.ravel(), z.ravel()])
        if isinstance(part, CapsulePart):
            for end in (part.a, part.b):
                xs, ys, zs = _sphere_surface(end, part.radius, 14)
                ax.plot_surface(xs, ys, zs, color=color, alpha=alpha, linewidth=0, shade=True)
    elif isinstance(part, ConvexPart):
        tris = part.vertices[part.triangles]
        ax.add_collection3d(
            Poly3DCollection(
                list(tris),
                facecolors=color,
                alpha=alpha,
                edgecolors=(0, 0, 0, 0.1),
                linewidths=0.1,
                shade=True,
            )
        )
        points.append(part.vertices)


def _draw_scene(ax: Axes, scene: Scene, show_parts: bool, points: list[np.ndarray]) -> None:
    palette = ["#1b9e77", "#7570b3", "#e7298a", "#66a61e", "#e6ab02", "#a6761d", "#666666"]
    for obstacle in scene.obstacles:
        if obstacle.mesh is not None and not show_parts:
            tris = np.asarray(obstacle.mesh.triangles)
            ax.add_collection3d(
                Poly3DCollection(
                    list(tris),
                    facecolors=MESH_COLOR,
                    alpha=0.3,
                    edgecolors=(0, 0, 0, 0.0),
                    linewidths=0.0,
                    shade=True,
                )
            )
            points.append(tris.reshape(-1, 3))
            continue
        for i, part in enumerate(obstacle.parts):
            color = palette[i % len(palette)] if show_parts else OBSTACLE_COLOR
            _draw_part(ax, part, color, 0.45 if show_parts else 0.6, points)


# ================================================================ public API


def draw(
    robot: Robot,
    q: Any = None,
    scene: Scene | None = None,
    trajectory: Sequence[Any] | None = None,
    targets: Sequence[Any] | None = None,
    ax: Axes | None = None,
    *,
    tendons: bool = False,
    show_parts: bool = False,
    title: str | None = None,
    elev: float = 20.0,
    azim: float = -135.0,
) -> Axes:
    """Draw the robot at q (3n; rad, rad, m) as a tube of radius ``backbone_radius``, with
    its tendons (``tendons``), the scene's obstacles (meshes as loaded, or their convex
    parts with ``show_parts``), a trajectory (a sequence of q: faded backbones and the tip
    path) and target frames (each a 4×4 pose, a (position (3,), rotation (3, 3)) pair or a
    position). Axes are scaled equally. Returns the 3-D axes (new, Agg-backed, if None)."""
    if ax is None:
        fig = Figure(figsize=(7.5, 7.5))
        FigureCanvasAgg(fig)
        ax = fig.add_subplot(projection="3d")
    points: list[np.ndarray] = [np.asarray(robot.base_position, dtype=float)[None]]
    samples = 24

    if scene is not None:
        _draw_scene(ax, scene, show_parts, points)

    if trajectory is not None and len(trajectory):
        colors = _colormap(len(trajectory))
        tips = []
        for k, qk in enumerate(trajectory):
            pos, _ = backbone_frames(robot, qk, samples=8)
            ax.plot(pos[:, 0], pos[:, 1], pos[:, 2], color=colors[k], alpha=0.55, linewidth=1.2)
            tips.append(pos[-1])
            points.append(pos)
        tips_arr = np.array(tips)
        ax.plot(
            tips_arr[:, 0],
            tips_arr[:, 1],
            tips_arr[:, 2],
            color="#ff7f00",
            linewidth=2.0,
            label="tip path",
        )
        if q is None:
            q = trajectory[-1]

    if q is not None:
        pos, rot = backbone_frames(robot, q, samples=samples)
        x, y, z = tube_grid(pos, rot, robot.backbone_radius)
        ax.plot_surface(
            x, y, z, color=ROBOT_COLOR, alpha=0.35 if tendons else 0.95, linewidth=0, shade=True
        )
        points.append(pos)
        ends = pos[::samples]
        ax.scatter(ends[:, 0], ends[:, 1], ends[:, 2], color="k", s=8, depthshade=False)
        if tendons:
            for path in tendon_paths(robot, pos, rot, samples):
                ax.plot(path[:, 0], path[:, 1], path[:, 2], color="#1f78b4", linewidth=0.8)

    for target in [] if targets is None else targets:  # a list, or an (N, 3) array
        position, rotation = _pose(target)
        points.append(position[None])
        if rotation is None:
            ax.scatter(*position, color="#e31a1c", s=20)
            continue
        for axis, color in zip(range(3), ("#e41a1c", "#4daf4a", "#377eb8"), strict=True):
            ax.quiver(*position, *(0.15 * rotation[:, axis]), color=color, linewidth=1.5)

    _equal_axes(ax, np.concatenate(points))
    ax.view_init(elev=elev, azim=azim)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    if title:
        ax.set_title(title)
    return ax


def save_figure(
    robot: Robot,
    q: Any = None,
    scene: Scene | None = None,
    trajectory: Sequence[Any] | None = None,
    targets: Sequence[Any] | None = None,
    *,
    path: str | Path,
    dpi: int = 150,
    **options: Any,
) -> Path:
    """Draw as ``draw`` does and save a PNG (or any format matplotlib knows by the
    suffix) to ``path``; returns the path. ``options`` go to ``draw``."""
    ax = draw(robot, q, scene, trajectory, targets, **options)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_figure(ax.figure, path, dpi=dpi, bbox_inches="tight")


def write_figure(figure: Figure, path: str | Path, **options: Any) -> Path:
    """``figure.savefig(path, **options)``, written atomically (a reader sees the old file
    or the whole new one): the format by the suffix as ``savefig`` picks it (no suffix:
    matplotlib's default format, its suffix added to the name). Returns the written path."""
    import matplotlib

    path = Path(path)
    _, suffix = os.path.splitext(path.name)
    file_format = suffix[1:].lower()
    if not file_format:
        file_format = matplotlib.rcParams["savefig.format"]
        path = path.with_name(path.name.rstrip(".") + "." + file_format)
    with atomic_open(path, "wb") as handle:
        figure.savefig(handle, format=file_format, **options)
    return path


def _colormap(count: int) -> np.ndarray:
    from matplotlib import colormaps

    return colormaps["viridis"](np.linspace(0.0, 0.9, count))


def _pose(target: Any) -> tuple[np.ndarray, np.ndarray | None]:
    if isinstance(target, tuple | list) and len(target) == 2:
        return np.asarray(target[0], dtype=float), np.asarray(target[1], dtype=float)
    t = np.asarray(target, dtype=float)
    if t.shape == (4, 4):
        return t[:3, 3], t[:3, :3]
    return t.reshape(3), None


def _equal_axes(ax: Axes, points: np.ndarray) -> None:
    """Limits around the drawn points with one scale on every axis."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.05 * float(np.max(hi - lo)) + 1e-3
    lo, hi = lo - pad, hi + pad
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo))


# ================================================================ time series and errors


def _axes_2d(ax: Axes | None, figsize: tuple[float, float] = (7.0, 3.2)) -> Axes:
    if ax is not None:
        return ax
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig.add_subplot()


def plot_tendon_lengths(
    times: Any,
    lengths: Any,
    names: Sequence[str] | None = None,
    ax: Axes | None = None,
    columns: Sequence[int] | None = None,
    title: str | None = None,
) -> Axes:
    """Tendon lengths over time: ``times`` (T,) seconds, ``lengths`` (T, n_tendons) metres,
    one line per tendon in ``columns`` (default all), labelled by ``names``. A trajectory
    result's series is what a controller consumes (``TrajectoryResult.save_csv``)."""
    ax = _axes_2d(ax)
    times = np.asarray(times, dtype=float)
    lengths = np.asarray(lengths, dtype=float).reshape(len(times), -1)
    columns = range(lengths.shape[1]) if columns is None else columns
    for j in columns:
        label = names[j] if names is not None else f"tendon {j + 1}"
        ax.plot(times, lengths[:, j], marker=".", markersize=3, linewidth=1.2, label=label)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tendon length (m)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", ncol=min(3, len(list(columns))))
    if title:
        ax.set_title(title)
    return ax


def plot_error_boxes(
    errors: dict[str, Any],
    ax: Axes | None = None,
    ylabel: str = "",
    title: str | None = None,
    log: bool = False,
) -> Axes:
    """One box plot per entry of ``errors`` (label → values), e.g. per-waypoint position
    errors in mm for the penalty and the exact answer; whiskers at the 5th and 95th
    percentiles, every value beyond them drawn."""
    ax = _axes_2d(ax, (4.5, 3.2))
    labels = list(errors)
    data = [np.asarray(errors[k], dtype=float).reshape(-1) for k in labels]
    ax.boxplot(data, whis=(5, 95), showmeans=True)
    ax.set_xticks(range(1, len(labels) + 1), labels)
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.grid(alpha=0.3, axis="y")
    if title:
        ax.set_title(title)
    return ax


# ================================================================ task figures


def trajectory_figure(
    result: Any,
    scene: Scene | None = None,
    names: Sequence[str] | None = None,
    title: str | None = None,
) -> Figure:
    """A planned trajectory (a ``TrajectoryResult``: ``robot``, ``q`` (H+1, 3n), ``times``
    s, ``tendon_lengths`` m): left the robot's motion and tip path in the scene, right the
    first segment's tendon lengths over time."""
    fig = Figure(figsize=(13, 5.5))
    FigureCanvasAgg(fig)
    draw(
        result.robot,
        None,
        scene,
        trajectory=list(result.q),
        ax=fig.add_subplot(1, 2, 1, projection="3d"),
        title=title,
    )
    plot_tendon_lengths(
        result.times,
        result.tendon_lengths,
        names,
        ax=fig.add_subplot(1, 2, 2),
        columns=range(result.robot.tendons.per_segment),
        title="tendon lengths, segment 1",
    )
    fig.tight_layout()
    return fig


def follow_figure(
    result: Any,
    scene: Scene | None = None,
    names: Sequence[str] | None = None,
    snapshots: int = 8,
    title: str | None = None,
) -> Figure:
    """A followed path (a ``FollowResult``: ``robot``, ``path`` with ``positions`` m and
    ``dt`` s, ``q`` (T, 3n), ``position_error`` m, ``rotation_error`` rad,
    ``tendon_lengths`` m): the reference waypoints with the robot at ``snapshots`` evenly
    spaced waypoints (seen from behind the drawing plane, so that letters read left to
    right), box plots of the per-waypoint errors, and the first segment's tendon lengths
    over time."""
    fig = Figure(figsize=(15, 5.5))
    FigureCanvasAgg(fig)
    spec = fig.add_gridspec(2, 3, width_ratios=(1.4, 0.6, 1.0))
    every = max(1, len(result.q) // snapshots)
    draw(
        result.robot,
        result.q[-1],
        scene,
        trajectory=list(result.q[::every]),
        targets=list(result.path.positions),
        ax=fig.add_subplot(spec[:, 0], projection="3d"),
        azim=20.0,
        elev=15.0,
        title=title,
    )
    plot_error_boxes(
        {"position": 1e3 * np.asarray(result.position_error)},
        ax=fig.add_subplot(spec[0, 1]),
        ylabel="mm",
        title="tracking error per waypoint",
    )
    plot_error_boxes(
        {"rotation": np.degrees(result.rotation_error)},
        ax=fig.add_subplot(spec[1, 1]),
        ylabel="degrees",
    )
    times = np.arange(len(result.q)) * result.path.dt
    plot_tendon_lengths(
        times,
        result.tendon_lengths,
        names,
        ax=fig.add_subplot(spec[:, 2]),
        columns=range(result.robot.tendons.per_segment),
        title="tendon lengths, segment 1",
    )
    fig.tight_layout()
    return fig

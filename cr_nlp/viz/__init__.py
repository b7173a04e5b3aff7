"""Pictures of robots, scenes and results.

- Static figures (matplotlib, Agg backend): ``draw``, ``save_figure``,
  ``trajectory_figure``, ``follow_figure``, ``plot_tendon_lengths``, ``plot_error_boxes``.

Lengths in metres, angles in radians, times in seconds.
"""

from __future__ import annotations

from ._figures import (
    MESH_COLOR,
    OBSTACLE_COLOR,
    ROBOT_COLOR,
    draw,
    follow_figure,
    plot_error_boxes,
    plot_tendon_lengths,
    save_figure,
    trajectory_figure,
)
from ._geometry import backbone_frames

__all__ = [
    "MESH_COLOR",
    "OBSTACLE_COLOR",
    "ROBOT_COLOR",
    "backbone_frames",
    "draw",
    "follow_figure",
    "plot_error_boxes",
    "plot_tendon_lengths",
    "save_figure",
    "trajectory_figure",
]

"""Pictures of robots, scenes and results.

- Static figures (matplotlib, Agg backend): ``draw``, ``save_figure``,
  ``trajectory_figure``, ``follow_figure``, ``plot_tendon_lengths``, ``plot_error_boxes``.
- The interactive 3-D viewer in the browser (viser, the optional extra
  ``pip install 'cr_nlp[viewer]'``): ``view``. Its module is imported only when ``view``
  is called, so the figures never need viser.

Lengths in metres, angles in radians, times in seconds.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

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
    "view",
]

if TYPE_CHECKING:
    from .viewer import Viewer


def view(
    robot: Any, scene: Any = None, result: Any = None, port: int | None = None, **options: Any
) -> Viewer:
    """Serve the interactive viewer on localhost and return it (a ``viewer.Viewer``: its
    ``url`` is the page's address, ``wait()`` blocks until Ctrl-C, ``stop()`` ends the
    server).

    Args:
        robot: a Robot, a robot file or a bundled name ("tdcr3").
        scene: a Scene, a scene file or a bundled name ("shelf"), or None.
        result: a RESULT.json path of ``cr-nlp ik``, ``plan`` or ``follow`` (or its
            loaded content), or None.
        port: TCP port; None picks a free one.
        options: ``host``, ``targets`` (an ik result's target poses), ``live_ik``, ``q``,
            ``model="cosserat"`` with ``loads={"gravity": [0, 0, -9.81], …}`` (live IK of
            tendon tensions on the Cosserat rod; see ``viewer.Viewer``).

    Raises:
        ImportError: viser is not installed (``pip install 'cr_nlp[viewer]'``).
    """
    from .viewer import Viewer

    return Viewer(robot, scene, result, port=port, **options)

"""Live IK on the Cosserat rod in the viewer: the dragged target solved for tendon tensions
under the loads the viewer was started with (``tasks.mechanics.live_ik``), and the tube of
the rod's equilibrium drawn from the verdict's fresh statics, not from PCC arcs. Without
viser (the viewer imports it). Units: metres, newtons, seconds.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from ..model import Robot
from ..model.rotations import wxyz_from_matrix
from ..world import Scene
from ._replay import SAMPLES, RobotMesh


def resample_frames(positions: np.ndarray, rotations: np.ndarray, n_segments: int,
                    samples: int = SAMPLES) -> tuple[np.ndarray, np.ndarray]:
    """The rod's frames at the drawn tube's rings: positions (1 + n·samples, 3) m and
    rotations (…, 3, 3), linearly interpolated along a rod grid of ``positions`` (P, 3)
    and ``rotations`` (P, 3, 3) with the same number of steps per segment (the statics'
    grid), the rotations made orthonormal again."""
    steps = (len(positions) - 1) // n_segments
    where = np.arange(1 + n_segments * samples) * (steps / samples)
    lower = np.minimum(np.floor(where).astype(int), len(positions) - 2)
    w = (where - lower)[:, None]
    pos = (1.0 - w) * positions[lower] + w * positions[lower + 1]
    mixed = (1.0 - w[..., None]) * rotations[lower] + w[..., None] * rotations[lower + 1]
    u, _, vt = np.linalg.svd(mixed)
    return pos, u @ vt


class TensionLive:
    """The viewer's live IK on the rod: the tensions on screen (N), their equilibrium
    under ``loads`` (``gravity``, ``tip_force``, … as for ``TensionIKSolver.solve``, world
    frame) and the solver, built on first use (it compiles: seconds, cached on disk).
    Targets are tip positions; the gizmo's orientation is not a target (a rod of few
    segments under load rarely reaches an orientation as well)."""

    def __init__(self, robot: Robot, scene: Scene | None, mesh: RobotMesh,
                 loads: dict[str, Any]) -> None:
        self.robot, self.scene, self.mesh, self.loads = robot, scene, mesh, dict(loads)
        self.tensions = np.zeros(robot.n_tendons)
        """The tensions on screen, N (the robot file's tendon order)."""
        self.frames: tuple[np.ndarray, np.ndarray] | None = None
        """The rod's backbone points (P, 3) m and frames (P, 3, 3) at ``tensions``."""
        self._solver: Any = None
        self._lock = threading.Lock()

    @classmethod
    def of(cls, model: str, loads: dict[str, Any] | None, result: Any, robot: Robot,
           scene: Scene | None, mesh: RobotMesh) -> TensionLive | None:
        """The viewer's live IK on the rod for ``model="cosserat"`` (a robot with a
        ``mechanics`` block, no result; ``loads`` as keyword arguments of
        ``TensionIKSolver.solve``: ``gravity`` m/s², ``tip_force`` N, …, world frame),
        None for "pcc" (live IK of configurations).

        Raises:
            ValueError: another model, a robot without mechanics, or a result given.
        """
        if model not in ("pcc", "cosserat"):
            raise ValueError(f"model: expected 'pcc' or 'cosserat', got {model!r}")
        if model == "pcc":
            return None
        if robot.mechanics is None:
            raise ValueError(f"model 'cosserat': {robot.name} has no 'mechanics' block")
        if result is not None:
            raise ValueError("model 'cosserat': the viewer shows the rod's live IK, no result")
        return cls(robot, scene, mesh, loads or {})

    def solver(self) -> Any:
        """The ``TensionLiveIKSolver`` under the viewer's loads."""
        with self._lock:
            if self._solver is None:
                from ..tasks.mechanics.ik import TensionIKConfig
                from ..tasks.mechanics.live_ik import TensionLiveIKSolver

                # A pool of 4096 seed tension sets: the fallback search of a dragged
                # target, built in seconds under new loads (cached on disk).
                self._solver = TensionLiveIKSolver(self.robot, self.scene,
                                                   TensionIKConfig(pool_size=4096),
                                                   **self.loads)
            return self._solver

    def warm(self) -> float:
        """Solve the shape of the tensions on screen under the loads (the rest shape at
        first) and compile the updates of a drag (one solve to that tip, nothing changed,
        then one from its answer: the program of an update whose last equilibrium is
        known); returns those solves' seconds."""
        if self.frames is None:
            rest = self.solver().equilibrium(self.tensions)
            self.frames = (rest.positions[0], rest.rotations[0])
        tip = self.frames[0][-1]
        answer = self.solver().solve(self.tensions, tip, search=False)
        again = self.solver().solve(answer.tensions, tip, search=False)
        return float(answer.seconds + again.seconds)

    def tip(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The tip position (3,) m and orientation (4,) wxyz on screen; None before the
        rest shape is known (the viewer shows the straight robot until then)."""
        if self.frames is None:
            return None
        return self.frames[0][-1], wxyz_from_matrix(self.frames[1][-1][None])[0]

    def geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """Tube vertices (V, 3) and tendon segments (S, 2, 3), m, of the shape on screen."""
        assert self.frames is not None
        return self.mesh.tube(*resample_frames(*self.frames, self.robot.n_segments))

    def solve(self, position: np.ndarray, search: bool) -> Any:
        """Re-solve for the tip ``position`` (3,) m from the tensions on screen; the new
        answer (``TensionLiveIKResult``) becomes the shape on screen."""
        answer = self.solver().solve(self.tensions, position, search=search)
        self.tensions = np.array(answer.tensions)
        self.frames = (answer.backbone, answer.backbone_rotations)
        return answer

    def text(self, answer: Any) -> str:
        """The page's lines on an answer: verdict, time, tip error, clearance, tensions."""
        verdict = "**reached**" if answer.success else f"**not reached**: {answer.reason}"
        lines = [verdict, f"solve {1e3 * answer.seconds:.1f} ms ({answer.stage}, Cosserat rod)",
                 f"tip error {answer.position_error:.2e} m"]
        if np.isfinite(answer.min_clearance):
            lines.append(f"clearance {answer.min_clearance:.4f} m (python-fcl)")
        lines.append("tensions " + ", ".join(f"{t:.2f}" for t in answer.tensions) + " N")
        return "  \n".join(lines)

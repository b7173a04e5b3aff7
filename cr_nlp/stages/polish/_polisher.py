"""What both Ipopt polishers share (``IKPolisher`` for IK answers, ``TrajectoryPolisher``
for trajectories and paths): the robot and scene, the clearance δ, the simple bounds of
the bending vector z, the clearance-row slots with their CasADi functions, the float64
pair distances of the independent re-evaluation, and the two violation families every
task has (limits and clearance).

Each polisher keeps only its own problem: which rows it adds, how it places them over its
configurations and which attempt wins.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...model import CasadiModel, Robot, load_robot, z_to_q_numpy
from ...model.limits import limit_violation_q
from ...world.clearance import PairDistances, body_gap_tolerance, self_pairs
from ...world.scene import Scene, load_scene
from ._clearance_rows import SlotRows, make_slot_groups
from ._ipopt import Deadline, NLPSettings


class ClearancePolisher:
    """The base of the Ipopt polishers of one robot in one scene.

    Args:
        robot: a ``Robot`` or a robot file / bundled name.
        scene: a ``Scene``, a scene file or bundled name, or None (no obstacles; self pairs,
            segments at least two apart, are still constrained).
        safety_margin: δ (m), the clearance every pair must keep on the sphere body;
            default ``body_gap_tolerance(robot) + 0.002``, so that clearance ≥ δ proves the
            capsule body collision-free for ``world.check`` (python-fcl sees ≥ 2 mm).
        config: the polisher's settings (an ``NLPSettings``).
    """

    def __init__(self, robot: Robot | str | Path, scene: Scene | str | Path | dict | None,
                 safety_margin: float | None, config: NLPSettings) -> None:
        self.robot = robot = load_robot(robot)
        self.scene = load_scene(scene) if scene is not None else None
        self.config = config
        self.safety_margin = float(body_gap_tolerance(robot) + 0.002 if safety_margin is None
                                   else safety_margin)
        self.builds = 0
        """How many ``nlpsol`` solvers this polisher constructed."""
        self._deadline = Deadline()
        self._theta_max = np.array([s.theta_max for s in robot.segments])
        self._lbx = np.ravel([[-s.theta_max, -s.theta_max, s.length_min] for s in robot.segments])
        self._ubx = np.ravel([[s.theta_max, s.theta_max, s.length_max] for s in robot.segments])
        self._n_bodies = robot.n_points + 1
        self._self_pairs = (self_pairs(robot) if robot.has_self_pairs
                            else np.zeros((0, 2), dtype=np.int64))
        self._groups, _ = make_slot_groups(robot, self.scene, config.max_pairs, include_self=True)
        self._pairs = PairDistances(robot, self.scene)
        self._model = CasadiModel(robot)
        self._rows = SlotRows(self._model, self._groups, config.face_smoothing)
        self._interpreted = False
        """Some solver was built on CasADi's virtual machine while the compiled functions
        were being built (``stages.polish._compiled_functions``): rebuilt on them before the
        first solve after that."""

    @property
    def _margin(self) -> float:
        """Metres: below this a pair distance is exact (the slots' ``near_margin``, or δ
        where larger); above it ``PairDistances.near`` gives lower bounds."""
        return max(self.config.near_margin, self.safety_margin)

    def _shared_violations(self, z: np.ndarray, distances: np.ndarray) -> dict[str, float]:
        """The families every task has, float64: ``limits`` (rad, m) of the (…, 3n)
        configurations z and ``clearance`` (m), δ minus the smallest pair distance."""
        shortfall = (max(0.0, self.safety_margin - float(np.min(distances)))
                     if distances.size else 0.0)
        return {"limits": float(np.max(limit_violation_q(self.robot, z_to_q_numpy(z)))),
                "clearance": shortfall}

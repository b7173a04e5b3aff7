"""Live tension-space IK: one target at a time on the Cosserat rod, warm-started from the
current tensions (the viewer's dragged target under gravity), as ``tasks.geometry.live_ik`` does
for the PCC model.

Each update runs the refine stage of ``tasks.mechanics.ik`` (its LM rows: tip,
equilibrium, backbone clearance; a difference Jacobian, then Broyden's updates) on one
target from the current tensions and the current moment at the base (so the first LM
step starts at an equilibrium), a program compiled once for a batch of one, stopped at
``LIVE_PRECISION`` of the tolerance (each trip of the LM is a visible share of an
update). Where the warm start misses (a jump across the workspace, a drag pressed
against a bound or an obstacle), the solver answers from its seed pool as the batch
does: the nearest clear set with its equilibrium, then the next ones (``search``). Every
answer is judged by the tension IK's one verdict: a fresh forward
statics solve of its tensions, the tension bounds, and python-fcl on the solved backbone.
The fresh solve of a warm-started answer starts from the equilibrium the verdict found
for the previous answer (``solve_statics(start_moment=…)``: Newton under the full loads, the
equilibrium a robot dragged from there stays on; where that fails or is unstable, the
loading path from rest as everywhere else), whose first Jacobian is that equilibrium's
own ∂M(L)/∂M(0) (``start_jacobian``): 3 shooting iterations instead of 10 from rest, with
the shape and the stability test in the same program. Where that equilibrium is known and
the rod is loaded (M(0) unknown), the update is one compiled program: the LM, then the
settle of the LM's tensions (``model.cosserat.settle_function``), with no host work between
them. Its Newton starts from the LM's own M(0) where the LM moved M(0) only a drag's step
from the last equilibrium (``newton_start``: its steps kept the rod at an equilibrium
all the way; 2–3 iterations instead of 4–5), else from the last equilibrium; the verdict
is still Newton's own equilibrium of the answer's tensions on the statics' grid, its
stability test and python-fcl on its shape (docs/benchmarks.md).
Units: metres, radians, newtons, N·m, seconds.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._cached_jit import CachedProgram
from ..._compile_effort import compiles_fully
from ...model import Robot
from ...model.cosserat import (
    StaticsResult,
    moment_scale,
    settle_arguments,
    settle_function,
    settled_statics,
)
from ...model.loads import static_loads
from ...stages.refine import (
    base_frame,
    box_bounds,
    lm_solve,
    tensions_of_batch,
    unknowns_of,
)
from ...world.scene import Scene
from .._result import Stage
from .._timing import StageTiming
from .ik import TensionIKConfig, TensionIKSolver

LIVE_NEWTON_START = 0.1
"""The verdict's Newton starts from the LM's own M(0) where the LM moved M(0) less than
this many radians of bending over the robot (|ΔM(0)|·L/(E·I)) from the last equilibrium,
else from that equilibrium. On the benchmark's drags in clutter the LM moves it 0.016 rad
(median; 0.045 at most) and Newton takes 2–3 iterations instead of 4–5 (1.27 against
2.13 ms of the settle); on 300 jumps across the workspace (moves 0.17 rad median, 0.68 at
most) both starts settled on the same equilibrium (tips within 1e-9 m) or both missed."""

LIVE_PRECISION = 0.3
"""The live LM stops once its residual is below this fraction of the tolerance
(``TensionIKConfig.lm_precision``, unless a config sets it). On drags in clutter the
verified answers end 4–15 µm from their targets (tolerance 0.1 mm) and the LM takes 3–4
trips instead of 5 (1e-3, a batch's): 0.3–0.6 ms less per update (docs/benchmarks.md)."""


@dataclass(frozen=True)
class TensionLiveIKResult:
    """One live answer, judged by the verdict (float64). Units: N, m, N·m, s."""

    tensions: np.ndarray
    """(n,) tensions, N."""
    position: np.ndarray
    """(3,) tip of the fresh statics solve, m."""
    position_error: float
    """Distance of that tip from the target, m."""
    min_clearance: float
    """python-fcl obstacle distance of the solved backbone, m (inf without a scene)."""
    success: bool
    """The verdict accepts the answer."""
    reason: str
    """"" on success, else why not."""
    stage: Stage
    """``Stage.REFINE`` (warm-started LM) or ``Stage.SEARCH`` (the pool's seeds)."""
    base_moment: np.ndarray
    """(3,) moment at the base of the solved rod, N·m, world frame: the next warm start."""
    seconds: float
    """Wall time of the update, verdict included."""
    timing: StageTiming
    """Where ``seconds`` went: ``refine`` the warm-started LM (with the verdict's fresh
    statics where both ran in one program: the last equilibrium known, the rod loaded),
    ``explore`` the pool's seeds and their LM (where the warm start missed), ``verify``
    the rest of the verdicts (python-fcl, bounds, pose; the statics where it ran apart);
    the rest is the update's own bookkeeping."""
    backbone: np.ndarray
    """(P, 3) the solved rod's backbone points from the base to the tip, m (the verdict's
    fresh statics)."""
    backbone_rotations: np.ndarray
    """(P, 3, 3) its frames at the same points (columns: the disk's x, y, z axes)."""


class TensionLiveIKSolver:
    """Single-target tension IK warm-started from the current tensions; reuse it.

    The loads are fixed per solver (``tip_force``, ``gravity``, … as for
    ``TensionIKSolver.solve``, world frame). ``solve(tensions, position)`` returns a
    ``TensionLiveIKResult``; the first call compiles (seconds, cached on disk).
    """

    def __init__(self, robot: Robot | str | dict, scene: Scene | str | None = None,
                 config: TensionIKConfig | None = None, **loads: Any) -> None:
        # One target: the LM in one round (rounds only shrink a batch's stragglers).
        config = config or TensionIKConfig()
        self.ik = TensionIKSolver(robot, scene, replace(
            config, round_iterations=0,
            lm_precision=(LIVE_PRECISION if config.lm_precision is None
                          else config.lm_precision)))
        self.robot = self.ik.robot
        self.loads = static_loads(1, self.ik.length, **loads)
        self._shoot = bool(np.any(self.loads.has_force()))   # M(0) unknown: the rod is shot
        self._warm: tuple | None = None
        self._program: CachedProgram | None = None

    @compiles_fully
    def solve(self, tensions: Any, position: Any, wxyz: Any = None, *,
              search: bool = True) -> TensionLiveIKResult:
        """Move the robot's tip from the equilibrium of ``tensions`` (n,) N to ``position``
        (3,) m, world frame (``wxyz``: (4,) orientation, or None: free).

        Args:
            tensions: the current tensions, e.g. the previous answer's.
            position: the target tip position, m.
            wxyz: the target orientation (unit quaternion w, x, y, z) or None.
            search: where the warm start misses, answer from the pool's seeds as the
                batch does: the nearest clear set, then up to ``retry_seeds`` more, until
                one verifies (milliseconds each).

        Raises:
            ValueError: tensions of the wrong size, a non-finite target.
        """
        start = time.perf_counter()
        current = np.asarray(tensions, dtype=float).reshape(1, -1)
        if current.shape[1] != self.robot.n_tendons or not np.all(np.isfinite(current)):
            raise ValueError(f"tensions: expected {self.robot.n_tendons} finite numbers, N")
        target = np.asarray(position, dtype=float).reshape(1, 3)
        if not np.all(np.isfinite(target)):
            raise ValueError("position: expected 3 finite numbers, m")
        quats = (np.full((1, 4), np.nan) if wxyz is None
                 else np.asarray(wxyz, dtype=float).reshape(1, 4))
        moment, verified, jacobian = self._warm_start(current)
        timing, t0 = StageTiming(), time.perf_counter()
        if verified is not None and self._shoot:
            answer, shape = self._update(current, target, quats, moment, verified, jacobian)
            timing.refine = time.perf_counter() - t0
            t0 = time.perf_counter()
            if shape is None:   # Newton near the last equilibrium missed: from rest
                shape = self.ik._forward(answer, self.loads)
        else:
            answer = self.ik._lm(current, target, quats, self.loads, moment, smallest=1)
            timing.refine = time.perf_counter() - t0
            t0 = time.perf_counter()
            shape = self.ik._forward(answer, self.loads, verified, jacobian)
        judged = self.ik._judge(shape, answer, target, quats, self.loads, StageTiming())
        timing.verify = time.perf_counter() - t0
        stage = Stage.REFINE
        for rank in range(self.ik.config.retry_seeds + 1 if search else 0):
            if judged.success[0]:
                break
            # The pool's rank-th nearest clear set and its equilibrium, as the batch's
            # first try and retries do.
            t0 = time.perf_counter()
            seeds, moments = self.ik._start(target, self.loads, rank)
            again = self.ik._lm(seeds, target, quats, self.loads, moments, smallest=1)
            timing.explore += time.perf_counter() - t0
            t0 = time.perf_counter()
            other_shape = self.ik._forward(again, self.loads)
            other = self.ik._judge(other_shape, again, target, quats, self.loads,
                                   StageTiming())
            timing.verify += time.perf_counter() - t0
            if other.success[0] or other.pose_error[0] < judged.pose_error[0]:
                answer, judged, shape, stage = again, other, other_shape, Stage.SEARCH
        self._warm = (answer.tobytes(), base_frame(self.robot, judged.base_moment),
                      judged.base_moment[0], shape.tip_moment_jacobian)
        return TensionLiveIKResult(
            tensions=answer[0], position=judged.position[0],
            position_error=float(judged.position_error[0]),
            min_clearance=float(judged.min_clearance[0]), success=bool(judged.success[0]),
            reason=judged.reason[0], stage=stage, base_moment=judged.base_moment[0],
            seconds=time.perf_counter() - start, timing=timing, backbone=shape.positions[0],
            backbone_rotations=shape.rotations[0])

    @compiles_fully
    def equilibrium(self, tensions: Any) -> StaticsResult:
        """The shape the rod takes under ``tensions`` (n,) N and the solver's loads: a
        one-case forward statics solve (the verdict's), e.g. the rest shape to show
        before the first target."""
        current = np.asarray(tensions, dtype=float).reshape(1, -1)
        if current.shape[1] != self.robot.n_tendons or not np.all(np.isfinite(current)):
            raise ValueError(f"tensions: expected {self.robot.n_tendons} finite numbers, N")
        return self.ik._forward(current, self.loads)

    def _update(self, current: np.ndarray, target: np.ndarray, quats: np.ndarray,
                moment: np.ndarray, verified: np.ndarray, jacobian: np.ndarray | None
                ) -> tuple[np.ndarray, StaticsResult | None]:
        """A warm-started update in one compiled program: the LM from ``current`` (1, n) N
        and M(0) ``moment`` (1, 3) N·m, base frame, then the verdict's statics of its
        tensions near the last equilibrium (``verified`` (3,) N·m and ``jacobian`` (3, 3),
        world frame; Newton's start: ``newton_start``), with no host work between the two
        (0.3–0.6 ms of an update). Returns the tensions (1, n) N and their
        ``StaticsResult``, or None where Newton did not settle (``settled_statics``)."""
        ik, statics = self.ik, self.ik.config.statics
        if self._program is None:
            self._program = _update_program(ik)
        terms = ik.terms(True)
        _, params, _ = ik.waypoint_params(target, quats, self.loads)
        dtype = statics.numpy_dtype
        with jax.enable_x64(dtype == np.float64):
            tensions, settled = self._program(
                *ik.lm_arguments(unknowns_of(terms, current, moment), params,
                                 ik.config.iterations), box_bounds(terms, dtype),
                *settle_arguments(self.robot, statics, self.loads, verified, jacobian))
            return (np.asarray(tensions, dtype=float),
                    settled_statics(self.robot, statics, settled))

    def _warm_start(self, current: np.ndarray) -> tuple[Any, Any, Any]:
        """Where ``current`` is the last answer (its equilibrium is known): its M(0),
        (1, 3) N·m in the base frame for the LM and (3,) in the world frame for the
        verdict's statics, with the statics' ∂M(L)/∂M(0) there (None where that answer
        came from the loading path); else (None, None, None): the LM starts from the tip
        moments, the statics from rest."""
        if self._warm is not None and self._warm[0] == current.tobytes():
            return self._warm[1:]
        return None, None, None


def newton_start(z: Any, last_moment: Any, scale: float) -> Any:
    """Where the verdict's Newton starts (1, 3) N·m, base frame: the LM's own M(0) (the
    last three unknowns of ``z`` (1, width), in units of ``scale`` = E·I/L, N·m) where the
    LM moved it less than ``LIVE_NEWTON_START`` rad of bending from ``last_moment`` (1, 3)
    N·m, the last equilibrium's, else that last equilibrium."""
    lm_moment = z[:, -3:] * scale
    moved = jnp.linalg.norm(lm_moment - last_moment, axis=1, keepdims=True) / scale
    return jnp.where(moved <= LIVE_NEWTON_START, lm_moment, last_moment)


def _update_program(ik: TensionIKSolver) -> CachedProgram:
    """``TensionLiveIKSolver._update``'s program for ``ik``'s rows (M(0) an unknown): its
    LM (``stages.refine.lm_solve``), the tensions of the answer, and
    ``model.cosserat.settle_function`` on them from ``newton_start``."""
    residual, project, terms = ik._residuals[True], ik._project, ik.terms(True)
    lm, settle = ik.waypoint_lm_config(), settle_function(ik.robot, ik.config.statics)
    scale = moment_scale(ik.robot)

    def update(z0: Any, params: Any, scene: Any, free: Any, budget: Any, bounds: Any,
               loads: Any, last_moment: Any, start_jacobian: Any) -> tuple:
        z = lm_solve(residual, project, z0, params, scene, free, budget, lm, bounds=bounds).z
        tensions = tensions_of_batch(terms, z)
        start = newton_start(z, last_moment, scale)
        return tensions, settle(tensions, loads, start.astype(last_moment.dtype),
                                start_jacobian)

    return CachedProgram(update, name="the live tension update")


from ..._moved import moved_names  # noqa: E402 — the old names, for one release

__getattr__ = moved_names(__name__, {"TensionLiveIK": ":TensionLiveIKSolver",
                                     "TensionLiveResult": ":TensionLiveIKResult"})

"""Live IK: one target at a time, warm-started from the answer before it (the viewer's
dragged target).

Problem: the IK problem of ``tasks.geometry.ik`` (``ik_residual``: pose error and the clearance
penalty, limits by projection), for a single target. Stages: refine (LM from the current
answer, one compiled program for every update), an optional polish (Ipopt with the
constraints as constraints, warm-started from the LM answer), and, when the warm start
ends far from the target (a jump across the workspace), a fallback to the batched search
of ``IKSolver``. Every answer is judged by ``IKSolver.verify`` (float64 pose error,
limits, python-fcl clearance) and the one verdict of ``world.verdict``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..._compile_effort import compiles_fully
from ...model import Robot, load_robot, q_to_z_numpy, z_to_q_numpy
from ...model.limits import clip_to_limits, project_z
from ...model.rotations import matrix_from_wxyz
from ...runtime import configure
from ...stages.polish import Polished, accept_first
from ...stages.refine import LMConfig, lm_solve
from ...world import Scene, load_scene, scene_arrays
from .._result import Stage
from .ik import IKConfig, IKSolver, IKVerification, ik_residual, validate_targets


@dataclass(frozen=True)
class LiveIKConfig:
    """Settings of the live IK solver."""

    iterations: int = 30
    """LM iterations at most per update (the loop stops early once converged)."""
    success_tolerance: float = 1e-2
    """An answer reaches its target when the pose error ‖log(T⁻¹T_target)‖ is below this."""
    converged_error: float = 1e-6
    """LM stops once the pose error is below this."""
    safety_margin: float = 0.002
    """δ, metres: the clearance every answer must keep (python-fcl, capsule body)."""
    clearance_weight: float = 30.0
    """Penalty weight of a clearance shortfall (per metre) in the LM stage."""
    fallback_search: bool = True
    """When the warm-started LM misses the target, run the batched search of
    ``IKSolver`` (seconds, not milliseconds) and keep the better answer."""
    dtype: str = "float32"
    """JAX dtype of the LM stage ("float64" needs jax_enable_x64)."""


@dataclass
class LiveIKResult:
    """One live-IK answer, verified in float64. Units: rad, m, s.

    Outside ``tasks._result.ResultIO`` on purpose: one interactive answer of the viewer
    (one target, timed in milliseconds), never written to or read from a RESULT.json; its
    fields keep the base's names (``q``, ``success``, ``reason``, ``stage``, …)."""

    q: np.ndarray
    """(3n,) θ, φ, L."""
    position: np.ndarray
    """(3,) tip position reached, m."""
    wxyz: np.ndarray
    """(4,) tip orientation reached, unit quaternion."""
    pose_error: float
    """‖log(T_tip⁻¹·T_target)‖ (mixed m/rad)."""
    position_error: float
    """m."""
    rotation_error: float
    """rad."""
    min_clearance: float
    """python-fcl signed distance, m (nan without a scene)."""
    max_violation: float
    """Largest limit violation (rad, m) or clearance shortfall below δ (m)."""
    success: bool
    """Pose error below the tolerance, every violation ≤ 1e-6, collision-free."""
    reason: str
    """"" on success, else why not."""
    stage: Stage
    """What produced ``q``: ``Stage.REFINE`` (warm-started LM), ``Stage.SEARCH`` (the
    batched fallback) or ``Stage.POLISH`` (Ipopt)."""
    seconds: float
    """Wall time of the update, verification included."""
    timing: dict[str, float] = field(default_factory=dict)
    """Seconds per part of the update: "refine", "search", "polish", "verify"."""
    violations: dict[str, float] = field(default_factory=dict)
    """Largest violation per family (``world.verdict.UNITS``: limits rad or m, clearance
    and self_clearance m below δ)."""


class LiveIKSolver:
    """Single-target IK warm-started from the previous answer; reuse it across updates.

    The first ``solve`` compiles the LM program (seconds; cached on disk); later ones run
    it. ``solve(q_current, position, wxyz, exact=False)`` returns a ``LiveIKResult``.
    """

    def __init__(
        self,
        robot: Robot | str | dict,
        scene: Scene | str | None = None,
        config: LiveIKConfig = LiveIKConfig(),
    ) -> None:
        configure()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if isinstance(scene, str) else scene
        self.config = config
        self.ik = IKSolver(
            self.robot,
            self.scene,
            IKConfig(
                success_tolerance=config.success_tolerance,
                converged_error=config.converged_error,
                safety_margin=config.safety_margin,
                clearance_weight=config.clearance_weight,
                dtype=config.dtype,
            ),
        )
        """The batched solver: the fallback search and the float64 verification."""
        self.dtype = jnp.dtype(config.dtype)
        self._arrays = (
            scene_arrays(self.scene, dtype=self.dtype) if self.scene is not None else None
        )
        self._residual = partial(
            ik_residual, self.robot, float(self.ik.margin), float(config.clearance_weight)
        )
        self._project = partial(project_z, self.robot)
        free = np.ones(self.robot.dof)
        free[2::3] = ~self.robot.lengths_fixed()
        self._free = jnp.asarray(free, self.dtype)
        self._lm_config = LMConfig(cost_tolerance=0.5 * config.converged_error**2)
        self._polisher: Any = None

    def _refine(self, q0: np.ndarray, position: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        """LM from q0 on the one target; returns q (3n,) clipped to the limits."""
        z0 = q_to_z_numpy(q0)[None]
        params = (
            jnp.asarray(position[None], self.dtype),
            jnp.asarray(rotation.reshape(1, 9), self.dtype),
        )
        z = lm_solve(
            self._residual,
            self._project,
            jnp.asarray(z0, self.dtype),
            params,
            self._arrays,
            self._free,
            jnp.int32(self.config.iterations),
            config=self._lm_config,
        ).z
        return clip_to_limits(self.robot, z_to_q_numpy(np.asarray(z[0], dtype=float)))

    def _verify(self, q: np.ndarray, position: np.ndarray, wxyz: np.ndarray) -> IKVerification:
        """``IKSolver.verify`` of one answer (B = 1): its numbers and the verdict."""
        return self.ik.verify(q[None], position[None], wxyz[None])

    @compiles_fully
    def solve(
        self,
        q_current: Any,
        position: Any,
        wxyz: Any,
        exact: bool = False,
        search: bool | None = None,
    ) -> LiveIKResult:
        """Move the answer ``q_current`` (3n; rad, rad, m) to the target pose.

        Long: one update in order (warm start, search, polish, verdict) timing each stage.

        Args:
            q_current: the answer to start from, e.g. the previous update's ``q``.
            position: (3,) target tip position, metres.
            wxyz: (4,) target tip orientation, unit quaternion (w, x, y, z).
            exact: polish the answer with Ipopt (constraints as constraints;
                ``stages.polish._accept``): the polished answer replaces it where the verdict
                accepts the polished one, else the answer stays with its own verdict.
            search: run the batched search when the warm start misses (seconds on a CPU);
                None: ``config.fallback_search``. The viewer searches only when a drag
                ends, so that dragging stays fast.

        Raises:
            ValueError: q_current of the wrong size, or an invalid target (not finite,
                not a unit quaternion, out of reach).
        """
        t_start = time.perf_counter()
        timing: dict[str, float] = {}
        q0 = self.robot.full_q(np.asarray(q_current, dtype=float).ravel())
        positions, quats, reasons = self._validate(position, wxyz)
        position, wxyz = positions[0], quats[0]
        rotation = matrix_from_wxyz(wxyz[None])[0]

        t0 = time.perf_counter()
        q = self._refine(np.asarray(q0, dtype=float), position, rotation)
        timing["refine"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        row = self._verify(q, position, wxyz)
        timing["verify"] = time.perf_counter() - t0
        stage = Stage.REFINE

        search = self.config.fallback_search if search is None else search
        if not row.success[0] and search:
            t0 = time.perf_counter()
            found = self.ik.solve(position[None], wxyz[None])
            timing["search"] = time.perf_counter() - t0
            if np.all(np.isfinite(found.q[0])):
                other = self._verify(found.q[0], position, wxyz)
                if _better(other, row):
                    q, row, stage = found.q[0], other, Stage.SEARCH

        if exact:
            t0 = time.perf_counter()
            if self._polisher is None:
                from ...stages.polish import IKPolisher

                self._polisher = IKPolisher(self.robot, self.scene, safety_margin=self.ik.margin)

            def polish(start: np.ndarray) -> Polished[np.ndarray]:
                out = self._polisher.solve(start, position, rotation)
                return (Polished(np.asarray(out.q, dtype=float)) if np.all(np.isfinite(out.q))
                        else Polished(None, out.failure()))

            def judge(answer: np.ndarray) -> _Row:
                checked = self._verify(answer, position, wxyz)
                return _Row(bool(checked.success[0]), str(checked.reason[0]), checked)

            outcome = accept_first([q], q, _Row(bool(row.success[0]), str(row.reason[0]), row),
                                   polish, judge)
            timing["polish"] = time.perf_counter() - t0
            if outcome.accepted:
                q, row, stage = outcome.answer, outcome.verdict.checked, Stage.POLISH

        return LiveIKResult(
            q=np.asarray(q, dtype=float),
            position=np.asarray(row.position[0], dtype=float),
            wxyz=np.asarray(row.wxyz[0], dtype=float),
            pose_error=float(row.pose_error[0]),
            position_error=float(row.position_error[0]),
            rotation_error=float(row.rotation_error[0]),
            min_clearance=float(row.clearance[0]),
            max_violation=float(row.max_violation[0]),
            success=bool(row.success[0]),
            reason=str(row.reason[0]),
            stage=stage,
            violations={k: float(v[0]) for k, v in row.violations.items()},
            seconds=time.perf_counter() - t_start,
            timing=timing,
        )

    def _validate(self, position: Any, wxyz: Any) -> tuple[np.ndarray, np.ndarray, list[str]]:
        positions, quats, reasons = validate_targets(self.robot, np.ravel(position), np.ravel(wxyz))
        if reasons[0]:
            raise ValueError(reasons[0])
        return positions, quats, reasons


@dataclass(frozen=True)
class _Row:
    """One verified answer as ``stages.polish._accept`` reads it."""

    success: bool
    reason: str
    checked: IKVerification
    """``IKSolver.verify``'s report on the answer (B = 1)."""


def _better(a: IKVerification, b: IKVerification) -> bool:
    """Is verified answer a better than b (each B = 1): a success over a failure, else
    the smaller pose error."""
    if bool(a.success[0]) != bool(b.success[0]):
        return bool(a.success[0])
    return float(a.pose_error[0]) < float(b.pose_error[0])

"""The kinds of batch job (``cr_nlp.batch``): what a job is on the worker (``JobSpec``)
and, per kind and model, the adapter of what differs between them: the solver, the
inputs, a chunk's answers and the assembled results. PCC IK and planning (``_IKJobs``,
``_PlanJobs``) and their twins on the Cosserat rod under one load case
(``_TensionIKJobs``, ``_TensionPlanJobs``), looked up by ``adapter(kind, model)``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._batch_files import BatchError, digest, plain_rows

KINDS = ("ik", "plan")
"""The job kinds: IK targets, start/goal planning problems."""
MODELS = ("pcc", "cosserat")
"""The robot models a job solves on: PCC configurations, or tendon tensions on the
Cosserat rod (robots with a ``mechanics`` block)."""


@dataclass(frozen=True)
class JobSpec:
    """What every chunk of a job needs on the worker (pickled with each task)."""

    kind: str
    """"ik" or "plan"."""
    robot: Any
    """The ``Robot``."""
    scene: Any
    """The ``Scene`` or None."""
    config: Any
    """``IKConfig`` / ``TrajectoryConfig`` (pcc), ``TensionIKConfig`` /
    ``TensionTrajectoryConfig`` (cosserat)."""
    exact: bool
    """Polish with Ipopt (the single-process solvers' ``exact``)."""
    init: str
    """PCC planning only: "roadmap" or "straight" (``TrajectoryPlanner.plan``)."""
    key: str
    """Digest of (kind, model, robot, scene, config): the worker's solver cache key."""
    model: str = "pcc"
    """"pcc" or "cosserat" (``MODELS``)."""
    loads: dict[str, Any] | None = None
    """Cosserat: the one load case of every problem, keyword arguments of the tension
    solvers (tip_force N, tip_moment N·m, gravity m/s², distributed_force N/m, world
    frame; point_loads ``[{"s": m, "force": [N], "moment": [N·m]}]``)."""
    time_limit: float | None = None
    """Cosserat IK with ``exact``: seconds of polishing per target (None: no limit)."""

    @property
    def jobs(self) -> Any:
        """The adapter of this job's kind and model."""
        return adapter(self.kind, self.model)


def _float_digest(inputs: tuple[Any, Any], marks: list[str]) -> str:
    """Digest of float inputs and the per-problem marks. The float64 bytes: hashing their
    JSON text cost ~5 ms per 1000."""
    arrays = [np.ascontiguousarray(x, dtype="<f8") for x in inputs]
    return digest(b"".join([json.dumps([[a.shape for a in arrays], marks]).encode(),
                             *(a.tobytes() for a in arrays)]))


class _PCCSettings:
    """What a PCC job takes besides its config: no loads, the time limit in the config."""

    @staticmethod
    def settings(robot: Any, exact: bool, loads: Any, time_limit: float | None
                 ) -> dict[str, Any] | None:
        del robot, exact
        if loads is not None or time_limit is not None:
            raise BatchError("loads and time_limit are for model='cosserat' (a PCC job takes "
                             "its time limit in the config: polish_time_limit)")
        return None

    @staticmethod
    def manifest_fields(spec: JobSpec) -> dict[str, Any]:
        return {}


# ================================================================ PCC


class _IKJobs(_PCCSettings):
    """IK targets: inputs (positions (T, 3) m, wxyz (T, 4)); a chunk's answers are the
    ``IKResult`` columns as arrays (``IKResult.columns``)."""

    answers = "columns"
    uses_init = False

    @staticmethod
    def chunking(exact: bool) -> tuple[int, int]:
        return (2, 256) if exact else (1, 4096)

    @staticmethod
    def default_config() -> Any:
        from .tasks.geometry.ik import IKConfig

        return IKConfig()

    @staticmethod
    def solver(spec: JobSpec) -> Any:
        from .tasks.geometry.ik import IKSolver

        return IKSolver(spec.robot, spec.scene, spec.config)

    @staticmethod
    def normalise(first: Any, second: Any) -> tuple[Any, Any]:
        first = np.asarray(first, dtype=float).reshape(-1, 3)
        second = np.asarray(second, dtype=float).reshape(-1, 4)
        if len(first) != len(second):
            raise BatchError(f"{len(first)} positions but {len(second)} orientations")
        return first, second

    inputsdigest = staticmethod(_float_digest)

    @staticmethod
    def solve(spec: JobSpec, solver: Any, first: Any, second: Any) -> tuple[Any, dict]:
        result = solver.solve(first, second, exact=spec.exact)
        return result.columns(), result.timing.as_dict()

    @staticmethod
    def failed(spec: JobSpec, count: int, reason: str) -> Any:
        from .tasks._result import Stage
        from .tasks.geometry.ik import IKResult

        nan = np.full(count, np.nan)
        return IKResult(
            spec.robot, np.full((count, spec.robot.dof), np.nan), np.full((count, 3), np.nan),
            np.full((count, 4), np.nan), nan, nan, nan, nan, nan,
            collision_free=np.zeros(count, bool), success=np.zeros(count, bool),
            stage=[Stage.ERROR] * count, reason=[reason] * count).columns()

    @staticmethod
    def join(parts: list[Any]) -> Any:
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}

    @staticmethod
    def assemble(spec: JobSpec, answers: list[Any], timing: dict[str, float],
                 problems: Sequence[str] | None) -> tuple[Any, dict[str, Any]]:
        from .tasks.geometry.ik import IKResult

        result = IKResult.from_columns(spec.robot, _IKJobs.join(answers), timing,
                                       has_scene=spec.scene is not None)
        for i, problem in enumerate(problems or []):
            if problem:
                result.reason[i] = problem
        return result, result.to_dict()


class _PlanJobs(_PCCSettings):
    """Planning problems: inputs (starts, goals), raw rows θ, φ, L validated per problem
    on the worker; a chunk's answers are RESULT.json entries (``TrajectoryResult.entry``)."""

    answers = "rows"
    uses_init = True

    @staticmethod
    def chunking(exact: bool) -> tuple[int, int]:
        return (4, 8)

    @staticmethod
    def default_config() -> Any:
        from .tasks.geometry.trajectory import TrajectoryConfig

        return TrajectoryConfig()

    @staticmethod
    def solver(spec: JobSpec) -> Any:
        from .tasks.geometry.trajectory import TrajectoryPlanner

        return TrajectoryPlanner(spec.robot, spec.scene, spec.config)

    @staticmethod
    def normalise(first: Any, second: Any) -> tuple[Any, Any]:
        first, second = list(first), list(second)
        if len(first) != len(second):
            raise BatchError(f"{len(first)} starts but {len(second)} goals")
        return first, second

    @staticmethod
    def inputsdigest(inputs: tuple[Any, Any], marks: list[str]) -> str:
        # Raw rows, possibly ragged or malformed: validated per problem on the worker.
        return digest(json.dumps([[plain_rows(inputs[0]), plain_rows(inputs[1])], marks]).encode())

    @staticmethod
    def solve(spec: JobSpec, solver: Any, first: Any, second: Any) -> tuple[Any, dict]:
        results = solver.plan(list(first), list(second), exact=spec.exact, init=spec.init)
        return [r.entry() for r in results], solver.last_timing.as_dict()

    @staticmethod
    def failed(spec: JobSpec, count: int, reason: str) -> Any:
        from .tasks.geometry.trajectory import TrajectoryResult

        return [TrajectoryResult(spec.robot, None, spec.config.dt, False, reason,
                                 "error").entry() for _ in range(count)]

    @staticmethod
    def join(parts: list[Any]) -> Any:
        return [row for part in parts for row in part]

    @staticmethod
    def assemble(spec: JobSpec, answers: list[Any], timing: dict[str, float],
                 problems: Sequence[str] | None) -> tuple[Any, dict[str, Any]]:
        from .tasks.geometry.trajectory import TrajectoryResult, trajectories_to_dict

        results = [TrajectoryResult.from_entry(spec.robot, row)
                   for row in _PlanJobs.join(answers)]
        return results, trajectories_to_dict(results, timing)


# ================================================================ Cosserat (tensions)


class _TensionSettings:
    """What a Cosserat job takes besides its config: one load case, checked."""

    kind = ""
    has_exact = False
    """Whether the task has an exact (Ipopt) stage on the rod."""

    @classmethod
    def settings(cls, robot: Any, exact: bool, loads: Any, time_limit: float | None
                 ) -> dict[str, Any] | None:
        from .model.loads import LOAD_KEYS, static_loads

        if getattr(robot, "mechanics", None) is None:
            raise BatchError(f"model='cosserat': {robot.name} has no 'mechanics' block (the "
                             f"rod's stiffness and tension limit); see models/README.md")
        if time_limit is not None and not (isinstance(time_limit, (int, float))
                                           and 0 < time_limit < float("inf")):
            raise BatchError(f"time_limit must be a positive number of seconds, got "
                             f"{time_limit!r}")
        if (exact or time_limit is not None) and not cls.has_exact:
            raise BatchError(f"exact: the Cosserat model has no exact (Ipopt) stage for "
                             f"{cls.kind}")
        loads = dict(loads or {})
        unknown = sorted(set(loads) - set(LOAD_KEYS))
        if unknown:
            raise BatchError(f"loads: {unknown[0]}: unknown key (loads have "
                             f"{', '.join(LOAD_KEYS)})")
        try:
            case = static_loads(1, float(sum(s.length_min for s in robot.segments)), **loads)
        except ValueError as exc:
            raise BatchError(f"loads: {str(exc).removeprefix('case 0: ')}") from None
        return {"tip_force": case.tip_force[0].tolist(),
                "tip_moment": case.tip_moment[0].tolist(), "gravity": case.gravity[0].tolist(),
                "distributed_force": case.distributed_force[0].tolist(),
                "point_loads": case.point_load_lists()[0]}

    @staticmethod
    def manifest_fields(spec: JobSpec) -> dict[str, Any]:
        return {"model": spec.model, "loads": spec.loads, "time_limit": spec.time_limit}


class _TensionIKJobs(_TensionSettings):
    """Tension IK targets: inputs (positions (T, 3) m, wxyz (T, 4), NaN rows or None for
    position-only targets); a chunk's answers are ``TensionIKResult.columns``."""

    answers = "columns"
    uses_init = False
    kind = "ik"
    has_exact = True

    @staticmethod
    def chunking(exact: bool) -> tuple[int, int]:
        return (2, 256)  # ~0.05-0.2 s per target, each chunk pays the LM's fixed costs

    @staticmethod
    def default_config() -> Any:
        from .tasks.mechanics.ik import TensionIKConfig

        return TensionIKConfig()

    @staticmethod
    def solver(spec: JobSpec) -> Any:
        from .tasks.mechanics.ik import TensionIKSolver

        return TensionIKSolver(spec.robot, spec.scene, spec.config)

    @staticmethod
    def normalise(first: Any, second: Any) -> tuple[Any, Any]:
        first = np.asarray(first, dtype=float).reshape(-1, 3)
        second = (np.full((len(first), 4), np.nan) if second is None
                  else np.asarray(second, dtype=float).reshape(-1, 4))
        if len(first) != len(second):
            raise BatchError(f"{len(first)} positions but {len(second)} orientations")
        return first, second

    inputsdigest = staticmethod(_float_digest)

    @staticmethod
    def solve(spec: JobSpec, solver: Any, first: Any, second: Any) -> tuple[Any, dict]:
        result = solver.solve(first, second, **spec.loads, exact=spec.exact,
                              time_limit=spec.time_limit)
        return result.columns(), result.timing.as_dict()

    @staticmethod
    def failed(spec: JobSpec, count: int, reason: str) -> Any:
        from .tasks._result import Stage
        from .tasks.mechanics.ik import TensionIKResult

        def nan(*shape: int) -> np.ndarray:
            return np.full((count, *shape), np.nan)

        loads = {k: np.tile(spec.loads[k], (count, 1))
                 for k in ("tip_force", "tip_moment", "gravity", "distributed_force")}
        tendons = spec.robot.n_tendons
        return TensionIKResult(
            robot=spec.robot, tensions=nan(tendons), target_position=nan(3),
            target_wxyz=nan(4), position=nan(3), wxyz=nan(4), pose_error=nan(),
            position_error=nan(), rotation_error=nan(), min_clearance=nan(),
            max_violation=nan(), success=np.zeros(count, bool), reason=[reason] * count,
            **loads, point_loads=[list(spec.loads["point_loads"]) for _ in range(count)],
            tendon_displacements=nan(tendons), stage=[Stage.ERROR] * count).columns()

    join = staticmethod(_IKJobs.join)

    @staticmethod
    def assemble(spec: JobSpec, answers: list[Any], timing: dict[str, float],
                 problems: Sequence[str] | None) -> tuple[Any, dict[str, Any]]:
        from .tasks.mechanics.ik import TensionIKResult

        result = TensionIKResult.from_columns(spec.robot, _IKJobs.join(answers), timing)
        for i, problem in enumerate(problems or []):
            if problem:
                result.reason[i] = problem
        return result, result.to_dict()


class _TensionPlanJobs(_TensionSettings):
    """Tension planning problems: inputs (starts (B, n), goals (B, n)) N, checked per
    problem on the worker; a chunk's answers are RESULT.json entries
    (``TensionTrajectoryResult.entry``)."""

    answers = "rows"
    uses_init = False
    kind = "plan"
    has_exact = True

    @staticmethod
    def chunking(exact: bool) -> tuple[int, int]:
        return (4, 8)  # seconds per problem, uneven: as PCC planning

    @staticmethod
    def default_config() -> Any:
        from .tasks.mechanics.trajectory import TensionTrajectoryConfig

        return TensionTrajectoryConfig()

    @staticmethod
    def solver(spec: JobSpec) -> Any:
        from .tasks.mechanics.trajectory import TensionTrajectoryPlanner

        return TensionTrajectoryPlanner(spec.robot, spec.scene, spec.config)

    @staticmethod
    def normalise(first: Any, second: Any) -> tuple[Any, Any]:
        try:
            first, second = (np.asarray(v, dtype=float) for v in (first, second))
        except (TypeError, ValueError):
            raise BatchError("starts and goals: expected (B, n) tensions in N") from None
        if first.ndim != 2 or first.shape != second.shape:
            raise BatchError(f"starts {first.shape} and goals {second.shape}: expected two "
                             "(B, n) arrays of tensions in N")
        return first, second

    inputsdigest = staticmethod(_float_digest)

    @staticmethod
    def solve(spec: JobSpec, solver: Any, first: Any, second: Any) -> tuple[Any, dict]:
        results = solver.plan(first, second, **spec.loads, exact=spec.exact,
                              time_limit=spec.time_limit)
        timing: dict[str, float] = {}
        for result in results:
            for key, value in result.timing.as_dict().items():
                timing[key] = timing.get(key, 0.0) + value
        return [r.entry() for r in results], timing

    @staticmethod
    def failed(spec: JobSpec, count: int, reason: str) -> Any:
        from .tasks._result import Stage
        from .tasks.mechanics.trajectory import TensionTrajectoryResult

        n, cfg, loads = spec.robot.n_tendons, spec.config, spec.loads
        return [TensionTrajectoryResult(
            robot=spec.robot, tensions=np.zeros((0, n)), dt=cfg.dt, position=np.zeros((0, 3)),
            wxyz=np.zeros((0, 4)), backbone=np.zeros((0, 0, 3)), clearance=np.zeros(0),
            min_clearance=np.nan, max_violation=np.nan, success=False, reason=reason,
            **{k: np.asarray(loads[k], float) for k in ("tip_force", "tip_moment", "gravity",
                                                        "distributed_force")},
            point_loads=list(loads["point_loads"]), tension_rate_max=cfg.tension_rate_max,
            stage=Stage.ERROR).entry() for _ in range(count)]

    join = staticmethod(_PlanJobs.join)

    @staticmethod
    def assemble(spec: JobSpec, answers: list[Any], timing: dict[str, float],
                 problems: Sequence[str] | None) -> tuple[Any, dict[str, Any]]:
        from .tasks._timing import StageTiming
        from .tasks.mechanics._motion_result import tension_trajectories_to_dict
        from .tasks.mechanics.trajectory import TensionTrajectoryResult

        results = [TensionTrajectoryResult.from_entry(row, spec.robot)
                   for row in _PlanJobs.join(answers)]
        return results, tension_trajectories_to_dict(results, StageTiming.from_dict(timing),
                                                     spec.robot)


_ADAPTERS: dict[tuple[str, str], Any] = {
    ("ik", "pcc"): _IKJobs, ("plan", "pcc"): _PlanJobs,
    ("ik", "cosserat"): _TensionIKJobs, ("plan", "cosserat"): _TensionPlanJobs}
"""(kind, model) → what differs between kinds: solver, inputs, answers, results."""


def adapter(kind: str, model: str = "pcc") -> Any:
    """The adapter of a job's kind ("ik", "plan") and model ("pcc", "cosserat").

    Raises:
        BatchError: an unknown kind or model.
    """
    if kind not in KINDS:
        raise BatchError(f"kind must be one of {KINDS}, got {kind!r}")
    if model not in MODELS:
        raise BatchError(f"model must be one of {MODELS}, got {model!r}")
    return _ADAPTERS[(kind, model)]

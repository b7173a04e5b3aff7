"""cr_nlp: IK, trajectory planning and path following for tendon-driven continuum robots.

Batched JAX search and refinement, an exact CasADi/Ipopt polish, and independent
verdicts (float64 re-evaluation, python-fcl). Units: metres, radians, seconds.

The public names below are imported on first use: ``import cr_nlp`` loads neither JAX
nor CasADi, trimesh, python-fcl, Dask or matplotlib, and a task imports only what it
needs.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_PUBLIC = {
    "use_host_devices": ".runtime",
    "configure": ".runtime",
    "clear_caches": ".runtime",
    "bundled_file": "._resources",
    "models_root": "._resources",
    "run_batch": ".batch",
    "CasadiModel": ".model",
    "ModelFileError": ".model",
    "Robot": ".model",
    "backbone_points": ".model",
    "load_robot": ".model",
    "pose_error": ".model",
    "tendon_lengths": ".model",
    "tip_pose": ".model",
    "StaticsConfig": ".model.cosserat",
    "StaticsResult": ".model.cosserat",
    "solve_statics": ".model.statics",
    "matrix_from_wxyz": ".model.rotations",
    "wxyz_from_matrix": ".model.rotations",
    "SCHEMA_VERSION": ".tasks._result",
    "load_result": ".tasks._result",
    "load_results": ".tasks._result",
    "CalibrationConfig": ".tasks.calibration.calibrate",
    "CalibrationResult": ".tasks.calibration.calibrate",
    "calibrate": ".tasks.calibration.calibrate",
    "read_measurements": ".tasks.readers",
    "follow_path": ".tasks.geometry.follow",
    "FollowConfig": ".tasks.geometry.follow",
    "FollowResult": ".tasks.geometry.follow",
    "PathFollower": ".tasks.geometry.follow",
    "IKConfig": ".tasks.geometry.ik",
    "IKResult": ".tasks.geometry.ik",
    "IKSolver": ".tasks.geometry.ik",
    "solve_ik": ".tasks.geometry.ik",
    "LiveIKConfig": ".tasks.geometry.live_ik",
    "LiveIKResult": ".tasks.geometry.live_ik",
    "LiveIKSolver": ".tasks.geometry.live_ik",
    "ReferencePath": ".tasks.paths",
    "load_path": ".tasks.readers",
    "TensionIKConfig": ".tasks.mechanics.ik",
    "TensionIKResult": ".tasks.mechanics.ik",
    "TensionIKSolver": ".tasks.mechanics.ik",
    "solve_tension_ik": ".tasks.mechanics.ik",
    "TensionLiveIKSolver": ".tasks.mechanics.live_ik",
    "TensionLiveIK": ".tasks.mechanics.live_ik",           # deprecated names (0.2 drops them)
    "TensionFollower": ".tasks.mechanics.follow",
    "follow_tensions": ".tasks.mechanics.follow",
    "TensionPlanConfig": ".tasks.mechanics.trajectory",
    "TensionPlanner": ".tasks.mechanics.trajectory",
    "plan_tensions": ".tasks.mechanics.trajectory",
    "TensionFollowConfig": ".tasks.mechanics.follow",
    "TensionPathFollower": ".tasks.mechanics.follow",
    "TensionFollowResult": ".tasks.mechanics.follow",
    "follow_tension_path": ".tasks.mechanics.follow",
    "TensionTrajectoryConfig": ".tasks.mechanics.trajectory",
    "TensionTrajectoryPlanner": ".tasks.mechanics.trajectory",
    "TensionTrajectoryResult": ".tasks.mechanics.trajectory",
    "plan_tension_trajectories": ".tasks.mechanics.trajectory",
    "replay_pcc_motion": ".tasks.mechanics.trajectory",
    "TrajectoryConfig": ".tasks.geometry.trajectory",
    "TrajectoryPlanner": ".tasks.geometry.trajectory",
    "TrajectoryResult": ".tasks.geometry.trajectory",
    "plan_trajectories": ".tasks.geometry.trajectory",
    "save_results": ".tasks.geometry.trajectory",
    "Scene": ".world",
    "check": ".world",
    "check_many": ".world",
    "load_scene": ".world",
}
"""Each public name and the module it lives in."""

__all__ = sorted(_PUBLIC)


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'cr_nlp' has no attribute {name!r}")
    value = getattr(importlib.import_module(module, __name__), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_PUBLIC))


if TYPE_CHECKING:  # the same names for type checkers and editors
    from ._resources import bundled_file as bundled_file
    from ._resources import models_root as models_root
    from .batch import run_batch as run_batch
    from .model import CasadiModel as CasadiModel
    from .model import ModelFileError as ModelFileError
    from .model import Robot as Robot
    from .model import backbone_points as backbone_points
    from .model import load_robot as load_robot
    from .model import pose_error as pose_error
    from .model import tendon_lengths as tendon_lengths
    from .model import tip_pose as tip_pose
    from .model.cosserat import StaticsConfig as StaticsConfig
    from .model.cosserat import StaticsResult as StaticsResult
    from .model.cosserat import solve_statics as solve_statics
    from .model.rotations import matrix_from_wxyz as matrix_from_wxyz
    from .model.rotations import wxyz_from_matrix as wxyz_from_matrix
    from .runtime import clear_caches as clear_caches
    from .runtime import configure as configure
    from .runtime import use_host_devices as use_host_devices
    from .tasks._result import SCHEMA_VERSION as SCHEMA_VERSION
    from .tasks._result import load_result as load_result
    from .tasks._result import load_results as load_results
    from .tasks.calibration.calibrate import CalibrationConfig as CalibrationConfig
    from .tasks.calibration.calibrate import CalibrationResult as CalibrationResult
    from .tasks.calibration.calibrate import calibrate as calibrate
    from .tasks.geometry.follow import FollowConfig as FollowConfig
    from .tasks.geometry.follow import FollowResult as FollowResult
    from .tasks.geometry.follow import PathFollower as PathFollower
    from .tasks.geometry.follow import follow_path as follow_path
    from .tasks.geometry.ik import IKConfig as IKConfig
    from .tasks.geometry.ik import IKResult as IKResult
    from .tasks.geometry.ik import IKSolver as IKSolver
    from .tasks.geometry.ik import solve_ik as solve_ik
    from .tasks.geometry.live_ik import LiveIKConfig as LiveIKConfig
    from .tasks.geometry.live_ik import LiveIKResult as LiveIKResult
    from .tasks.geometry.live_ik import LiveIKSolver as LiveIKSolver
    from .tasks.geometry.trajectory import TrajectoryConfig as TrajectoryConfig
    from .tasks.geometry.trajectory import TrajectoryPlanner as TrajectoryPlanner
    from .tasks.geometry.trajectory import TrajectoryResult as TrajectoryResult
    from .tasks.geometry.trajectory import plan_trajectories as plan_trajectories
    from .tasks.geometry.trajectory import save_results as save_results
    from .tasks.mechanics.follow import TensionFollowConfig as TensionFollowConfig
    from .tasks.mechanics.follow import TensionFollowResult as TensionFollowResult
    from .tasks.mechanics.follow import TensionPathFollower as TensionPathFollower
    from .tasks.mechanics.follow import follow_tension_path as follow_tension_path
    from .tasks.mechanics.ik import TensionIKConfig as TensionIKConfig
    from .tasks.mechanics.ik import TensionIKResult as TensionIKResult
    from .tasks.mechanics.ik import TensionIKSolver as TensionIKSolver
    from .tasks.mechanics.ik import solve_tension_ik as solve_tension_ik
    from .tasks.mechanics.live_ik import TensionLiveIKSolver as TensionLiveIKSolver
    from .tasks.mechanics.trajectory import TensionTrajectoryConfig as TensionTrajectoryConfig
    from .tasks.mechanics.trajectory import TensionTrajectoryPlanner as TensionTrajectoryPlanner
    from .tasks.mechanics.trajectory import TensionTrajectoryResult as TensionTrajectoryResult
    from .tasks.mechanics.trajectory import plan_tension_trajectories as plan_tension_trajectories
    from .tasks.mechanics.trajectory import replay_pcc_motion as replay_pcc_motion
    from .tasks.paths import ReferencePath as ReferencePath
    from .tasks.readers import load_path as load_path
    from .tasks.readers import read_measurements as read_measurements
    from .world import Scene as Scene
    from .world import check as check
    from .world import check_many as check_many
    from .world import load_scene as load_scene

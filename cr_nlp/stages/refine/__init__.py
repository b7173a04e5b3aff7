"""Stage 2, refine: batched penalty LM in JAX.

The public face (what ``tasks/`` imports): the dense LM (``lm_solve``, ``LMConfig``, its
``LMSolution`` with why each problem stopped, ``STOP_REASONS``) and the banded LM of
chains (``banded_lm_solve``, ``ChainResidual``); loaded on first use (a PCC task does not
import the rod, nor a mechanics task the PCC search): the mechanics family's rows on the
Cosserat rod for one waypoint and for a motion (``_tension_lm``), and the PCC family's
fused IK search (``IKSearch``, ``SearchSettings``, ``SearchPlan``, ``RetryPlan``), chain
stream (``ChainBatchLM``), trajectory guess selection (``select_guesses``), path
continuation (``BranchContinuation``, ``ContinuationSettings``) and tendon-limit
penalties (``tendon_speed_excess``, ``tendon_accel_excess``)."""

from .._faces import lazy_face
from ._banded_lm import ChainResidual as ChainResidual
from ._banded_lm import banded_lm_solve as banded_lm_solve
from ._lm import STOP_REASONS as STOP_REASONS
from ._lm import LMConfig as LMConfig
from ._lm import LMSolution as LMSolution
from ._lm import iteration_budget as iteration_budget
from ._lm import lm_solve as lm_solve

_LAZY = {"MotionTerms": ("._tension_lm", "MotionTerms"),
         "TensionTerms": ("._tension_lm", "TensionTerms"),
         "WaypointParams": ("._tension_lm", "WaypointParams"),
         "base_frame": ("._tension_lm", "base_frame"),
         "box_bounds": ("._tension_lm", "box_bounds"),
         "chain_length": ("._tension_lm", "chain_length"),
         "moments_of_unknowns": ("._tension_lm", "moments_of_unknowns"),
         "project_box": ("._tension_lm", "project_box"),
         "solve_motion": ("._tension_lm", "solve_motion"),
         "solve_motions": ("._tension_lm", "solve_motions"),
         "solve_waypoints": ("._tension_lm", "solve_waypoints"),
         "tensions_of_batch": ("._tension_lm", "tensions_of_batch"),
         "tensions_of_unknowns": ("._tension_lm", "tensions_of_unknowns"),
         "unknowns_of": ("._tension_lm", "unknowns_of"),
         "waypoint_params": ("._tension_lm", "waypoint_params"),
         "waypoint_residual": ("._tension_lm", "waypoint_residual"),
         "world_frame": ("._tension_lm", "world_frame"),
         "IKSearch": ("._ik_driver", "IKSearch"),
         "SearchSettings": ("._ik_driver", "SearchSettings"),
         "SearchPlan": ("._ik_program", "SearchPlan"),
         "RetryPlan": ("._ik_program", "RetryPlan"),
         "ChainBatchLM": ("._chain_stream", "ChainBatchLM"),
         "select_guesses": ("._trajectory_select", "select_guesses"),
         "BranchContinuation": ("._path_continuation", "BranchContinuation"),
         "ContinuationSettings": ("._path_continuation", "ContinuationSettings"),
         "tendon_speed_excess": ("._tendon_penalty", "tendon_speed_excess"),
         "tendon_accel_excess": ("._tendon_penalty", "tendon_accel_excess")}

__getattr__ = lazy_face(__name__, _LAZY)

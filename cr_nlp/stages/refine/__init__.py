"""Stage 2, refine: batched penalty LM in JAX.

The public face (what ``tasks/`` imports): the dense LM (``lm_solve``, ``LMConfig``, its
``LMSolution`` with why each problem stopped, ``STOP_REASONS``), the
banded LM of chains (``banded_lm_solve``, ``ChainResidual``), and the mechanics family's
rows on the Cosserat rod for one waypoint and for a motion (``_tension_lm``); loaded on
first use, the PCC family's machinery: the fused IK search (``IKSearch``,
``SearchSettings``, ``SearchPlan``, ``RetryPlan``), the chain stream (``ChainBatchLM``),
trajectory guess selection (``select_guesses``), path continuation
(``BranchContinuation``, ``ContinuationSettings``) and the tendon-limit penalties
(``tendon_speed_excess``, ``tendon_accel_excess``)."""

from .._faces import lazy_face
from ._banded_lm import ChainResidual as ChainResidual
from ._banded_lm import banded_lm_solve as banded_lm_solve
from ._lm import STOP_REASONS as STOP_REASONS
from ._lm import LMConfig as LMConfig
from ._lm import LMSolution as LMSolution
from ._lm import lm_solve as lm_solve
from ._tension_lm import MotionTerms as MotionTerms
from ._tension_lm import TensionTerms as TensionTerms
from ._tension_lm import WaypointParams as WaypointParams
from ._tension_lm import base_frame as base_frame
from ._tension_lm import box_bounds as box_bounds
from ._tension_lm import chain_length as chain_length
from ._tension_lm import project_box as project_box
from ._tension_lm import solve_motion as solve_motion
from ._tension_lm import tensions_of_unknowns as tensions_of_unknowns
from ._tension_lm import unknowns_of as unknowns_of
from ._tension_lm import waypoint_params as waypoint_params
from ._tension_lm import waypoint_residual as waypoint_residual

_LAZY = {"IKSearch": ("._ik_driver", "IKSearch"),
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

"""Stage 2, refine: batched penalty LM in JAX.

The public face (what ``tasks/`` imports): the dense LM (``lm_solve``, ``LMConfig``), the
banded LM of chains (``banded_lm_solve``), and the mechanics family's rows on the Cosserat
rod for one waypoint and for a motion (``_tension_lm``)."""

from ._banded_lm import ChainResidual as ChainResidual
from ._banded_lm import banded_lm_solve as banded_lm_solve
from ._lm import LMConfig as LMConfig
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

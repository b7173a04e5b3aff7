"""Stage 3, polish: Ipopt with the constraints as constraints, and the one acceptance.

The public face (what ``tasks/`` imports): the one acceptance policy (``polish_and_accept``,
``accept_first``, ``Acceptance``, ``Judged``, ``Polished``, ``RowVerdict``, ``polish_note``,
``check_time_limit``), Ipopt's status words, the PCC IK polish (``IKPolisher``,
``build_polisher``, ``polish_many``) and trajectory polish (``TrajectoryPolisher``,
``trajectory_polisher``, ``polish_one``, ``describe_polish``, ``TrajectoryPolishConfig``),
their process pool (``PolishPool``), and on the Cosserat rod the tension-space IK polish
(``polish_tension_ik``, its formulation ``POLISH_EXACT_MODE``) and that of tension
motions, plans and followed paths (``polish_tension_motion``, ``MOTION_EXACT_MODE``,
``TensionMotionPolishConfig``). Everything beyond the
acceptance is imported on first use: importing this package (as every task does for the
acceptance) does not load CasADi."""

from .._faces import lazy_face
from ._accept import Acceptance as Acceptance
from ._accept import Judged as Judged
from ._accept import Polished as Polished
from ._accept import RowVerdict as RowVerdict
from ._accept import accept_first as accept_first
from ._accept import check_time_limit as check_time_limit
from ._accept import polish_and_accept as polish_and_accept
from ._accept import polish_note as polish_note

_LAZY = {"SUCCESS_STATUSES": ("._ipopt", "SUCCESS_STATUSES"),
         "TIME_LIMIT_STATUS": ("._ipopt", "TIME_LIMIT_STATUS"),
         "POLISH_EXACT_MODE": ("._tension_ik_nlp", "EXACT_MODE"),
         "MOTION_EXACT_MODE": ("._tension_motion_config", "EXACT_MODE"),
         "TensionMotionPolishConfig": ("._tension_motion_config",
                                       "TensionMotionPolishConfig"),
         "polish_tension_motion": ("._tension_motion_nlp", "polish_tension_motion"),
         "TensionPolishConfig": ("._tension_ik_nlp", "TensionPolishConfig"),
         "polish_tension_ik": ("._tension_ik_nlp", "polish_tension_ik"),
         "IKPolisher": ("._ik_nlp", "IKPolisher"),
         "build_polisher": ("._ik_nlp", "build_polisher"),
         "polish_many": ("._ik_nlp", "polish_many"),
         "PolishPool": ("._process_pool", "PolishPool"),
         "TrajectoryPolishConfig": ("._trajectory_config", "TrajectoryPolishConfig"),
         "TrajectoryPolisher": ("._trajectory_nlp", "TrajectoryPolisher"),
         "describe_polish": ("._trajectory_nlp", "describe_polish"),
         "polish_one": ("._trajectory_nlp", "polish_one"),
         "trajectory_polisher": ("._trajectory_nlp", "trajectory_polisher")}

__getattr__ = lazy_face(__name__, _LAZY)

__all__ = sorted([*_LAZY, "Acceptance", "Judged", "Polished", "RowVerdict", "accept_first",
                  "check_time_limit", "polish_and_accept", "polish_note"])

"""Stage 3, polish: Ipopt with the constraints as constraints, and the one acceptance.

The public face (what the mechanics tasks import): the acceptance policy
(``polish_and_accept``, ``Polished``, ``RowVerdict``, ``polish_note``,
``check_time_limit``), Ipopt's status words, and the tension-space IK polish on the
Cosserat rod (``polish_tension_ik``, its formulation ``POLISH_EXACT_MODE``)."""

from ._accept import Polished as Polished
from ._accept import RowVerdict as RowVerdict
from ._accept import check_time_limit as check_time_limit
from ._accept import polish_and_accept as polish_and_accept
from ._accept import polish_note as polish_note
from ._ipopt import SUCCESS_STATUSES as SUCCESS_STATUSES
from ._ipopt import TIME_LIMIT_STATUS as TIME_LIMIT_STATUS
from ._tension_ik_nlp import EXACT_MODE as POLISH_EXACT_MODE
from ._tension_ik_nlp import TensionPolishConfig as TensionPolishConfig
from ._tension_ik_nlp import polish_tension_ik as polish_tension_ik

__all__ = ["POLISH_EXACT_MODE", "SUCCESS_STATUSES", "TIME_LIMIT_STATUS", "Polished",
           "RowVerdict", "TensionPolishConfig", "check_time_limit", "polish_and_accept",
           "polish_note", "polish_tension_ik"]

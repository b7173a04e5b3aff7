"""Stage 3, polish: Ipopt with the constraints as constraints, and the one acceptance.

The public face (what the mechanics tasks import): the acceptance policy
(``polish_and_accept``, ``Polished``, ``RowVerdict``, ``polish_note``,
``check_time_limit``), Ipopt's status words, and the tension-space IK polish on the
Cosserat rod (``polish_tension_ik``, its formulation ``POLISH_EXACT_MODE``) and of
tension motions, plans and followed paths (``polish_tension_motion``,
``MOTION_EXACT_MODE``). The Ipopt
names are imported on first use: importing this package (as every task does for the
acceptance) does not load CasADi."""

from importlib import import_module
from typing import Any

from ._accept import Polished as Polished
from ._accept import RowVerdict as RowVerdict
from ._accept import check_time_limit as check_time_limit
from ._accept import polish_and_accept as polish_and_accept
from ._accept import polish_note as polish_note

_LAZY = {"SUCCESS_STATUSES": ("._ipopt", "SUCCESS_STATUSES"),
         "TIME_LIMIT_STATUS": ("._ipopt", "TIME_LIMIT_STATUS"),
         "POLISH_EXACT_MODE": ("._tension_ik_nlp", "EXACT_MODE"),
         "MOTION_EXACT_MODE": ("._tension_motion_nlp", "EXACT_MODE"),
         "TensionMotionPolishConfig": ("._tension_motion_nlp", "TensionMotionPolishConfig"),
         "polish_tension_motion": ("._tension_motion_nlp", "polish_tension_motion"),
         "TensionPolishConfig": ("._tension_ik_nlp", "TensionPolishConfig"),
         "polish_tension_ik": ("._tension_ik_nlp", "polish_tension_ik")}

__all__ = ["MOTION_EXACT_MODE", "POLISH_EXACT_MODE", "SUCCESS_STATUSES", "TIME_LIMIT_STATUS",
           "Polished", "RowVerdict", "TensionMotionPolishConfig", "TensionPolishConfig",
           "check_time_limit", "polish_and_accept", "polish_note", "polish_tension_ik",
           "polish_tension_motion"]


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _LAZY[name]
    value = getattr(import_module(module, __name__), attribute)
    globals()[name] = value
    return value

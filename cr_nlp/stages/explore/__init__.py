"""Stage 1, explore: starting points for the LM (seed pool, roadmap, guesses, sequences).

The public face (what ``tasks/`` imports): the mechanics family's tension seed pool,
cached on disk per robot and load case (``tension_pool``, ``TensionPool``); loaded on
first use, the PCC planner's roadmap (``Roadmap``, ``RoadmapConfig``) and initial
trajectory guesses (``initial_guesses``)."""

from .._faces import lazy_face
from ._tension_pool import TensionPool as TensionPool
from ._tension_pool import random_tensions as random_tensions
from ._tension_pool import tension_pool as tension_pool
from ._tension_pool import tension_pool_cache_stats as tension_pool_cache_stats
from ._tension_pool import tension_pool_path as tension_pool_path

_LAZY = {"Roadmap": ("._roadmap", "Roadmap"),
         "RoadmapConfig": ("._roadmap", "RoadmapConfig"),
         "initial_guesses": ("._trajectory_guesses", "initial_guesses")}

__getattr__ = lazy_face(__name__, _LAZY)

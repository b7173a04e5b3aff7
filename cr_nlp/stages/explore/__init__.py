"""Stage 1, explore: starting points for the LM (seed pool, roadmap, guesses, sequences).

The public face (what ``tasks/`` imports): the mechanics family's tension seed pool,
cached on disk per robot and load case (``tension_pool``, ``TensionPool``)."""

from ._tension_pool import TensionPool as TensionPool
from ._tension_pool import random_tensions as random_tensions
from ._tension_pool import tension_pool as tension_pool
from ._tension_pool import tension_pool_cache_stats as tension_pool_cache_stats
from ._tension_pool import tension_pool_path as tension_pool_path

"""The three solver stages, each a package (lowest first; a later one may import an
earlier one, never the reverse, ``tests/system/test_import_structure.py``):

- ``explore``: where to start: the Sobol seed pool and its nearest-pose lookup and beam,
  the roadmap (PRM) and its batched shortest paths, initial trajectory guesses, the
  smoothest sequence of per-waypoint answers.
- ``refine``: batched penalty LM in JAX: the dense LM and its one step rule, the banded
  LM of chains, the fused IK program and its host driver, the chain stream that feeds
  trajectories through a few device slots, path continuation, tendon-limit penalties.
- ``polish``: the exact stage: Ipopt NLPs for IK and trajectories, their clearance rows
  and compiled C functions, the process pool, and the one acceptance policy.

``_chunks`` (batch chunk sizes) serves all three; ``_faces`` loads the packages' public
faces on first use.
"""

from ._chunks import SMALLEST_CHUNK as SMALLEST_CHUNK
from ._chunks import chunk_plan as chunk_plan

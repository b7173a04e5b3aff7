"""Stage 1, explore: starting points for the LM (seed pool, roadmap, guesses, sequences).

The public face (what ``tasks/`` imports), every name loaded on first use (a PCC task
does not import the rod): the mechanics family's tension seed pool, cached on disk per
robot and load case (``tension_pool``, ``TensionPool``) and its planner's roadmap in
tension space (``tension_roadmap``, ``TensionRoadmap``), the PCC planner's roadmap
(``Roadmap``, ``RoadmapConfig``) and initial trajectory guesses (``initial_guesses``)."""

from .._faces import lazy_face

_LAZY = {"TensionPool": ("._tension_pool", "TensionPool"),
         "random_tensions": ("._tension_pool", "random_tensions"),
         "tension_pool": ("._tension_pool", "tension_pool"),
         "tension_pool_cache_stats": ("._tension_pool", "tension_pool_cache_stats"),
         "tension_pool_path": ("._tension_pool", "tension_pool_path"),
         "TensionRoadmap": ("._tension_roadmap", "TensionRoadmap"),
         "tension_roadmap": ("._tension_roadmap", "tension_roadmap"),
         "leg_change": ("._tension_roadmap", "leg_change"),
         "clear_nodes": ("._tension_roadmap", "clear_nodes"),
         "tension_roadmap_cache_stats": ("._tension_roadmap", "tension_roadmap_cache_stats"),
         "Roadmap": ("._roadmap", "Roadmap"),
         "RoadmapConfig": ("._roadmap", "RoadmapConfig"),
         "initial_guesses": ("._trajectory_guesses", "initial_guesses")}

__getattr__ = lazy_face(__name__, _LAZY)

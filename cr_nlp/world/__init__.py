"""Scenes, clearance and the independent collision verdict.

- ``scene``: scene files, obstacles, mesh loading and the cached convex decomposition.
- ``_distances``: body sphere ↔ part signed distances, written once for JAX and CasADi.
- ``clearance``: the differentiable clearance (JAX, batched) and per-pair CasADi functions.
- ``check``: the python-fcl verdict that decides collision-free.
- ``verdict``: the one success rule of every task (``Verdict``, ``judge``, ``judge_many``).
- ``_builders``: the bundled scenes and furniture meshes, as code.
"""

from ._builders import lattice_scene as lattice_scene
from ._builders import path_scene as path_scene
from ._builders import random_spheres_scene as random_spheres_scene
from ._builders import union_of_boxes as union_of_boxes
from .check import CheckManyResult as CheckManyResult
from .check import CheckResult as CheckResult
from .check import body_chain as body_chain
from .check import check as check
from .check import check_many as check_many
from .check import fcl_distance as fcl_distance
from .check import fcl_object as fcl_object
from .clearance import CasadiClearance as CasadiClearance
from .clearance import SceneArrays as SceneArrays
from .clearance import body_gap_tolerance as body_gap_tolerance
from .clearance import casadi_clearance as casadi_clearance
from .clearance import clearance as clearance
from .clearance import clearance_z as clearance_z
from .clearance import pair_distances as pair_distances
from .clearance import pair_distances_z as pair_distances_z
from .clearance import scene_arrays as scene_arrays
from .clearance import scene_digest as scene_digest
from .clearance import self_distances as self_distances
from .clearance import self_distances_z as self_distances_z
from .clearance import self_pairs as self_pairs
from .clearance import soft_clearance as soft_clearance
from .clearance import soft_clearance_z as soft_clearance_z
from .scene import PART_KINDS as PART_KINDS
from .scene import BoxPart as BoxPart
from .scene import CapsulePart as CapsulePart
from .scene import ConvexPart as ConvexPart
from .scene import CylinderPart as CylinderPart
from .scene import DecompositionSettings as DecompositionSettings
from .scene import Obstacle as Obstacle
from .scene import Part as Part
from .scene import Scene as Scene
from .scene import SpherePart as SpherePart
from .scene import bundled_scene_path as bundled_scene_path
from .scene import coacd_cache_dir as coacd_cache_dir
from .scene import coacd_cache_stats as coacd_cache_stats
from .scene import load_scene as load_scene
from .verdict import Verdict as Verdict
from .verdict import Verdicts as Verdicts
from .verdict import judge as judge
from .verdict import judge_many as judge_many

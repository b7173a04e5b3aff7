"""The names and sizes of the benchmark suites: what ``cr-nlp bench --help`` lists.

Kept apart from the suites' code (JAX, scipy, CasADi) so that building the command's
parser imports nothing heavy.
"""

from __future__ import annotations

from dataclasses import dataclass

# ================================================================ ik

IK_SUITES = ("free", "lattice", "scaling", "polish", "throughput")
"""Every IK suite (``cr-nlp bench ik --suite``)."""


@dataclass(frozen=True)
class IKBenchSizes:
    """How big each suite is."""

    free_targets: int = 1000
    """Targets of the obstacle-free tdcr3 suite."""
    lattice_targets: int = 100
    """Targets per robot in the lattice scene."""
    scaling_targets: int = 200
    """Targets per robot of the scaling suite."""
    scipy_targets: int = 50
    """The scipy baseline solves only the first this-many targets of each case (it takes
    0.1–0.6 s per target; with 100 the full run took 18 minutes on 2 busy cores)."""
    repeats: int = 3
    """Timed calls after the warm-up; the table reports their median."""
    throughput_targets: tuple[int, ...] = (1000, 10_000, 100_000)
    """Batch sizes of the throughput suite (tdcr3, no obstacles)."""


IK_FULL = IKBenchSizes()
IK_QUICK = IKBenchSizes(free_targets=50, lattice_targets=20, scaling_targets=20,
                        scipy_targets=10, repeats=1, throughput_targets=(100, 1000))

# ================================================================ plan

PLAN_SCENES = ("shelf", "cabinet", "random_27")
ROADMAP_OPT = "roadmap+opt"
STRAIGHT_OPT = "straight-line+opt"
RRT = "RRT-Connect"
EXACT = "roadmap+opt+exact"
PLAN_METHODS = (ROADMAP_OPT, STRAIGHT_OPT, RRT, EXACT)
"""The rows of every planning table, in order."""


@dataclass(frozen=True)
class PlanBenchSizes:
    """Problem counts of one benchmark run."""

    pairs_per_scene: int
    iteration_budgets: tuple[int, ...]
    sweep_pairs: int
    """Problems per scene of the iteration sweep (its first ones)."""


PLAN_FULL = PlanBenchSizes(pairs_per_scene=100, iteration_budgets=(0, 10, 25, 50, 100),
                           sweep_pairs=20)
PLAN_QUICK = PlanBenchSizes(pairs_per_scene=3, iteration_budgets=(0, 25), sweep_pairs=3)

# ================================================================ follow, statics, batch

FOLLOW_SHAPES = ("square", "sine", "icra")
FOLLOW_MODES = ("penalty", "exact")
STATICS_SETS = ("tensions", "mixed")
BATCH_MODES = ("penalty", "exact")
"""Penalty: the JAX stages only; exact: with the Ipopt polish of every answer."""

# ================================================================ startup

STARTUP_ENTRIES = ("import", "ik", "plan", "follow", "statics", "calibrate", "predict",
                   "demo", "ik-new", "plan-new")
"""The entry points that ``cr-nlp bench startup`` times as whole processes."""


# ================================================================ calibration

CALIBRATION_FAMILIES = ("pair12", "pair13", "pair23", "tendon", "seg")
"""The FTDCR v6 training file's pattern families, as its ``pattern_label`` column names them
(``cr-nlp bench calibration --families``)."""

"""The smoothest-sequence choice against brute force, and on real IK candidates."""

import itertools

import numpy as np

from cr_nlp.model import Robot, q_to_z
from cr_nlp.stages.sequence import smoothest_sequence
from cr_nlp.tasks.ik import IKSolver
from cr_nlp.tasks.paths import SHAPES

from .conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")


def brute_force(robot: Robot, cands: np.ndarray, usable: np.ndarray) -> float:
    z = np.asarray(q_to_z(robot, cands))
    best = np.inf
    for pick in itertools.product(range(cands.shape[1]), repeat=cands.shape[0]):
        if not all(usable[i, j] for i, j in enumerate(pick)):
            continue
        cost = sum(np.sum((z[i, pick[i]] - z[i - 1, pick[i - 1]]) ** 2)
                   for i in range(1, len(pick)))
        best = min(best, cost)
    return best


def test_matches_brute_force_on_random_candidate_sets() -> None:
    rng = np.random.default_rng(0)
    lo, hi = TDCR3.q_bounds()
    for _ in range(20):
        cands = rng.uniform(lo, hi, (5, 3, 9))
        errors = rng.uniform(0, 0.02, (5, 3))
        errors[:, 0] = 0.0  # every waypoint has a usable candidate
        pick = smoothest_sequence(TDCR3, cands, errors, 0.01)
        z = np.asarray(q_to_z(TDCR3, cands))
        chosen = sum(np.sum((z[i, pick[i]] - z[i - 1, pick[i - 1]]) ** 2) for i in range(1, 5))
        assert np.all(errors[np.arange(5), pick] < 0.01)
        np.testing.assert_allclose(chosen, brute_force(TDCR3, cands, errors < 0.01))


def test_a_waypoint_without_a_usable_candidate_keeps_its_best() -> None:
    cands = np.zeros((3, 2, 9)) + [0.1, 0, 1] * 3
    errors = np.array([[0.0, 0.0], [0.5, 0.2], [0.0, 0.0]])
    assert smoothest_sequence(TDCR3, cands, errors, 0.01)[1] == 1


def test_sequence_on_a_path_moves_less_than_the_best_per_waypoint() -> None:
    path = SHAPES["sine"](count=40)
    solver = IKSolver(TDCR3)
    cands, errors = solver.candidates(path.positions, path.wxyz)
    assert cands.shape == (40, solver.config.beam_width, 9)
    pick = smoothest_sequence(TDCR3, cands, errors, 0.01)
    z = np.asarray(q_to_z(TDCR3, cands))

    def motion(choice: np.ndarray) -> float:
        zs = z[np.arange(40), choice]
        return float(np.sum(np.diff(zs, axis=0) ** 2))

    greedy = np.argmin(errors, axis=1)
    assert np.all(errors[np.arange(40), pick] < 0.01)
    assert motion(pick) <= motion(greedy) + 1e-12

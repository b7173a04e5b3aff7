"""The smoothest-sequence choice (JAX, on the device) against a numpy Viterbi and brute
force, and on real IK candidates."""

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cr_nlp.model import Robot, q_to_z
from cr_nlp.stages.explore._sequence import smoothest_choice, smoothest_sequence
from cr_nlp.tasks.geometry.ik import IKSolver
from cr_nlp.tasks.paths import SHAPES

from ...conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")


def numpy_viterbi(z: np.ndarray, errors: np.ndarray, tolerance: float) -> np.ndarray:
    """The reference: the same dynamic programme in float64 numpy, a loop over waypoints
    (the library's implementation before it moved to the device)."""
    t, k, _ = z.shape
    usable = errors < tolerance
    none = ~usable.any(axis=1)
    usable[none, np.argmin(errors[none], axis=1)] = True
    node = np.where(usable, 0.0, np.inf)
    total = node[0].copy()
    back = np.zeros((t, k), dtype=int)
    for i in range(1, t):
        jump = np.sum((z[i][None, :, :] - z[i - 1][:, None, :]) ** 2, axis=-1)
        options = total[:, None] + jump
        back[i] = np.argmin(options, axis=0)
        total = options[back[i], np.arange(k)] + node[i]
    choice = np.empty(t, dtype=int)
    choice[-1] = int(np.argmin(total))
    for i in range(t - 1, 0, -1):
        choice[i - 1] = back[i, choice[i]]
    return choice


def sequence_cost(z: np.ndarray, choice: np.ndarray) -> float:
    """Σ of squared jumps of the chosen sequence."""
    picked = z[np.arange(len(choice)), choice]
    return float(np.sum(np.diff(picked, axis=0) ** 2))


@settings(max_examples=60, deadline=None)
@given(st.sampled_from([(1, 3), (2, 1), (7, 4), (12, 6)]), st.integers(0, 2**32 - 1),
       st.floats(0.0, 1.0), st.booleans())
def test_device_choice_matches_the_numpy_viterbi(shape: tuple[int, int], seed: int,
                                                 unusable_share: float,
                                                 repeats: bool) -> None:
    t, k = shape   # a few shapes: each one compiles the program once
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(t, k, 9))
    if repeats and k > 1:  # duplicated candidates: exact ties, broken by the lowest index
        z[:, -1] = z[:, 0]
    errors = rng.uniform(0.0, 0.02, (t, k))
    errors[rng.random((t, k)) < unusable_share] = np.inf   # empty slots
    errors[rng.random(t) < unusable_share, :] += 0.02       # waypoints with no usable one
    pick = np.asarray(smoothest_choice(z, errors, 0.01))
    reference = numpy_viterbi(z, errors, 0.01)
    # Same usable/unusable decision per waypoint, same cost; same picks up to ties.
    np.testing.assert_array_equal(errors[np.arange(t), pick] < 0.01,
                                  errors[np.arange(t), reference] < 0.01)
    np.testing.assert_allclose(sequence_cost(z, pick), sequence_cost(z, reference),
                               rtol=1e-12, atol=1e-12)
    if not repeats:
        np.testing.assert_array_equal(pick, reference)
    unusable = ~(errors < 0.01).any(axis=1)
    np.testing.assert_array_equal(pick[unusable], np.argmin(errors[unusable], axis=1))


def test_empty_slots_with_nan_configurations_are_never_chosen() -> None:
    rng = np.random.default_rng(1)
    z = rng.normal(size=(6, 4, 9))
    errors = rng.uniform(0.0, 0.005, (6, 4))
    z[:, 2], errors[:, 2] = np.nan, np.inf     # a diverged chain's slot
    pick = np.asarray(smoothest_choice(z, errors, 0.01))
    assert not np.any(pick == 2)
    np.testing.assert_array_equal(pick, numpy_viterbi(np.nan_to_num(z), errors, 0.01))


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

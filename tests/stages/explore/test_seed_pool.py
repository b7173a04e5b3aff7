"""The device explore stage against its host references: the JAX nearest-pose lookup
against scipy's cKDTree, the JAX beam selection against the numpy ``select_beam``, and a
large batch streamed through ``IKSolver.solve`` in bounded parts."""

import tracemalloc

import numpy as np
import pytest
from scipy.spatial import cKDTree

from cr_nlp.bench.ik import free_case
from cr_nlp.model import Robot, tip_pose
from cr_nlp.stages.explore._seed_pool import (
    SeedPool,
    pose_features,
    select_beam,
    select_beam_device,
    sobol_configurations,
)
from cr_nlp.tasks.geometry.ik import IKConfig, IKSolver, part_sizes

from ...conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")


def random_rotations(rng: np.random.Generator, count: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(count, 3, 3)))
    q *= np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    return q * np.sign(np.linalg.det(q))[:, None, None]


@pytest.fixture(scope="module")
def pool() -> SeedPool:
    # 1000 entries in blocks of 256: four blocks, the last one part padding.
    return SeedPool(TDCR3, sobol_configurations(TDCR3, 1000, seed=2), block=256, chunk_size=256)


@pytest.mark.parametrize("count, k", [(300, 12), (129, 40), (1, 1)])
def test_nearest_pose_lookup_picks_what_a_kd_tree_picks(pool: SeedPool, count: int, k: int) -> None:
    rng = np.random.default_rng(count)
    positions = rng.uniform(-2.5, 2.5, (count, 3))
    rotations = random_rotations(rng, count)
    picked = pool.nearest(positions, rotations, k)
    features = pose_features(positions, rotations)
    distance, expected = cKDTree(pool.features).query(features, k=k)
    distance, expected = distance.reshape(count, k), expected.reshape(count, k)
    assert picked.shape == (count, k)
    assert np.all((picked >= 0) & (picked < len(pool)))
    assert all(len(set(row)) == k for row in picked)  # no entry twice, no padding row
    mine = np.linalg.norm(pool.features[picked] - features[:, None, :], axis=-1)
    # Same picks up to ties: the same sorted distances (float32 features on the device).
    np.testing.assert_allclose(mine, distance, atol=2e-5)
    assert np.mean(picked == expected) > 0.99


def test_nearest_pose_lookup_finds_the_pool_entries_themselves(pool: SeedPool) -> None:
    position, rotation = (np.asarray(x) for x in tip_pose(TDCR3, pool.q[::37]))
    picked = pool.nearest(position, rotation, 3)
    np.testing.assert_array_equal(picked[:, 0], np.arange(0, len(pool), 37))


def test_nearest_pose_lookup_asks_for_at_most_the_pool(pool: SeedPool) -> None:
    rng = np.random.default_rng(0)
    picked = pool.nearest(rng.uniform(-1, 1, (5, 3)), random_rotations(rng, 5), 5000)
    assert picked.shape == (5, len(pool))
    assert all(sorted(row) == list(range(len(pool))) for row in picked)


@pytest.mark.parametrize("min_distance", [0.0, 0.5, 2.5, 3.2, 10.0])
@pytest.mark.parametrize("width", [1, 3, 5])
def test_device_beam_selection_picks_what_the_numpy_one_picks(
    min_distance: float, width: int
) -> None:
    rng = np.random.default_rng(width)
    z = rng.normal(size=(257, 12, 6))
    cost = rng.random((257, 12))
    expected = select_beam(z, cost, width, min_distance)
    picked = np.asarray(select_beam_device(z, cost, width, min_distance))
    np.testing.assert_array_equal(picked, expected)
    # Picked candidates (other than the repeated best) are min_distance apart.
    for row, zt in zip(picked, z, strict=True):
        distinct = list(dict.fromkeys(row))
        pairs = [
            np.linalg.norm(zt[a] - zt[b]) for i, a in enumerate(distinct) for b in distinct[i + 1 :]
        ]
        assert all(d > min_distance for d in pairs)


def test_device_beam_selection_with_tied_costs_keeps_a_lowest_cost_pick() -> None:
    rng = np.random.default_rng(4)
    z = rng.normal(size=(64, 8, 3))
    cost = np.round(rng.random((64, 8)), 1)  # many ties
    picked = np.asarray(select_beam_device(z, cost, 3, 0.3))
    expected = select_beam(z, cost, 3, 0.3)
    np.testing.assert_allclose(
        np.take_along_axis(cost, picked[:, :1], 1), np.take_along_axis(cost, expected[:, :1], 1)
    )
    assert np.all(picked >= 0) and np.all(picked < 8)


def targets(robot: Robot, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Tip poses of configurations drawn inside the limits whose segments keep the
    verdict's margin from each other (the benchmark's free targets)."""
    case = free_case(robot, count, seed)
    return case.positions, case.wxyz


def _streamed_peak(solver: IKSolver, positions: np.ndarray, wxyz: np.ndarray) -> tuple:
    tracemalloc.start()
    try:
        result = solver.solve(positions, wxyz)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return result, peak


def _stream_check(count: int, part: int) -> None:
    solver = IKSolver(TDCR3, config=IKConfig(stream_size=part))
    positions, wxyz = targets(TDCR3, count, seed=1)
    # Compiles every program the batch needs (the retries' fused search has its own shape,
    # which a part without failures never compiles) and builds the pool: compiling inside
    # a measured call would count the compiler's allocations as the stream's.
    solver.solve(positions, wxyz)
    search = solver._search
    programs = set(search.main.compiled) | set(search.repair.compiled)
    small, small_peak = _streamed_peak(solver, positions[:part], wxyz[:part])
    large, large_peak = _streamed_peak(solver, positions, wxyz)
    assert set(search.main.compiled) | set(search.repair.compiled) == programs
    assert solver.stream_parts == [part] * (count // part) + (
        [count % part] if count % part else []
    )
    # Fused search: a program holds at most ``chunk_size`` targets, each with its seeds.
    cfg = solver.config
    seeds = max(cfg.seeds_per_target, cfg.retry_seeds)
    assert max(call[1] for call in solver.lm_calls) <= cfg.chunk_size * seeds
    assert large.success.mean() >= 0.99
    np.testing.assert_array_equal(large.success[:part], small.success)
    # The large batch holds its answers (a few hundred bytes per target) and the float64
    # verification's temporaries over all of them, plus one part in flight: not
    # ``count / part`` times the memory of one part. Measured (20 000 targets, parts of
    # 2048, tracemalloc): whole batch 22.7 MB host-driven, 22.6 MB fused; one part 7.1
    # and 3.0 MB; answers 3.4 MB.
    answers = sum(v.nbytes for v in vars(large).values() if isinstance(v, np.ndarray))
    assert large_peak < 2.0 * small_peak + 6 * answers, (large_peak, small_peak, answers)


def test_a_batch_is_streamed_in_parts_without_growing_memory() -> None:
    _stream_check(count=1000, part=250)


@pytest.mark.slow  # a benchmark-sized run: `pytest -m slow`
def test_twenty_thousand_targets_stream_without_growing_memory() -> None:
    _stream_check(count=20_000, part=2048)


def test_part_sizes_follow_the_backend_unless_given() -> None:
    """Unset sizes are the backend's (an accelerator waits on each program's loops, so it
    takes one part of large programs); given ones are kept, and the solver uses them."""
    assert part_sizes(IKConfig(), "cpu") == (16384, 4096)
    assert part_sizes(IKConfig(), "gpu") == (131072, 16384)
    given = IKConfig(stream_size=500, large_chunk_size=2048)
    assert part_sizes(given, "gpu") == part_sizes(given, "cpu") == (500, 2048)
    solver = IKSolver(TDCR3, config=IKConfig(stream_size=700))
    assert (solver.stream_size, solver.large_chunk_size) == (700, 4096)  # on CI's CPU


@pytest.mark.parametrize("field", ["chunk_size", "stream_size"])
def test_part_sizes_below_one_are_refused(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        IKConfig(**{field: 0})

"""The batched IK search as the host drives it: seed pool, chunks of targets, the fused
device programs of ``stages.refine._ik_program``, the retry rounds and the self-clearance repair.

One part of a stream of targets is solved by

1. explore and search, one ``search_pooled`` program per chunk of targets
   (``ChunkRunner.search_pool``): the pool entries nearest each target in pose (the
   lookup of ``SeedPool.nearest``, on the device), coarse LM on every seed, a diverse
   beam, the refinement rounds (``search_targets``, which the self-repair runs on seeds
   it gives). The seeds never pass through the host (a separate lookup program used to
   send (T, k) indices back; the host gathered the (T, k, n) seeds, cast them and sent
   them out again); booked as refinement;
2. retry: every retry round of the targets whose best cost is still above the success
   level, as one ``retry_targets`` program per chunk (only when some target failed);
3. self-repair (without a scene only; the search then ran on the pose alone, because the
   self-clearance rows in every LM row made a free tdcr3 solve ~8× slower): the targets
   whose answer's segments at least two apart come closer than δ by ``world.check`` are
   searched again with the self-clearance rows, first from their own beam in a small
   chunk (the answer and its alternatives, a few LM rows), then, for those still
   rejected, by the retry program; a new answer replaces the old one where the verdict
   accepts it and not the old.

Chunks come from ``chunks.chunk_plan`` (two compiled shapes per program); padding
targets are masked out of every LM round. The self-repair runs on the few rows that need
it in chunks of ``REPAIR_CHUNK`` targets (one compiled shape; padding targets cost no
LM work), so a solve whose answers all keep δ launches nothing for it, and one with two
such answers does not pay for a 128-target chunk. The repair program is twice the main
search's size (its residual has the self-clearance rows) and few targets need it (3 of
1000 free tdcr3 targets), so a part of at least ``REPAIR_AHEAD`` targets starts compiling
it beside the main search (``_programs.compile_ahead``) rather than after it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from ..._programs import compile_ahead, compile_program
from ...model import Robot, q_to_z_numpy, z_to_q_numpy
from ...model.limits import clip_to_limits
from ...world import check_many
from ...world._verdict_program import answer_geometry
from .._chunks import SMALLEST_CHUNK, chunk_plan
from ..explore._seed_pool import SeedPool, random_configurations_z, sobol_configurations
from ._ik_program import RetryPlan, SearchPlan, retry_targets, search_pooled, search_targets
from ._lm import Projection, Residual

REPAIR_CHUNK = 16
"""Targets per self-repair program."""
REPAIR_AHEAD = 256
"""Targets in a part from which the self-repair program is compiled beside the main search
(on a 2-core CPU, tdcr3, empty caches: the two one after the other took 9.6 + 14.0 s;
measured 0.3 % of free targets need the repair, so a part this large needs it with
probability ≈ 1 − 0.997²⁵⁶ ≈ 0.5, and the compile runs on a core the main one leaves idle)."""
REPAIR_BLOCK = 32
"""LM rows per block of the self-repair programs on a CPU (a repair iterates tens of
rows, not the main search's thousands)."""


class Booking(Protocol):
    """Where the search books its seconds (``tasks._timing.StageTiming`` is one)."""

    compile: float
    explore: float
    refine: float
    verify: float


@dataclass
class SearchCounters:
    """What the last solve launched, for profiling (reset by ``IKSearch.reset``)."""

    lm_calls: list[tuple[int, int, int, int]] = field(default_factory=list)
    """Per round of a fused program that iterated any row: (rows iterated, rows of the
    chunk, iteration budget, most iterations run)."""
    retried: list[int] = field(default_factory=list)
    """Targets retried in each retry round (0 for a round that did not run)."""
    device_calls: int = 0
    """Compiled programs launched (lookups and fused searches): device round trips."""
    device_wait: float = 0.0
    """Seconds spent waiting for device results with no host work to overlap."""
    device_launch: float = 0.0
    """Seconds inside the calls that launch compiled programs (on a CPU, XLA may run
    the program there, e.g. one split over several host devices)."""
    self_repaired: int = 0
    """Targets whose first answer's segments came closer than δ and were searched again
    with the self-clearance rows."""


def _chunk_rows(x: np.ndarray, start: int, stop: int, size: int) -> np.ndarray:
    """Rows ``start:stop`` of x padded to ``size`` rows with copies of the first (a
    chunk of a compiled program's fixed batch shape)."""
    part = x[start:stop]
    pad = size - (stop - start)
    return np.concatenate([part, np.repeat(part[:1], pad, 0)]) if pad else part


class ChunkRunner:
    """Runs one problem's fused search programs (``stages.refine._ik_program``) over chunks of
    targets: one compiled program per program name and chunk shape, split over every
    JAX device.

    Args:
        residual, project: the problem, as for ``stages.refine._lm.lm_solve``.
        shared: pytree given whole to every residual (scene arrays, or None).
        free: (n,) 1.0 for the variables LM may move.
        dtype: JAX dtype of the real inputs.
        counters: where launches, waits and LM rounds are counted.
        chunk: (largest, smallest[, large]) targets per program (``chunk_plan``).
    """

    def __init__(self, residual: Residual, project: Projection, shared: Any, free: jax.Array,
                 dtype: Any, counters: SearchCounters,
                 chunk: tuple[int, int] | tuple[int, int, int | None]) -> None:
        self.residual, self.project = residual, project
        self.shared, self.free, self.dtype = shared, free, dtype
        self.counters = counters
        self.chunk = chunk
        self.compiled: dict[Any, Any] = {}

    def search(self, plan: SearchPlan, z_seeds: np.ndarray, positions: np.ndarray,
               rotations: np.ndarray, timing: Booking) -> tuple[np.ndarray, np.ndarray]:
        """Coarse LM on (T, K, n) seeds, a diverse beam, refinement: z (T, width, n) and
        cost ½‖r‖² (T, width), best first, as ``search_targets`` programs. Booked as
        refinement."""
        k = z_seeds.shape[1]
        search = partial(search_targets, self.residual, self.project, plan)
        z, cost, runs = self._run(("search", k, plan), search,
                                  (z_seeds, (positions, rotations.reshape(-1, 9))), 4, timing)
        for chunk, (_, _, counted, iterated) in runs:
            self._count_rounds(counted, iterated, chunk * k, plan.budgets)
        return z, cost

    def search_pool(self, plan: SearchPlan, pool: SeedPool, k: int, positions: np.ndarray,
                    rotations: np.ndarray, timing: Booking) -> tuple[np.ndarray, np.ndarray]:
        """``search`` from the ``k`` entries of ``pool`` nearest each target in pose, the
        lookup inside the same ``search_pooled`` programs (no seeds through the host).
        Booked as refinement."""
        search = partial(search_pooled, self.residual, self.project, plan, k)
        z, cost, runs = self._run(
            ("search", k, plan, "pool"), search,
            (pool.target_features(positions, rotations), (positions, rotations.reshape(-1, 9))),
            4, timing, pool.device_arrays(padded=True))
        for chunk, (_, _, counted, iterated) in runs:
            self._count_rounds(counted, iterated, chunk * k, plan.budgets)
        return z, cost

    def retry(self, plan: SearchPlan, retry: RetryPlan, sample: Callable, z_best: np.ndarray,
              cost: np.ndarray, positions: np.ndarray, rotations: np.ndarray,
              stream: np.ndarray, pool: SeedPool, timing: Booking) -> tuple[np.ndarray,
                                                                           np.ndarray]:
        """Every retry round of the targets given (best z (T, n), cost (T,)) as
        ``retry_targets`` programs: z (T, n), cost (T,). ``stream``: (T,) numbers keying
        each target's random seeds. Booked as refinement."""
        search = partial(retry_targets, self.residual, self.project, sample, plan, retry)
        z, cost, runs = self._run(
            ("retry", retry, plan), search,
            (z_best, cost, (positions, rotations.reshape(-1, 9)),
             pool.target_features(positions, rotations), stream.astype(np.int32)),
            5, timing, pool.device_arrays())
        counters = self.counters
        for chunk, (_, _, counted, iterated, retried) in runs:
            self._count_rounds(counted, iterated, chunk * retry.seeds,
                               plan.budgets * retry.rounds)
            counters.retried = [a + int(b) for a, b in
                                zip(counters.retried, np.asarray(retried).sum(0), strict=True)]
        return z, cost

    def search_ahead(self, plan: SearchPlan, seeds: int, chunk: int) -> None:
        """Start compiling the ``search`` program of ``chunk`` targets with ``seeds`` seeds
        each in the background (``_programs.compile_ahead``), unless compiled already."""
        key = ("search", seeds, plan, chunk)
        if key in self.compiled:
            return
        n = len(self.free)
        per_target = (np.zeros((chunk, seeds, n)), (np.zeros((chunk, 3)), np.zeros((chunk, 9))))
        compile_ahead(partial(search_targets, self.residual, self.project, plan),
                      self._chunk_args(per_target, 0, chunk, chunk, ()),
                      name="the IK search", batched=self._batched(per_target, ()), outputs=4,
                      by_shape=True)

    def _chunk_args(self, per_target: tuple, start: int, stop: int, chunk: int,
                    whole: tuple) -> tuple:
        """A program's arguments for targets ``start:stop`` padded to ``chunk`` (see
        ``_run``)."""
        padded = partial(_chunk_rows, start=start, stop=stop, size=chunk)
        # Cast on the host, then transfer: ``jnp.asarray`` of a float64 array converts on
        # the device, behind the chunks already launched (measured: 4.3 s of a 33 s solve
        # of 20 000 free tdcr3 targets on 2 CPU cores, the host blocked).
        # One transfer for every argument (one call per array cost ~0.1 s of host per
        # 100 000 targets).
        rows, mask = jax.device_put((jax.tree.map(lambda x: np.asarray(
            padded(x), self.dtype if x.dtype.kind == "f" else None), per_target),
            np.arange(chunk) < stop - start))
        return (*rows, mask, self.shared, self.free, *whole)

    @staticmethod
    def _batched(per_target: tuple, whole: tuple) -> tuple[bool, ...]:
        """Which of ``_chunk_args``'s arguments are split over the devices."""
        return (True,) * (len(per_target) + 1) + (False,) * (2 + len(whole))

    def _run(self, name: tuple, search: Any, per_target: tuple, outputs: int,
             timing: Booking, *whole: Any) -> tuple[np.ndarray, np.ndarray,
                                                     list[tuple[int, Any]]]:
        """Launch ``search`` over ``chunk_plan`` chunks of the targets: its arguments are
        the ``per_target`` arrays (pytrees of leading dimension T, padded per chunk; real
        numbers in ``dtype``), the valid-target mask, the shared arrays, the free-variable
        mask and ``whole``; its first two outputs are z and cost per target. Every chunk
        is dispatched before the first result is waited for. Returns z and cost of the T
        targets, and (chunk, outputs) per chunk, all ready."""
        t0 = time.perf_counter()
        c0 = timing.compile
        count = len(jax.tree.leaves(per_target)[0])
        runs = []
        start = 0
        for chunk in chunk_plan(count, *self.chunk):
            stop = min(start + chunk, count)
            args = self._chunk_args(per_target, start, stop, chunk, whole)
            key = (*name, chunk)
            if key not in self.compiled:
                t1 = time.perf_counter()
                self.compiled[key] = compile_program(search, args, name=f"the IK {name[0]}",
                                                     batched=self._batched(per_target, whole),
                                                     outputs=outputs, by_shape=True)
                timing.compile += time.perf_counter() - t1
            t1 = time.perf_counter()
            runs.append((stop - start, chunk, self.compiled[key](*args)))
            self.counters.device_launch += time.perf_counter() - t1
            self.counters.device_calls += 1
            start = stop
        wait(self.counters, (out for _, _, out in runs))
        z = np.concatenate([np.asarray(out[0])[:rows] for rows, _, out in runs])
        cost = np.concatenate([np.asarray(out[1])[:rows] for rows, _, out in runs])
        timing.refine += time.perf_counter() - t0 - (timing.compile - c0)
        return z, cost, [(chunk, out) for _, chunk, out in runs]

    def _count_rounds(self, counted: Any, iterated: Any, rows: int,
                      budgets: tuple[int, ...]) -> None:
        """One ``lm_calls`` entry per round of a fused program that iterated any row."""
        counted, iterated = np.asarray(counted).sum(0), np.asarray(iterated).max(0)
        self.counters.lm_calls += [(int(c), rows, b, int(i))
                                   for c, b, i in zip(counted, budgets, iterated, strict=True)
                                   if c]


def wait(counters: SearchCounters, arrays: Iterable[Any]) -> None:
    """Block until device results are ready, adding the wait to ``device_wait``."""
    t0 = time.perf_counter()
    jax.block_until_ready(list(arrays))
    counters.device_wait += time.perf_counter() - t0


@dataclass(frozen=True)
class SearchSettings:
    """The static settings of ``IKSearch`` (the IK task fills them from its config)."""

    plan: SearchPlan
    """The main search (``per_target`` True: only the best candidate is wanted)."""
    retry: RetryPlan
    """The retry rounds (``rounds`` 0: none)."""
    seeds_per_target: int
    """Pool entries nearest each target that start the coarse LM steps."""
    pool_size: int
    """Sobol configurations in the seed pool."""
    seed: int
    """Seed of the pool."""
    chunk_size: int
    """Most targets per fused program."""
    large_chunk_size: int | None
    """Targets per fused program of batches at least this large (``chunk_plan``'s
    ``large``)."""
    margin: float
    """δ on the sphere body (m): pool entries closer than this to an obstacle or to the
    robot itself are left out of the pool."""
    safety_margin: float
    """δ the verdict checks (m): answers whose segments come closer than this are
    repaired."""
    dtype: str = "float32"
    """JAX dtype of the batched stages."""


class IKSearch:
    """The batched search of one IK problem (robot, optional scene, residuals).

    Args:
        robot: the robot.
        scene: the ``Scene`` or None.
        shared: the scene's arrays for the residuals (``world.scene_arrays``) or None.
        residuals: the IK residual for the main search, and with the self-clearance rows
            (the same function when the main search models them already).
        project: the projection onto the limits (``model.limits.project_z``).
        free: (n,) 1.0 for the variables LM may move.
        settings: ``SearchSettings``.
        self_repair: repair answers whose segments come closer than δ (no scene, the main
            search on the pose alone).
    """

    def __init__(self, robot: Robot, scene: Any, shared: Any,
                 residuals: tuple[Residual, Residual], project: Projection, free: jax.Array,
                 settings: SearchSettings, self_repair: bool) -> None:
        self.robot, self.scene, self.settings = robot, scene, settings
        self.self_repair = self_repair
        self.dtype = jnp.dtype(settings.dtype)
        self.counters = SearchCounters()
        self.main = ChunkRunner(residuals[0], project, shared, free, self.dtype,
                                self.counters, (settings.chunk_size, SMALLEST_CHUNK,
                                                settings.large_chunk_size))
        self.repair = ChunkRunner(residuals[1], project, shared, free, self.dtype,
                                  self.counters, (REPAIR_CHUNK, REPAIR_CHUNK))
        self.pool: SeedPool | None = None
        self.sample = partial(random_configurations_z, robot, count=settings.retry.seeds,
                              dtype=self.dtype)

    def reset(self) -> None:
        """Zero the counters (start of a solve)."""
        self.counters.lm_calls = []
        self.counters.retried = [0] * self.settings.retry.rounds
        self.counters.device_calls = 0
        self.counters.device_wait = 0.0
        self.counters.device_launch = 0.0
        self.counters.self_repaired = 0

    # ------------------------------------------------------------ explore
    def seed_pool(self, timing: Booking) -> SeedPool:
        """The Sobol pool (built once; entries without δ of clearance left out)."""
        if self.pool is None:
            t0 = time.perf_counter()
            s = self.settings
            q = sobol_configurations(self.robot, s.pool_size, s.seed)
            if self.scene is not None or self.robot.has_self_pairs:
                q = q[self._collision_free(q)]
            self.pool = SeedPool(self.robot, q, dtype=s.dtype, chunk_size=s.chunk_size)
            timing.explore += time.perf_counter() - t0
        return self.pool

    def _collision_free(self, q: np.ndarray) -> np.ndarray:
        """Which configurations keep clearance ≥ δ (obstacles and self) by the
        differentiable clearance (fast)."""
        from ...world import clearance, self_distances

        x = jnp.asarray(q, self.dtype)
        if self.scene is None:
            d = np.min(np.asarray(self_distances(self.robot, x)), axis=-1)
        else:
            d = np.asarray(clearance(self.robot, self.main.shared, x))
        return d >= self.settings.margin

    # ------------------------------------------------------------ the search
    def beam(self, positions: np.ndarray, rotations: np.ndarray, per_target: bool,
             timing: Booking) -> tuple[np.ndarray, np.ndarray]:
        """Lookup and search, one program per chunk: the refined beam z (T, width, n), best
        first, and its cost ½‖r‖² (T, width). ``per_target``: a target's other candidates
        stop refining once one converged (only the best is wanted)."""
        pool = self.seed_pool(timing)
        k = min(self.settings.seeds_per_target, len(pool))
        plan = replace(self.settings.plan, per_target=per_target)
        if k == 0:  # no pool entry keeps clear of the scene: no seeds, as the lookup gave
            seeds = np.zeros((len(positions), 0, len(self.main.free)), self.main.dtype)
            return self.main.search(plan, seeds, positions, rotations, timing)
        return self.main.search_pool(plan, pool, k, positions, rotations, timing)

    def solve_part(self, positions: np.ndarray, rotations: np.ndarray, timing: Booking,
                   accepts: Callable[[np.ndarray, np.ndarray], np.ndarray]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Search, retry and self-repair one part of a stream (valid targets).

        Args:
            positions: (T, 3) target positions, m; rotations: (T, 3, 3).
            timing: where the seconds are booked.
            accepts: ``(q (B, 3n), rows (B,)) → (B,) bool``: the verdict on answers to
                the targets ``rows`` of this part (used by the self-repair).

        Returns:
            q (T, 3n) answers θ, φ, L (rad, rad, m) clipped to the limits; the refined
            beam (T, width, 3n) best first as bending vectors (ux, uy rad, L m; ``beam_q``
            makes them configurations, for the few targets that need them); and, with
            ``self_repair``, the answers'
            self-clearance (T,) by ``world.check`` (m) for the verdict to reuse (+inf
            without: not measured here).
        """
        s = self.settings
        if self.self_repair and len(positions) >= REPAIR_AHEAD:
            width = min(s.plan.width, s.seeds_per_target)
            self.repair.search_ahead(self._repair_plan(), width + 1, REPAIR_CHUNK)
        z_beam, c_beam = self.beam(positions, rotations, True, timing)
        z_best, cost = z_beam[:, 0].copy(), c_beam[:, 0].copy()
        todo = np.flatnonzero(~(cost < s.retry.success_cost))
        if s.retry.rounds > 0 and len(todo):
            # Every retry round in one more program, only when some target failed.
            pool = self.seed_pool(timing)
            z_best[todo], cost[todo] = self.main.retry(
                s.plan, self._retry_plan(pool), self.sample, z_best[todo], cost[todo],
                positions[todo], rotations[todo], todo, pool, timing)
        q = self._to_q(z_best)
        own = np.full(len(q), np.inf)
        if self.self_repair:
            t0 = time.perf_counter()
            own = answer_geometry(self.robot, q, positions, rotations, self.counters,
                                  pose=False).self_distance
            timing.verify += time.perf_counter() - t0
            self._repair(q, own, z_beam, positions, rotations, timing, accepts)
        return q, z_beam, own

    def _repair(self, q: np.ndarray, own: np.ndarray, z_beam: np.ndarray,
                positions: np.ndarray, rotations: np.ndarray, timing: Booking,
                accepts: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> None:
        """Search the targets whose answer's segments come closer than δ again, with the
        self-clearance rows; replace q (and ``own``) in place where the verdict accepts
        the new answer and not the old. First from each target's own beam (its answer
        first), then, for those still rejected, the retry program."""
        s = self.settings
        bad = np.flatnonzero(~(own >= s.safety_margin))
        if not len(bad):
            return
        self.counters.self_repaired += len(bad)
        t0 = time.perf_counter()
        before = accepts(q[bad], bad)
        timing.verify += time.perf_counter() - t0
        # The answer itself first, then its beam: all near the target in pose.
        seeds = np.concatenate([q_to_z_numpy(q[bad])[:, None], z_beam[bad]], axis=1)
        plan = self._repair_plan()
        z, cost = self.repair.search(plan, seeds, positions[bad], rotations[bad], timing)
        candidates = self._to_q(z[np.arange(len(bad)), np.argmin(cost, axis=1)])
        left = self._take(q, own, bad, candidates, before, accepts, timing)
        if s.retry.rounds > 0 and len(left):
            rows, pool = bad[left], self.seed_pool(timing)
            z_new, _ = self.repair.retry(
                plan, self._retry_plan(pool), self.sample, q_to_z_numpy(q[rows]),
                np.full(len(rows), np.inf), positions[rows], rotations[rows], rows, pool,
                timing)
            self._take(q, own, rows, self._to_q(z_new), before[left], accepts, timing)

    def _take(self, q: np.ndarray, own: np.ndarray, rows: np.ndarray, q_new: np.ndarray,
              before: np.ndarray, accepts: Callable[[np.ndarray, np.ndarray], np.ndarray],
              timing: Booking) -> np.ndarray:
        """Put q_new into q (and its self-clearance into ``own``) at ``rows`` where the
        verdict accepts it and not the answer there (``before``); returns the positions
        within ``rows`` still not accepted."""
        t0 = time.perf_counter()
        ok = accepts(q_new, rows)
        take = ok & ~before
        if take.any():
            q[rows[take]] = q_new[take]
            own[rows[take]] = check_many(self.robot, None, q_new[take]).self_distance
        timing.verify += time.perf_counter() - t0
        return np.flatnonzero(~(ok | before))

    def _retry_plan(self, pool: SeedPool) -> RetryPlan:
        """The retry rounds, past the pool ranks the main search used (the pool may hold
        fewer entries than seeds per target)."""
        return replace(self.settings.retry,
                       first_rank=min(self.settings.seeds_per_target, len(pool)))

    def _repair_plan(self) -> SearchPlan:
        """The search plan of the repair programs: LM blocks of a few rows on a CPU, the
        whole chunk on an accelerator (as the main search)."""
        block = self.settings.plan.block
        return replace(self.settings.plan, block=min(REPAIR_BLOCK, block)
                       if jax.default_backend() == "cpu" else block)

    def _to_q(self, z: np.ndarray) -> np.ndarray:
        return clip_to_limits(self.robot, z_to_q_numpy(z))

    def beam_q(self, z: np.ndarray) -> np.ndarray:
        """Beam members (…, n) as bending vectors (``solve_part``) → configurations θ, φ, L
        (…, 3n; rad, rad, m) clipped to the limits, NaN rows (no member) kept NaN."""
        z = np.asarray(z, dtype=float)
        with np.errstate(invalid="ignore"):
            q = self._to_q(z)
        return np.where(np.isnan(z).any(axis=-1, keepdims=True), np.nan, q)

    def candidates(self, positions: np.ndarray, rotations: np.ndarray,
                   timing: Booking) -> tuple[np.ndarray, np.ndarray]:
        """Every beam member refined: q (T, width, 3n) best first and the penalised
        residual norms (T, width)."""
        z, cost = self.beam(positions, rotations, False, timing)
        q = self._to_q(z.reshape(-1, z.shape[-1])).reshape(*z.shape[:2], -1)
        return q, np.sqrt(2.0 * cost)

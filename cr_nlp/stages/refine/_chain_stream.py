"""Batched LM over many chains of waypoints (trajectories): continuous batching in slots.

A batch of B chains, each (waypoints, d) flattened to (waypoints·d,), is solved in one of
two schedules:

- "slots" (banded structure only): a fixed number S of slots, one compiled program per S.
  Every device call loads waiting chains into the free slots, runs LM trips on the
  occupied ones (``stages.refine._banded_lm``'s trip, vmapped; a slot whose chain converged,
  stalled or used its iteration budget is masked) until fewer than a wanted number of
  slots are still running or ``trips`` trips were made, and returns; the host then
  retires the finished chains, refills their slots and launches the next call before it
  runs the caller's ``more`` on the retired ones (asynchronous dispatch: the host's work
  overlaps the device's). A draining stream moves to a program of fewer slots. The
  whole LM state (iterate, cost, normal equations, λ, ν, iteration count, pending trial
  point) stays on the device between calls, so a chain takes exactly the iterates it
  would take in one uninterrupted solve, and no slot waits for the slowest chain of a
  chunk. A caller can also add chains while the solve runs (``more``): the trajectory
  planner's second round of guesses goes into the same stream. With several JAX devices
  (a CPU process's host devices, or GPUs) each device is a lane with its own slots and
  programs, fed from the one queue of waiting chains; the host launches every idle
  lane's call before it waits for the oldest, so the lanes compute side by side (a slot
  program's small batch keeps one CPU core busy, not two).
- "chunks": the batch is cut into chunks of one size (the last padded with copies of its
  first row), one device program per chunk, each running until its slowest chain
  stops. The "dense" structure (``stages.refine._lm``: one Jacobian of the whole chain and a
  dense Cholesky of its (waypoints·d)² normal matrix; the reference the banded form is
  checked against) always runs so; the banded structure can, for comparison.

The residuals are the caller's (``ChainResidual`` window terms for "banded", one
function of the flat chain for "dense"); this module only batches, schedules, compiles
and counts.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..._programs import compile_ahead, compile_program
from ._banded_lm import (
    BandedLMState,
    ChainResidual,
    banded_lm_running,
    banded_lm_solve,
    banded_lm_start,
    banded_lm_trip,
)
from ._lm import LMConfig, lm_solve

MoreChains = Callable[[np.ndarray, np.ndarray, np.ndarray],
                      tuple[np.ndarray, np.ndarray] | None]
"""``more(finished, z, cost)``: called after every device call with the indices of the
chains that finished in it, their z (k, waypoints·d) and costs (k,) (float64); returns
new chains to solve as (z0 (m, waypoints·d), step (m,)), or None. New chains get the
next indices (B, B + 1, …) in order."""


@dataclass
class ChainSolution:
    """What ``ChainBatchLM.solve`` returns for B chains (float64 numpy)."""

    z: np.ndarray
    """(B, waypoints·d): the answers."""
    cost: np.ndarray
    """(B,): final costs ½‖r‖²."""
    iterations: np.ndarray
    """(B,): LM iterations used per chain (-1 where the schedule does not count them:
    the dense structure counts per chunk)."""
    compile: float
    """Seconds spent compiling programs for new slot counts or chunk sizes."""
    callback: float
    """Seconds spent in the caller's ``more`` (counted neither as LM nor as compiling;
    with slots it runs while the next device call computes, so the LM's own time is the
    rest of the wall time)."""


class ChainBatchLM:
    """LM on batches of chains (waypoints, d) with a per-chain scalar (a time step, s).

    Args:
        terms: the window residual terms of one chain (banded structure).
        project: feasibility projection of one chain (waypoints, d) (hashable).
        waypoints: chain length.
        free: (waypoints·d,) 1.0 for the variables the solver may move, 0.0 for fixed.
        dtype: the device dtype.
        chunk_size: most chains per compiled call (slots, or chunk size).
        structure: "banded" or "dense".
        dense_residual: ``(z (waypoints·d,), step, arrays) → r``, the whole chain's
            residual (needed for "dense").
        dense_project: projection of a (B, waypoints·d) batch (needed for "dense").
        extra: unbatched data passed to every term besides the scene arrays and the
            per-chain scalar (e.g. a broad phase), as the banded terms' ``shared`` =
            (arrays, extra, step).
        schedule: "slots" (continuous batching; banded only) or "chunks".
        trips: slots: most LM trips per device call.
        refill: slots: a call returns once this many slots are free (or fewer, if fewer
            chains wait) and chains wait for them; while none wait, it runs until every
            slot is done or ``trips`` trips were made. Simulated with the iteration counts
            measured on 40 shelf trajectories, 8 slots: returning at the first free slot
            makes the least device work (1168 slot-trips in 30 calls; ``refill=4``: 1336
            in 9), and a call costs far less than a trip, so ``trips`` need not cap it.
        resize: slots: once the running and waiting chains fit in half the slots, move
            them to a program of fewer slots (powers of two, at least 2; each compiled on
            first use), and back to more (up to ``chunk_size``) when chains are added. A
            trip's cost grows about linearly with its slots, idle ones included (tdcr3
            shelf trajectories, 2-core CPU: 1.5, 2.9, 5.2 ms for 1, 2, 4 slots). The
            first stream of this object moves down only to programs it has already: the
            tail of a one-shot ``cr-nlp plan`` (20 shelf problems) saved 0.16 s of 0.86
            by fewer slots and cost ~25 s to compile them (two lanes, empty cache; ~1 s
            to load them from a warm one). From its second stream on (a process that
            plans again), it compiles them when the stream drains.
        overlap: slots: run ``more`` on a call's finished chains while the next call
            computes (False: before it, the former order; kept for comparison).
        lanes: slots: most JAX devices that run slot programs side by side (None: as
            many as have 2 of the ``chunk_size`` slots each; a CPU process's host devices,
            ``use_host_devices``, or the GPUs), each with its own slots (``chunk_size``
            split between them) fed from one queue of waiting chains. A slot program runs
            its small batch on one core, so on a 2-core CPU two lanes use both. Each lane
            compiles its own programs (XLA's CPU cache keys on the device): measured on
            the shelf with an empty cache, 2 lanes compiled 4 programs in 161 s where one
            lane compiled 3 in 130 s (2-core CPU under load 3).
        config: the banded LM's stopping rules (default: ``LMConfig(cost_tolerance=0)``,
            no cost floor: a chain stops when it stalls).
    """

    def __init__(self, terms: ChainResidual, project: Callable[[jax.Array], jax.Array],
                 waypoints: int, free: jax.Array, dtype: Any, chunk_size: int,
                 structure: str = "banded", dense_residual: Callable | None = None,
                 dense_project: Callable | None = None, extra: Any = None,
                 schedule: str = "slots", trips: int = 1 << 30, refill: int = 1,
                 resize: bool = True, overlap: bool = True, lanes: int | None = None,
                 config: LMConfig | None = None) -> None:
        if structure not in ("banded", "dense"):
            raise ValueError(f"structure must be 'banded' or 'dense', got {structure!r}")
        if structure == "dense" and (dense_residual is None or dense_project is None):
            raise ValueError("the dense structure needs dense_residual and dense_project")
        if schedule not in ("slots", "chunks"):
            raise ValueError(f"schedule must be 'slots' or 'chunks', got {schedule!r}")
        if lanes is not None and lanes < 1:
            raise ValueError(f"lanes must be ≥ 1 or None, got {lanes}")
        if chunk_size < 1 or trips < 1 or refill < 1:
            raise ValueError(f"chunk_size, trips and refill must be ≥ 1, got {chunk_size}, "
                             f"{trips}, {refill}")
        self.terms, self.project = terms, project
        self.waypoints, self.free, self.dtype = waypoints, free, dtype
        self.chunk_size, self.structure = chunk_size, structure
        self.dense_residual, self.dense_project, self.extra = (dense_residual, dense_project,
                                                               extra)
        self.schedule = "chunks" if structure == "dense" else schedule
        self.trips, self.refill, self.resize, self.overlap = trips, refill, resize, overlap
        self.config = LMConfig(cost_tolerance=0.0) if config is None else config
        """The banded LM's stopping rules."""
        self.devices = jax.devices()[:lanes or max(1, chunk_size // 2)]
        """The devices of the slot schedule's lanes."""
        self.lane_slots = max(2, chunk_size // len(self.devices))
        """Most slots of one lane."""
        self._compiled: dict[int, Any] = {}
        self._slot_programs: dict[tuple[int, int], Any] = {}
        self._idle_shapes: dict[int, Any] = {}
        self.programs = 0
        """Device programs launched so far (one per chunk or slot call)."""
        self.streams = 0
        """Streams solved so far with the slot schedule (``resize``)."""
        self.slot_trips = 0
        """LM trips made so far times the slots (chunk rows) they ran on: the device work,
        idle slots included (a trip of one chain is one evaluation and one step)."""

    def _size(self, count: int, compiled: dict[int, Any]) -> int:
        """Chunk size for ``count`` chains: the smallest power of two (≥ the device count)
        that holds them, at most ``chunk_size``, and no smaller than a size already
        compiled (one program serves every later batch)."""
        return max(self._fitting(count, max(2, len(jax.devices())), self.chunk_size),
                   min(compiled, default=0))

    def solve(self, z0: np.ndarray, step: np.ndarray, arrays: Any, iterations: int,
              more: MoreChains | None = None) -> ChainSolution:
        """LM on (B, waypoints·d) chains z0 with per-chain scalars ``step`` (B,), at most
        ``iterations`` iterations each; ``more`` may add chains as others finish
        (``MoreChains``; the "chunks" schedule calls it once all given chains are done)."""
        z0 = np.asarray(z0, dtype=np.float64)
        step = np.asarray(step, dtype=np.float64)
        if self.schedule == "slots":
            return self._solve_slots(z0, step, arrays, iterations, more)
        z_all, cost_all, it_all = [], [], []
        compile_seconds = callback = 0.0
        while len(z0):
            z, cost, its, compiled = self._solve_chunks(z0, step, arrays, iterations)
            z_all.append(z)
            cost_all.append(cost)
            it_all.append(its)
            compile_seconds += compiled
            z0 = np.zeros((0, z0.shape[1]))
            if more is not None:
                t0 = time.perf_counter()
                start = sum(len(c) for c in cost_all) - len(cost)
                added = more(start + np.arange(len(cost)), z, cost)
                callback += time.perf_counter() - t0
                if added is not None:
                    z0, step = (np.asarray(x, dtype=np.float64) for x in added)
        return ChainSolution(np.concatenate(z_all), np.concatenate(cost_all),
                             np.concatenate(it_all), compile_seconds, callback)

    # ------------------------------------------------------------ slots
    def compile_ahead(self, chains: int, arrays: Any) -> None:
        """Start compiling, in the background, the slot program a stream of ``chains``
        chains (at most) will first run, for each lane's device: the caller's host work
        (a roadmap) then overlaps XLA's. Compiled, the first device's copy is moved to
        the others (``_programs``); loaded from XLA's cache, each device loads its own,
        side by side (a warm ``cr-nlp plan``: both copies ready 0.6 s sooner). Only for
        the slot schedule; nothing when that program is compiled already. A stream that
        starts with fewer chains may want a smaller program: this one is then not used
        in this process, but stored for later ones."""
        if self.schedule != "slots" or self.structure != "banded" or chains < 1:
            return
        slots = self._first_slots(chains)
        for device in self.devices:
            if (device.id, slots) in self._slot_programs:
                continue
            lane = _Lane(device, slots, self, arrays)
            self._compile_slots(self._slot_args(lane, np.zeros((slots, np.size(self.free))),
                                                np.zeros(slots, bool), 1, placed=True),
                                ahead=True)

    def _first_slots(self, chains: int) -> int:
        """Slots per lane when a stream of ``chains`` chains starts: the fitting size for
        a lane's share, no smaller than a slot program compiled already."""
        share = -(-chains // len(self.devices))
        return max(self._fitting(share),
                   min((slots for _, slots in self._slot_programs), default=0))

    def _slot_args(self, lane: _Lane, z_new: np.ndarray, load: np.ndarray,
                   wanted: int, placed: bool = False) -> tuple:
        """The slot program's arguments for ``lane``'s next call: its state on its device
        and the chains loaded into it (``z_new`` where ``load``), then the scene arrays,
        the free mask, the trip budget and how many running slots end the call.
        ``placed``: the new chains on the lane's device too, as a compile needs them (it
        reads the device from them); a call moves numpy itself (4 arrays: 49 against 153
        µs with ``jax.device_put`` first)."""
        state = lane.state
        if not isinstance(state.z, jax.Array):      # idle or moved slots: numpy
            state = jax.device_put(state, lane.device)
        # (The state of the lane's last call is on its device already: moving it again
        # took half of this call's 0.2 ms.)
        args = (z_new.astype(self.dtype), load, lane.slot_step.astype(self.dtype),
                lane.budget)
        if placed:
            args = jax.device_put(args, lane.device)
        return (state, *args, lane.arrays, lane.extra, lane.free, np.int32(self.trips),
                np.int32(wanted))

    def _solve_slots(self, z0: np.ndarray, step: np.ndarray, arrays: Any, iterations: int,
                     more: MoreChains | None) -> ChainSolution:
        self.streams += 1
        width = z0.shape[1]
        z_list, step_list = list(z0), list(step)
        out_z: dict[int, np.ndarray] = {}
        out_cost: dict[int, float] = {}
        out_it: dict[int, int] = {}
        waiting = deque(range(len(z0)))
        slots = self._first_slots(len(z0))
        lanes = [_Lane(device, slots, self, arrays) for device in self.devices]
        in_flight: deque[_Lane] = deque()               # oldest call first
        compile_seconds = callback = 0.0
        # Chains finished in the last call whose ``more`` has not run yet: it runs while
        # the other calls compute (the caller's verdict on the host, the LM on the
        # devices), so chains it adds join one call later. Each chain's iterates are
        # unchanged.
        pending: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

        def run_more(finished: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
            t0 = time.perf_counter()
            added = more(*finished) if more is not None else None
            if added is not None:
                for z_add, step_add in zip(*added, strict=True):
                    waiting.append(len(z_list))
                    z_list.append(np.asarray(z_add, dtype=np.float64))
                    step_list.append(float(step_add))
            return time.perf_counter() - t0

        while True:
            for lane in lanes:
                if lane.out is None:
                    compile_seconds += self._launch(lane, waiting, z_list, step_list,
                                                    iterations, pending is not None)
                    if lane.out is not None:
                        in_flight.append(lane)
            if pending is not None:
                callback += run_more(pending)      # overlaps the calls in flight, if any
                pending = None
                continue                           # idle lanes take the added chains
            if not in_flight:
                break
            finished = self._retire(in_flight.popleft(), out_z, out_cost, out_it)
            if more is not None and finished is not None:
                pending = finished
                if not self.overlap:
                    callback += run_more(pending)
                    pending = None
        order = range(len(z_list))
        return ChainSolution(np.array([out_z[k] for k in order]).reshape(len(z_list), width),
                             np.array([out_cost[k] for k in order]),
                             np.array([out_it[k] for k in order], dtype=int),
                             compile_seconds, callback)

    def _launch(self, lane: _Lane, waiting: deque, z_list: list, step_list: list,
                iterations: int, more_pending: bool) -> float:
        """Load waiting chains into the lane's free slots and start its next call
        (asynchronous; ``lane.out``), unless no slot is occupied. Returns the seconds
        spent compiling."""
        # Fewer chains than half the slots (the stream draining), or more than the slots
        # while a larger program is allowed: move the running chains' states into a
        # program of the fitting size (a trip's cost grows with its slots, idle ones
        # included). The states move whole, so the iterates are unchanged.
        need = int(np.sum(lane.chain >= 0)) + len(waiting)
        size = self._fitting(need) if self.resize else lane.slots
        shrink = size < lane.slots and 2 * need <= lane.slots and (
            self.streams > 1 or (lane.device.id, size) in self._slot_programs)
        if need and (shrink or size > lane.slots):
            keep = np.flatnonzero(lane.chain >= 0)
            lane.state = self._moved(lane.state, keep, size)
            lane.chain, lane.budget, lane.slot_step = (
                np.concatenate([x[keep], np.full(size - len(keep), fill, x.dtype)])
                for x, fill in ((lane.chain, -1), (lane.budget, -1), (lane.slot_step, 0.0)))
            lane.slots = size
        load = np.zeros(lane.slots, bool)
        z_new = np.zeros((lane.slots, len(z_list[0]) if z_list else 0))
        for s in np.flatnonzero(lane.chain < 0):
            if not waiting:
                break
            k = waiting.popleft()
            lane.chain[s], load[s], z_new[s] = k, True, z_list[k]
            lane.slot_step[s], lane.budget[s] = step_list[k], iterations
        occupied = int(np.sum(lane.chain >= 0))
        if not occupied:
            return 0.0
        if waiting:
            wanted = max(lane.slots - min(self.refill, len(waiting)) + 1, 1)
        elif more_pending:
            wanted = occupied      # return at the first finish: more may add chains
        else:
            wanted = 1
        key = (lane.device.id, lane.slots)
        seconds = 0.0
        if key not in self._slot_programs:
            args = self._slot_args(lane, z_new, load, wanted, placed=True)
            t0 = time.perf_counter()
            # XLA's CPU programs are bound to a device, so each lane has its own copy of
            # a slot program: the other lanes' copies compile side by side with this one.
            for device in self.devices:
                if (device.id, lane.slots) not in self._slot_programs and device != lane.device:
                    self._compile_slots((*jax.device_put(args[:8], device), *args[8:]),
                                        ahead=True)
            self._slot_programs[key] = self._compile_slots(args)
            seconds = time.perf_counter() - t0
        else:
            args = self._slot_args(lane, z_new, load, wanted)
        lane.out = self._slot_programs[key](*args)          # asynchronous
        self.programs += 1
        return seconds

    def _retire(self, lane: _Lane, out_z: dict, out_cost: dict,
                out_it: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Wait for the lane's call, store its finished chains' answers and free their
        slots; returns (chain indices, z, cost) of those chains, or None if none
        finished."""
        lane.state, report = lane.out
        lane.out = None
        report = np.asarray(report, dtype=np.float64)        # ``_report``'s columns
        self.slot_trips += lane.slots * int(report[0, -1])
        finished = np.flatnonzero((lane.chain >= 0) & (report[:, -2] == 0.0))
        if not len(finished):
            return None
        z_done = report[finished, :-4]
        cost_done = report[finished, -4]
        it_done = report[finished, -3].astype(np.int64)
        indices = lane.chain[finished].copy()
        for k, s in enumerate(finished):
            out_z[lane.chain[s]], out_cost[lane.chain[s]] = z_done[k], cost_done[k]
            out_it[lane.chain[s]] = it_done[k]
            lane.chain[s], lane.budget[s] = -1, -1
        return indices, z_done, cost_done

    def _fitting(self, count: int, least: int = 2, most: int | None = None) -> int:
        """Slots for ``count`` running or waiting chains: the smallest power of two (at
        least ``least``) that holds them, at most ``most`` (default: a lane's slots; need
        not be a power of two)."""
        most = self.lane_slots if most is None else most
        size = least
        while size < min(count, most):
            size *= 2
        return min(size, most)

    def _moved(self, state: BandedLMState, keep: np.ndarray, slots: int) -> BandedLMState:
        """The LM states of the slots ``keep`` (in order) in the first rows of a state of
        ``slots`` slots, the other rows idle (numpy)."""
        idle = self._idle_state(slots)
        return jax.tree_util.tree_map(
            lambda x, y: np.concatenate([np.asarray(x)[keep], y[len(keep):]]), state, idle)

    def _idle_state(self, slots: int) -> BandedLMState:
        """The LM state of ``slots`` empty slots (numpy; every field zero, iteration −1):
        the program loads a chain into a slot before it runs."""
        if slots not in self._idle_shapes:      # traced once per slot count
            n = self.waypoints
            d = int(np.size(self.free)) // n
            self._idle_shapes[slots] = jax.eval_shape(
                jax.vmap(partial(banded_lm_start, self.project, config=self.config)),
                jax.ShapeDtypeStruct((slots, n, d), self.dtype))
        state = jax.tree_util.tree_map(lambda x: np.zeros(x.shape, x.dtype),
                                       self._idle_shapes[slots])
        return state._replace(iteration=np.full(slots, -1, np.int32))

    def _compile_slots(self, args: tuple, ahead: bool = False) -> Any:
        """The slot program: load chains, then LM trips on the occupied slots until fewer
        than ``wanted`` run or ``trips`` were made; returns the state and ``_report``
        (each slot's answer, whether it still runs, the trips made). One device (see
        ``_compile_chunk``). ``ahead``: start compiling it in the background
        (``_programs.compile_ahead``), return None."""
        advance = partial(_advance, self.terms, self.project, self.waypoints, self.config)
        return (compile_ahead if ahead else compile_program)(
            advance, args, name="the trajectory LM", by_shape=True)

    # ------------------------------------------------------------ chunks
    def _solve_chunks(self, z0: np.ndarray, step: np.ndarray, arrays: Any,
                      iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Every chunk run until its slowest chain stops: z, cost, iterations (-1 for the
        dense structure), compile seconds."""
        chunk = self._size(len(z0), self._compiled)
        z_out, cost_out, it_out, compile_seconds = [], [], [], 0.0
        for start in range(0, len(z0), chunk):
            stop = min(start + chunk, len(z0))
            pad = chunk - (stop - start)

            def padded(x: np.ndarray, start: int = start, stop: int = stop,
                       pad: int = pad) -> np.ndarray:
                part = x[start:stop]
                return np.concatenate([part, np.repeat(part[:1], pad, 0)]) if pad else part

            args = (jnp.asarray(padded(z0), self.dtype), jnp.asarray(padded(step), self.dtype),
                    arrays, self.free, jnp.int32(iterations))
            if chunk not in self._compiled:
                t0 = time.perf_counter()
                self._compiled[chunk] = self._compile_chunk(args)
                compile_seconds += time.perf_counter() - t0
            z, cost, its = self._compiled[chunk](*args)
            self.programs += 1
            self.slot_trips += chunk * (int(np.max(its)) + 1)     # dense: unknown (0)
            z_out.append(np.array(z[: stop - start], dtype=np.float64))
            cost_out.append(np.array(cost[: stop - start], dtype=np.float64))
            it_out.append(np.array(its[: stop - start], dtype=int))
        return (np.concatenate(z_out), np.concatenate(cost_out), np.concatenate(it_out),
                compile_seconds)

    def _compile_chunk(self, args: tuple) -> Any:
        """The LM program for one chunk, on one device. Unlike IK it is not split with
        ``shard_map`` over host devices: measured with jax 0.10 on 2 CPU host devices,
        the sharded program of a 16-trajectory chunk never returned (every thread waiting
        on a futex), while the same program unsharded, where XLA's own thread pool
        parallelises the large JᵀJ products, runs normally."""
        if self.structure == "dense":
            config = LMConfig(cost_tolerance=0.0, linear_solver="cholesky")
            solve = partial(lm_solve, self.dense_residual, self.dense_project, config=config)
            # The dense LM counts iterations per chunk (its loop stops for all at once).
            return compile_program(lambda *a: (*solve(*a)[:2], jnp.full(len(a[0]), -1)), args,
                                   name="the trajectory LM (dense)")
        n = self.waypoints
        one = partial(banded_lm_solve, self.terms, self.project, config=self.config)
        extra = self.extra

        def solve_chunk(z0: jax.Array, step: jax.Array, arrays: Any, free: jax.Array,
                        iterations: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
            def single(z: jax.Array, h: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
                out, cost, it = one(z.reshape(n, -1), None, (arrays, extra, h),
                                    free.reshape(n, -1), iterations)
                return out.reshape(-1), cost, it

            return jax.vmap(single)(z0, step)

        return compile_program(solve_chunk, args, name="the trajectory LM")


class _Lane:
    """One device's share of the slot schedule: its slots, their chains and LM state,
    the scene arrays on that device, and the call in flight (``out``)."""

    def __init__(self, device: Any, slots: int, lm: ChainBatchLM, arrays: Any) -> None:
        self.device, self.slots = device, slots
        self.chain = np.full(slots, -1)                 # the chain in each slot, -1: none
        self.budget = np.full(slots, -1, np.int32)      # -1: the slot does not run
        self.slot_step = np.zeros(slots)
        self.state: Any = lm._idle_state(slots)
        self.arrays, self.extra, self.free = jax.device_put((arrays, lm.extra, lm.free),
                                                            device)
        self.out: Any = None


def _advance(terms: ChainResidual, project: Callable, n: int, config: LMConfig,
             state: BandedLMState, z_new: jax.Array, load: jax.Array, step: jax.Array,
             budget: jax.Array, arrays: Any, extra: Any, free: jax.Array, trips: jax.Array,
             wanted: jax.Array) -> tuple[BandedLMState, jax.Array]:
    """The slot program (``ChainBatchLM._compile_slots``) of chains of n waypoints: the
    problem (``terms``, ``project``) and LM settings first, as partial arguments (its
    robot is data: ``compile_program``'s ``by_shape``); ``extra`` (the scene's broad
    phase) is an argument too, so a robot of the same shape shares the program."""
    def select(mask: jax.Array, a: Any, b: Any) -> Any:
        return jax.tree_util.tree_map(
            lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y),
            a, b)

    fresh = jax.vmap(partial(banded_lm_start, project, config=config))(
        z_new.reshape(len(z_new), n, -1))
    state = select(load, fresh, state)
    running = jax.vmap(partial(banded_lm_running, config=config))

    def trip(one: BandedLMState, h: jax.Array) -> BandedLMState:
        return banded_lm_trip(terms, project, one, None, (arrays, extra, h),
                              free.reshape(n, -1), config)

    def more(carry: tuple) -> jax.Array:
        state, count = carry
        return (count < trips) & (jnp.sum(running(state, budget)) >= wanted)

    def body(carry: tuple) -> tuple:
        state, count = carry
        moving = running(state, budget)
        return select(moving, jax.vmap(trip)(state, step), state), count + 1

    state, count = jax.lax.while_loop(more, body, (state, jnp.int32(0)))
    return state, _report(state, running(state, budget), count)


def _report(state: BandedLMState, running: jax.Array, count: jax.Array) -> jax.Array:
    """What the host reads of a slot call, as one array (reading each of five small ones
    cost ~25 µs): (slots, width + 4) in z's dtype, per slot its z, cost, iteration
    (exact: fewer than 2²⁴), whether it still runs (1 or 0) and the call's trip count."""
    z = state.z.reshape(len(state.z), -1)
    columns = (state.cost, state.iteration, running, jnp.broadcast_to(count, running.shape))
    return jnp.concatenate([z, jnp.stack([c.astype(z.dtype) for c in columns], axis=1)],
                           axis=1)

"""The host side of the IK search (``stages.refine._ik_driver``): the self-clearance repair runs
only on the answers that need it, in a small chunk, from their own beam first."""

import numpy as np
import pytest

from cr_nlp.bench.ik import free_case
from cr_nlp.stages.refine._ik_driver import REPAIR_CHUNK, ChunkRunner
from cr_nlp.tasks.geometry.ik import IKSolver

from ...tasks.geometry.test_ik import TDCR3
from ...world.test_verdict import fcl_self_clearance


def _first_answers_that_overlap(case, limit: int = 1000, part: int = 250) -> list[int]:
    """Rows of the free benchmark whose first answers' segments overlap (the solver repairs
    them), in the first ``limit``: which rows do depends on the CPU's floating point and
    XLA's settings (41 and 418 on one machine, 405 on another with the tests' XLA flags),
    so the test finds them on the machine it runs on."""
    solver = IKSolver(TDCR3)
    for start in range(0, limit, part):
        rows = np.arange(start, start + part)
        solver.solve(case.positions[rows], case.wxyz[rows])
        if solver.self_repaired:
            found = []
            for i in rows.tolist():
                solver.solve(case.positions[[i]], case.wxyz[[i]])
                if solver.self_repaired:
                    found.append(i)
            if found:
                return found[:2]
    return []


def test_self_colliding_free_answers_are_repaired_in_a_small_chunk() -> None:
    """Free targets (reachable without self-collision: forward kinematics of
    configurations that keep δ) whose first answers' segments overlap (found on this
    machine, ``_first_answers_that_overlap``), between targets 0 and 1, which need no
    repair. The repair searches only the answers that need it, in a repair chunk (its
    padding targets never iterate), and the answers pass python-fcl's self-distance."""
    case = free_case(TDCR3, 1000, seed=0)
    overlap = _first_answers_that_overlap(case)
    assert overlap, "no free target of the first 1000 needed the repair on this machine"
    rows = [0, overlap[0], 1, *overlap[1:]]
    solver = IKSolver(TDCR3)
    result = solver.solve(case.positions[rows], case.wxyz[rows])
    assert result.success.all(), result.reason
    repaired = solver.self_repaired
    assert 1 <= repaired <= 2
    own = fcl_self_clearance(TDCR3, result.q)
    assert np.all(own >= solver.config.safety_margin - 1e-6), own
    # The search with its seed lookup, one repair program from the answers' own beams
    # (their answer and its three beam candidates: 4 seeds), no retry program: 2 device
    # calls; the repair's
    # coarse round iterated 4 rows per repaired target in a REPAIR_CHUNK-target chunk,
    # not 32 seeds per target in a 128-target chunk.
    assert solver.device_calls == 2
    repair = [call for call in solver.lm_calls if call[1] == REPAIR_CHUNK * 4]
    assert repair and repair[0][0] == repaired * 4, solver.lm_calls
    # The verdict reused the repair's self-clearance: it equals world.check's own.
    checked = solver.verify(result.q, case.positions[rows], case.wxyz[rows])
    np.testing.assert_allclose(result.min_clearance, checked.clearance, atol=1e-12)


@pytest.mark.slow  # compiles the repair's retry program (~15 s on 2 cores): -m slow
def test_answers_the_beam_cannot_repair_go_to_the_retry_program(monkeypatch) -> None:
    """When the search from the answers' own beams comes back unrepaired (here: made to
    return its seeds), the retry program with the self-clearance rows races those
    targets again; the answers still pass python-fcl's self-distance."""
    case = free_case(TDCR3, 1000, seed=0)
    rows = [41, 418]
    solver = IKSolver(TDCR3)
    real = ChunkRunner.search

    def unrepaired(runner, plan, z_seeds, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003
        if runner is not solver._search.repair:
            return real(runner, plan, z_seeds, *args, **kwargs)
        return z_seeds[:, :plan.width], np.full(z_seeds.shape[:1] + (plan.width,), np.inf)

    monkeypatch.setattr(ChunkRunner, "search", unrepaired)
    result = solver.solve(case.positions[rows], case.wxyz[rows])
    repaired = solver.self_repaired
    assert repaired >= 1
    assert result.success.all(), result.reason
    own = fcl_self_clearance(TDCR3, result.q)
    assert np.all(own >= solver.config.safety_margin - 1e-6), own
    # The search (its lookup inside), then the retry program (the repair's search was
    # replaced here).
    assert solver.device_calls == 2
    assert solver.retried[0] == repaired

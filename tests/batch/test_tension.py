"""Batch jobs on the Cosserat model (``run_batch(..., model="cosserat")``, ``cr-nlp batch
ik|plan --model cosserat``) on an in-process Dask cluster of one worker: the answers of
the single-process tension solvers under the same loads, a resume that solves only the
missing chunks, a resume under other loads refused, and bad input named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cr_nlp import load_result, load_results
from cr_nlp.batch import MANIFEST, RESULTS, BatchError, chunk_file, read_chunk, run_batch
from cr_nlp.model import load_robot
from cr_nlp.model.cosserat import solve_statics
from cr_nlp.stages.polish import POLISH_EXACT_MODE
from cr_nlp.tasks.mechanics.ik import TensionIKConfig, TensionIKResult, TensionIKSolver
from cr_nlp.tasks.mechanics.trajectory import (
    TensionTrajectoryConfig,
    TensionTrajectoryPlanner,
    TensionTrajectoryResult,
)

RAO = load_robot("tdcr2_rao2021")
LOADS = {"gravity": [0.0, 0.0, -9.81], "tip_force": [0.0, 0.0, -0.049]}  # a 5 g payload
IK_CONFIG = TensionIKConfig(pool_size=4096)
PLAN_CONFIG = TensionTrajectoryConfig(via_pool=64)
TARGETS = 6
CHUNK = 3


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                           dashboard_address=None)
    client = Client(cluster)
    yield client
    client.close()
    cluster.close()


@pytest.fixture(scope="module")
def positions() -> np.ndarray:
    """Tips the loaded robot reaches (forward statics of random tensions, N)."""
    rng = np.random.default_rng(5)
    tensions = rng.uniform(0.0, 0.6 * RAO.mechanics.tension_max, (TARGETS, RAO.n_tendons))
    tensions[rng.random(tensions.shape) < 0.4] = 0.0
    return np.asarray(solve_statics(RAO, tensions, LOADS["tip_force"], None,
                                    LOADS["gravity"]).tip_position)


@pytest.fixture(scope="module")
def job(client, positions, tmp_path_factory) -> tuple[Path, TensionIKResult]:
    out = tmp_path_factory.mktemp("tension_ik") / "job"
    result = run_batch("ik", RAO, (positions, None), out_dir=out, model="cosserat",
                       loads=LOADS, config=IK_CONFIG, client=client, chunk=CHUNK,
                       progress=False)
    return out, result


def _chunk_stamps(out: Path) -> dict[str, tuple[int, int]]:
    return {p.name: (p.stat().st_mtime_ns, read_chunk(p)["run"])
            for p in sorted(out.glob("chunk_*.npz"))}


def test_cosserat_ik_batch_gives_the_direct_solver_answers(job, positions) -> None:
    out, result = job
    assert isinstance(result, TensionIKResult) and len(result) == TARGETS
    assert len(_chunk_stamps(out)) == TARGETS // CHUNK
    # Each chunk is one TensionIKSolver.solve on the worker: the same tensions as a
    # direct solve of those targets under the same loads.
    solver = TensionIKSolver(RAO, None, IK_CONFIG)
    direct = [solver.solve(positions[a:a + CHUNK], None, **LOADS)
              for a in range(0, TARGETS, CHUNK)]
    np.testing.assert_allclose(result.tensions, np.concatenate([d.tensions for d in direct]),
                               rtol=0, atol=1e-9)
    np.testing.assert_array_equal(result.success,
                                  np.concatenate([d.success for d in direct]))
    assert result.success.all()
    # One direct solve of all the targets agrees on the verdict (the batched LM's rows
    # stop together, so its tensions differ from the chunks' within the tolerance).
    whole = solver.solve(positions, None, **LOADS)
    np.testing.assert_array_equal(result.success, whole.success)
    # An independent forward solve of the batch's tensions under the loads hits the tips.
    again = solve_statics(RAO, result.tensions, LOADS["tip_force"], None, LOADS["gravity"])
    assert np.linalg.norm(again.tip_position - positions, axis=1).max() < IK_CONFIG.tolerance
    # results.json: the file of `cr-nlp ik --model cosserat`, with the loads.
    data = json.loads((out / RESULTS).read_text())
    assert data["kind"] == "tension_ik" and data.keys() == direct[0].to_dict().keys()
    back = load_result(out / RESULTS)
    assert isinstance(back, TensionIKResult)
    np.testing.assert_array_equal(back.tensions, result.tensions)
    np.testing.assert_array_equal(back.gravity, np.tile(LOADS["gravity"], (TARGETS, 1)))
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["model"] == "cosserat" and manifest["loads"]["gravity"] == LOADS["gravity"]


def test_a_rerun_resumes_and_other_loads_are_refused(job, client, positions) -> None:
    out, first = job
    options = dict(out_dir=out, model="cosserat", config=IK_CONFIG, client=client,
                   progress=False)
    before = _chunk_stamps(out)
    again = run_batch("ik", RAO, (positions, None), loads=LOADS, resume=True, **options)
    assert _chunk_stamps(out) == before  # no chunk solved again
    assert json.loads((out / MANIFEST).read_text())["runs"][-1]["solved"] == []
    np.testing.assert_array_equal(again.tensions, first.tensions)
    # A lost chunk: only it is solved, to the same answers.
    chunk_file(out, 1).unlink()
    again = run_batch("ik", RAO, (positions, None), loads=LOADS, resume=True, **options)
    after = _chunk_stamps(out)
    assert after[chunk_file(out, 0).name] == before[chunk_file(out, 0).name]
    assert json.loads((out / MANIFEST).read_text())["runs"][-1]["solved"] == [1]
    np.testing.assert_allclose(again.tensions, first.tensions, rtol=0, atol=1e-9)
    # Another job in the folder is refused, naming what differs.
    with pytest.raises(BatchError, match="already holds a batch job"):
        run_batch("ik", RAO, (positions, None), loads=LOADS, **options)
    with pytest.raises(BatchError, match="loads"):
        run_batch("ik", RAO, (positions, None), loads={"gravity": [0.0, 0.0, -9.0]},
                  resume=True, **options)
    with pytest.raises(BatchError, match="config"):  # the PCC job on the same targets
        run_batch("ik", RAO, (positions, np.tile([1.0, 0, 0, 0], (TARGETS, 1))),
                  out_dir=out, client=client, resume=True, progress=False)


def test_cosserat_plan_batch_gives_the_direct_planner_answers(client, tmp_path) -> None:
    starts = np.array([[0.0, 0, 0, 0, 0, 0], [1.0, 0, 0, 0, 0, 0]])
    goals = np.array([[0.0, 1.0, 0, 0, 0, 0.5], [0.0, 0, 1.0, 0.5, 0, 0]])
    out = tmp_path / "job"
    results = run_batch("plan", RAO, (starts, goals), out_dir=out, model="cosserat",
                        loads=LOADS, config=PLAN_CONFIG, client=client, chunk=1,
                        progress=False)
    assert len(list(out.glob("chunk_*.npz"))) == 2
    planner = TensionTrajectoryPlanner(RAO, None, PLAN_CONFIG)
    for i, result in enumerate(results):
        direct = planner.plan(starts[i], goals[i], **LOADS)[0]
        np.testing.assert_allclose(result.tensions, direct.tensions, rtol=0, atol=1e-9)
        assert result.success == direct.success and result.stage == direct.stage
    assert all(r.success for r in results)
    data = json.loads((out / RESULTS).read_text())
    assert data["kind"] == "tension_trajectory" and data["summary"]["problems"] == 2
    back = load_results(out / RESULTS, RAO)
    assert all(isinstance(b, TensionTrajectoryResult) for b in back)
    np.testing.assert_array_equal(back[1].tensions, results[1].tensions)


def test_cli_batch_ik_cosserat_with_the_load_options(client, positions, tmp_path) -> None:
    from cr_nlp.cli.main import main

    targets = tmp_path / "targets.json"
    targets.write_text(json.dumps({"poses": [{"position": p.tolist(), "wxyz": [1, 0, 0, 0]}
                                             for p in positions[:2]]}))
    out = tmp_path / "job"
    argv = ["batch", "ik", "--model", "cosserat", "--robot", "tdcr2_rao2021", "--targets",
            str(targets), "--gravity", "0,0,-9.81", "--tip-force", "0,0,-0.049", "--out",
            str(out), "--scheduler", client.scheduler.address, "--chunk", "1",
            "--no-progress", "--exact", "--time-limit", "5",
            # the module's pool (built for the job fixture), not 16 384 more forward solves
            "--pool-size", str(IK_CONFIG.pool_size)]
    assert main(argv) == 0
    data = json.loads((out / RESULTS).read_text())
    assert data["kind"] == "tension_ik" and all(data["success"])
    assert data["exact_mode"] == POLISH_EXACT_MODE  # --exact reached the solver
    assert json.loads((out / MANIFEST).read_text())["time_limit"] == 5.0
    assert data["tip_force"] == [LOADS["tip_force"]] * 2
    assert main([*argv, "--resume"]) == 0  # nothing missing: solves nothing
    assert json.loads((out / MANIFEST).read_text())["runs"][-1]["solved"] == []
    assert main(argv) == 2  # the folder holds a job: rerun with --resume
    other = ["0,0,-9.0" if a == "0,0,-9.81" else a for a in argv]
    assert main([*other, "--resume"]) == 2  # other loads: another job


@pytest.mark.parametrize(("kind", "robot", "extra", "words"), [
    ("ik", "tdcr3", [], "--model cosserat: tdcr3 has no 'mechanics' block"),
    ("plan", "tdcr2_rao2021", ["--time-limit", "5"],
     "--time-limit bounds the exact stage (Ipopt): give it with --exact"),
    ("ik", "tdcr2_rao2021", ["--gravity", "0,-9.81"], "--gravity: expected 3 numbers"),
    ("ik", "tdcr2_rao2021", ["--pool-size", "8"], "--pool-size: must be at least 16"),
])
def test_cli_bad_cosserat_input_is_named(kind, robot, extra, words, tmp_path, capsys) -> None:
    from cr_nlp.cli.main import main

    source = ["--targets", "tdcr3_lattice"] if kind == "ik" else ["--problems", "x.json"]
    code = main(["batch", kind, "--model", "cosserat", "--robot", robot, *source, *extra,
                 "--out", str(tmp_path / "job"), "--workers", "1"])
    assert code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "job").exists()  # refused before a cluster or a folder


def test_api_bad_cosserat_input_is_named(tmp_path) -> None:
    with pytest.raises(BatchError, match="tdcr3 has no 'mechanics' block"):
        run_batch("ik", "tdcr3", (np.zeros((1, 3)), None), out_dir=tmp_path / "a",
                  model="cosserat")
    with pytest.raises(BatchError, match="time_limit must be a positive number"):
        run_batch("plan", RAO, (np.zeros((1, 6)), np.zeros((1, 6))), out_dir=tmp_path / "b",
                  model="cosserat", exact=True, time_limit=-1.0)
    with pytest.raises(BatchError, match="loads: gravity"):
        run_batch("ik", RAO, (np.zeros((1, 3)), None), out_dir=tmp_path / "c",
                  model="cosserat", loads={"gravity": [0.0, 9.81]})
    with pytest.raises(BatchError, match="model='cosserat'"):
        run_batch("ik", RAO, (np.zeros((1, 3)), np.zeros((1, 4))), out_dir=tmp_path / "d",
                  loads=LOADS)

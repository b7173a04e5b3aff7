"""Batch jobs on Dask (``cr_nlp.batch``, ``cr-nlp batch``) on a 2-worker LocalCluster:
the answers of the single-process solver, nothing lost when a worker or the client dies,
a resume that solves only the missing chunks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cr_nlp import load_result, load_results
from cr_nlp.batch import (
    _SOLVERS,
    MANIFEST,
    RESULTS,
    BatchError,
    JobSpec,
    chunk_file,
    close_cluster,
    read_chunk,
    run_batch,
    solve_chunk,
    start_local_cluster,
    write_chunk,
)
from cr_nlp.bench.ik import forward_kinematics
from cr_nlp.model import load_robot
from cr_nlp.tasks.geometry.ik import IKConfig, IKResult, IKSolver

from ..conftest import ROOT, random_q
from ..tasks.test_result import assert_same_result

TARGETS = 30
BAD = "target wxyz is not a unit quaternion"


@pytest.fixture(scope="module")
def robot():
    return load_robot("tdcr3")


@pytest.fixture(scope="module")
def client():
    client = start_local_cluster(2, quiet=True)
    yield client
    close_cluster(client)


@pytest.fixture(scope="module")
def targets(robot):
    """Reachable targets (forward kinematics of random configurations) and one bad one."""
    positions, wxyz = forward_kinematics(robot, random_q(robot, TARGETS, seed=13))
    wxyz[7] *= 2.0  # not a unit quaternion: a failed result with its reason
    return positions, wxyz


@pytest.fixture(scope="module")
def single(robot, targets):
    """The single-process solver's answers on the same targets."""
    return IKSolver(robot, None, IKConfig()).solve(*targets)


def _pose_errors(robot, q, positions, wxyz):
    """Tip position (m) and orientation (rad) errors of q, by numpy forward kinematics."""
    p, w = forward_kinematics(robot, q)
    angle = 2 * np.arccos(np.clip(np.abs(np.sum(w * wxyz, axis=1)), 0, 1))
    return np.linalg.norm(p - positions, axis=1), angle


def _targets_file(path: Path, positions, wxyz) -> Path:
    poses = [
        {"position": p.tolist(), "wxyz": w.tolist()} for p, w in zip(positions, wxyz, strict=True)
    ]
    path.write_text(json.dumps({"poses": poses}))
    return path


def _chunk_files(out: Path) -> list[Path]:
    return sorted(out.glob("chunk_*.npz"))


def test_batch_ik_gives_the_single_process_answers(robot, client, targets, single, tmp_path):
    out = tmp_path / "job"
    result = run_batch("ik", robot, targets, out_dir=out, client=client, chunk=7, progress=False)
    assert len(result) == TARGETS and len(_chunk_files(out)) == 5  # 7+7+7+7+2
    np.testing.assert_array_equal(result.success, single.success)
    assert result.success.sum() == TARGETS - 1
    assert result.reason[7] == single.reason[7] and result.reason[7].startswith(BAD)
    ok = result.success
    tol = IKConfig().success_tolerance
    assert np.all(result.pose_error[ok] < tol) and np.all(single.pose_error[ok] < tol)
    # The answers reach their own targets by an independent forward kinematics (input
    # order kept), within the tolerance the single-process answers keep.
    dp, da = _pose_errors(robot, result.q[ok], targets[0][ok], targets[1][ok])
    assert dp.max() < tol and da.max() < tol
    # results.json: the schema of `cr-nlp ik --out`, the rows of the returned result.
    data = json.loads((out / RESULTS).read_text())
    reference = single.to_dict()
    assert data.keys() == reference.keys()
    assert data["summary"].keys() == reference["summary"].keys()
    assert data["timing"].keys() == reference["timing"].keys()
    assert [row.keys() for row in data["results"]] == [row.keys() for row in reference["results"]]
    assert data["results"] == json.loads(json.dumps(result.to_dict()["results"]))
    # ...read back through the result protocol, as `cr-nlp view` reads it.
    back = load_result(out / RESULTS)
    assert isinstance(back, IKResult) and back.to_dict()["results"] == data["results"]
    assert data["summary"]["success_rate"] == pytest.approx((TARGETS - 1) / TARGETS)
    # Solvers were built once per worker process, not per chunk (5 chunks, 2 workers).
    built = client.run(lambda: len(__import__("cr_nlp.batch").batch._SOLVERS))
    assert set(built.values()) <= {0, 1} and sum(built.values()) >= 1


def test_a_chunk_file_round_trips_and_a_damaged_one_is_solved_again(robot, single, tmp_path):
    """The worker's record survives its chunk file unchanged (arrays bit for bit, the
    IKResult rebuilt from them gives the same RESULT.json rows); a truncated file, or one
    of another range, reads as missing."""
    columns = single.columns()
    record = {"chunk": 3, "start": 30, "stop": 30 + TARGETS, "run": 2, "worker": "tcp://w",
              "pid": 7, "seconds": 1.5, "timing": {"explore": 0.25}, "columns": columns}
    path = chunk_file(tmp_path, 3)
    write_chunk(path, record)
    back = read_chunk(path)
    assert {k: v for k, v in back.items() if k != "columns"} == {
        k: v for k, v in record.items() if k != "columns"
    }
    for key, value in columns.items():
        np.testing.assert_array_equal(back["columns"][key], value)
        assert back["columns"][key].dtype == value.dtype
    rebuilt = IKResult.from_columns(robot, back["columns"], {}, has_scene=False)
    assert rebuilt.to_dict()["results"] == single.to_dict()["results"]
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary file left

    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    assert read_chunk(path) is None
    write_chunk(path, {**record, "stop": 31})  # its answers do not fill the range
    assert read_chunk(path) is None
    assert read_chunk(tmp_path / "absent.npz") is None


def test_a_problem_that_raises_is_a_failed_result_not_a_failed_chunk(robot, targets):
    class Fragile:
        """The real solver, except that it raises on targets above 2.5 m."""

        def __init__(self):
            self.solver = IKSolver(robot, None, IKConfig())

        def solve(self, positions, wxyz, exact=False):
            if np.any(positions[:, 2] > 2.5):
                raise RuntimeError("the fragile solver broke")
            return self.solver.solve(positions, wxyz, exact=exact)

    positions, wxyz = targets[0][:4].copy(), targets[1][:4].copy()
    positions[2] = [0.0, 0.0, 2.9]  # reachable (tdcr3 is 3 m long), but this solver raises
    spec = JobSpec("ik", robot, None, IKConfig(), False, "roadmap", "fragile-test")
    _SOLVERS[spec.key] = Fragile()
    try:
        record = solve_chunk(spec, 0, positions, wxyz)
    finally:
        del _SOLVERS[spec.key]
    columns = record["columns"]
    assert len(columns["success"]) == 4
    assert not columns["success"][2] and np.all(np.isnan(columns["q"][2]))
    assert columns["reason"][2] == "solver raised RuntimeError: the fragile solver broke"
    assert columns["success"][[0, 1, 3]].all()


def test_a_killed_worker_loses_nothing(robot, client, targets, single, tmp_path):
    out = tmp_path / "job"
    pids = client.run(os.getpid)
    victim = sorted(pids.values())[0]
    box = {}

    def job():
        try:
            box["result"] = run_batch(
                "ik", robot, targets, out_dir=out, client=client, chunk=1, progress=False
            )
        except BaseException as exc:  # reported by the test thread
            box["error"] = exc

    thread = threading.Thread(target=job)
    thread.start()
    deadline = time.monotonic() + 300
    while not _chunk_files(out) and thread.is_alive() and time.monotonic() < deadline:
        time.sleep(0.005)
    os.kill(victim, signal.SIGKILL)
    written_at_kill = len(_chunk_files(out))
    thread.join(timeout=300)
    assert "error" not in box, box.get("error")
    assert 1 <= written_at_kill < TARGETS, "the worker must die mid-job"
    result = box["result"]
    assert len(_chunk_files(out)) == TARGETS
    np.testing.assert_array_equal(result.success, single.success)
    assert np.all(np.isfinite(result.q[result.success]))
    # Dask replaced the dead worker.
    assert victim not in client.run(os.getpid).values()
    manifest = json.loads((out / MANIFEST).read_text())
    assert sorted(manifest["runs"][0]["solved"]) == list(range(TARGETS))


def _worker_settings():
    import dask

    return (
        os.environ.get("MALLOC_TRIM_THRESHOLD_"),
        os.environ.get("CR_NLP_BATCH_DEVICES"),
        dask.config.get("distributed.worker.profile.enabled"),
        dask.config.get("distributed.admin.tick.interval"),
    )


def test_local_workers_run_without_the_malloc_setting_and_the_profiler(client):
    """Every worker of ``start_local_cluster`` (replacements of killed ones too: this runs
    after the kill test on the same cluster) has its share of the cores, keeps glibc's
    adaptive mmap threshold and runs without Dask's statistical profiler."""
    client.wait_for_workers(2, timeout=120)
    settings = client.run(_worker_settings)
    assert len(settings) == 2
    cores = len(os.sched_getaffinity(0))
    for malloc, devices, profile, tick in settings.values():
        assert malloc is None
        assert devices == str(max(1, cores // 2))
        assert profile is False
        assert tick == "500ms"


def test_resume_after_the_client_is_killed_solves_only_the_missing_chunks(
    robot, client, targets, single, tmp_path
):
    targets_file = _targets_file(tmp_path / "targets.json", *targets)
    out = tmp_path / "job"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    command = [
        sys.executable,
        "-m",
        "cr_nlp.cli",
        "batch",
        "ik",
        "--robot",
        "tdcr3",
        "--targets",
        str(targets_file),
        "--out",
        str(out),
        "--chunk",
        "1",
        "--scheduler",
        client.cluster.scheduler_address,
        "--no-progress",
    ]
    proc = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 300
    while not _chunk_files(out) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    proc.kill()
    _, stderr = proc.communicate()
    before = {
        p.name: (p.stat().st_mtime_ns, read_chunk(p)["run"]) for p in _chunk_files(out)
    }
    assert 1 <= len(before) < TARGETS, stderr.decode()[-2000:]
    assert not (out / RESULTS).exists()

    # Another job in the same folder is refused, with the reason.
    with pytest.raises(BatchError, match="already holds a batch job"):
        run_batch("ik", robot, targets, out_dir=out, client=client, chunk=1, progress=False)
    moved = (targets[0] + 0.01, targets[1])
    with pytest.raises(BatchError, match="inputs"):
        run_batch(
            "ik",
            robot,
            moved,
            out_dir=out,
            client=client,
            resume=True,
            problems=[""] * TARGETS,
            progress=False,
        )
    with pytest.raises(BatchError, match="chunk"):
        run_batch(
            "ik",
            robot,
            targets,
            out_dir=out,
            client=client,
            chunk=2,
            resume=True,
            problems=[""] * TARGETS,
            progress=False,
        )
    with pytest.raises(BatchError, match="config"):  # another seed: another job
        run_batch(
            "ik",
            robot,
            targets,
            out_dir=out,
            client=client,
            config=IKConfig(seed=1),
            resume=True,
            progress=False,
        )

    result = run_batch(
        "ik",
        robot,
        targets,
        out_dir=out,
        client=client,
        resume=True,
        progress=False,
    )
    after = {
        p.name: (p.stat().st_mtime_ns, read_chunk(p)["run"]) for p in _chunk_files(out)
    }
    assert len(after) == TARGETS
    assert {name: after[name] for name in before} == before  # not solved again
    missing = sorted(set(range(TARGETS)) - {int(n[6:12]) for n in before})
    manifest = json.loads((out / MANIFEST).read_text())
    assert sorted(manifest["runs"][-1]["solved"]) == missing
    assert all(after[chunk_file(out, i).name][1] == len(manifest["runs"]) for i in missing)
    np.testing.assert_array_equal(result.success, single.success)
    data = json.loads((out / RESULTS).read_text())
    assert len(data["results"]) == TARGETS and data["results"][7]["reason"].startswith(BAD)


def test_cli_batch_ik_writes_the_schema_of_cr_nlp_ik(client, targets, tmp_path):
    from cr_nlp.cli.main import main

    targets_file = _targets_file(tmp_path / "targets.json", *targets)
    out = tmp_path / "job"
    argv = [
        "batch",
        "ik",
        "--robot",
        "tdcr3",
        "--targets",
        str(targets_file),
        "--out",
        str(out),
        "--scheduler",
        client.cluster.scheduler_address,
        "--chunk",
        "10",
        "--no-progress",
    ]
    assert main(argv) == 0
    data = json.loads((out / RESULTS).read_text())
    assert len(data["results"]) == TARGETS and data["robot"] == "tdcr3"
    assert main(argv) == 2  # the folder holds a job: rerun with --resume
    assert main([*argv, "--resume"]) == 0  # nothing missing: solves nothing
    assert json.loads((out / MANIFEST).read_text())["runs"][-1]["solved"] == []
    assert (
        main(
            [
                "batch",
                "ik",
                "--robot",
                "tdcr3",
                "--targets",
                str(targets_file),
                "--out",
                str(out),
                "--workers",
                "0",
            ]
        )
        == 2
    )


def test_batch_plan_results_pass_the_independent_check(robot, client, tmp_path):
    from cr_nlp.tasks.geometry.trajectory import TrajectoryConfig, verify_trajectory
    from cr_nlp.world import load_scene

    scene = load_scene("shelf")
    problems = json.loads((ROOT / "models/problems/tdcr3_shelf.json").read_text())["problems"]
    starts = [problems[0]["start"], [1.0, 2.0], problems[1]["start"]]
    goals = [problems[0]["goal"], problems[1]["goal"], problems[1]["goal"]]
    out = tmp_path / "job"
    results = run_batch(
        "plan",
        robot,
        (starts, goals),
        scene=scene,
        out_dir=out,
        client=client,
        chunk=2,
        progress=False,
    )
    assert len(results) == 3 and len(_chunk_files(out)) == 2
    assert results[1].stage == "rejected" and results[1].reason.startswith("bad start")
    config = TrajectoryConfig()
    for i in (0, 2):
        result = results[i]
        np.testing.assert_allclose(result.q[0], starts[i], atol=1e-9)  # input order kept
        np.testing.assert_allclose(result.q[-1], goals[i], atol=1e-9)
        verdict = verify_trajectory(
            robot, scene, result.q, result.dt, config.safety_margin, config.verify_samples
        )
        assert verdict.success == result.success
        assert verdict.max_violation == pytest.approx(result.max_violation, abs=1e-12)
    assert results[0].success and results[2].success
    data = json.loads((out / RESULTS).read_text())
    assert data.keys() == {"kind", "schema_version", "robot", "results", "summary", "timing"}
    assert data["kind"] == "trajectory"
    # Read back through the result protocol: the TrajectoryResults run_batch returned.
    for back, result in zip(load_results(out / RESULTS, robot), results, strict=True):
        assert_same_result(back, result)
    assert data["summary"]["problems"] == 3
    assert data["summary"]["success_rate"] == pytest.approx(2 / 3)
    assert [row["stage"] for row in data["results"]] == [r.stage for r in results]

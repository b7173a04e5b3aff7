"""The IK benchmark and its baselines on tiny sizes: the baselines solve easy targets, the
benchmark writes its documented files, and its numbers come from the shared judge."""

from pathlib import Path

import numpy as np
import pytest

from cr_nlp.bench import _baselines as baselines
from cr_nlp.bench._common import Column, format_number, markdown_table, read_csv
from cr_nlp.bench.ik import (
    CR_BEAM,
    CR_SINGLE,
    CSV_KEYS,
    METHODS,
    NEWTON,
    NEWTON_CONFIG,
    SCIPY,
    IKBenchSizes,
    forward_kinematics,
    free_case,
    ik_config_overrides,
    judge,
    lattice_case,
    run_ik_benchmark,
)
from cr_nlp.cli import build_parser
from cr_nlp.model import Robot
from cr_nlp.model.limits import limit_violation_q
from cr_nlp.tasks.geometry.ik import IKSolver
from cr_nlp.world import check_many, load_scene

from ..conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")
TINY = IKBenchSizes(free_targets=6, lattice_targets=3, scaling_targets=3, scipy_targets=2,
                    repeats=1)


@pytest.fixture(scope="module")
def easy() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Targets from known configurations and starts 0.05 rad / 0 m away from them."""
    q_true = np.array([[0.6, 0.4, 1.0, 0.9, -1.2, 1.0, 0.5, 2.0, 1.0],
                       [1.2, -2.0, 1.0, 0.3, 0.5, 1.0, 1.1, -0.7, 1.0]])
    positions, wxyz = forward_kinematics(TDCR3, q_true)
    starts = q_true + np.tile([0.05, -0.05, 0.0], 3)
    return q_true, positions, wxyz, starts


@pytest.fixture(scope="module")
def free_rows(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[dict], object]:
    out = tmp_path_factory.mktemp("bench_ik")
    rows = run_ik_benchmark(suite="free", sizes=TINY, out=out, seed=3, progress=False,
                            echo=False)
    return rows, out


def test_damped_newton_solves_a_target_near_its_start(easy: tuple) -> None:
    q_true, positions, wxyz, starts = easy
    solved = baselines.damped_newton_ik(TDCR3, positions, wxyz, starts=starts)
    checked = IKSolver(TDCR3).verify(solved.q, positions, wxyz)
    assert solved.q.shape == (2, TDCR3.dof)
    assert np.all(checked.pose_error < 1e-2)
    assert np.all(checked.max_violation == 0.0)
    assert solved.seconds > 0.0


def test_scipy_solves_a_target_near_its_start(easy: tuple) -> None:
    q_true, positions, wxyz, starts = easy
    solved = baselines.scipy_ik(TDCR3, positions, wxyz, starts=starts)
    checked = IKSolver(TDCR3).verify(solved.q, positions, wxyz)
    assert np.all(checked.pose_error < 1e-2)
    assert np.all(checked.max_violation == 0.0)


def test_baselines_keep_answers_inside_the_limits() -> None:
    # Targets past the fully bent pose pull θ beyond π; answers must stay inside the limits.
    q = np.tile([np.pi, 0.0, 1.0], (2, 3))
    positions, wxyz = forward_kinematics(TDCR3, q)
    positions = positions + np.array([[0.3, 0.0, 0.0], [0.0, -0.3, 0.0]])
    for solve in (baselines.damped_newton_ik, baselines.scipy_ik):
        solved = solve(TDCR3, positions, wxyz, starts=q)
        assert np.all(limit_violation_q(TDCR3, solved.q) == 0.0), solve.__name__


def test_lattice_targets_keep_the_solver_margin() -> None:
    scene = load_scene("lattice")
    margin = IKSolver(TDCR3, scene).margin
    case = lattice_case(TDCR3, scene, 3, margin, seed=1, batch=200)
    assert case.positions.shape == (3, 3) and case.wxyz.shape == (3, 4)
    assert np.all(check_many(TDCR3, scene, case.q).min_distance >= margin)
    positions, _ = forward_kinematics(TDCR3, case.q)
    np.testing.assert_allclose(positions, case.positions)


@pytest.mark.slow  # a benchmark run or a repeat of covered work: `pytest -m slow`
def test_benchmark_writes_csv_and_markdown(free_rows: tuple) -> None:
    rows, out = free_rows
    assert [r["method"] for r in rows] == list(METHODS)
    csv_rows = read_csv(out / "ik.csv")
    assert list(csv_rows[0]) == list(CSV_KEYS)
    assert [r["method"] for r in csv_rows] == list(METHODS)
    text = (out / "ik.md").read_text()
    for header in ("success %", "collision-free %", "mean pose error", "max violation",
                   "time s (median)", "first call s", "compile s"):
        assert header in text
    for key in ("python", "jax", "jaxlib", "casadi", "numpy", "scipy", "devices", "cpu",
                "cores"):
        assert f"- {key}: " in text
    assert (out / "environment.json").exists()
    by_method = {r["method"]: r for r in rows}
    assert by_method[SCIPY]["targets"] == TINY.scipy_targets
    assert by_method[CR_BEAM]["targets"] == TINY.free_targets
    for row in rows:
        assert row["total_s"] > 0.0 and row["first_call_s"] > 0.0
        assert row["collision_free_pct"] is None  # no scene in this suite


def test_every_row_success_is_the_library_verdict_on_its_answers(free_rows: tuple) -> None:
    """Each row's success flags, and the success % it prints, are the library's verdict
    (``IKSolver.verify``, self-collision included) on that row's own answers."""
    rows, _ = free_rows
    solver = IKSolver(TDCR3)
    for row in rows:
        answers = row["answers"]
        checked = solver.verify(answers.q, answers.positions, answers.wxyz)
        np.testing.assert_array_equal(checked.success, answers.success, row["method"])
        assert row["success_pct"] == pytest.approx(100.0 * checked.success.mean())
        assert row["targets"] == len(answers.q)


@pytest.mark.slow  # a benchmark run or a repeat of covered work: `pytest -m slow`
def test_benchmark_success_is_the_shared_judge(free_rows: tuple) -> None:
    """The baseline's success column is recomputed from its answers by the same judge,
    and that judge agrees with the library's own success flags."""
    rows, _ = free_rows
    case = free_case(TDCR3, TINY.free_targets, seed=3)
    solver = IKSolver(TDCR3)
    newton = baselines.damped_newton_ik(TDCR3, case.positions, case.wxyz, NEWTON_CONFIG,
                                        seed=3 + 7919)
    checked = judge(solver, newton.q, case.positions, case.wxyz)
    row = next(r for r in rows if r["method"] == NEWTON)
    assert row["success_pct"] == pytest.approx(100.0 * checked.success.mean())
    assert row["mean_pose_error"] == pytest.approx(checked.pose_error.mean(), rel=1e-6)

    result = solver.solve(case.positions, case.wxyz)
    mine = judge(solver, result.q, case.positions, case.wxyz)
    np.testing.assert_array_equal(mine.success, result.success)
    # Rows are measured, not constants: the baselines' numbers differ from cr_nlp's.
    beam = next(r for r in rows if r["method"] == CR_BEAM)
    assert beam["success_pct"] == pytest.approx(100.0 * result.success.mean())
    for method in (NEWTON, SCIPY):
        other = next(r for r in rows if r["method"] == method)
        assert other["mean_pose_error"] != beam["mean_pose_error"]
    assert next(r for r in rows if r["method"] == CR_SINGLE)["refine_s"] > 0.0


def test_table_formatting() -> None:
    table = markdown_table([{"a": 0.000123456, "b": "x"}, {"a": 1234.5, "b": None}],
                           [Column("a", "a"), Column("b", "b")])
    assert table.splitlines()[1] == "|---:|---|"
    assert "1.23e-04" in table and "1234" in table and "—" in table
    assert format_number(float("nan")) == "—" and format_number(12) == "12"


def test_cli_parser_defaults() -> None:
    parser = build_parser()
    args = parser.parse_args(["bench", "ik", "--quick", "--suite", "lattice"])
    assert (args.suite, args.quick, args.repeats, args.out, args.seed) == (
        "lattice", True, None, "bench_results/ik", 0)
    assert callable(args.run)
    with pytest.raises(SystemExit):
        parser.parse_args(["bench", "ik", "--suite", "nowhere"])


def test_throughput_suite_reports_where_the_time_goes(tmp_path: Path) -> None:
    sizes = IKBenchSizes(throughput_targets=(5, 20, 40), repeats=2)
    rows = run_ik_benchmark(suite="throughput", sizes=sizes, out=tmp_path, seed=2,
                            progress=False, echo=False, max_targets=30,
                            ik_config={"stream_size": 16})
    assert [r["targets"] for r in rows] == [5, 20]  # 40 is above max_targets
    for row in rows:
        assert row["suite"] == "throughput" and row["runs"] == 2
        assert row["success_pct"] == 100.0
        assert row["targets_per_s"] == pytest.approx(row["targets"] / row["total_s"])
        assert 0.0 < row["device_wait_s"] < row["total_s"]
        # Host: the wall time outside compiled programs, its share, and per 10⁵ targets.
        assert 0.0 < row["host_s"] < row["max_s"] and 0.0 < row["host_pct"] < 100.0
        assert row["host_pct"] == pytest.approx(100.0 * row["host_s"] / row["total_s"])
        assert row["host_per_1e5_s"] == pytest.approx(row["host_s"] * 1e5 / row["targets"])
        stages = row["explore_s"] + row["refine_s"] + row["verify_s"]
        assert 0.0 < stages <= row["max_s"] * 1.01
    assert [r["stream_parts"] for r in rows] == [1, 2]  # 20 targets in parts of 16
    text = (tmp_path / "ik.md").read_text()
    for header in ("targets / s", "device wait s", "host %", "host s / 10⁵ targets",
                   "explore s", "verify s"):
        assert header in text
    assert [r["targets"] for r in read_csv(tmp_path / "ik.csv")] == ["5", "20"]


def test_ik_config_overrides_from_the_command_line() -> None:
    parser = build_parser()
    args = parser.parse_args(["bench", "ik", "--suite", "throughput", "--max-targets", "5000",
                              "--ik-config", "chunk_size=4096", "beam_min_distance=0.2"])
    assert args.max_targets == 5000
    assert ik_config_overrides(args.ik_config) == {"chunk_size": 4096,
                                                   "beam_min_distance": 0.2}
    assert ik_config_overrides(["search_block=none", "dtype=float64"]) == {
        "search_block": None, "dtype": "float64"}
    assert ik_config_overrides(["search_block=32"]) == {"search_block": 32}
    for bad in (["chunk_size"], ["no_such_field=1"], ["chunk_size=big"], ["stream_size=0"],
                ["search_block=maybe"], ["chunk_size=none"], ["fused=false"]):
        with pytest.raises(ValueError):
            ik_config_overrides(bad)

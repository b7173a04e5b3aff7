"""The one result protocol (``cr_nlp.tasks._result``): every task result round-trips
through ``to_dict`` / ``from_dict`` and its file, carries ``kind`` and
``schema_version``, and is read back as the class its kind names. The results here are
built from the float64 verdicts (no solver, no compilation); the solvers' own results
round-trip in test_ik, test_trajectory and test_follow."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from cr_nlp import (
    SCHEMA_VERSION,
    FollowResult,
    IKResult,
    TrajectoryResult,
    load_result,
    load_results,
    load_robot,
)
from cr_nlp.tasks._result import (
    ResultFileError,
    Stage,
    Status,
    result_from_dict,
    split_stage,
    stage_text,
    status_of,
    typed_stages,
)
from cr_nlp.tasks._timing import StageTiming
from cr_nlp.tasks.geometry._follow_result import tracking_errors
from cr_nlp.tasks.geometry.ik import IKSolver
from cr_nlp.tasks.geometry.trajectory import (
    trajectories_from_dict,
    trajectories_to_dict,
    verify_trajectory,
)
from cr_nlp.tasks.paths import sine_path
from cr_nlp.world import load_scene

from ..conftest import random_q


def assert_same_result(a: object, b: object) -> None:
    """Field by field: arrays equal bit for bit (NaN where NaN), the robot by name, the
    reference path by its dict, everything else by ==."""
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "robot":
            assert x.name == y.name
        elif f.name == "path":
            assert x.to_dict() == y.to_dict()
        elif isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f.name)
            assert np.asarray(x).dtype == np.asarray(y).dtype, f.name
        elif isinstance(x, float) and math.isnan(x):
            assert isinstance(y, float) and math.isnan(y), f.name
        elif isinstance(x, dict):
            assert x.keys() == y.keys(), f.name
            for k in x:
                if isinstance(x[k], np.ndarray):   # IK: per family, one value per answer
                    np.testing.assert_array_equal(x[k], y[k], err_msg=f"{f.name}.{k}")
                    continue
                assert x[k] == y[k] or (math.isnan(x[k]) and math.isnan(y[k])), (f.name, k)
        else:
            assert x == y, f.name


def round_trip(result: object, tmp_path) -> object:
    """``from_dict(to_dict())``, through JSON text and through ``save``/``load_result``;
    both must give the same result back."""
    data = result.to_dict()
    assert data["kind"] == result.kind and data["schema_version"] == SCHEMA_VERSION
    back = type(result).from_dict(json.loads(json.dumps(data, allow_nan=False)))
    assert_same_result(result, back)
    loaded = load_result(result.save(tmp_path / f"{result.kind}.json"))
    assert_same_result(result, loaded)
    return back


@pytest.fixture(scope="module")
def ik_result() -> IKResult:
    """Verified answers of configurations in the lattice: some collide, one row is
    unsolved (NaN), one failed with a reason."""
    robot, scene = load_robot("tdcr3"), load_scene("lattice")
    q = random_q(robot, 6, seed=4)
    solver = IKSolver(robot, scene)
    from cr_nlp.model import tip_pose
    from cr_nlp.model.rotations import wxyz_from_matrix

    position, rotation = tip_pose(robot, q)
    checked = solver.verify(q, position + 0.001, wxyz_from_matrix(rotation))
    result = IKResult(robot, q, checked.position, checked.wxyz,
                      *(getattr(checked, k) for k in ("pose_error", "position_error",
                                                      "rotation_error", "max_violation",
                                                      "clearance")),
                      collision_free=checked.collision_free,
                      success=checked.pose_error < 0.01, stage=["refine"] * 6,
                      reason=[""] * 6, timing=StageTiming(explore=0.25, refine=0.5),
                      has_scene=True)
    for name in ("q", "position", "wxyz"):
        getattr(result, name)[2] = np.nan
    for name in ("pose_error", "position_error", "rotation_error", "max_violation",
                 "min_clearance"):
        getattr(result, name)[2] = np.nan
    result.success[2], result.stage[2] = False, "rejected"
    result.reason[2] = "target is out of reach"
    return result


def test_an_ik_result_round_trips_with_its_unsolved_rows(ik_result, tmp_path) -> None:
    assert not ik_result.collision_free.all() and ik_result.collision_free.any()
    back = round_trip(ik_result, tmp_path)
    assert np.isnan(back.q[2]).all() and back.reason[2] == "target is out of reach"
    # Without a scene the clearance columns are absent from the file and come back NaN.
    free = dataclasses.replace(ik_result, has_scene=False,
                               collision_free=np.ones(len(ik_result), bool),
                               min_clearance=np.full(len(ik_result), np.nan))
    round_trip(free, tmp_path)


def test_the_ik_csv_has_a_row_per_target_in_si_units(ik_result, tmp_path) -> None:
    rows = list(csv.DictReader(ik_result.save_csv(tmp_path / "ik.csv").open()))
    assert len(rows) == len(ik_result)
    for i, row in enumerate(rows):
        assert row["success"] == str(int(ik_result.success[i]))
        if i == 2:
            assert row["pose_error"] == "" and row["theta_1"] == ""
            continue
        assert float(row["position_error_m"]) == pytest.approx(ik_result.position_error[i],
                                                               rel=1e-8)
        assert float(row["min_clearance_m"]) == pytest.approx(ik_result.min_clearance[i],
                                                              rel=1e-8)
        assert float(row["length_3"]) == pytest.approx(ik_result.q[i, 8], rel=1e-8)


def _trajectory(robot, q: np.ndarray, dt: float) -> TrajectoryResult:
    verdict = verify_trajectory(robot, load_scene("shelf"), q, dt)
    return TrajectoryResult(
        robot, q, dt, verdict.success, verdict.reason, "refine (straight)",
        path_length=verdict.path_length, min_clearance=verdict.min_clearance,
        max_violation=verdict.max_violation, violations=verdict.violations,
        tendon_lengths=verdict.tendon_lengths, tendon_speed=verdict.tendon_speed,
        tendon_accel=verdict.tendon_accel, cost=1.5,
        timing=StageTiming(explore=0.1, refine=0.2, verify=0.05))


def test_trajectories_round_trip_one_by_one_and_as_a_plan_file(tmp_path) -> None:
    robot = load_robot("tdcr3")
    a, b = random_q(robot, 2, seed=8)
    moved = _trajectory(robot, a + np.linspace(0, 1, 7)[:, None] * (b - a), 0.5)
    rejected = TrajectoryResult(robot, None, 0.5, False, "bad start: 2 values", "rejected")
    for result in (moved, rejected):
        round_trip(result, tmp_path)
    data = trajectories_to_dict([moved, rejected], StageTiming(refine=1.0))
    assert data["kind"] == "trajectory" and data["timing"]["total"] == 1.0
    path = tmp_path / "plan.json"
    path.write_text(json.dumps(data))
    for back in (trajectories_from_dict(data), load_results(path)):
        assert len(back) == 2
        assert_same_result(back[0], moved)
        assert_same_result(back[1], rejected)
    with pytest.raises(ResultFileError, match="holds 2 trajectories"):
        load_result(path)


def test_a_follow_result_round_trips_with_its_reference(tmp_path) -> None:
    robot = load_robot("tdcr3")
    reference = sine_path(count=12, dt=0.2)
    q = random_q(robot, 12, seed=2)
    errors = tracking_errors(robot, q, reference.positions, reference.wxyz)
    verdict = verify_trajectory(robot, None, q, reference.dt)
    result = FollowResult(
        robot, reference, q, errors["position"], errors["wxyz"], errors["pose_error"],
        errors["position_error"], errors["rotation_error"], errors["position_error"] < 0.005,
        verdict.tendon_lengths, verdict.tendon_speed, verdict.tendon_accel, True,
        verdict.min_clearance, verdict.max_violation, verdict.violations,
        success=False, reason="12 of 12 waypoints not reached", stage="refine",
        timing=StageTiming(compile=2.0, refine=0.3))
    back = round_trip(result, tmp_path)
    assert back.summary() == result.summary()
    # The pose error is the IK metric: the IK verdict on the same poses agrees.
    checked = IKSolver(robot).verify(q, reference.positions, reference.wxyz)
    np.testing.assert_allclose(result.pose_error, checked.pose_error, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.rotation_error, checked.rotation_error, atol=1e-9)


def test_a_file_is_read_as_the_class_its_kind_names_or_refused_by_name(ik_result,
                                                                      tmp_path) -> None:
    data = ik_result.to_dict()
    assert type(result_from_dict(data)) is IKResult
    old = tmp_path / "old.json"
    old.write_text(json.dumps({k: v for k, v in data.items() if k != "kind"}))
    with pytest.raises(ResultFileError, match=rf"{old}: no 'kind' field"):
        load_result(old)
    with pytest.raises(ResultFileError, match="unknown kind 'banana'"):
        result_from_dict(dict(data, kind="banana"))
    with pytest.raises(ResultFileError, match="schema_version 0"):
        result_from_dict(dict(data, schema_version=0))
    with pytest.raises(ResultFileError, match="holds a 'ik' result, not 'follow'"):
        FollowResult.from_dict(data)
    with pytest.raises(ResultFileError, match="for robot 'tdcr3', not 'tdcr4_ext'"):
        result_from_dict(data, robot=load_robot("tdcr4_ext"))
    with pytest.raises(ResultFileError, match=r"broken.json: q\[0\] has 1 entries, expected 9"):
        result_from_dict(dict(data, results=[{"q": [0.0]}]), source="broken.json")
    with pytest.raises(ResultFileError, match="broken.json: not a valid ik result .field 'q'"):
        result_from_dict(dict(data, results=[{}]), source="broken.json")


def test_stage_timing_reads_as_a_mapping_and_round_trips() -> None:
    timing = StageTiming(compile=1.0, refine=0.5, verify=0.25)
    assert timing["total"] == timing.total == 1.75
    assert dict(timing) == timing.as_dict() and list(timing)[-1] == "total"
    assert StageTiming.from_dict(timing.as_dict()) == timing
    with pytest.raises(ValueError, match="unknown stage"):
        StageTiming.from_dict({"init": 1.0})


def test_the_public_api_is_one_import_line() -> None:
    namespace: dict = {}
    exec("from cr_nlp import IKSolver, IKConfig, IKResult, TrajectoryPlanner, TrajectoryConfig, "
         "TrajectoryResult, PathFollower, FollowConfig, FollowResult, LiveIKSolver, run_batch, "
         "load_path", namespace)
    from cr_nlp.batch import run_batch
    from cr_nlp.tasks.geometry.follow import PathFollower
    from cr_nlp.tasks.geometry.live_ik import LiveIKSolver

    assert namespace["run_batch"] is run_batch and namespace["PathFollower"] is PathFollower
    assert namespace["LiveIKSolver"] is LiveIKSolver
    # Every result class is the one its kind names in the registry.
    from cr_nlp.tasks._result import result_class

    for cls in (namespace["IKResult"], namespace["TrajectoryResult"], namespace["FollowResult"]):
        assert result_class(cls.kind) is cls


DATA = Path(__file__).parents[1] / "data"


def test_results_of_schema_1_are_read_with_stage_and_notes_apart():
    # tests/data holds files of schema 1, whose ``stage`` held the notes in parentheses.
    ik = load_result(DATA / "ik_lattice_result.json")
    assert json.loads((DATA / "ik_lattice_result.json").read_text())["schema_version"] == 1
    assert ik.stage == [Stage.REFINE] * len(ik) and ik.notes == [[]] * len(ik)
    assert ik.status == [Status.SUCCESS if s else Status.FAILED for s in ik.success]
    assert ik.success.all() and np.isnan(ik.violations["limits"]).all()  # schema 1 had none
    follow = load_result(DATA / "follow_icra_result.json")
    assert follow.stage == Stage.REFINE and follow.notes == [] and follow.stage_text == "refine"
    data = json.loads((DATA / "plan_shelf_result.json").read_text())
    (plan,) = trajectories_from_dict(data)
    assert plan.stage == Stage.REFINE and plan.notes == ["roadmap"]
    assert plan.stage_text == "refine (roadmap)"
    # A note with parentheses of its own, as a time limit writes it.
    late = "polish out of time: Ipopt stopped at the time limit (7 iterations, 2 s)"
    data["results"][0]["stage"] = f"refine (roadmap) ({late})"
    (plan,) = trajectories_from_dict(data)
    assert plan.stage == "refine" and plan.notes == ["roadmap", late]
    assert plan.stage_text == f"refine (roadmap) ({late})"
    # Written again as schema 2: the stage's value, the notes apart, the status.
    entry = plan.to_dict()["results"][0]
    assert plan.to_dict()["schema_version"] == SCHEMA_VERSION == 2
    assert (entry["stage"], entry["notes"], entry["status"]) == ("refine", ["roadmap", late],
                                                                 "success")
    assert trajectories_from_dict(plan.to_dict())[0].notes == plan.notes
    data["results"][0]["stage"] = "lucky guess"
    with pytest.raises(ResultFileError, match="unknown stage 'lucky guess'"):
        trajectories_from_dict(data)


def test_split_stage_and_stage_text_are_inverse():
    for text in ("polish", "rejected", "refine (feasible: polish not needed)",
                 "refine (straight) (polish failed: from refine (straight): Ipopt: "
                 "Infeasible_Problem_Detected)"):
        stage, notes = split_stage(text)
        assert stage_text(stage, notes) == text
    assert split_stage("refine (straight) (polish failed: x)") == (
        Stage.REFINE, ["straight", "polish failed: x"])
    with pytest.raises(ValueError, match="unbalanced"):
        split_stage("refine (polish failed")
    assert status_of(False, "rejected") == Status.REJECTED == status_of(False, Stage.NONE)
    # One word for a refused input in every task; IK files of before 2026-12-02 said "none".
    assert Stage("none") is Stage.REJECTED is Stage.NONE
    assert status_of(False, "polish") == Status.FAILED and status_of(True, "refine") == "success"


def test_typed_stages_leave_the_collector_as_they_found_it() -> None:
    """``typed_stages`` freezes older objects while it makes its note lists and thaws them
    after; objects the caller froze stay frozen."""
    import gc

    stages = [Stage.REFINE] * 3 + ["refine (roadmap)"]
    assert gc.get_freeze_count() == 0
    got, notes = typed_stages(stages)
    assert gc.get_freeze_count() == 0
    assert got == [Stage.REFINE] * 4 and notes == [[], [], [], ["roadmap"]]
    assert len({id(n) for n in notes}) == 4            # a list of its own per answer
    gc.freeze()
    try:
        typed_stages(stages)
        assert gc.get_freeze_count() > 0      # not thawed (frozen objects may still be freed)
    finally:
        gc.unfreeze()

"""Robot files: the bundled ones load, bad ones fail with one clear error."""

import json
import math
from pathlib import Path

import pytest

from cr_nlp.model import ModelFileError, Robot

from ..conftest import MODELS

GOOD = {
    "name": "tdcr3",
    "segments": [{"length": 1.0, "theta_max": 3.14159},
                 {"length": [0.5, 1.5], "theta_max": 3.14159}],
    "backbone_radius": 0.1, "points_per_segment": 10,
    "tendons": {"per_segment": 3, "radius": 0.08, "offsets": [0.0, 0.0], "routing": "per_segment"},
    "base": {"position": [0, 0, 0], "wxyz": [1, 0, 0, 0]},
    "tendon_speed_max": 0.2, "tendon_accel_max": 1.0,
}


@pytest.mark.parametrize("name", ["tdcr3", "tdcr4_ext", "tdcr5_ext", "tdcr6_ext"])
def test_bundled_robots_load(name: str) -> None:
    robot = Robot.from_file(MODELS / "robots" / f"{name}.json")
    assert robot.name == name
    assert robot.backbone_radius == 0.1 and robot.tendons.radius == 0.08
    assert all(s.extendable for s in robot.segments) == name.endswith("_ext")
    assert Robot.from_dict(robot.to_dict()) == robot


def test_issue_example_loads_and_mixes_fixed_and_extendable() -> None:
    robot = Robot.from_dict(GOOD)
    assert [s.extendable for s in robot.segments] == [False, True]
    lo, hi = robot.q_bounds()
    assert list(lo) == [0.0, -math.pi, 1.0, 0.0, -math.pi, 0.5]
    assert hi[5] == 1.5 and robot.n_tendons == 6


def broken(**changes: object) -> dict:
    data = json.loads(json.dumps(GOOD))
    for path, value in changes.items():
        keys = path.split("__")
        target = data
        for k in keys[:-1]:
            target = target[int(k)] if isinstance(target, list) else target[k]
        if value is KeyError:
            del target[keys[-1]]
        elif isinstance(target, list):
            target[int(keys[-1])] = value
        else:
            target[keys[-1]] = value
    return data


CASES = [
    (broken(segments=KeyError), "segments", "missing required field"),
    (broken(segments=[]), "segments", "at least one segment"),
    (broken(segments__0__length=-1.0), "segments[0].length", "positive"),
    (broken(segments__1__length=[1.5, 0.5]), "segments[1].length", "max < min"),
    (broken(segments__0__theta_max=4.0), "segments[0].theta_max", "at most π"),
    (broken(segments__0__theta_max="pi"), "segments[0].theta_max", "expected a number"),
    (broken(backbone_radius=0), "backbone_radius", "positive"),
    (broken(points_per_segment=2.5), "points_per_segment", "integer"),
    (broken(tendons__routing="spiral"), "tendons.routing", "'shared' or 'per_segment'"),
    (broken(tendons__offsets=[0.0]), "tendons.offsets", "list of 2 numbers"),
    (broken(base__wxyz=[1, 1, 0, 0]), "base.wxyz", "unit quaternion"),
    (broken(colour="red"), "colour", "unknown key"),
    (broken(segments__0__lenght=1.0), "segments[0].lenght", "unknown key"),
    (broken(tendon_speed_max=-0.2), "tendon_speed_max", "positive"),
    ([1, 2, 3], "<top>", "expected an object"),
]


@pytest.mark.parametrize(("data", "field", "problem"), CASES, ids=[c[1] for c in CASES])
def test_bad_robot_files_name_file_field_and_problem(tmp_path: Path, data: object, field: str,
                                                     problem: str) -> None:
    path = tmp_path / "bad_robot.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ModelFileError) as info:
        Robot.from_file(path)
    message = str(info.value)
    assert str(path) in message and f"'{field}'" in message and problem in message


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(ModelFileError, match="file not found"):
        Robot.from_file(tmp_path / "missing.json")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="not valid JSON"):
        Robot.from_file(tmp_path / "bad.json")


def test_load_robot_takes_a_bundled_name_or_a_path() -> None:
    from cr_nlp.model import load_robot

    assert load_robot("tdcr4_ext") == Robot.from_file(MODELS / "robots" / "tdcr4_ext.json")
    with pytest.raises(ModelFileError, match="file not found"):
        load_robot("no_such_robot")


def test_bundled_names_resolve_through_the_one_resolver_from_any_directory(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from cr_nlp._resources import resolve_file
    from cr_nlp.model import load_robot

    monkeypatch.chdir(tmp_path)  # no models/ folder here
    bundled = Robot.from_file(resolve_file("tdcr3", "robots"))
    assert load_robot("tdcr3") == bundled and Robot.from_file("tdcr3") == bundled
    assert load_robot("tdcr3").source == str(resolve_file("tdcr3", "robots"))
    with pytest.raises(ModelFileError, match="not a bundled robot name") as err:
        load_robot("tdcr9")
    assert "tdcr3, tdcr4_ext" in str(err.value)
    # A local file of that name wins over the bundled robot, as in the resolver.
    data = json.loads((MODELS / "robots" / "tdcr3.json").read_text())
    data["name"] = "local"
    (tmp_path / "tdcr3").write_text(json.dumps(data))
    assert load_robot("tdcr3").name == "local"

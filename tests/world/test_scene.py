"""Scene files: bundled scenes, validation errors, mesh loading and the decomposition cache."""

import json
from pathlib import Path

import numpy as np
import pytest

from cr_nlp.model import ModelFileError, Robot
from cr_nlp.world import (
    BoxPart,
    CapsulePart,
    ConvexPart,
    CylinderPart,
    Scene,
    SpherePart,
    check,
    coacd_cache_stats,
    lattice_scene,
    load_scene,
    random_spheres_scene,
    union_of_boxes,
)
from cr_nlp.world import (
    _builders as builders,
)

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
BUNDLED = ["lattice", "random_27", "shelf", "cabinet", "follow_square", "follow_sine",
           "follow_icra"]


@pytest.fixture(scope="module")
def tdcr3() -> Robot:
    return Robot.from_file(MODELS / "robots" / "tdcr3.json")


@pytest.fixture
def l_mesh(tmp_path: Path) -> Path:
    """A small closed L-shaped solid (two joined boards) as an OBJ file."""
    path = tmp_path / "meshes" / "corner.obj"
    path.parent.mkdir()
    union_of_boxes([((0, 0, 0), (0.6, 0.1, 0.4)), ((0, 0, 0), (0.1, 0.5, 0.4))]).export(path)
    return path


# ---------------------------------------------------------------- bundled scenes

@pytest.mark.parametrize("name", BUNDLED)
def test_bundled_scene_loads_and_straight_robot_is_free(name: str, tdcr3: Robot) -> None:
    scene = load_scene(name)
    assert scene.name == name and scene.obstacles
    straight = np.array([0.0, 0.0, 1.0] * 3)
    verdict = check(tdcr3, scene, straight)
    assert not verdict.collision, verdict


def test_bundled_files_match_their_generators(tmp_path: Path) -> None:
    """The committed scenes and meshes are exactly what ``builders.write_bundled`` makes."""
    builders.write_bundled(tmp_path)
    for name in BUNDLED:
        assert (tmp_path / "scenes" / f"{name}.json").read_text() == \
            (MODELS / "scenes" / f"{name}.json").read_text(), name
    import trimesh

    for mesh in ("shelf", "cabinet"):
        # Geometry, not bytes: the OBJ text may differ between trimesh versions.
        made, kept = (trimesh.load(root / "meshes" / f"{mesh}.obj", force="mesh")
                      for root in (tmp_path, MODELS))
        np.testing.assert_allclose(np.unique(made.vertices.round(9), axis=0),
                                   np.unique(kept.vertices.round(9), axis=0))
        assert made.volume == pytest.approx(kept.volume) and kept.is_watertight


def test_lattice_is_the_benchmark_lattice() -> None:
    scene = Scene.from_dict(lattice_scene())
    centres = np.array([p.center for p in scene.parts])
    assert len(scene.parts) == 27 and all(p.radius == 0.2 for p in scene.parts)
    assert sorted(set(centres[:, 0])) == [-0.8, 0.0, 0.8]
    assert sorted(set(centres[:, 1])) == [-0.4, 0.4, 1.2]
    assert sorted(set(centres[:, 2])) == [-0.8, 0.2, 1.2]


def test_random_spheres_are_seeded_and_inside_the_box() -> None:
    a, b, c = random_spheres_scene(3), random_spheres_scene(3), random_spheres_scene(4)
    assert a == b and a != c
    centres = np.array([o["center"] for o in a["obstacles"]])
    radii = np.array([o["radius"] for o in a["obstacles"]])
    assert len(radii) == 27 and np.all((radii >= 0.15) & (radii <= 0.30))
    assert np.all(np.abs(centres) <= 1.5)
    assert np.all(np.linalg.norm(centres, axis=1) - radii >= 0.3)   # base kept clear


def test_shelf_mesh_is_closed_and_nonconvex() -> None:
    mesh = union_of_boxes(builders.shelf_boards())
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume < 0.5 * mesh.convex_hull.volume   # compartments: far from convex


def test_every_primitive_kind_parses(tmp_path: Path, l_mesh: Path) -> None:
    data = {"name": "kinds", "obstacles": [
        {"type": "sphere", "center": [1, 0, 0], "radius": 0.2},
        {"type": "box", "name": "crate", "center": [0, 1, 0], "size": [0.2, 0.3, 0.4],
         "wxyz": [0.7071068, 0, 0, 0.7071068]},
        {"type": "capsule", "a": [0, 0, 2], "b": [1, 0, 2], "radius": 0.1},
        {"type": "cylinder", "a": [0, -1, 0], "b": [0, -1, 1], "radius": 0.15},
        {"type": "mesh", "name": "corner", "path": "meshes/corner.obj", "scale": 2.0,
         "position": [1, 1, 0], "wxyz": [1, 0, 0, 0]},
    ]}
    file = tmp_path / "kinds.json"
    file.write_text(json.dumps(data))
    scene = Scene.from_file(file)
    kinds = [type(p) for p in scene.parts]
    # Parts come grouped by kind, spheres first, convex parts last.
    assert kinds[:4] == [SpherePart, BoxPart, CapsulePart, CylinderPart]
    assert all(k is ConvexPart for k in kinds[4:]) and len(kinds) > 4
    assert [o.name for o in scene.obstacles] == ["sphere_0", "crate", "capsule_2",
                                                 "cylinder_3", "corner"]
    box = scene.parts[1]
    np.testing.assert_allclose(box.rotation @ [1, 0, 0], [0, 1, 0], atol=1e-6)
    # The mesh is scaled by 2 and moved by (1, 1, 0): its parts cover that region.
    verts = np.concatenate([p.vertices for p in scene.parts[4:]])
    np.testing.assert_allclose(verts.min(axis=0), [1, 1, 0], atol=1e-6)
    np.testing.assert_allclose(verts.max(axis=0), [2.2, 2.0, 0.8], atol=1e-6)
    for part in scene.parts[4:]:
        assert np.all(part.vertices @ part.normals.T <= part.offsets + 1e-9)
    assert scene.to_dict()["obstacles"][1]["name"] == "crate"


def test_second_mesh_load_hits_the_cache(tmp_path: Path, l_mesh: Path,
                                         monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CR_NLP_CACHE_DIR", str(tmp_path / "cache"))
    data = {"obstacles": [{"type": "mesh", "path": "meshes/corner.obj"}]}
    before = coacd_cache_stats()
    first = Scene.from_dict(data, base_dir=tmp_path)
    middle = coacd_cache_stats()
    second = Scene.from_dict(data, base_dir=tmp_path)
    after = coacd_cache_stats()
    assert middle["misses"] == before["misses"] + 1 and middle["hits"] == before["hits"]
    assert after["hits"] == middle["hits"] + 1 and after["misses"] == middle["misses"]
    assert list((tmp_path / "cache" / "coacd").glob("*.npz"))
    for p, q in zip(first.parts, second.parts, strict=True):
        np.testing.assert_array_equal(p.vertices, q.vertices)
    # Other settings are another cache entry.
    from cr_nlp.world import DecompositionSettings

    Scene.from_dict(data, base_dir=tmp_path, settings=DecompositionSettings(threshold=0.1))
    assert coacd_cache_stats()["misses"] == after["misses"] + 1


# ---------------------------------------------------------------- broken files

def _obstacle(**fields: object) -> dict:
    return {"obstacles": [fields]}


BROKEN = [
    ("not json", "{", "<file>", "not valid JSON"),
    ("no obstacles", {"name": "x"}, "obstacles", "missing required field"),
    ("obstacles not a list", {"obstacles": {}}, "obstacles", "expected a list"),
    ("unknown top key", {"obstacles": [], "gravity": 1}, "gravity", "unknown key"),
    ("unknown type", _obstacle(type="torus", name="donut"), "obstacles[0] (donut).type",
     "unknown obstacle type 'torus'"),
    ("missing type", _obstacle(center=[0, 0, 0], radius=1), "obstacles[0].type",
     "missing required field"),
    ("zero radius", _obstacle(type="sphere", name="ball", center=[0, 0, 0], radius=0),
     "obstacles[0] (ball).radius", "must be positive"),
    ("negative radius", _obstacle(type="capsule", a=[0, 0, 0], b=[0, 0, 1], radius=-1),
     "obstacles[0].radius", "must be positive"),
    ("radius not a number", _obstacle(type="sphere", center=[0, 0, 0], radius="big"),
     "obstacles[0].radius", "expected a number"),
    ("short centre", _obstacle(type="sphere", center=[0, 0], radius=1),
     "obstacles[0].center", "list of 3 numbers"),
    ("zero box side", _obstacle(type="box", name="flat", center=[0, 0, 0], size=[1, 0, 1]),
     "obstacles[0] (flat).size", "every side must be positive"),
    ("bad quaternion", _obstacle(type="box", center=[0, 0, 0], size=[1, 1, 1], wxyz=[1, 1, 0, 0]),
     "obstacles[0].wxyz", "unit quaternion"),
    ("unknown obstacle key", _obstacle(type="sphere", center=[0, 0, 0], radius=1, colour="red"),
     "obstacles[0].colour", "unknown key"),
    ("capsule ends coincide", _obstacle(type="capsule", a=[1, 1, 1], b=[1, 1, 1], radius=1),
     "obstacles[0].b", "coincide"),
    ("duplicate names", {"obstacles": [
        {"type": "sphere", "name": "s", "center": [0, 0, 0], "radius": 1},
        {"type": "sphere", "name": "s", "center": [1, 0, 0], "radius": 1}]},
     "obstacles[1].name", "already used"),
    ("missing mesh file", _obstacle(type="mesh", name="shelf", path="meshes/none.obj"),
     "obstacles[0] (shelf).path", "mesh file not found"),
    ("empty mesh", _obstacle(type="mesh", path="empty.obj"), "obstacles[0].path", "no faces"),
    ("flat mesh", _obstacle(type="mesh", path="flat.obj"), "obstacles[0].path", "zero volume"),
    ("open mesh", _obstacle(type="mesh", path="open.obj"), "obstacles[0].path",
     "not closed"),
    ("mesh scale zero", _obstacle(type="mesh", path="meshes/corner.obj", scale=0),
     "obstacles[0].scale", "must be positive"),
]


@pytest.mark.parametrize(("label", "content", "field", "problem"), BROKEN,
                         ids=[b[0] for b in BROKEN])
def test_broken_scene_files_name_file_obstacle_and_problem(
        tmp_path: Path, l_mesh: Path, label: str, content: object, field: str,
        problem: str) -> None:
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    (tmp_path / "flat.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\nf 1 3 2\nf 1 4 3\n")
    (tmp_path / "open.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\n")
    file = tmp_path / "broken.json"
    file.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(ModelFileError) as err:
        Scene.from_file(file)
    assert err.value.source == str(file)
    assert err.value.field_path == field
    assert problem in err.value.problem
    assert str(file) in str(err.value)


def test_missing_scene_file() -> None:
    with pytest.raises(ModelFileError, match="file not found"):
        load_scene("/nonexistent/scene.json")


def test_rotation_z_to_turns_z_onto_the_direction():
    """A proper rotation whose third column is the direction normalised (the capsules of
    the verdict are built with it), to rounding also near −z (where 1/(1 + c) once lost
    the digits: 5.9e-12 m in a sphere–cylinder distance)."""
    from cr_nlp.world.scene import rotation_z_to

    rng = np.random.default_rng(4)
    for d in [*rng.normal(size=(200, 3)), np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -3.0]),
              np.array([1e-7, 0.0, -1.0]), np.array([0.0, 0.0078125, -1.5])]:
        r = rotation_z_to(d)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=2e-15)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=2e-15)
        np.testing.assert_allclose(r[:, 2], d / np.linalg.norm(d), atol=2e-15)

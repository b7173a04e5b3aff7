"""The bundled scenes and meshes, as code: run ``python -m cr_nlp.world._builders`` to
regenerate ``models/scenes/*.json`` and ``models/meshes/*.obj``.

Sizes are for ``tdcr3`` (three 1.0 m segments growing up +z from the origin, backbone
radius 0.1 m): the furniture stands in front of the robot (+x), its compartments are
wide enough for the robot's body, and the straight configuration is collision-free.
All lengths are metres.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .._files import write_atomic
from .._resources import models_root

Box = tuple[tuple[float, float, float], tuple[float, float, float]]

# ================================================================ meshes from boards


def union_of_boxes(boxes: list[Box]) -> Any:
    """The exact closed surface of a union of axis-aligned boxes ``(lo, hi)`` (m) as one
    watertight ``trimesh.Trimesh``.

    Boards that overlap or touch are joined into one solid (no internal faces), which
    CoACD needs with ``preprocess_mode="off"``: the cells of the grid spanned by all box
    bounds are marked occupied, and every face between an occupied and an empty cell
    becomes two triangles facing the empty one.
    """
    import trimesh

    lows = np.array([b[0] for b in boxes], dtype=float)
    highs = np.array([b[1] for b in boxes], dtype=float)
    axes = [np.unique(np.r_[lows[:, k], highs[:, k]]) for k in range(3)]
    occupied = np.zeros([len(a) - 1 for a in axes], dtype=bool)
    for lo, hi in zip(lows, highs, strict=True):
        index = tuple(slice(np.searchsorted(axes[k], lo[k]), np.searchsorted(axes[k], hi[k]))
                      for k in range(3))
        occupied[index] = True
    padded = np.pad(occupied, 1).astype(np.int8)

    vertex_ids: dict[tuple[int, int, int], int] = {}
    triangles = []

    def vertex(grid: list[int]) -> int:
        return vertex_ids.setdefault((grid[0], grid[1], grid[2]), len(vertex_ids))

    for k in range(3):
        u, v = (k + 1) % 3, (k + 2) % 3
        change = np.diff(padded, axis=k)  # +1: empty → full along +k, −1: full → empty
        for cell in np.argwhere(change != 0):
            # Padded cell indices shift the other axes by one; along k the face lies on
            # grid plane cell[k].
            corner = [int(cell[a]) - 1 for a in range(3)]
            corner[k] = int(cell[k])
            quad = []
            for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                g = list(corner)
                g[u] += du
                g[v] += dv
                quad.append(vertex(g))
            if change[tuple(cell)] > 0:  # the solid lies on the +k side: face towards −k
                quad.reverse()
            triangles += [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]]
    grid = np.array(list(vertex_ids), dtype=np.int64)
    points = np.stack([axes[k][grid[:, k]] for k in range(3)], axis=1)
    mesh = trimesh.Trimesh(points, np.array(triangles), process=True)
    assert mesh.is_watertight and mesh.volume > 0, "union of boxes must be a closed solid"
    return mesh


def shelf_boards(width: float = 2.0, depth: float = 0.6, height: float = 2.4,
                 board: float = 0.05, levels: tuple[float, ...] = (0.8, 1.6)) -> list[Box]:
    """A bookshelf open towards −x, in its own frame (front bottom centre at the origin):
    back panel, two sides, a vertical divider at y = 0, bottom, top and shelf boards at
    the heights ``levels`` (m). Eight compartments of 0.925 × 0.75 × 0.55 m by default."""
    w, t = width / 2.0, board
    boxes: list[Box] = [
        ((depth - t, -w, 0.0), (depth, w, height)),      # back panel
        ((0.0, -w, 0.0), (depth, -w + t, height)),       # left side
        ((0.0, w - t, 0.0), (depth, w, height)),         # right side
        ((0.0, -t / 2, 0.0), (depth, t / 2, height)),    # divider
    ]
    for z in (0.0, *(z - t / 2 for z in levels), height - t):
        boxes.append(((0.0, -w, z), (depth, w, z + t)))
    return boxes


def cabinet_boards(width: float = 1.2, depth: float = 0.8, bottom: float = 0.5,
                   top: float = 2.1, board: float = 0.04, door: float = 0.45,
                   leg: float = 0.05) -> list[Box]:
    """A cabinet open towards −x on four legs, in its own frame (front face at x = 0):
    bottom, top, back, two sides, a middle shelf, and two doors opened wide (side walls
    continued towards the robot by ``door`` m). Two compartments about 1.12 × 0.72 m."""
    w, t = width / 2.0, board
    middle = 0.5 * (bottom + top)
    boxes: list[Box] = [
        ((0.0, -w, bottom), (depth, w, bottom + t)),               # bottom
        ((0.0, -w, top - t), (depth, w, top)),                     # top
        ((depth - t, -w, bottom), (depth, w, top)),                # back
        ((-door, -w, bottom), (depth, -w + t, top)),               # left side + open door
        ((-door, w - t, bottom), (depth, w, top)),                 # right side + open door
        ((0.0, -w, middle - t / 2), (depth, w, middle + t / 2)),   # middle shelf
    ]
    for x in (0.0, depth - leg):
        for y in (-w, w - leg):
            boxes.append(((x, y, 0.0), (x + leg, y + leg, bottom)))
    return boxes


# ================================================================ sphere scenes

LATTICE_X = (-0.8, 0.0, 0.8)
LATTICE_Y = (-0.4, 0.4, 1.2)
LATTICE_Z = (-0.8, 0.2, 1.2)


def lattice_scene(radius: float = 0.2) -> dict[str, Any]:
    """The collision-IK benchmark (docs/design.md §4): 27 spheres of ``radius`` m on the
    3×3×3 lattice x ∈ {−0.8, 0, 0.8}, y ∈ {−0.4, 0.4, 1.2}, z ∈ {−0.8, 0.2, 1.2} m."""
    obstacles = [
        {"type": "sphere", "name": f"lattice_{i}{j}{k}", "center": [x, y, z], "radius": radius}
        for i, x in enumerate(LATTICE_X)
        for j, y in enumerate(LATTICE_Y)
        for k, z in enumerate(LATTICE_Z)
    ]
    return {"name": "lattice",
            "description": "27 spheres r = 0.2 m on a 3x3x3 lattice (collision IK benchmark).",
            "obstacles": obstacles}


def random_spheres_scene(seed: int, count: int = 27,
                         radius_range: tuple[float, float] = (0.15, 0.30), box_size: float = 3.0,
                         keep_clear: tuple[float, float, float] = (0.0, 0.0, 0.0),
                         keep_clear_radius: float = 0.3) -> dict[str, Any]:
    """``count`` spheres with radii uniform in ``radius_range`` (m) and centres uniform in
    a cube of side ``box_size`` (m) centred at the origin (the paper's random scenes).

    A sphere whose surface comes within ``keep_clear_radius`` m of ``keep_clear`` (the
    robot's base) is drawn again: the body near the base barely moves, so an obstacle
    there would make every configuration collide. Deterministic for a given seed.
    """
    rng = np.random.default_rng(seed)
    anchor = np.asarray(keep_clear, dtype=float)
    obstacles = []
    while len(obstacles) < count:
        center = rng.uniform(-box_size / 2, box_size / 2, 3)
        radius = float(rng.uniform(*radius_range))
        if np.linalg.norm(center - anchor) - radius < keep_clear_radius:
            continue
        obstacles.append({"type": "sphere", "name": f"sphere_{len(obstacles):02d}",
                          "center": [round(float(v), 6) for v in center],
                          "radius": round(radius, 6)})
    return {"name": f"random_{count}",
            "description": (f"{count} random spheres, radii U[{radius_range[0]}, "
                            f"{radius_range[1]}] m, centres in a {box_size} m cube at the origin, "
                            f"seed {seed}; none within {keep_clear_radius} m of the robot base."),
            "obstacles": obstacles}


# Path-following scenes: the reference paths lie in the plane x = 1.5 m facing the robot,
# inside y ∈ [−0.8, 0.8] m, z ∈ [1.0, 2.0] m. Each scene places two spheres (r = 0.3 m)
# close to the robot's body but off it: one below the path, near the lower body, and one
# beside the path. Placed against tdcr3 following the path without obstacles: each
# sphere is 6–10 cm from that motion's body (python-fcl), so the path stays trackable
# while the clearance is tight. (A first placement, between the robot and the path,
# blocked every IK branch of the paths: no collision-free motion tracked them.)
PATH_SPHERES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "square": ((1.1, 0.0, 0.2), (1.5, -1.0, 1.5)),
    "sine": ((1.1, 0.35, 0.15), (1.45, -0.35, 2.25)),
    "icra": ((1.7, -0.3, 0.6), (1.5, 1.2, 1.5)),
}
PATH_REGIONS = {
    "square": "a 1.0 m square in the plane x = 1.5 m, y ∈ [-0.5, 0.5] m, z ∈ [1.0, 2.0] m",
    "sine": "a sinusoid in the plane x = 1.5 m, y ∈ [-0.75, 0.75] m, z = 1.5 ± 0.3 m",
    "icra": "the letters ICRA in the plane x = 1.5 m, y ∈ [-0.8, 0.8] m, z ∈ [1.2, 1.8] m",
}


def path_scene(shape: str) -> dict[str, Any]:
    """The obstacle scene of a path-following benchmark (``"square"``, ``"sine"``, ``"icra"``)."""
    first, second = PATH_SPHERES[shape]
    return {"name": f"follow_{shape}",
            "description": (f"Path following among obstacles; the path is {PATH_REGIONS[shape]}. "
                            "Two spheres r = 0.3 m near the path, off it."),
            "obstacles": [
                {"type": "sphere", "name": "below_path", "center": list(first), "radius": 0.3},
                {"type": "sphere", "name": "beside_path", "center": list(second), "radius": 0.3},
            ]}


def furniture_scene(kind: str) -> dict[str, Any]:
    """The shelf or cabinet scene: the furniture mesh placed in front of the robot."""
    if kind == "shelf":
        return {"name": "shelf",
                "description": ("A bookshelf (2.0 m wide, 0.6 m deep, 2.4 m high, 8 compartments "
                                "0.925 x 0.75 m) open towards the robot, front face at x = 0.8 m."),
                "obstacles": [{"type": "mesh", "name": "shelf", "path": "../meshes/shelf.obj",
                               "scale": 1.0, "position": [0.8, 0.0, 0.0]}]}
    return {"name": "cabinet",
            "description": ("A cabinet on legs (1.2 m wide, 0.8 m deep, body z in [0.5, 2.1] m) "
                            "open towards the robot with its doors opened wide, front face at "
                            "x = 0.75 m; the door edges come to x = 0.3 m."),
            "obstacles": [{"type": "mesh", "name": "cabinet", "path": "../meshes/cabinet.obj",
                           "position": [0.75, 0.0, 0.0]}]}


# ================================================================ regenerate the files


def write_bundled(models_dir: str | Path | None = None) -> list[Path]:
    """Write every bundled scene and mesh under ``models_dir`` (default: the repository's
    ``models/``); returns the written paths."""
    root = Path(models_dir) if models_dir else models_root()
    (root / "scenes").mkdir(parents=True, exist_ok=True)
    (root / "meshes").mkdir(parents=True, exist_ok=True)
    written = []
    for name, boxes in (("shelf", shelf_boards()), ("cabinet", cabinet_boards())):
        path = root / "meshes" / f"{name}.obj"
        text = union_of_boxes(boxes).export(file_type="obj", include_normals=False)
        write_atomic(path, text.encode("utf-8"))  # as trimesh writes it to a path
        written.append(path)
    scenes = {"lattice": lattice_scene(), "random_27": random_spheres_scene(seed=0),
              "shelf": furniture_scene("shelf"), "cabinet": furniture_scene("cabinet"),
              **{f"follow_{s}": path_scene(s) for s in PATH_SPHERES}}
    for name, data in scenes.items():
        path = root / "scenes" / f"{name}.json"
        write_atomic(path, _dump(data).encode("utf-8"))
        written.append(path)
    return written


def _dump(data: dict[str, Any]) -> str:
    """JSON with one obstacle per line, so diffs of scene files stay readable."""
    head = {k: v for k, v in data.items() if k != "obstacles"}
    lines = [json.dumps(head, indent=2, ensure_ascii=False)[:-2] + ",", '  "obstacles": [']
    rows = [f"    {json.dumps(o)}" for o in data["obstacles"]]
    lines.append(",\n".join(rows))
    lines += ["  ]", "}"]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    for p in write_bundled():
        print(p)

"""Robot model files: schema, validation and the immutable ``Robot``.

A robot file is JSON (schema in ``models/README.md``). Loading checks every
field and raises one ``ModelFileError`` that names the file, the field and
what is wrong, before anything reaches JAX or CasADi.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .._files import InputFileError, read_json_or
from .._resources import resolve_file
from ._actuation_block import parse_actuation
from .mechanics import Mechanics, parse_mechanics
from .routing import tendon_count

if TYPE_CHECKING:
    from ._actuation_block import Actuation

Routing = Literal["shared", "per_segment"]


class ModelFileError(InputFileError):
    """A robot or scene file (or an in-memory dict) that does not follow the schema."""

    def __init__(self, source: str, field_path: str, problem: str) -> None:
        self.source = source
        self.field_path = field_path
        self.problem = problem
        where = f"{source}: " if source else ""
        super().__init__(f"{where}field '{field_path}': {problem}")


@dataclass(frozen=True)
class Segment:
    """One constant-curvature segment.

    Lengths in metres, angles in radians. A fixed segment has
    ``length_min == length_max``.
    """

    length_min: float
    length_max: float
    theta_max: float
    phi_min: float = -math.inf
    phi_max: float = math.inf

    @property
    def extendable(self) -> bool:
        return self.length_max > self.length_min

    @property
    def phi_limited(self) -> bool:
        return math.isfinite(self.phi_min) or math.isfinite(self.phi_max)


@dataclass(frozen=True)
class NumberAt:
    """In a robot's program template (``Robot.program_data``): the number a compiled
    program takes as entry ``index`` of its robot vector."""

    index: int


@dataclass(frozen=True)
class _ProgramSegment(Segment):
    """A segment of a program template or of the robot a compiled program rebuilds from
    its data: the numbers may be ``NumberAt`` or traced, so whether the length can change
    and whether the azimuth is limited are kept as they were (part of the program's
    shape, not of its data)."""

    flags: tuple[bool, bool] = (True, False)
    """(extendable, phi_limited) of the segment it stands for."""

    @property
    def extendable(self) -> bool:
        return self.flags[0]

    @property
    def phi_limited(self) -> bool:
        return self.flags[1]


def _take(value: Any, numbers: list[float]) -> Any:
    """A finite number of the robot as ``NumberAt`` (appended to ``numbers``); anything
    else (an infinite limit, a flag, a name) stays where it is, part of the shape."""
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
        numbers.append(float(value))
        return NumberAt(len(numbers) - 1)
    return value


@functools.lru_cache(maxsize=64)
def _rotation(wxyz: tuple[float, ...]) -> np.ndarray:
    """``matrix_from_wxyz`` of a base orientation, read-only (a live update asked for it
    four times: 30–45 µs each)."""
    from .rotations import matrix_from_wxyz

    matrix = matrix_from_wxyz(np.asarray(wxyz, dtype=float))
    matrix.flags.writeable = False
    return matrix


def _finite(value: Any) -> bool:
    """Whether a limit is finite; a traced one is (only finite numbers become data)."""
    return not isinstance(value, float) or math.isfinite(value)


def _fill(value: Any, numbers: Any) -> Any:
    """``value`` with every ``NumberAt`` replaced by its entry of ``numbers``."""
    if isinstance(value, NumberAt):
        return numbers[value.index]
    if isinstance(value, tuple):
        return tuple(_fill(v, numbers) for v in value)
    if is_dataclass(value) and isinstance(value, Segment | Tendons | Robot):
        return replace(value, **{f.name: _fill(getattr(value, f.name), numbers)
                                 for f in fields(value) if f.init})
    return value


@dataclass(frozen=True)
class Tendons:
    """Tendon routing: ``per_segment`` tendons per segment at ``radius`` metres
    from the backbone, at angles (j−1)·2π/m + ``offsets[i]`` radians."""

    per_segment: int
    radius: float
    offsets: tuple[float, ...]
    routing: Routing


@dataclass(frozen=True)
class Robot:
    """A tendon-driven continuum robot with piecewise constant curvature.

    Configuration order: ``q = [θ1, φ1, L1, …, θn, φn, Ln]`` (radians, radians, metres).
    """

    name: str
    segments: tuple[Segment, ...]
    backbone_radius: float
    points_per_segment: int
    tendons: Tendons
    base_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    tendon_speed_max: float = math.inf
    tendon_accel_max: float = math.inf
    self_collision: bool = True
    """Whether segments at least two apart must keep clear of each other (every task's
    verdict and model); false only for robots whose segments cannot meet."""
    source: str = field(default="", compare=False)
    actuation: Actuation | None = None
    """Calibrated motor-command model (``model.actuation``), or None: nominal."""
    mechanics: Mechanics | None = None
    """Material and masses for the Cosserat statics model (``mechanics`` block), or None."""

    # ------------------------------------------------------------ sizes and bounds
    @property
    def n_segments(self) -> int:
        return len(self.segments)

    @property
    def has_self_pairs(self) -> bool:
        """True when self-collision is checked and some segments are two or more apart."""
        return self.self_collision and self.n_segments >= 3

    @property
    def speed_limited(self) -> bool:
        """Whether the tendons have a speed limit (m/s)."""
        return _finite(self.tendon_speed_max)

    @property
    def accel_limited(self) -> bool:
        """Whether the tendons have an acceleration limit (m/s²)."""
        return _finite(self.tendon_accel_max)

    @property
    def dof(self) -> int:
        """Length of q (three entries per segment, fixed lengths included)."""
        return 3 * self.n_segments

    @property
    def n_tendons(self) -> int:
        return tendon_count(self.tendons.per_segment, self.n_segments, self.tendons.routing)

    @property
    def n_points(self) -> int:
        """Backbone points returned by ``backbone_points`` (the base is not included)."""
        return self.points_per_segment * self.n_segments

    @property
    def base_rotation(self) -> np.ndarray:
        """(3, 3) rotation of the base frame in the world frame (``base_wxyz``; columns: the
        base's axes), float64, read-only, made once per orientation."""
        return _rotation(self.base_wxyz)

    @property
    def total_length_max(self) -> float:
        """Longest possible backbone, metres."""
        return float(sum(s.length_max for s in self.segments))

    def q_bounds(self, xp: Any = np) -> tuple[Any, Any]:
        """Lower and upper bounds of q; an unlimited azimuth is bounded by ±π for sampling.
        ``xp``: numpy (float64), or ``jax.numpy`` where the numbers are traced."""
        lo, hi = [], []
        for s in self.segments:
            lo += [0.0, s.phi_min if _finite(s.phi_min) else -math.pi, s.length_min]
            hi += [s.theta_max, s.phi_max if _finite(s.phi_max) else math.pi, s.length_max]
        return xp.array(lo), xp.array(hi)

    def lengths_fixed(self) -> np.ndarray:
        """Boolean mask over segments: True where the length cannot change."""
        return np.array([not s.extendable for s in self.segments])

    def full_q(self, values: Any) -> np.ndarray:
        """A complete q (3n) from user input, checked against the limits.

        Accepts either all 3n entries ``[θ1, φ1, L1, …]``, or the short form that
        omits L for every fixed-length segment. A given fixed length must equal the
        segment's length; θ must lie in [0, θmax], L in its range (radians, metres).
        Raises ``ValueError`` naming the offending entry.
        """
        try:
            v = np.asarray(values, dtype=float).reshape(-1)
        except OverflowError:  # an integer past float's range
            raise ValueError(f"{self.name}: configuration has non-finite entries "
                             f"(a number too large for a float)") from None
        fixed = self.lengths_fixed()
        short = 3 * self.n_segments - int(fixed.sum())
        if v.size == self.dof:
            q = v.copy()
        elif v.size == short and fixed.any():
            q, k = np.empty(self.dof), 0
            for i, seg in enumerate(self.segments):
                take = 2 if fixed[i] else 3
                q[3 * i: 3 * i + take] = v[k: k + take]
                if fixed[i]:
                    q[3 * i + 2] = seg.length_min
                k += take
        else:
            forms = f"{self.dof}" + (f" or {short} (fixed lengths omitted)" if fixed.any() else "")
            raise ValueError(f"{self.name}: a configuration needs {forms} numbers "
                             f"[θ1, φ1, L1, …], got {v.size}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"{self.name}: configuration has non-finite entries: {q.tolist()}")
        for i, seg in enumerate(self.segments):
            theta, phi, length = q[3 * i: 3 * i + 3]
            if not 0.0 <= theta <= seg.theta_max + 1e-9:
                raise ValueError(f"{self.name}: θ{i + 1} = {theta} rad is outside "
                                 f"[0, {seg.theta_max}]")
            if not seg.phi_min - 1e-9 <= phi <= seg.phi_max + 1e-9:
                raise ValueError(f"{self.name}: φ{i + 1} = {phi} rad is outside "
                                 f"[{seg.phi_min}, {seg.phi_max}]")
            if not seg.length_min - 1e-9 <= length <= seg.length_max + 1e-9:
                what = (f"must equal the fixed length {seg.length_min}" if not seg.extendable
                        else f"is outside [{seg.length_min}, {seg.length_max}]")
                raise ValueError(f"{self.name}: L{i + 1} = {length} m {what}")
        return q

    # ------------------------------------------------------------ compiled programs
    def program_data(self) -> tuple[Robot, np.ndarray]:
        """This robot as a compiled program takes it (``_programs.compile_program``'s
        ``by_shape``): (template, numbers). The template is the robot with each finite
        number (lengths, limits and angles in m and rad, radii, tendon offsets, base pose,
        tendon rate limits) replaced by ``NumberAt`` and without its name: its shape,
        which keys the program. ``numbers`` (float64, in the template's order) are the
        program's data, so robots of one shape share one program."""
        numbers: list[float] = []
        segments = tuple(_ProgramSegment(
            *(_take(getattr(s, f), numbers)
              for f in ("length_min", "length_max", "theta_max", "phi_min", "phi_max")),
            flags=(s.extendable, s.phi_limited)) for s in self.segments)
        template = replace(
            self, name="", segments=segments,
            backbone_radius=_take(self.backbone_radius, numbers),
            tendons=replace(self.tendons, radius=_take(self.tendons.radius, numbers),
                            offsets=tuple(_take(o, numbers) for o in self.tendons.offsets)),
            base_position=tuple(_take(v, numbers) for v in self.base_position),
            base_wxyz=tuple(_take(v, numbers) for v in self.base_wxyz),
            tendon_speed_max=_take(self.tendon_speed_max, numbers),
            tendon_accel_max=_take(self.tendon_accel_max, numbers))
        return template, np.array(numbers, dtype=np.float64)

    def filled(self, numbers: Any) -> Robot:
        """A template's robot (``program_data``) with its numbers: ``numbers[i]`` in place
        of each ``NumberAt(i)`` (inside a compiled program, traced scalars)."""
        return _fill(self, numbers)

    # ------------------------------------------------------------ construction
    @classmethod
    def from_file(cls, path: str | Path) -> Robot:
        """Load and validate a robot JSON file, or a bundled robot by name ("tdcr3")."""
        try:
            path = resolve_file(path, "robots")
        except FileNotFoundError as exc:
            raise ModelFileError(str(path), "<file>", str(exc).removeprefix(f"{path}: ")) from None
        return cls.from_dict(read_model_file(path), source=str(path))

    @classmethod
    def from_dict(cls, data: Any, source: str = "") -> Robot:
        """Validate a robot description (the JSON file's content as a dict)."""
        return _parse_robot(data, source)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of this robot (round-trips through ``from_dict``)."""
        segs = []
        for s in self.segments:
            seg: dict[str, Any] = {
                "length": s.length_min if not s.extendable else [s.length_min, s.length_max],
                "theta_max": s.theta_max,
            }
            if s.phi_limited:
                seg["phi_range"] = [s.phi_min, s.phi_max]
            segs.append(seg)
        out: dict[str, Any] = {
            "name": self.name,
            "segments": segs,
            "backbone_radius": self.backbone_radius,
            "points_per_segment": self.points_per_segment,
            "tendons": {
                "per_segment": self.tendons.per_segment,
                "radius": self.tendons.radius,
                "offsets": list(self.tendons.offsets),
                "routing": self.tendons.routing,
            },
            "base": {"position": list(self.base_position), "wxyz": list(self.base_wxyz)},
        }
        if math.isfinite(self.tendon_speed_max):
            out["tendon_speed_max"] = self.tendon_speed_max
        if math.isfinite(self.tendon_accel_max):
            out["tendon_accel_max"] = self.tendon_accel_max
        if self.actuation is not None:
            out["actuation"] = self.actuation.to_dict()
        if not self.self_collision:
            out["self_collision"] = False
        if self.mechanics is not None:
            out["mechanics"] = self.mechanics.to_dict()
        return out


def robot_jit(fn: Callable) -> Callable:
    """``jax.jit(fn, static_argnums=0)`` for a function of a robot first; called with a
    robot whose numbers are traced (inside a program that takes the robot as data,
    ``Robot.program_data``), which cannot be a static argument, ``fn`` runs inline in
    that program's trace."""
    import jax  # here: a robot file is read without importing JAX

    jitted = jax.jit(fn, static_argnums=0)

    @functools.wraps(fn)
    def call(robot: Robot, *args: Any) -> Any:
        try:
            hash(robot)
        except TypeError:  # traced numbers
            return fn(robot, *args)
        return jitted(robot, *args)

    return call


def read_model_file(path: str | Path) -> Any:
    """The parsed JSON of a model file; a missing, unreadable or malformed file raises
    ``ModelFileError`` naming it."""
    return read_json_or(path, lambda reason: ModelFileError(str(path), "<file>", reason))


def load_robot(robot: str | Path | Robot | dict) -> Robot:
    """A ``Robot`` from a file path, a bundled robot name ("tdcr3", "tdcr4_ext", …), a
    dict, or a ``Robot`` (returned as is). Names resolve through the one resolver,
    ``_resources.resolve_file``, from any directory.

    Raises:
        ModelFileError: neither a file nor a bundled name (the message lists the bundled
            robots), or a file that does not follow the schema.
    """
    if isinstance(robot, Robot):
        return robot
    if isinstance(robot, dict):
        return Robot.from_dict(robot)
    return Robot.from_file(robot)


# ---------------------------------------------------------------- validation helpers

MAX_POINTS_PER_SEGMENT = 1000
"""Most backbone points per segment a robot file may ask for (the bundled robots use 10);
past it the collision model's arrays, not the file, would be the error."""
MAX_TENDONS_PER_SEGMENT = 64
"""Most tendons per segment a robot file may ask for (the bundled robots have 3)."""

_TOP_KEYS = {"name", "description", "segments", "backbone_radius", "points_per_segment",
             "tendons", "base", "tendon_speed_max", "tendon_accel_max", "actuation",
             "self_collision", "mechanics"}
_SEGMENT_KEYS = {"length", "theta_max", "phi_range", "name"}
_TENDON_KEYS = {"per_segment", "radius", "offsets", "routing"}
_BASE_KEYS = {"position", "wxyz"}


def _short(value: Any) -> str:
    """``repr`` of a file's value, cut to 40 characters (a 400-digit integer stays readable)."""
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:37]}..."


class _Checker:
    def __init__(self, source: str) -> None:
        self.source = source

    def fail(self, field_path: str, problem: str) -> ModelFileError:
        return ModelFileError(self.source, field_path, problem)

    def obj(self, value: Any, path: str, allowed: set[str], required: set[str]) -> dict:
        if not isinstance(value, dict):
            raise self.fail(path or "<top>", f"expected an object, got {type(value).__name__}")
        unknown = sorted(set(value) - allowed)
        if unknown:
            raise self.fail(f"{path}.{unknown[0]}" if path else unknown[0],
                            f"unknown key (allowed: {', '.join(sorted(allowed))})")
        missing = sorted(required - set(value))
        if missing:
            raise self.fail(f"{path}.{missing[0]}" if path else missing[0],
                            "missing required field")
        return value

    def number(self, value: Any, path: str, *, positive: bool = False,
               nonnegative: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(path, f"expected a number, got {type(value).__name__} {value!r}")
        try:
            x = float(value)
        except OverflowError:  # an integer past float's range (JSON allows any length)
            x = math.inf
        if not math.isfinite(x):
            raise self.fail(path, f"must be finite, got {_short(value)}")
        if positive and x <= 0:
            raise self.fail(path, f"must be positive, got {value!r}")
        if nonnegative and x < 0:
            raise self.fail(path, f"must not be negative, got {value!r}")
        return x

    def integer(self, value: Any, path: str, minimum: int, maximum: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(path, f"expected an integer, got {type(value).__name__} {value!r}")
        if value < minimum:
            raise self.fail(path, f"must be at least {minimum}, got {_short(value)}")
        if value > maximum:
            raise self.fail(path, f"must be at most {maximum}, got {_short(value)}")
        return value

    def vector(self, value: Any, path: str, size: int) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)) or len(value) != size:
            raise self.fail(path, f"expected a list of {size} numbers, got {_short(value)}")
        return tuple(self.number(v, f"{path}[{i}]") for i, v in enumerate(value))


def _parse_robot(data: Any, source: str) -> Robot:
    c = _Checker(source)
    d = c.obj(data, "", _TOP_KEYS,
              {"segments", "backbone_radius", "points_per_segment", "tendons"})
    name = d.get("name", Path(source).stem if source else "robot")
    if not isinstance(name, str) or not name:
        raise c.fail("name", f"expected a non-empty string, got {name!r}")

    raw_segments = d["segments"]
    if not isinstance(raw_segments, list):
        raise c.fail("segments", f"expected a list of segments, got {type(raw_segments).__name__}")
    if not raw_segments:
        raise c.fail("segments", "the robot needs at least one segment")
    segments = tuple(_parse_segment(c, s, f"segments[{i}]") for i, s in enumerate(raw_segments))
    n = len(segments)

    backbone_radius = c.number(d["backbone_radius"], "backbone_radius", positive=True)
    points = c.integer(d["points_per_segment"], "points_per_segment", 1,
                       MAX_POINTS_PER_SEGMENT)

    t = c.obj(d["tendons"], "tendons", _TENDON_KEYS, {"per_segment", "radius"})
    per_segment = c.integer(t["per_segment"], "tendons.per_segment", 1,
                            MAX_TENDONS_PER_SEGMENT)
    radius = c.number(t["radius"], "tendons.radius", positive=True)
    offsets = c.vector(t.get("offsets", [0.0] * n), "tendons.offsets", n)
    routing = t.get("routing", "per_segment")
    if routing not in ("shared", "per_segment"):
        raise c.fail("tendons.routing", f"must be 'shared' or 'per_segment', got {routing!r}")

    base = c.obj(d.get("base", {}), "base", _BASE_KEYS, set())
    position = c.vector(base.get("position", [0.0, 0.0, 0.0]), "base.position", 3)
    wxyz = c.vector(base.get("wxyz", [1.0, 0.0, 0.0, 0.0]), "base.wxyz", 4)
    norm = math.sqrt(sum(v * v for v in wxyz))
    if abs(norm - 1.0) > 1e-6:
        raise c.fail("base.wxyz", f"must be a unit quaternion, its norm is {norm:.6g}")

    speed = c.number(d["tendon_speed_max"], "tendon_speed_max",
                     positive=True) if "tendon_speed_max" in d else math.inf
    accel = c.number(d["tendon_accel_max"], "tendon_accel_max",
                     positive=True) if "tendon_accel_max" in d else math.inf
    self_collision = d.get("self_collision", True)
    if not isinstance(self_collision, bool):
        raise c.fail("self_collision", f"expected true or false, got {self_collision!r}")

    actuation = None
    if "actuation" in d:
        actuation = parse_actuation(c, d["actuation"], tendon_count(per_segment, n, routing), n)

    return Robot(
        name=name,
        segments=segments,
        backbone_radius=backbone_radius,
        points_per_segment=points,
        tendons=Tendons(per_segment, radius, offsets, routing),
        base_position=position,  # type: ignore[arg-type]
        base_wxyz=wxyz,  # type: ignore[arg-type]
        tendon_speed_max=speed,
        tendon_accel_max=accel,
        self_collision=self_collision,
        source=source,
        actuation=actuation,
        mechanics=parse_mechanics(c, d["mechanics"], n) if "mechanics" in d else None,
    )


def _parse_segment(c: _Checker, raw: Any, path: str) -> Segment:
    s = c.obj(raw, path, _SEGMENT_KEYS, {"length", "theta_max"})
    length = s["length"]
    if isinstance(length, (list, tuple)):
        lo, hi = c.vector(length, f"{path}.length", 2)
        if lo <= 0:
            raise c.fail(f"{path}.length", f"lengths must be positive, got minimum {lo}")
        if hi < lo:
            raise c.fail(f"{path}.length", f"range [min, max] has max < min: {list(length)}")
    else:
        lo = hi = c.number(length, f"{path}.length", positive=True)
    theta_max = c.number(s["theta_max"], f"{path}.theta_max", positive=True)
    if theta_max > math.pi + 1e-6:
        raise c.fail(f"{path}.theta_max", f"must be at most π (3.14159…), got {theta_max}")
    theta_max = min(theta_max, math.pi)
    phi_min, phi_max = -math.inf, math.inf
    if "phi_range" in s:
        phi_min, phi_max = c.vector(s["phi_range"], f"{path}.phi_range", 2)
        if phi_max <= phi_min:
            raise c.fail(f"{path}.phi_range", f"needs min < max, got {list(s['phi_range'])}")
    return Segment(lo, hi, theta_max, phi_min, phi_max)

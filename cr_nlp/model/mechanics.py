"""The optional ``mechanics`` block of a robot file: material, cross-section and masses.

The block turns a PCC robot file into one the Cosserat statics model
(``cr_nlp.model.cosserat``) can solve: a backbone tube or rod of Young's modulus E and
Poisson ratio ν, its mass per metre, the spacer disks along each segment and their mass,
and the largest tension a tendon may carry. Units: Pa, metres, kg/m, kg, newtons.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

_MECHANICS_KEYS = {"youngs_modulus", "poisson_ratio", "backbone_outer_radius",
                   "backbone_inner_radius", "linear_density", "disks_per_segment",
                   "disk_mass", "tension_max", "segment_stiffness", "tendon_stiffness",
                   "tendon_take_up", "calibration_gravity"}
MAX_DISKS_PER_SEGMENT = 1000
"""Most spacer disks per segment a ``mechanics`` block may list (each is a point load)."""
_REQUIRED = {"youngs_modulus", "poisson_ratio", "backbone_outer_radius"}


def require_mechanics(robot: Any, needs: str) -> Mechanics:
    """The robot's ``mechanics`` block; ``needs`` names what asks for it ("tension-space
    IK") in the error.

    Raises:
        ValueError: the robot file has no ``mechanics`` block.
    """
    if robot.mechanics is None:
        raise ValueError(f"{robot.name}: {needs} needs a 'mechanics' block in the robot file "
                         "(see models/README.md)")
    return robot.mechanics


@dataclass(frozen=True)
class Mechanics:
    """Material and mass data of the backbone (the robot file's ``mechanics`` block)."""

    youngs_modulus: float
    """Young's modulus E of the backbone, Pa."""
    poisson_ratio: float
    """Poisson ratio ν; the shear modulus is G = E / (2 (1 + ν))."""
    backbone_outer_radius: float
    """Outer radius of the backbone's cross-section, metres."""
    backbone_inner_radius: float
    """Inner radius (0 for a solid rod), metres."""
    linear_density: float
    """Mass per metre of backbone, kg/m (gravity only)."""
    disks_per_segment: tuple[int, ...]
    """Spacer disks per segment, evenly spaced, the last at the segment's end."""
    disk_mass: float
    """Mass of one disk, kg (gravity only)."""
    tension_max: float
    """Largest tension a tendon may carry, newtons (inf: unlimited)."""
    segment_stiffness: tuple[float, ...] = ()
    """Per segment, a factor on every stiffness of its cross-section (E·I, E·A, G·A, G·J;
    dimensionless, > 0): segments of one backbone that bend unlike the nominal section
    (``cr-nlp calibrate --model cosserat`` fits it). Empty: 1 for every segment."""
    tendon_stiffness: tuple[float, ...] = ()
    """Per segment, the axial stiffness k of each tendon anchored there, N/m (tension per
    metre of stretch beyond its free length): what makes the rod follow commanded tendon
    displacements (``model.cosserat.solve_displacement_statics``). Empty: not given (tension-driven
    statics only)."""
    calibration_gravity: tuple[float, ...] = ()
    """The gravitational acceleration (3,) in the robot file's world (measurement) frame
    that ``cr-nlp calibrate --model cosserat`` found, m/s²; its size also carries the
    fitted scale of the masses (only the product of mass and g acts). ``predict --model
    cosserat`` applies it; other commands take loads from their options. Empty: none."""
    tendon_take_up: tuple[float, ...] = ()
    """Per segment, the take-up compliance c_i, m/N: every tendon running through segment
    i loses c_i · N_i of its path, N_i the sum of the tensions through segment i (the
    section's axial give under the tendon load: the take-up of ``cr-nlp calibrate
    --axial-compression tendons`` on the geometric model). It changes which tensions a
    command gives (``model.cosserat.solve_displacement_statics``, ``motor_commands``),
    not the shape that tensions give. Empty: none."""

    # ------------------------------------------------------------ section properties
    @property
    def area(self) -> float:
        """Cross-section area A, m²."""
        return math.pi * (self.backbone_outer_radius ** 2 - self.backbone_inner_radius ** 2)

    @property
    def second_moment(self) -> float:
        """Second moment of area I about a bending axis, m⁴ (J = 2 I for torsion)."""
        return math.pi / 4 * (self.backbone_outer_radius ** 4 - self.backbone_inner_radius ** 4)

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + ν)), Pa."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def bending_stiffness(self) -> float:
        """E·I, N·m²."""
        return self.youngs_modulus * self.second_moment

    def stiffness_diagonals(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(Kse, Kbt) diagonals: (GA, GA, EA) in N and (EI, EI, G·2I) in N·m²."""
        g, a, i = self.shear_modulus, self.area, self.second_moment
        e = self.youngs_modulus
        return (g * a, g * a, e * a), (e * i, e * i, 2.0 * g * i)

    def to_dict(self) -> dict[str, Any]:
        """The JSON form of the block (round-trips through ``parse_mechanics``)."""
        out: dict[str, Any] = {
            "youngs_modulus": self.youngs_modulus,
            "poisson_ratio": self.poisson_ratio,
            "backbone_outer_radius": self.backbone_outer_radius,
            "backbone_inner_radius": self.backbone_inner_radius,
            "linear_density": self.linear_density,
            "disks_per_segment": list(self.disks_per_segment),
            "disk_mass": self.disk_mass,
        }
        if math.isfinite(self.tension_max):
            out["tension_max"] = self.tension_max
        if self.segment_stiffness:
            out["segment_stiffness"] = list(self.segment_stiffness)
        if self.tendon_stiffness:
            out["tendon_stiffness"] = list(self.tendon_stiffness)
        if self.calibration_gravity:
            out["calibration_gravity"] = list(self.calibration_gravity)
        if self.tendon_take_up:
            out["tendon_take_up"] = list(self.tendon_take_up)
        return out

    def stiffness_factors(self, n_segments: int) -> tuple[float, ...]:
        """(n,) the segments' stiffness factors (1 where the block gives none)."""
        return self.segment_stiffness or (1.0,) * n_segments

    def take_up(self, n_segments: int) -> tuple[float, ...]:
        """(n,) the segments' take-up compliances, m/N (0 where the block gives none)."""
        return self.tendon_take_up or (0.0,) * n_segments


def parse_mechanics(c: Any, raw: Any, n_segments: int) -> Mechanics:
    """Validate the ``mechanics`` block with the robot loader's checker ``c`` (robot.py's
    ``_Checker``; not imported here, robot.py imports this module).

    Raises ``ModelFileError`` naming ``mechanics.<field>`` for a missing, unknown or
    out-of-range entry.
    """
    d = c.obj(raw, "mechanics", _MECHANICS_KEYS, _REQUIRED)
    e = c.number(d["youngs_modulus"], "mechanics.youngs_modulus", positive=True)
    nu = c.number(d["poisson_ratio"], "mechanics.poisson_ratio")
    if not -1.0 < nu < 0.5:
        raise c.fail("mechanics.poisson_ratio", f"must lie in (-1, 0.5), got {nu}")
    outer = c.number(d["backbone_outer_radius"], "mechanics.backbone_outer_radius",
                     positive=True)
    inner = c.number(d.get("backbone_inner_radius", 0.0), "mechanics.backbone_inner_radius",
                     nonnegative=True)
    if inner >= outer:
        raise c.fail("mechanics.backbone_inner_radius",
                     f"must be smaller than backbone_outer_radius ({outer}), got {inner}")
    density = c.number(d.get("linear_density", 0.0), "mechanics.linear_density",
                       nonnegative=True)
    raw_disks = d.get("disks_per_segment", [1] * n_segments)
    if not isinstance(raw_disks, list) or len(raw_disks) != n_segments:
        raise c.fail("mechanics.disks_per_segment",
                     f"expected a list of {n_segments} integers (one per segment), "
                     f"got {raw_disks!r}")
    disks = tuple(c.integer(v, f"mechanics.disks_per_segment[{i}]", 1, MAX_DISKS_PER_SEGMENT)
                  for i, v in enumerate(raw_disks))
    disk_mass = c.number(d.get("disk_mass", 0.0), "mechanics.disk_mass", nonnegative=True)
    tension_max = (c.number(d["tension_max"], "mechanics.tension_max", positive=True)
                   if "tension_max" in d else math.inf)
    factors = _per_segment(c, d, "segment_stiffness", n_segments)
    tendon_k = _per_segment(c, d, "tendon_stiffness", n_segments)
    gravity = (c.vector(d["calibration_gravity"], "mechanics.calibration_gravity", 3)
               if "calibration_gravity" in d else ())
    take_up = _per_segment(c, d, "tendon_take_up", n_segments)
    return Mechanics(e, nu, outer, inner, density, disks, disk_mass, tension_max, factors,
                     tendon_k, tuple(float(v) for v in gravity), take_up)


def _per_segment(c: Any, d: dict, key: str, n_segments: int) -> tuple[float, ...]:
    """An optional positive per-segment list (one number stands for every segment)."""
    if key not in d:
        return ()
    raw = d[key]
    if isinstance(raw, (int, float)) and not isinstance(raw, bool):
        raw = [raw] * n_segments
    values = c.vector(raw, f"mechanics.{key}", n_segments)
    if any(not v > 0 or not math.isfinite(v) for v in values):
        raise c.fail(f"mechanics.{key}", f"must be finite and positive, got {list(values)}")
    return tuple(float(v) for v in values)

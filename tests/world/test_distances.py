"""Body-sphere ↔ part distances against closed forms and against python-fcl."""

import math

import jax
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cr_nlp.model._ops import NUMPY
from cr_nlp.model.rotations import matrix_from_wxyz
from cr_nlp.world import BoxPart, CapsulePart, ConvexPart, CylinderPart, SpherePart
from cr_nlp.world import _distances as dist
from cr_nlp.world.check import fcl_distance, fcl_object

FCL_TOL = 2e-5   # fcl's GJK/EPA answers to about 1e-6 m; leave room
coord = st.floats(-2.0, 2.0, allow_nan=False)
point = st.tuples(coord, coord, coord).map(np.array)
radius = st.floats(0.05, 0.5)
quaternion = st.tuples(*[st.floats(-1, 1)] * 4).filter(
    lambda q: sum(v * v for v in q) > 0.1).map(lambda q: np.array(q) / np.linalg.norm(q))


def body_fcl(center: np.ndarray, r: float):
    return fcl_object(SpherePart(center, r))


def t(v: np.ndarray) -> tuple:
    return tuple(float(x) for x in v)


# ---------------------------------------------------------------- closed forms

@given(c=point, r=radius, o=point, R=radius)
def test_sphere_to_sphere(c, r, o, R) -> None:
    d = dist.sphere_to_sphere(NUMPY, t(c), r, t(o), R)
    assert d == pytest.approx(np.linalg.norm(c - o) - r - R, abs=1e-12)
    if np.linalg.norm(c - o) > 1e-3:
        assert d == pytest.approx(fcl_distance(body_fcl(c, r), fcl_object(SpherePart(o, R))),
                                  abs=FCL_TOL)


@given(c=point, r=radius, a=point, b=point, R=radius)
def test_sphere_to_capsule(c, r, a, b, R) -> None:
    if np.linalg.norm(b - a) < 1e-2:
        return
    d = dist.sphere_to_capsule(NUMPY, t(c), r, t(a), t(b), R)
    s = np.linspace(0.0, 1.0, 20001)[:, None]
    brute = np.min(np.linalg.norm(a + s * (b - a) - c, axis=1)) - R - r
    assert d == pytest.approx(brute, abs=1e-4) and d <= brute + 1e-12
    if d > -R - r + 1e-3:  # fcl's capsule penetration needs a non-degenerate direction
        assert d == pytest.approx(fcl_distance(body_fcl(c, r), fcl_object(CapsulePart(a, b, R))),
                                  abs=FCL_TOL)


@given(c=point, r=radius, center=point, q=quaternion,
       half=st.tuples(*[st.floats(0.05, 1.0)] * 3).map(np.array))
def test_sphere_to_box(c, r, center, q, half) -> None:
    rot = matrix_from_wxyz(q)
    d = dist.sphere_to_box(NUMPY, t(c), r, t(center), t(rot.ravel()), t(half))
    local = rot.T @ (c - center)
    outside = np.linalg.norm(np.maximum(np.abs(local) - half, 0.0))
    inside = np.min(half - np.abs(local))
    exact = (outside if outside > 0 else -inside) - r
    assert d == pytest.approx(exact, abs=1e-12)
    assert d == pytest.approx(fcl_distance(body_fcl(c, r), fcl_object(BoxPart(center, rot, half))),
                              abs=FCL_TOL)


@given(c=point, r=radius, a=point, b=point, R=radius)
def test_sphere_to_cylinder(c, r, a, b, R) -> None:
    if np.linalg.norm(b - a) < 0.05:
        return
    part = CylinderPart(a, b, R)
    d = dist.sphere_to_cylinder(NUMPY, t(c), r, t(part.center), t(part.rotation.ravel()), R,
                                part.half_length)
    axis = (b - a) / np.linalg.norm(b - a)
    along = (c - part.center) @ axis
    radial = np.linalg.norm(c - part.center - along * axis)
    qr, qa = radial - R, abs(along) - part.half_length
    exact = (math.hypot(max(qr, 0), max(qa, 0)) + min(max(qr, qa), 0.0)) - r
    assert d == pytest.approx(exact, abs=1e-12)
    # fcl's cylinder uses GJK/EPA on a curved shape: compare where that is well posed.
    if d > -r + 0.05:
        assert d == pytest.approx(fcl_distance(body_fcl(c, r), fcl_object(part)), abs=1e-3)


# ---------------------------------------------------------------- convex parts

def convex_planes(part: ConvexPart, count: int) -> tuple:
    rows = np.c_[part.normals, part.offsets]
    rows = np.concatenate([rows, np.repeat(rows[:1], count - len(rows), axis=0)])
    return tuple(rows[:, k] for k in range(4))


@settings(deadline=None)
@given(c=point, r=radius, seed=st.integers(0, 10_000))
def test_convex_plane_bound_never_exceeds_fcl(c, r, seed) -> None:
    part = ConvexPart.from_points(np.random.default_rng(seed).normal(size=(12, 3)) * 0.6)
    count = 1 << math.ceil(math.log2(len(part.offsets)))
    d = dist.sphere_to_convex(NUMPY, t(c), r, convex_planes(part, count), count)
    truth = fcl_distance(body_fcl(c, r), fcl_object(part))
    assert d <= truth + FCL_TOL
    for mu in (0.002, 0.01, 0.05):
        smooth = dist.sphere_to_convex(NUMPY, t(c), r, convex_planes(part, count), count, mu)
        assert smooth <= d + 1e-12
        assert smooth >= d - dist.smooth_max_shift(count, mu) - 1e-12


@given(u=st.floats(-0.9, 0.9), v=st.floats(-0.9, 0.9), gap=st.floats(-0.3, 1.0),
       face=st.integers(0, 5))
def test_convex_plane_bound_is_exact_over_a_face(u, v, gap, face) -> None:
    """A unit cube as a convex part: in front of a face (or inside) the bound is exact."""
    cube = BoxPart(np.zeros(3), np.eye(3), np.ones(3))
    part = ConvexPart.from_points(
        np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float))
    axis, sign = divmod(face, 2)
    c = np.empty(3)
    c[axis] = (1.0 + gap) * (1 if sign else -1)
    c[[k for k in range(3) if k != axis]] = (u, v)
    d = dist.sphere_to_convex(NUMPY, t(c), 0.1, convex_planes(part, 8), 8)
    exact = dist.sphere_to_box(NUMPY, t(c), 0.1, (0.0, 0.0, 0.0), t(np.eye(3).ravel()),
                               (1.0, 1.0, 1.0))
    assert len(part.offsets) == 6 and d == pytest.approx(exact, abs=1e-12)
    assert d == pytest.approx(fcl_distance(body_fcl(c, 0.1), fcl_object(cube)), abs=FCL_TOL)


def test_tree_max_is_max_and_smooth_bound_is_tight() -> None:
    values = np.array([0.3, -0.2, 0.31, 0.1, 0.0, 0.305, -1.0, 0.2])
    assert dist.tree_max(NUMPY, values, 8) == pytest.approx(0.31)
    for mu in (1e-3, 1e-2, 1e-1):
        smooth = dist.tree_max(NUMPY, values, 8, mu)
        assert 0.31 <= smooth <= 0.31 + dist.smooth_max_shift(8, mu)
    # Equal values are the worst case: μ/2 per level, log₂(8) = 3 levels.
    assert dist.tree_max(NUMPY, np.zeros(8), 8, 0.01) == pytest.approx(3 * 0.005)
    with pytest.raises(ValueError, match="power-of-two"):
        dist.tree_max(NUMPY, values[:6], 6)


def test_distances_have_finite_gradients_at_singular_points() -> None:
    """Centre on a sphere's centre, on a capsule's axis, inside a box: no NaN gradients."""
    import jax.numpy as jnp

    from cr_nlp.model._ops import JAX

    def total(c: jnp.ndarray) -> jnp.ndarray:
        e = (c[0], c[1], c[2])
        return (dist.sphere_to_sphere(JAX, e, 0.1, (0.0, 0.0, 0.0), 0.5)
                + dist.sphere_to_capsule(JAX, e, 0.1, (0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 0.2)
                + dist.sphere_to_box(JAX, e, 0.1, (0.0, 0.0, 0.0), tuple(np.eye(3).ravel()),
                                     (1.0, 1.0, 1.0))
                + dist.sphere_to_cylinder(JAX, e, 0.1, (0.0, 0.0, 0.0), tuple(np.eye(3).ravel()),
                                          0.5, 1.0))

    g = jax.grad(total)(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))


def test_capsule_sphere_closed_form_matches_fcl_and_handles_a_centre_on_the_axis() -> None:
    from cr_nlp.world.check import capsule_object, capsule_sphere_distance

    rng = np.random.default_rng(5)
    for _ in range(200):
        a, b, c = rng.normal(size=(3, 3))
        r, rs = rng.uniform(0.05, 0.3, 2)
        exact = capsule_sphere_distance(a, b, r, c, rs)
        if exact > 1e-3:  # fcl's separated-pair query is accurate; compare there
            fcl_d = fcl_distance(capsule_object(a, b, r), fcl_object(SpherePart(c, rs)))
            assert abs(exact - fcl_d) < 1e-6
    # The degenerate case fcl's penetration query hung on: the centre on the axis.
    a, b = np.zeros(3), np.array([0.0, 0.0, 1.0])
    on_axis = capsule_sphere_distance(a, b, 0.1, np.array([0.0, 0.0, 0.4]), 0.02)
    assert on_axis == pytest.approx(-0.12)

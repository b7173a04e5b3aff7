"""The public kinematics answer numpy in float64 (against an independent float64 evaluation
written here from docs/design.md §1), and JAX in with JAX out, traceable."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import cr_nlp
from cr_nlp.model import (
    Robot,
    backbone_points,
    pose_error,
    pose_error_vector,
    tendon_lengths,
    tip_pose,
)
from cr_nlp.model.rotations import matrix_from_wxyz, wxyz_from_matrix

from ..conftest import MODELS

TDCR3 = Robot.from_file(MODELS / "robots" / "tdcr3.json")
TDCR4 = Robot.from_file(MODELS / "robots" / "tdcr4_ext.json")
ROBOTS = [TDCR3, TDCR4]


# ------------------------------------------------------------------ independent float64 model


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def segment(theta: float, phi: float, length: float) -> np.ndarray:
    """The PCC segment transform as docs/design.md §1 writes it: Rz(φ)·Ry(θ)·Rz(−φ) and
    d = (L/θ)(cos φ (1 − cos θ), sin φ (1 − cos θ), sin θ), d = (0, 0, L) at θ = 0."""
    t = np.eye(4)
    t[:3, :3] = rz(phi) @ ry(theta) @ rz(-phi)
    versine = 2.0 * np.sin(theta / 2) ** 2  # 1 − cos θ without cancellation at small θ
    if theta == 0.0:
        t[:3, 3] = [0.0, 0.0, length]
    else:
        t[:3, 3] = (length / theta) * np.array(
            [np.cos(phi) * versine, np.sin(phi) * versine, np.sin(theta)]
        )
    return t


def base(robot: Robot) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_quat(np.roll(robot.base_wxyz, -1)).as_matrix()
    t[:3, 3] = robot.base_position
    return t


def reference_tip(robot: Robot, q: np.ndarray) -> np.ndarray:
    t = base(robot)
    for i in range(robot.n_segments):
        t = t @ segment(*q[3 * i : 3 * i + 3])
    return t


def reference_backbone(robot: Robot, q: np.ndarray) -> np.ndarray:
    t, out = base(robot), []
    k = robot.points_per_segment
    for i in range(robot.n_segments):
        theta, phi, length = q[3 * i : 3 * i + 3]
        for j in range(1, k + 1):
            out.append((t @ segment(theta * j / k, phi, length * j / k))[:3, 3])
        t = t @ segment(theta, phi, length)
    return np.array(out)


def reference_tendons(robot: Robot, q: np.ndarray) -> np.ndarray:
    n, m, r = robot.n_segments, robot.tendons.per_segment, robot.tendons.radius

    def part(i: int, angle: float) -> float:
        return q[3 * i + 2] - r * q[3 * i] * np.cos(angle - q[3 * i + 1])

    alpha = [[j * 2 * np.pi / m + robot.tendons.offsets[i] for j in range(m)] for i in range(n)]
    if robot.tendons.routing == "shared":
        return np.array([sum(part(i, alpha[i][j]) for i in range(n)) for j in range(m)])
    return np.array(
        [sum(part(i, alpha[k][j]) for i in range(k + 1)) for k in range(n) for j in range(m)]
    )


def reference_log(t: np.ndarray) -> np.ndarray:
    """SE(3) log by scipy's rotation vector and a numerical solve with V(ω)."""
    w = Rotation.from_matrix(t[:3, :3]).as_rotvec()
    theta = np.linalg.norm(w)
    hat = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-8:
        v_mat = np.eye(3) + 0.5 * hat
    else:
        v_mat = (
            np.eye(3)
            + (1 - np.cos(theta)) / theta**2 * hat
            + (theta - np.sin(theta)) / theta**3 * hat @ hat
        )
    return np.concatenate([np.linalg.solve(v_mat, t[:3, 3]), w])


def configurations(robot: Robot, count: int, seed: int) -> np.ndarray:
    lo, hi = robot.q_bounds()
    q = np.random.default_rng(seed).uniform(lo, hi, (count, robot.dof))
    q[0, 0::3] = 0.0  # straight
    q[1, 0::3] = hi[0::3]  # θ = θmax everywhere
    q[2, 3] = 0.0  # one straight segment among bent ones
    return q


# ------------------------------------------------------------------ numpy in, float64 out


@pytest.mark.parametrize("robot", ROBOTS, ids=lambda r: r.name)
def test_tip_pose_is_float64_numpy_and_matches_the_product_of_transforms(robot: Robot) -> None:
    q = configurations(robot, 40, 1)
    for given in (q, q.astype(np.float32).astype(np.float64), q.tolist()):
        p, r = tip_pose(robot, given)
        assert type(p) is np.ndarray and type(r) is np.ndarray
        assert p.dtype == np.float64 and r.dtype == np.float64
        assert p.shape == (40, 3) and r.shape == (40, 3, 3)
    p, r = tip_pose(robot, q)
    for i in range(len(q)):
        expected = reference_tip(robot, q[i])
        np.testing.assert_allclose(p[i], expected[:3, 3], rtol=0, atol=1e-12)
        np.testing.assert_allclose(r[i], expected[:3, :3], rtol=0, atol=1e-12)
    # One configuration (3n,) and batch shapes keep their shape.
    p1, r1 = tip_pose(robot, q[5])
    assert p1.shape == (3,) and r1.shape == (3, 3) and p1.dtype == np.float64
    np.testing.assert_array_equal(p1, p[5])
    assert tip_pose(robot, q[:12].reshape(3, 4, -1))[0].shape == (3, 4, 3)


def test_float32_numpy_input_is_evaluated_in_float64() -> None:
    q32 = configurations(TDCR3, 10, 2).astype(np.float32)
    p, _ = tip_pose(TDCR3, q32)
    assert p.dtype == np.float64
    for i in range(len(q32)):
        np.testing.assert_allclose(
            p[i], reference_tip(TDCR3, q32[i].astype(float))[:3, 3], rtol=0, atol=1e-12
        )


@pytest.mark.parametrize("robot", ROBOTS, ids=lambda r: r.name)
def test_backbone_and_tendons_are_float64_numpy_and_exact(robot: Robot) -> None:
    q = configurations(robot, 20, 3)
    points = backbone_points(robot, q)
    lengths = tendon_lengths(robot, q)
    assert type(points) is np.ndarray and points.dtype == np.float64
    assert type(lengths) is np.ndarray and lengths.dtype == np.float64
    assert points.shape == (20, robot.n_points, 3) and lengths.shape == (20, robot.n_tendons)
    for i in range(len(q)):
        np.testing.assert_allclose(points[i], reference_backbone(robot, q[i]), rtol=0, atol=1e-12)
        np.testing.assert_allclose(lengths[i], reference_tendons(robot, q[i]), rtol=0, atol=1e-12)
    assert tendon_lengths(robot, q[0]).shape == (robot.n_tendons,)


def test_pose_error_is_float64_numpy_and_matches_the_se3_log() -> None:
    q = configurations(TDCR3, 30, 4)
    goal = configurations(TDCR3, 30, 5)
    p, r = tip_pose(TDCR3, q)
    tp, tr = tip_pose(TDCR3, goal)
    err = pose_error(p, r, tp, tr)
    vec = pose_error_vector(p, r, tp, tr)
    assert type(err) is np.ndarray and err.dtype == np.float64 and err.shape == (30,)
    assert vec.dtype == np.float64 and vec.shape == (30, 6)
    for i in range(len(q)):
        a, b = reference_tip(TDCR3, q[i]), reference_tip(TDCR3, goal[i])
        inverse = np.eye(4)
        inverse[:3, :3], inverse[:3, 3] = a[:3, :3].T, -a[:3, :3].T @ a[:3, 3]
        expected = reference_log(inverse @ b)
        if np.linalg.norm(expected[3:]) > np.pi - 1e-6:
            continue  # the log's branch at a half turn is not unique
        np.testing.assert_allclose(vec[i], expected, rtol=0, atol=1e-12)
        assert abs(err[i] - np.linalg.norm(expected)) < 1e-12
    assert float(pose_error(p[0], r[0], p[0], r[0])) < 1e-15


def test_the_package_exports_the_float64_functions() -> None:
    q = configurations(TDCR3, 3, 6)
    assert cr_nlp.tip_pose(TDCR3, q)[0].dtype == np.float64
    assert cr_nlp.backbone_points(TDCR3, q).dtype == np.float64
    assert cr_nlp.tendon_lengths(TDCR3, q).dtype == np.float64
    p, r = cr_nlp.tip_pose(TDCR3, q)
    assert cr_nlp.pose_error(p, r, p, r).dtype == np.float64


def test_quaternion_conversions_are_float64() -> None:
    q = configurations(TDCR3, 10, 7)
    _, r = tip_pose(TDCR3, q)
    wxyz = wxyz_from_matrix(r)
    assert wxyz.dtype == np.float64
    expected = np.roll(Rotation.from_matrix(r).as_quat(), 1, axis=-1)
    expected *= np.where(expected[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(wxyz, expected, rtol=0, atol=1e-14)
    np.testing.assert_allclose(matrix_from_wxyz(wxyz), r, rtol=0, atol=1e-14)
    # one quaternion, and a batch of batches, keep their shapes
    np.testing.assert_allclose(matrix_from_wxyz(wxyz[3]), r[3], rtol=0, atol=1e-14)
    nested = matrix_from_wxyz(wxyz.reshape(2, 5, 4))
    assert nested.shape == (2, 5, 3, 3) and nested.dtype == np.float64
    np.testing.assert_allclose(nested.reshape(10, 3, 3), r, rtol=0, atol=1e-14)


# ------------------------------------------------------------------ JAX in, JAX out


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_jax_in_gives_jax_out_under_jit(dtype: jnp.dtype, request: pytest.FixtureRequest) -> None:
    if dtype == jnp.float64:
        request.getfixturevalue("float64")  # float64 JAX arrays need x64
    q = jnp.asarray(configurations(TDCR3, 8, 8), dtype)

    @jax.jit
    def everything(x: jax.Array) -> tuple:
        p, r = tip_pose(TDCR3, x)
        return (
            p,
            r,
            backbone_points(TDCR3, x),
            tendon_lengths(TDCR3, x),
            pose_error(p, r, p[::-1], r[::-1]),
        )

    p, r, points, lengths, err = everything(q)
    for x in (p, r, points, lengths, err):
        assert isinstance(x, jax.Array) and x.dtype == dtype
    p_np, r_np = tip_pose(TDCR3, np.asarray(q, dtype=np.float64))
    atol = 1e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_allclose(p, p_np, atol=atol)
    np.testing.assert_allclose(err, pose_error(p_np, r_np, p_np[::-1], r_np[::-1]), atol=10 * atol)
    # Traceable: jacfwd of the public function through the JAX path.
    jac = jax.jacfwd(lambda x: tip_pose(TDCR3, x)[0])(q[3])
    assert isinstance(jac, jax.Array) and jac.shape == (3, 9) and bool(jnp.all(jnp.isfinite(jac)))

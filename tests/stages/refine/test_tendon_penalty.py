"""The tendon speed/acceleration penalties of the LM stages against float64 finite
differences of the model's tendon lengths (numpy backend)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from cr_nlp.model import load_robot, tendon_lengths, z_to_q_numpy
from cr_nlp.stages.refine._tendon_penalty import tendon_accel_excess, tendon_speed_excess


def test_penalties_are_the_relative_overshoot_of_the_finite_differences() -> None:
    robot = load_robot("tdcr3")
    rng = np.random.default_rng(3)
    z = rng.uniform(-1.0, 1.0, (3, robot.dof))
    z[:, 2::3] = 1.0
    dt, fraction = 0.3, 0.9
    lengths = tendon_lengths(robot, z_to_q_numpy(z))            # (3, n_tendons), float64
    speed = (lengths[1] - lengths[0]) / dt
    accel = (lengths[2] - 2.0 * lengths[1] + lengths[0]) / dt**2
    expected_speed = np.maximum(np.abs(speed) / (fraction * robot.tendon_speed_max) - 1, 0)
    expected_accel = np.maximum(np.abs(accel) / (fraction * robot.tendon_accel_max) - 1, 0)
    zs = [jnp.asarray(row, jnp.float32) for row in z]
    got_speed = tendon_speed_excess(robot, fraction, zs[0], zs[1], jnp.float32(dt))
    got_accel = tendon_accel_excess(robot, fraction, *zs, jnp.float32(dt))
    assert got_speed.dtype == jnp.float32 and got_speed.shape == (robot.n_tendons,)
    # Some tendons over the limit, some under: both branches of max(0, ·) are exercised.
    assert np.any(expected_speed > 0) and np.any(expected_speed == 0)
    assert np.any(expected_accel > 0) and np.any(expected_accel == 0)
    np.testing.assert_allclose(got_speed, expected_speed, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(got_accel, expected_accel, rtol=1e-4, atol=1e-3)

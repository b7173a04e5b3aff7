"""Process-wide JAX settings: full float32 matrix products (no TF32 on NVIDIA GPUs) unless
the user chose a precision."""

import os
import subprocess
import sys

import jax

import cr_nlp  # noqa: F401  (importing cr_nlp applies the setting)


def _precision_in_fresh_process(env_value: str | None) -> str:
    env = dict(os.environ)
    env.pop("JAX_DEFAULT_MATMUL_PRECISION", None)
    if env_value is not None:
        env["JAX_DEFAULT_MATMUL_PRECISION"] = env_value
    code = "import cr_nlp, jax; print(jax.config.jax_default_matmul_precision)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True)
    return out.stdout.strip()


def test_importing_cr_nlp_asks_for_full_float32_products():
    assert jax.config.jax_default_matmul_precision in ("highest", "float32")
    assert _precision_in_fresh_process(None) == "highest"


def test_a_precision_the_user_chose_is_kept():
    assert _precision_in_fresh_process("bfloat16") == "bfloat16"


def test_the_tests_run_in_the_users_float32_default():
    """A user's process (``import cr_nlp`` and its CLI) leaves JAX's x64 off, and so does
    the test session (unless $JAX_ENABLE_X64 asks): JAX arrays default to float32."""
    import jax.numpy as jnp

    code = ("import cr_nlp, cr_nlp.cli.main, jax.numpy as jnp; "
            "print(jnp.asarray(1.0).dtype)")
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == "float32"
    session = jnp.float64 if os.environ.get("JAX_ENABLE_X64") else jnp.float32
    assert jnp.asarray(1.0).dtype == session


def test_the_float64_fixture_turns_x64_on_for_its_test(float64):  # noqa: ANN001
    import jax.numpy as jnp

    assert jnp.asarray(1.0).dtype == jnp.float64
    assert jax.jit(lambda x: x * 2)(jnp.ones(3)).dtype == jnp.float64

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

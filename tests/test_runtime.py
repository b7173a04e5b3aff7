"""Process-wide settings live in ``cr_nlp.runtime``: importing cr_nlp changes neither JAX's
configuration nor the environment; ``configure()`` does, once, and respects the user's
own choice; one ``clear_caches()`` empties every registered in-memory cache; every
environment variable the package reads is documented there."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np

import cr_nlp
from cr_nlp import _programs, runtime


def _python(code: str, **env: str) -> str:
    clean = {k: v for k, v in os.environ.items() if k != "JAX_DEFAULT_MATMUL_PRECISION"}
    run = subprocess.run([sys.executable, "-c", code], env={**clean, **env},
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return run.stdout.strip()


def test_importing_cr_nlp_leaves_jax_config_and_the_environment_as_they_were() -> None:
    out = _python(
        "import os, jax\n"
        "before = dict(jax.config.values); env = dict(os.environ)\n"
        "import cr_nlp\n"
        "cr_nlp.load_robot('tdcr3'); cr_nlp.IKConfig  # public names, imported on use\n"
        "changed = sorted(k for k in set(before) | set(jax.config.values)\n"
        "                 if before.get(k) != jax.config.values.get(k))\n"
        "print(changed, dict(os.environ) == env)\n")
    assert out == "[] True"
    # Before JAX is loaded, too: no JAX_DEFAULT_MATMUL_PRECISION left behind.
    out = _python("import os, cr_nlp\n"
                  "print(os.environ.get('JAX_DEFAULT_MATMUL_PRECISION'))\n")
    assert out == "None"


def test_configure_sets_full_precision_and_the_cache_once_unless_the_user_chose(
        tmp_path: Path) -> None:
    code = ("import jax\n"
            "from cr_nlp import runtime\n"
            "runtime.configure(); runtime.configure()\n"
            "print(jax.config.jax_default_matmul_precision,\n"
            "      jax.config.jax_compilation_cache_dir is not None)\n")
    assert _python(code, CR_NLP_CACHE_DIR=str(tmp_path)) == "highest True"
    assert _python(code, CR_NLP_CACHE_DIR=str(tmp_path),
                   JAX_DEFAULT_MATMUL_PRECISION="bfloat16") == "bfloat16 True"


def test_clear_caches_empties_every_registered_cache() -> None:
    calls = []

    @runtime.cached(maxsize=4)
    def square(x: int) -> int:
        calls.append(x)
        return x * x

    table = runtime.register({})
    assert square(3) == 9 and square(3) == 9 and calls == [3]
    table["a"] = 1
    assert runtime.clear_caches() >= 2
    assert not table and square(3) == 9 and calls == [3, 3]
    # The package's own: compiled programs in memory, scenes' and roadmaps' tables, and
    # the programs a cached_jit function keeps itself.
    assert any(cache is _programs._memory for cache in runtime._CACHES)
    from cr_nlp._cached_jit import cached_jit

    double = cached_jit(lambda x: 2.0 * x)
    assert float(double(np.float32(1.5))) == 3.0 and double._compiled
    runtime.clear_caches()
    assert not double._compiled


def test_every_environment_variable_the_package_reads_is_documented() -> None:
    root = Path(cr_nlp.__file__).parent
    named = set()
    for path in root.rglob("*.py"):
        named |= set(re.findall(r"\bCR_NLP_[A-Z_]+\b", path.read_text()))
    assert named == set(runtime.ENVIRONMENT), (
        f"undocumented: {sorted(named - set(runtime.ENVIRONMENT))}, "
        f"documented but unused: {sorted(set(runtime.ENVIRONMENT) - named)}")


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

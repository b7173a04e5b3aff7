"""Process-wide JAX settings that cr_nlp's entry points apply."""

from __future__ import annotations

import os
from pathlib import Path

import jax


def cache_dir() -> Path:
    """Where cr_nlp keeps its caches ($CR_NLP_CACHE_DIR, else ~/.cache/cr_nlp)."""
    root = os.environ.get("CR_NLP_CACHE_DIR")
    return Path(root) if root else Path.home() / ".cache" / "cr_nlp"


def enable_compilation_cache() -> None:
    """Turn on JAX's persistent compilation cache, unless the user configured one already.

    A second process then loads the solvers' compiled code instead of recompiling it.
    """
    if jax.config.jax_compilation_cache_dir:
        return
    path = Path(os.environ.get("CR_NLP_JAX_CACHE", cache_dir() / "jax"))
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)

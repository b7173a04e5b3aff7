"""Test-wide settings: float64 for agreement tests, a persistent JAX compilation cache."""

import os
from pathlib import Path

import jax

from cr_nlp._jax_setup import use_host_devices

ROOT = Path(__file__).resolve().parent.parent
MODELS = ROOT / "models"

use_host_devices()  # the solvers' sharded path runs in the tests as it does in the CLI
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_compilation_cache_dir",
                  os.environ.get("CR_NLP_JAX_CACHE", str(ROOT / ".jax_cache")))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

"""Shared set-up of the test processes: float64, and one persistent XLA compilation cache for
the whole run. The two xdist workers, the notebook kernels and the CLI subprocesses compile
many of the same solvers; with the cache each is compiled once (the variables are set before
jax is imported, and the subprocesses inherit them)."""
import os
from pathlib import Path

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      str(Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

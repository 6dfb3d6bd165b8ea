"""JAX's persistent compilation cache, on by default for the command line and the notebooks.

Every ``jaxrkpm`` run compiles the same solvers again; with the cache, a second run (another
process) loads them from disk instead (``experiments/bench_compile_cache.py`` measures the
demo's two runs). The cache lives in the user's cache folder (``$XDG_CACHE_HOME/jaxrkpm``,
else ``~/.cache/jaxrkpm``, or ``$JAXRKPM_CACHE_DIR``); ``JAXRKPM_COMPILATION_CACHE=off``
turns it off. A cache folder the user set for JAX already (``JAX_COMPILATION_CACHE_DIR``,
``jax.config``) is left as it is.
"""
from __future__ import annotations

import os
from pathlib import Path

OFF = ("0", "off", "false", "no")


def cache_dir() -> Path:
    """Where the cache is kept: ``$JAXRKPM_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxrkpm``, else
    ``~/.cache/jaxrkpm``."""
    if os.environ.get("JAXRKPM_CACHE_DIR"):
        return Path(os.environ["JAXRKPM_CACHE_DIR"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base).expanduser() / "jaxrkpm"


def use_compilation_cache(min_compile_s: float = 0.0, max_bytes: int = 2 * 2**30) -> Path | None:
    """Turn on JAX's persistent compilation cache in :func:`cache_dir` (call before the first
    compile; the command line's ``main`` and the notebooks' first cell do). Returns the
    folder in use, or None where it is off (``JAXRKPM_COMPILATION_CACHE=off``) or cannot be
    made. A folder JAX was given already is kept (and so are its settings).

    ``min_compile_s``: the compile time a program must take to be kept. Default every
    program: JAX's default threshold leaves out most of a tracking run's many small
    programs, which a second run then compiles again (``experiments/bench_compile_cache.py``
    compares); together they are small. ``max_bytes``: the cache's cap, past which the
    least recently used entries go."""
    if os.environ.get("JAXRKPM_COMPILATION_CACHE", "on").strip().lower() in OFF:
        return None
    import jax

    current = jax.config.jax_compilation_cache_dir
    if current:                       # the user's (or the test suite's) own choice
        return Path(current)
    folder = cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None                   # a read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s)
    try:                              # JAX bounds the cache's size only with filelock (a dependency)
        import filelock  # noqa: F401
        jax.config.update("jax_compilation_cache_max_size", max_bytes)
    except ImportError:
        pass
    return folder

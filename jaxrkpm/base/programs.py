"""Compiled programs hold memory mappings: when to let them go.

Linux caps a process at ``vm.max_map_count`` memory mappings (65,530 by default), and an
XLA:CPU executable holds a few per compiled kernel for as long as JAX's caches keep it, which
is as long as the process lives for a jitted function defined at module level: a tracking
loop takes thousands, a module of this project's test suite tens of thousands. A session that
compiles many different models (a notebook left open, a sweep over mesh sizes, ``jaxrkpm
reproduce``) can cross the cap, and XLA:CPU's next JIT allocation then fails inside a
compile: the process dies with SIGABRT, or SIGSEGV in libgcc's unwinder, with no Python
error. ``release_if_crowded`` after each independent piece of work keeps a process well below
it (``jax.clear_caches``: the next call of a released program compiles it again, or loads it
from JAX's persistent compilation cache where one is set).
"""
from __future__ import annotations

import gc

MAP_LIMIT_DEFAULT = 65_530


def memory_mappings() -> int:
    """This process's memory mappings (0 where /proc is not there: not Linux)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def mapping_limit() -> int:
    """The kernel's cap on a process's memory mappings (vm.max_map_count)."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return MAP_LIMIT_DEFAULT


def release_compiled_programs() -> None:
    """Drop every compiled program JAX holds (``jax.clear_caches``) and collect the garbage
    that kept them, which frees their mappings."""
    import jax
    jax.clear_caches()
    gc.collect()


def release_if_crowded(fraction: float = 0.6) -> bool:
    """``release_compiled_programs`` if the process holds more than ``fraction`` of its
    mapping cap; returns whether it did. The default leaves headroom: one large compile adds
    several thousand mappings."""
    if memory_mappings() > fraction * mapping_limit():
        release_compiled_programs()
        return True
    return False

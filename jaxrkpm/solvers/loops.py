"""Control flow shared by the solvers.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def when(need, f, default):
    """f() where ``need``, else ``default``, as a while loop that runs at most once: unlike a
    lax.cond under vmap (which evaluates both sides for every member), the loop costs nothing
    while no batch member needs it; and a ``default`` that holds large arrays (a kept
    factorisation) passes through in place, where a lax.cond copied it (measured in the
    control loop: ~40 ms a call for a 2,400^2 dense state)."""
    def body(c):
        return jnp.array(False), f()
    return jax.lax.while_loop(lambda c: c[0], body, (jnp.asarray(need), default))[1]

"""The one iteration loop of every solver and driver, and the conditional they share.

A solver (or driver) is a static object with ``step(problem, args, state) -> state`` and
``terminate(state) -> bool``; its state is a NamedTuple. ``iterate`` runs it inside jit
(``lax.while_loop``) or, for host-side iterations, as a plain Python loop.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def iterate(solver, problem, args, state, loop=jax.lax.while_loop):
    """``solver.step(problem, args, state)`` until ``solver.terminate(state)``."""
    return loop(lambda s: ~solver.terminate(s), lambda s: solver.step(problem, args, s), state)


def python_loop(cond, body, state):
    """``lax.while_loop``'s contract as a Python loop (host arrays, no tracing)."""
    while cond(state):
        state = body(state)
    return state


def when(need, f, default):
    """f() where ``need``, else ``default``, as a while loop that runs at most once: unlike a
    lax.cond under vmap (which evaluates both sides for every member), the loop costs nothing
    while no batch member needs it; and a ``default`` that holds large arrays (a kept
    factorisation) passes through in place, where a lax.cond copied it (the kept control loop
    of ``experiments/bench_cube3d.py``)."""
    def body(c):
        return jnp.array(False), f()
    return jax.lax.while_loop(lambda c: c[0], body, (jnp.asarray(need), default))[1]

"""The solver contract (``IterativeSolver``), the one loop that runs every solver and driver
(``iterate``, ``run``), and the conditional they share.

Every nonlinear solver and driver of the package (``Newton``, ``Chord``, ``StableDescent``,
``LoadPath``, ``ArcLength``, ``ArcLengthPath``, the tracking loop's ``Tracker``) is a static,
immutable object implementing ``IterativeSolver``; a solver written outside the package that
implements it runs through ``iterate`` and ``run`` the same way.
"""
from __future__ import annotations

from abc import abstractmethod
from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp


@runtime_checkable
class IterativeSolver(Protocol):
    """The contract of every solver: a static description whose iteration state is a pytree
    (a NamedTuple; host-side drivers: any immutable value), in the manner of optimistix.

    ``problem`` is what the iteration solves (a ``Problem``, or the models of a tracking
    loop); ``args`` the iteration's constants (the increment asked for, limits, the
    factorisation to start from), built by the solver's own method before the loop;
    ``start`` the iterate the loop starts from (an array, or a tuple of them).

    - ``init(problem, args, start) -> state``
    - ``step(problem, args, state) -> state``: one iteration
    - ``terminate(state) -> (done, status)``: whether the iteration is over, and its outcome
      code (the solver's own ``Outcome``: ``Status``, ``PathStatus``, ``TrackStatus``), valid
      at every state: the outcome the iteration has if it stops there
    - ``postprocess(problem, args, state, status) -> result``: the result of the final state

    Built-in solvers subclass it (so a missing method fails at construction, and the
    architecture test finds them); a solver defined elsewhere need only have the four
    methods (``isinstance(solver, IterativeSolver)``)."""

    @abstractmethod
    def init(self, problem, args, start) -> Any:
        """The state the loop starts from."""

    @abstractmethod
    def step(self, problem, args, state) -> Any:
        """The state after one iteration."""

    @abstractmethod
    def terminate(self, state) -> tuple:
        """(done, status): whether the iteration is over, and its outcome code."""

    @abstractmethod
    def postprocess(self, problem, args, state, status) -> Any:
        """The solve's result from its final state and outcome."""


def iterate(solver: IterativeSolver, problem, args, state, loop=jax.lax.while_loop):
    """``solver.step(problem, args, state)`` until ``solver.terminate(state)`` says done: the
    final state. ``loop``: ``jax.lax.while_loop`` (inside jit) or ``python_loop`` (a host-side
    iteration, whose steps may call compiled functions)."""
    def running(s):
        return jnp.logical_not(solver.terminate(s)[0])
    return loop(running, lambda s: solver.step(problem, args, s), state)


def run(solver: IterativeSolver, problem, args, start, loop=jax.lax.while_loop):
    """A whole solve through the contract: ``init``, ``iterate``, then ``postprocess`` of the
    final state with its outcome from ``terminate``."""
    state = iterate(solver, problem, args, solver.init(problem, args, start), loop)
    _, status = solver.terminate(state)
    return solver.postprocess(problem, args, state, status)


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

"""What a solve returns: its ``Status``, the ``Solution`` (a pytree; batched solves stack
every field), the critical points it passed, and the dynamic ``Limits`` it ran under.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.outcome import Outcome
from .linalg.base import LinearStats


class Status(Outcome):
    """Outcome of a solve (an int code inside jit; ``Status.of(sol.status)`` outside). A
    failure is that of the last attempt; why the path stopped there (the smallest load step
    allowed, or the failed attempts' work budget) is ``Solution.stop``."""

    CONVERGED = 0, "converged"
    MAX_ITERATIONS = 1, "Newton reached its iteration cap"
    NONFINITE = 2, "non-finite residual or energy (NaN/inf)"
    INVERTED = 3, "a step would invert the material (det F <= 0 at an integration point)"
    LINE_SEARCH = 4, "the line search found no decrease of energy or residual"
    UNSTABLE_TANGENT = 5, ("the tangent K_ff is not positive definite at the equilibrium "
                           "reached (loss of stability: a limit or bifurcation point, buckling "
                           "or loss of ellipticity passed); the path is stopped at the last "
                           "stable state (solve with check_stability=False to follow the "
                           "unstable branch)")
    STABILITY_UNKNOWN = 6, ("converged, but the linear solver could not tell whether K_ff is "
                            "positive definite (a factorisation with perturbed or permuted pivots, "
                            "or a Krylov solve that did not reach its tolerance): the state may lie "
                            "past a critical point")
    LINEAR_SOLVE = 7, "the iterative linear solver (solver='krylov') did not converge"

    @property
    def equilibrium(self) -> bool:
        """An equilibrium was reached (converged, whatever the stability check said)."""
        return self in (Status.CONVERGED, Status.STABILITY_UNKNOWN)


class Stop(Outcome):
    """Why a load path stopped short of its end (``Solution.stop``): a failed attempt is cut
    and retried until one of these ends the path."""

    NONE = 0, "the path did not stop"
    SMALLEST_STEP = 1, "on the smallest load step allowed (the initial step halved max_cuts times)"
    WORK_BUDGET = 2, ("once the failed attempts had spent their work budget (LoadPath.failed_work "
                      "x the useful Newton iterations)")
    NO_STABLE_STATE = 3, ("at a critical point, where the branch switch found no stable state of "
                          "that load")


def reached_equilibrium(status):
    """Inside jit: the status code(s) of an equilibrium (CONVERGED or STABILITY_UNKNOWN)."""
    return (status == Status.CONVERGED) | (status == Status.STABILITY_UNKNOWN)


class Limits(NamedTuple):
    """Dynamic solver limits (arrays, so changing them does not recompile).

    ``of`` bounds them by ``most_steps`` (initial load steps of one solve), ``most_iterations``
    (Newton iterations per load step) and ``most_cuts`` (halvings of the load step: 2**-50 of
    the increment is below round-off)."""

    steps: jax.Array      # initial (and largest) number of load steps
    max_iter: jax.Array   # Newton iterations per load step
    max_cuts: jax.Array   # halvings of the initial load step before giving up

    most_steps = 1000
    most_iterations = 1000
    most_cuts = 50

    @staticmethod
    def of(steps=1, max_iter=25, max_cuts=10) -> "Limits":
        """Validated limits: 1 <= steps <= most_steps, 1 <= max_iter <= most_iterations,
        0 <= max_cuts <= most_cuts (each step costs an assembly and a factorisation, so a
        bigger count only buys minutes of run time; the adaptive stepping refines where
        needed)."""
        for name, v, lo, hi in (("steps", steps, 1, Limits.most_steps),
                                ("max_iter", max_iter, 1, Limits.most_iterations),
                                ("max_cuts", max_cuts, 0, Limits.most_cuts)):
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
                raise TypeError(f"{name} must be an int, got {v!r}")
            if not lo <= int(v) <= hi:
                raise ValueError(f"{name} must lie in {lo}..{hi}, got {v}")
        return Limits(jnp.asarray(int(steps)), jnp.asarray(int(max_iter)), jnp.asarray(int(max_cuts)))


class Critical(NamedTuple):
    """Critical points a solve passed (the first ``capacity`` = K of them, more are counted in
    ``Solution.branch``; NaN where unfilled). Its sizes are the Solution's format, the same
    for every solve (a warm start or a control loop mixes Solutions of several solves).

    The tangent K_ff lost positive definiteness between the load fractions ``t_stable`` (the
    last stable equilibrium) and ``t_unstable`` (the first equilibrium on the path with a
    negative eigenvalue; ``t_unstable - t_stable`` <= dt0 / 2**LoadPath.locate); ``eigenvalues``
    (K, ``n_eigenvalues``) the lowest eigenvalues of K_ff there, ``mode`` (K, Nf, d) the
    critical mode (unit norm) along which the solve left the unstable branch."""

    t_stable: jax.Array      # (K,)
    t_unstable: jax.Array    # (K,)
    eigenvalues: jax.Array   # (K, n_eigenvalues)
    mode: jax.Array          # (K, Nf, d)

    capacity = 8        # critical points one solve records
    n_eigenvalues = 3   # lowest eigenvalues of K_ff recorded at each

    @staticmethod
    def empty(u) -> "Critical":
        nan = jnp.full((Critical.capacity,), jnp.nan, u.dtype)
        return Critical(nan, nan, jnp.full((Critical.capacity, Critical.n_eigenvalues), jnp.nan, u.dtype),
                        jnp.full((Critical.capacity,) + u.shape, jnp.nan, u.dtype))

    def record(self, k, when, t_stable, t_unstable, eigenvalues, mode) -> "Critical":
        """With entry k set where ``when`` (k >= capacity: dropped)."""
        def put(a, v):
            return jnp.where(when, a.at[k].set(v, mode="drop"), a)
        return Critical(put(self.t_stable, t_stable), put(self.t_unstable, t_unstable),
                        put(self.eigenvalues, eigenvalues), put(self.mode, mode))


class Solution(NamedTuple):
    """A solve's result (a pytree: batched solves stack every field).

    u (Nf, d) free coefficients at the last converged load; g (Nb, d) prescribed values and
    ``load`` the load scale there; ``t`` the fraction of the requested increment reached;
    ``status`` a Status code. ``branch`` counts the critical points this solve passed by
    switching to a stable branch (0: the state lies on the branch the solve started on;
    CONVERGED with branch > 0: a stable state of a secondary, bifurcated branch) and
    ``critical`` records them (see ``Critical``). ``linear``: the linear solver's last state
    (its factorisation of K_ff at the last tangent the solve made, an iterate near the state
    returned), where the solve keeps it (an eager ``Model.solve``; None otherwise): a solve
    started from this Solution and the implicit Jacobian at it use it instead of factorising
    again. ``params``: the problem's parameters at this state, where the solve keeps them (an
    eager ``Model.solve``; None otherwise): a solve started from this Solution with other
    parameters (a tool's new pose) ramps them from these along its path. ``stop``: a ``Stop``
    code, why a failed solve stopped where it did (``Solution.stopped`` as a member).
    ``stats``: the linear algebra this solve did (``LinearStats``: factorisations, solves, CG
    iterations, host seconds); None for a state no solve made (``Model.initial``)."""

    u: jax.Array
    g: jax.Array
    load: jax.Array
    status: jax.Array
    t: jax.Array
    iterations: jax.Array
    steps: jax.Array
    cuts: jax.Array
    residual_norm: jax.Array
    branch: jax.Array     # () critical points passed by switching to a stable branch (0: primary)
    critical: "Critical"  # the critical points this solve passed (fixed size, NaN where unfilled)
    linear: Any = None    # the linear solver's last state, where kept (LoadPath.keep_linear)
    params: Any = None    # the problem's parameters at this state, where kept (an eager Model.solve)
    # a Stop code: why the path stopped (a concrete int32 by default: the same pytree and
    # jit signature as a solve's)
    stop: Any = np.int32(Stop.NONE)
    stats: Any = None     # LinearStats of the solve that made it (None: no solve did)

    def __repr__(self) -> str:
        """The outcome and the shapes, not the arrays (the critical-point record is NaN where
        unfilled: printed whole, a converged solve looked like a failed one)."""
        if isinstance(self.status, jax.core.Tracer):
            return f"Solution(traced: u {tuple(self.u.shape)}, g {tuple(self.g.shape)})"
        shapes = f"u {tuple(np.shape(self.u))}, g {tuple(np.shape(self.g))}"
        if np.ndim(self.status):
            return f"Solution(batch of {np.size(self.status)}: {self.message}; {shapes})"
        return f"Solution({Status.of(self.status).name}: {self.message}; {shapes}, load {float(self.load):g})"

    @property
    def converged(self) -> bool:
        """Every solve reached an equilibrium (CONVERGED, or STABILITY_UNKNOWN)."""
        st = np.asarray(self.status)
        return bool(np.all((st == Status.CONVERGED) | (st == Status.STABILITY_UNKNOWN)))

    @property
    def outcome(self) -> Status:
        """The status as a Status member (prints as its name); one solve only."""
        return Status.of(self.status)

    @property
    def stopped(self) -> Stop:
        """Why the path stopped (a Stop member; NONE where it did not); one solve only."""
        return Stop.of(self.stop)

    @property
    def message(self) -> str:
        st = np.asarray(self.status)
        if st.ndim:
            bad = np.flatnonzero(st != 0)
            if not len(bad):
                return f"all {st.size} solves converged"
            why = Stop.of(np.broadcast_to(np.asarray(self.stop), st.shape).flat[bad[0]])
            return (f"{len(bad)} of {st.size} solves did not converge; first (#{bad[0]}): "
                    + Status.of(st.flat[bad[0]]).message + ("" if why == Stop.NONE else f", stopped {why.message}"))
        s = Status.of(st)
        if s == Status.CONVERGED:
            where = ""
            if int(self.branch):
                t = np.asarray(self.critical.t_unstable)
                where = (f" on a stable secondary branch, past {int(self.branch)} critical point(s) "
                         f"(first at {100 * t[0]:.2f}% of the increment)")
            return (f"converged{where} in {int(self.steps)} load steps, {int(self.iterations)} Newton "
                    f"iterations (|r| = {float(self.residual_norm):.2e})")
        if s == Status.STABILITY_UNKNOWN:
            return (f"{s.name}: {s.message} (after {int(self.steps)} load steps, "
                    f"{int(self.iterations)} Newton iterations)")
        why = self.stopped
        return (f"{s.name}: {s.message}; stopped at {100 * float(self.t):.1f}% of the increment "
                f"after {int(self.steps)} steps and {int(self.cuts)} step cuts"
                + ("" if why == Stop.NONE else f", {why.message}") + "; the last converged state is kept")


def joined(first: Solution, rest: Solution) -> Solution:
    """One Solution of a path solved in two parts: ``first`` stopped at the fraction t1 of
    the increment, ``rest`` went on from its state to the same end. Fractions of the rest
    (its t, its critical points) become fractions of the whole path, t1 + (1 - t1) t; the
    counters and the linear work add up; the state is the rest's."""
    t1 = first.t

    def whole(t):
        return t1 + (1 - t1) * t

    crit = rest.critical._replace(t_stable=whole(rest.critical.t_stable),
                                  t_unstable=whole(rest.critical.t_unstable))
    stats = rest.stats if first.stats is None or rest.stats is None else first.stats + rest.stats
    return rest._replace(t=whole(rest.t), iterations=first.iterations + rest.iterations,
                         steps=first.steps + rest.steps, cuts=first.cuts + rest.cuts,
                         branch=first.branch + rest.branch, critical=crit, stats=stats)

"""What every linear solver reports of the matrix it factorised.
"""
from __future__ import annotations

from ...base.outcome import Outcome


class Stability(Outcome):
    """What a factorisation says of K_ff (inside jit: the int code)."""

    STABLE = 0, "K_ff is positive definite (a stable equilibrium)"
    UNSTABLE = 1, "K_ff has negative eigenvalues (a limit or bifurcation point was passed)"
    UNKNOWN = 2, ("the factorisation could not tell the inertia of K_ff (pivots were perturbed "
                  "or permuted): stability is unknown")
    FAILED = 3, ("the iterative linear solve did not converge (jaxrkpm.solvers.linalg.multigrid): the Newton "
                 "step is not trusted")

"""Iterative refinement of a solve made in lower precision: the one rule shared by the dense
mixed-precision solver (inside jit) and the single-precision PARDISO factorisation (on the
host). Works on JAX and NumPy arrays alike."""
from __future__ import annotations

# refinement steps: each cuts the residual by ~cond(K_ff) eps_single (1e-6 measured on the
# 10^3 cube), so two reach ~1e-12
REFINEMENTS = 2


def refine(apply, matvec, b, steps: int = REFINEMENTS):
    """x ~ K^-1 b from ``apply`` (an approximate K^-1, e.g. a single-precision factorisation)
    and ``matvec`` (the exact K x): x = apply(b), then ``steps`` times x += apply(b - K x)."""
    x = apply(b)
    for _ in range(steps):
        x = x + apply(b - matvec(x))
    return x

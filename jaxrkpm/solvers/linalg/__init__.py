"""Linear solvers of the Newton iteration with explicit state (dense, sparse direct,
Krylov, quasi-Newton) and the host-side factorisations and multigrid they call.
"""

"""Solvers (layer 3): the nonlinear solvers (Newton family, stable-branch descent), the drivers
over them (load path, arc length), implicit differentiation, and linalg/ (dense, sparse,
Krylov linear solvers and their host bindings). Imports jaxrkpm.base, jaxrkpm.discretise and
jaxrkpm.mechanics.
"""

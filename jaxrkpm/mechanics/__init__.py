"""Mechanics (layer 2): materials (strain energies), the terms that make up a body's total
potential energy, their assembly into residuals and tangent blocks, and the Problem (the
discrete model as one jit-friendly pytree). Pure JAX. Imports jaxrkpm.base and
jaxrkpm.discretise.
"""

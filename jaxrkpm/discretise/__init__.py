"""Discretisation (layer 1): bodies (grids, polygons, meshes), RK shape functions,
quadrature tables (Gauss, SCNI/MSCNI), the integration-point groups and particle-pair pattern,
and the essential-boundary transformation. NumPy, outside jit, computed once (total
Lagrangian). Imports only jaxrkpm.base.
"""

"""Host callbacks: NumPy/SciPy work (sparse factorisations, multigrid, CG) inside jit.
"""
from __future__ import annotations

import jax
import numpy as np


try:
    from jax.experimental.buffer_callback import buffer_callback
except ImportError:      # JAX before buffer_callback: host callbacks copy their operands
    buffer_callback = None


def host_callback(fn, result_shape_dtypes, *args):
    """``fn(*args)`` on the host inside jit (the sparse and Krylov solvers' factorisations
    and CG), one batch member at a time under vmap. ``fn`` gets read-only NumPy views of
    XLA's own operand buffers, valid during the call only: what it keeps beyond the call
    it must copy (the factorisations and multigrid hierarchies do).

    Why not jax.pure_callback: it copies every operand onto a new device array before the
    call, and a Newton step passes two tangents (the current one and the factorised one),
    each hundreds of megabytes for a large 3D model: the copies cost far more than the call
    (``experiments/bench_cube3d_large.py``). (pure_callback remains the fallback on JAX
    versions without buffer_callback.)"""
    if buffer_callback is None:
        return jax.pure_callback(fn, result_shape_dtypes, *args, vmap_method="sequential")

    def run(ctx, out, *buffers):
        views = []
        for b in buffers:
            v = np.asarray(b)
            v.flags.writeable = False
            views.append(v)
        results = fn(*views)
        for o, r in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(results)):
            np.asarray(o)[...] = r

    return buffer_callback(run, result_shape_dtypes, vmap_method="sequential")(*args)

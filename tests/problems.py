"""Small test problems the test files share (import as ``from tests.problems import ...``).

The thesis' objects (the planar square with its paddle, the section 5.3.1 cube, the Figure
6.1 phantom outline) come from :mod:`jaxrkpm.thesis`; the rest are the generic unit
square / cube grids and the "block" (unit square, left edge held, right edge driven) that
several files solve.
"""
from __future__ import annotations

import jax.numpy as jnp

import jaxrkpm as jr
from jaxrkpm import thesis

FUNG = jr.Fung(alpha=1.0, beta=1.0)            # eq 5.2, Table 5.2 tensors
PHANTOM = [list(v) for v in thesis.PHANTOM_OUTLINE]   # Figure 6.1 outline


def unit_grid(n: int, dim: int = 2) -> jr.Body:
    """n particles per side on the unit square (dim 2) or cube (dim 3), spacing 1/(n-1)."""
    return jr.Body.grid((n,) * dim, 1.0 / (n - 1))


def phantom_body(spacing: float = 0.1) -> jr.Body:
    """The Figure 6.1 outline as a polygon body (clipped Voronoi cells)."""
    return jr.Body.polygon(PHANTOM, spacing)


def block_sets(body: jr.Body, right: str = "right") -> dict:
    """Sets "wall" = left edge x = 0 and ``right`` = the whole right edge x = 1."""
    return {"wall": body.select(lambda X: X[:, 0] < 1e-9), right: body.select(lambda X: X[:, 0] > 1 - 1e-9)}


def block(n: int = 9, material=FUNG, right: str = "right", **model_kw):
    """The unit-square block, left edge held and the right edge driven: (body, sets, model)."""
    body = unit_grid(n)
    sets = block_sets(body, right)
    return body, sets, jr.Model(body, material, essential=sets, **model_kw)


def planar_solved(paddle=(-0.08, 0.05), steps: int = 2, **kw):
    """The 9x9 chapter-5 square (:func:`jaxrkpm.thesis.planar_square`) solved with the paddle
    moved by ``paddle``: (model, solution)."""
    model = thesis.planar_square(9, **kw)
    return model, model.solve({"paddle": jnp.asarray(paddle)}, steps=steps)

"""The thesis' objects as models: :func:`planar_square` (the chapter-5 planar object with its
paddle) and :func:`cube` (the section 5.3.1 cube); the needle phantom of chapter 6 is
:class:`jaxrkpm.thesis.needle.Phantom`.
"""
from __future__ import annotations

import numpy as np

from ..discretise.body import Body
from ..mechanics.materials import Fung, Material, Quadratic
from ..model.model import Model
from .data import CUBE_ORIGIN, CUBES, TABLE_5_1


def planar_square(n: int = 9, integration: str = "gauss", material: Material | None = None,
                  paddle: str | float = "three", solver: str = "auto") -> Model:
    """The chapter-5 planar object on an n x n grid of the unit square (9x9: spacing 0.125):
    set "wall" = the left edge x = 0, set "paddle" on the right edge x = 1.

    material  default Fung(alpha=1, beta=1) (eq 5.2, Table 5.2 tensors)
    paddle    "three": the three right-edge particles nearest (1, 0.5) (the tracking model,
              three particles at every resolution); a number w: the right-edge particles with
              |y - 0.5| <= w (the same physical contact patch at every resolution: 3
              particles at 9x9 for w = 0.125, 5 at 17x17). The two agree at 9x9.
    """
    if n < 3:
        raise ValueError(f"n must be >= 3 particles per side, got {n}")
    body = Body.grid((n, n), 1.0 / (n - 1))
    wall = body.select(lambda X: X[:, 0] < 1e-9)
    if isinstance(paddle, str):
        if paddle != "three":
            raise ValueError(f"paddle must be 'three' or a half width, got {paddle!r}")
        right = np.asarray(body.select(lambda X: X[:, 0] > 1 - 1e-9))
        sel = np.sort(right[np.argsort(np.abs(body.X[right, 1] - 0.5), kind="stable")[:3]])
    else:
        w = float(paddle)
        if not w > 0:
            raise ValueError(f"the paddle half width must be > 0, got {paddle}")
        sel = body.select(lambda X: (X[:, 0] > 1 - 1e-9) & (np.abs(X[:, 1] - 0.5) <= w + 1e-9))
        if len(np.atleast_1d(sel)) < 1:
            raise ValueError(f"no right-edge particle within {w} of y = 0.5 at n = {n}")
    material = Fung(alpha=1.0, beta=1.0) if material is None else material
    return Model(body, material, integration=integration, essential={"wall": wall, "paddle": sel},
                 solver=solver)


def cube(kind: str = "reduced", integration: str = "gauss", alpha: float = 1.0,
         solver: str = "auto") -> Model:
    """The section 5.3.1 cube (material eq 5.1, :class:`Quadratic`): "wall" = face x=-1.5;
    "paddle" = face x=-2.5, its bottom two of three layers (z < 2.25) in the reduced model
    (3x3x3), the whole face in the refined one (5x5x5)."""
    if kind not in CUBES:
        raise ValueError(f"unknown cube model {kind!r}: choose {list(CUBES)}")
    n, h = CUBES[kind]
    body = Body.grid((n, n, n), h, origin=CUBE_ORIGIN)
    wall = body.select(lambda X: X[:, 0] > -1.5 - 1e-9)
    if kind == "reduced":
        paddle = body.select(lambda X: (X[:, 0] < -2.5 + 1e-9) & (X[:, 2] < 2.25))
    else:
        paddle = body.select(lambda X: X[:, 0] < -2.5 + 1e-9)
    return Model(body, Quadratic(alpha=alpha), integration=integration,
                 essential={"wall": wall, "paddle": paddle}, solver=solver)


def cube_path() -> np.ndarray:
    """Table 5.1 as control point displacements (the tracker's input): (6, 3)."""
    T = np.asarray(TABLE_5_1, float)
    return T - T[0]

"""A body's discretisation for a model, built once: the integration rules (Gauss or SCNI),
the essential sets and their boundary transformation, from the options of ``Model``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
import scipy.sparse as sp

from . import quadrature as integ
from . import scni
from .body import Body
from .constraints import EssentialSets, Transformation
from .quadrature import Table

MAX_SUPPORT_DIAMETERS = 2.0   # kernel support (support x spacing) allowed, in body diameters
INTEGRATIONS = ("gauss", *scni.SCHEMES)


@dataclass(frozen=True)
class Discretisation:
    """What the terms of a model are built on (host side, NumPy).

    a          the kernel dilation support x spacing (eq 3.20)
    volume     the volume integration table; ``surface`` the boundary one (tractions, contact)
    balanced   the boundary rule the volume rule's stresses balance exactly (SCNI's own
               boundary integral; Gauss: ``surface``)
    sets       the essential sets; ``trans`` their transformation (eq 3.22), None where there
               are none or a ``Roller`` holds only some components (then ``held_components``)
    patches    the dilatation patch of every volume point (the anti-locking formulation)"""

    body: Body
    integration: str
    support: float
    a: float
    volume: Table
    surface: Table
    balanced: Table
    sets: EssentialSets
    trans: Transformation | None
    patches: np.ndarray

    def constraint_matrix(self) -> sp.csr_matrix:
        """C = [D^nb D^b] (x) I (Nb d, N d): C d = 0 where the essential particles hold (the
        sparse form of the transformation, for the sparse and Krylov solvers)."""
        d, N, Nb = self.body.dim, self.body.n, len(self.sets.bnd)
        trans = self.trans
        if trans is None:
            return sp.csr_matrix((0, N * d))
        Kb = trans.nb_idx.shape[1]
        r = (np.arange(Nb)[:, None, None] * d + np.arange(d)[None, None, :]).repeat(Kb, 1)
        c = trans.nb_idx[:, :, None] * d + np.arange(d)[None, None, :]
        v = np.repeat(trans.rows_psi[:, :, None], d, axis=2)
        return sp.csr_matrix((v.ravel(), (r.ravel(), c.ravel())), shape=(Nb * d, N * d))


def check_support(body: Body, support) -> float:
    """``support`` as a float: positive, and a kernel that does not cover the whole body."""
    if not (np.isfinite(support) and support > 0):
        raise ValueError(f"support must be a positive number (x spacing), got {support}")
    diameter = float(np.linalg.norm(body.upper - body.lower))
    if support * body.spacing > MAX_SUPPORT_DIAMETERS * diameter:
        # every window covers the whole body many times over: the shape functions
        # degenerate towards the global linear basis and K_ff towards singular (the
        # solve then fails with MAX_ITERATIONS or LINE_SEARCH at 0%, naming neither)
        raise ValueError(f"support {support:g} x spacing {body.spacing:g} = {support * body.spacing:g} "
                         f"exceeds {MAX_SUPPORT_DIAMETERS:g} x the body's diameter {diameter:.3g}: "
                         "every shape function would cover the whole body; use a support of a "
                         "few spacings (e.g. 2.01 .. 4)")
    return float(support)


def check_options(body, integration, essential, support, order) -> float:
    """The options of ``discretise`` checked before anything is built: the support as a float."""
    if not isinstance(body, Body):
        raise ValueError(f"body must be a jaxrkpm Body, got {type(body).__name__}")
    if essential is not None and not isinstance(essential, Mapping):
        raise TypeError(f"essential must be a dict name -> particle indices (e.g. "
                        f"{{'wall': body.select(...)}}), got {type(essential).__name__}")
    support = check_support(body, support)
    if isinstance(order, (bool, np.bool_)) or not isinstance(order, (int, np.integer)) or not 1 <= order <= 20:
        raise ValueError(f"order must be a whole number of integration points per direction in 1..20 "
                         f"(2 is the default), got {order!r}")
    if integration not in INTEGRATIONS:
        raise ValueError(f"unknown integration {integration!r}: choose "
                         + ", ".join(repr(k) for k in INTEGRATIONS))
    return support


def discretise(body: Body, integration: str = "gauss", essential: Mapping | None = None,
               support: float = 2.01, order: int = 2, cell_size: float | None = None) -> Discretisation:
    """The ``Discretisation`` of ``body`` (the options as ``Model``'s)."""
    support = check_options(body, integration, essential, support, order)
    a = support * body.spacing
    bp, bw, bn = integ.boundary_points(body, order)
    surface = integ.table(body, bp, bw, a, normals=bn, support_factor=support)
    if integration == "gauss":
        volume = integ.gauss_table(body, a, order, cell_size, support_factor=support)
        balanced = surface
    else:
        smooth = scni.smoothing(body, a, integration, order, support_factor=support)
        volume, balanced = smooth.table, smooth.boundary
    sets = EssentialSets.build(body, dict(essential or {}))
    trans = Transformation.build(body, sets, a, support) if len(sets.bnd) and not sets.partial else None
    patches = integ.dilatation_patches(body, volume, integration, cell_size)
    return Discretisation(body, integration, support, a, volume, surface, balanced, sets, trans, patches)

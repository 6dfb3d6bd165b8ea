"""Static solver settings (part of the jit cache key).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np


@dataclass(frozen=True)
class Config:
    """Static solver settings (immutable and hashable: part of the jit cache key).

    ``Model.config(**overrides)`` gives a model's; every field may be overridden per solve
    (``model.solve(..., rtol=1e-12)``)."""

    W: Callable                   # strain energy W(E, params)
    linear: Any                   # jaxrkpm.solvers.linalg.dense.DenseSolver() or SparseSolver(system)
    rtol: float = 1e-10           # residual tolerance relative to the internal force scale
    line_search: int = 8          # step halvings in the line search
    armijo: float = 1e-4          # sufficient-decrease constant of the energy line search
    easy: int = 4                 # a load step converging within this many iterations lets dt grow
    growth: float = 1.5           # ... by this factor (never above the initial step)
    check_stability: bool = True  # an equilibrium with K_ff not positive definite -> UNSTABLE_TANGENT
    #                               (False also lets iterative linear solves stop early)
    stable_branch: bool = False   # past a critical point, go on to a stable equilibrium of the same
    #                               load (see ``switch_branch``); dense solver and check_stability only.
    #                               Off in Config: it makes every dense solve_path compile ~70% longer
    #                               (9x9: 6.2 -> 10.7 s CPU); ``Model.solve`` switches it on by
    #                               itself where a plain solve stops at a critical point. The compressed Fung / Quadratic squares
    #                               stop with or without it: past their last stable state the energy
    #                               has no minimum with det F > 0 (a corner collapses; see ``descend``)
    locate: int = 6               # halvings of the initial load step that pin a critical point
    #                               before the branch switch (it lies within dt0 / 2**locate)
    reuse: float = 0.0            # modified Newton (``newton``): 0 assembles and factorises the
    #                               tangent at every iteration; in (0, 1) a kept factorisation
    #                               serves the next iteration (the next load step's predictor
    #                               too) while the last step cut |r| by at least this factor.
    #                               Same residual tolerance; assembly dominates 3D solves.
    #                               Dense solver only (ignored by the sparse one)

    def __post_init__(self):
        if not callable(self.W):
            raise ValueError("Config.W must be the material's strain energy W(E, params)")
        for name in ("rtol", "armijo", "growth"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if int(self.line_search) < 0 or int(self.easy) < 0 or int(self.locate) < 0:
            raise ValueError("line_search, easy and locate must be >= 0")
        if not (isinstance(self.reuse, (int, float)) and 0 <= self.reuse < 1):
            raise ValueError(f"reuse must be a number in [0, 1) (0: full Newton), got {self.reuse!r}")

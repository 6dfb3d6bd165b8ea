"""Hyperelastic materials as scalar JAX strain energies W(E, p).

The 2nd Piola-Kirchhoff stress S = sym(dW/dE) and every tangent come from autodiff.
Scalar parameters may be fields: pass a callable X (Q, d) -> (Q,) and it is evaluated at
the integration points when a model is built (an inclusion is data, not code).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Mapping

import jax
import jax.numpy as jnp
from jax.experimental import checkify
import numpy as np


def _sym(A):
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


@dataclass(frozen=True, eq=False)
class Material:
    """A strain energy W(E, p) -> scalar, with E the (d, d) Green-Lagrange strain and p a
    dict of parameters at one point.

    ``params``: name -> float | callable field X (n, d) -> (n,) | array (global tensor).
    ``positive``: names of parameters that must be > 0 everywhere.
    ``tensors``: optional callable dim -> dict of extra global arrays (e.g. Fung's A, C).
    ``split``: W = W_iso(C̄) + U(J), a nearly incompressible energy (a model averages its volume
    change over patches by default: ``jaxrkpm.mechanics.strain.needs_anti_locking``)."""

    W: Callable
    params: dict = field(default_factory=dict)
    name: str = "custom"
    positive: tuple = ()
    nonnegative: tuple = ()
    tensors: Callable | None = None
    split: bool = False

    def __post_init__(self):
        if not callable(self.W):
            raise TypeError(f"{self.name}: W must be a strain energy function W(E, params) -> scalar, "
                            f"got {self.W!r}")
        if not isinstance(self.params, Mapping):
            raise TypeError(f"{self.name}: params must be a dict name -> value (e.g. {{'alpha': 1.0}}), "
                            f"got {type(self.params).__name__} {self.params!r}")
        for k, v in self.params.items():
            if not isinstance(k, str):
                raise TypeError(f"{self.name}: parameter names must be strings, got {k!r}")
            if callable(v):
                continue
            arr = np.asarray(v, float)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{self.name}: parameter {k!r} is not finite: {v}")
            self.check_sign(k, arr)
        errors = {}
        for dim in (2, 3):   # the body's dimension is not known yet: W must work in one of them
            try:
                self.check_energy(dim)
                return
            except ValueError as e:
                errors[dim] = e
        raise errors[2]

    def check_energy(self, dim: int, point: Mapping | None = None) -> None:
        """Call W once on a small (dim, dim) test strain and check that it returns a finite
        scalar, traced as in the solver (so a W that returns a vector, reads a parameter it
        is not given or needs concrete values fails here, named, not inside a solve).
        ``point``: the scalar parameters at one point (default: the plain values, 1.0 for
        fields)."""
        if point is None:
            point = {k: 1.0 if callable(v) else self._one(v) for k, v in self.params.items()}
        E = 0.01 * (np.arange(dim)[:, None] + np.arange(dim)[None, :] + 1.0) / dim
        try:
            p = {**{k: jnp.asarray(v, jnp.float64) for k, v in point.items()},
                 **{k: jnp.asarray(v) for k, v in self.global_params(dim).items()}}
            shape = jax.eval_shape(self.W, jnp.asarray(E), p).shape
            value, outside = None, None
            if shape == ():
                # JAX clamps an index past the strain's size (E[2, 2] of a 2D strain): checked here
                err, value = jax.jit(checkify.checkify(self.W, errors=checkify.index_checks))(jnp.asarray(E), p)
                value, outside = float(value), err.get()
        except Exception as e:   # any failure of user code: name it and where it happened
            raise ValueError(f"{self.name}: the strain energy W(E, params) fails on a {dim}D test "
                             f"strain with parameters {sorted(p) if 'p' in locals() else sorted(point)}: "
                             f"{type(e).__name__}: {e}") from e
        if outside:
            raise ValueError(f"{self.name}: the strain energy W(E, params) reads outside the {dim}x{dim} "
                             f"strain of a {dim}D body ({outside.strip()}): index E by the body's dimension")
        if shape != ():
            raise ValueError(f"{self.name}: the strain energy W(E, params) must return a scalar, "
                             f"got shape {shape} (sum it, e.g. jnp.sum(...))")
        if not np.isfinite(value):
            raise ValueError(f"{self.name}: the strain energy W(E, params) is not finite ({value}) "
                             f"at a small {dim}D test strain")

    @staticmethod
    def _one(v):
        arr = np.asarray(v, float)
        return arr if arr.ndim == 0 else arr.reshape(-1)[0]

    def check_sign(self, k, arr):
        """A ValueError where the values ``arr`` of parameter ``k`` break its declared sign."""
        if k in self.positive and np.any(arr <= 0):
            raise ValueError(f"{self.name}: parameter {k!r} must be positive, got {np.min(arr):g}")
        if k in self.nonnegative and np.any(arr < 0):
            raise ValueError(f"{self.name}: parameter {k!r} must be non-negative, got {np.min(arr):g}")

    def point_params(self, points: np.ndarray) -> dict:
        """Scalar parameters (plain or fields) evaluated to (Q,) arrays at ``points``."""
        out = {}
        for k, v in self.params.items():
            if callable(v):
                arr = np.asarray(v(points), float)
                if arr.shape != (len(points),):
                    raise ValueError(f"{self.name}: field {k!r} must return shape ({len(points)},), "
                                     f"got {arr.shape}")
                if not np.all(np.isfinite(arr)):
                    raise ValueError(f"{self.name}: field {k!r} has non-finite values")
                self.check_sign(k, arr)
            else:
                arr = np.asarray(v, float)
                if arr.ndim == 0:
                    arr = np.full(len(points), float(arr))
            out[k] = arr
        return out

    def global_params(self, dim: int) -> dict:
        return {} if self.tensors is None else {k: np.asarray(v, float) for k, v in self.tensors(dim).items()}

    def describe(self) -> dict:
        return {"name": self.name, **{k: (v if not callable(v) else "field")
                                      for k, v in self.params.items()}}


def pk2(W: Callable, E, p):
    """S = sym(dW/dE)."""
    return _sym(jax.grad(W)(E, p))


def det(A):
    """Determinant of (..., d, d) matrices by cofactors for d <= 3. jnp.linalg.det factorises
    each matrix by LU, and its derivatives (a log-det energy's stress and tangent) are chains
    of batched LAPACK calls on 2x2 or 3x3 matrices (``experiments/bench_cube3d.py`` times the
    tangent blocks that differentiate it)."""
    d = A.shape[-1]
    a = lambda i, j: A[..., i, j]
    if d == 1:
        return a(0, 0)
    if d == 2:
        return a(0, 0) * a(1, 1) - a(0, 1) * a(1, 0)
    if d == 3:
        return (a(0, 0) * (a(1, 1) * a(2, 2) - a(1, 2) * a(2, 1))
                - a(0, 1) * (a(1, 0) * a(2, 2) - a(1, 2) * a(2, 0))
                + a(0, 2) * (a(1, 0) * a(2, 1) - a(1, 1) * a(2, 0)))
    return jnp.linalg.det(A)


def green_lagrange(F):
    return 0.5 * (jnp.swapaxes(F, -1, -2) @ F - jnp.eye(F.shape[-1]))


# ---------------------------------------------------------------------------- energies
def _quadratic(E, p):
    return 0.5 * p["alpha"] * jnp.sum(E * E)


def _fung(E, p):
    q = jnp.einsum("ij,ijkl,kl->", E, p["C"], E)
    return p["alpha"] * jnp.expm1(q) + p["beta"] * jnp.einsum("ij,ijkl,kl->", E, p["A"], E)


def _svk(E, p):
    tr = jnp.trace(E)
    return 0.5 * p["lam"] * tr**2 + p["mu"] * jnp.sum(E * E)


def _neo_hookean(E, p):
    d = E.shape[-1]
    C = jnp.eye(d) + 2.0 * E
    lnJ = 0.5 * jnp.log(det(C))
    return 0.5 * p["mu"] * (jnp.trace(C) - d) - p["mu"] * lnJ + 0.5 * p["lam"] * lnJ**2


def fung_tensor(dim: int, iiii: float, ijij: float, iijj: float) -> np.ndarray:
    """Orthotropic-pattern 4th-order tensor of thesis Table 5.2: T_iiii, T_ijij and
    T_iijj = T_ijji (i != j); every other entry zero."""
    T = np.zeros((dim,) * 4)
    for i in range(dim):
        T[i, i, i, i] = iiii
        for j in range(dim):
            if i != j:
                T[i, j, i, j] = ijij
                T[i, i, j, j] = iijj
                T[i, j, j, i] = iijj
    return T


def Quadratic(alpha: float = 1.0) -> Material:
    """W = 1/2 alpha E:E (thesis eq 5.1)."""
    return Material(_quadratic, {"alpha": alpha}, "Quadratic", positive=("alpha",))


def Fung(alpha: float = 1.0, beta: float = 1.0, A=None, C=None) -> Material:
    """W = alpha (exp(E:C:E) - 1) + beta E:A:E (thesis eq 5.2; the constant -alpha makes
    W(0) = 0). A and C default to Table 5.2 (2D) and its 3D pattern."""
    def given(name, T, dim):
        T = np.asarray(T, float)
        if T.shape != (dim,) * 4 or not np.all(np.isfinite(T)):
            raise ValueError(f"Fung: {name} must be a finite 4th-order tensor of shape {(dim,) * 4} "
                             f"for a {dim}D body, got shape {T.shape}")
        return T

    def tensors(dim):
        return {"A": fung_tensor(dim, 1020.0, 254.0, 383.0) if A is None else given("A", A, dim),
                "C": fung_tensor(dim, 3.5, 0.5, 1.5) if C is None else given("C", C, dim)}
    return Material(_fung, {"alpha": alpha, "beta": beta}, "Fung", positive=("alpha", "beta"),
                    tensors=tensors)


def check_young(young) -> float:
    """Young's modulus as a float, checked positive (a number, not a field)."""
    young = float(young)
    if not young > 0:
        raise ValueError(f"Young's modulus must be positive, got {young:g}")
    return young


def check_poisson(nu) -> float:
    """Poisson's ratio as a float, checked in (-1, 1/2): the one range check of every material
    that takes ν."""
    nu = float(nu)
    if not -1.0 < nu < 0.5:
        raise ValueError(f"Poisson's ratio nu must lie in (-1, 0.5), got {nu:g} (nu = 0.5 is exactly "
                         "incompressible, which nearly incompressible energies approach with nu = 0.499)")
    return nu


def SaintVenantKirchhoff(lam: float, mu: float) -> Material:
    """W = lam/2 tr(E)^2 + mu E:E. In 2D this is plane strain; for plane stress use
    ``SaintVenantKirchhoff.plane_stress(E, nu)``."""
    return Material(_svk, {"lam": lam, "mu": mu}, "SaintVenantKirchhoff",
                    positive=("mu",), nonnegative=("lam",))


def _svk_plane_stress(young: float, nu: float) -> Material:
    """2D SVK whose small-strain limit is plane-stress linear elasticity."""
    check_young(young)
    nu = check_poisson(nu)
    mu = young / (2 * (1 + nu))
    return SaintVenantKirchhoff(young * nu / (1 - nu**2), mu)


def _svk_from_young(young: float, nu: float) -> Material:
    check_young(young)
    nu = check_poisson(nu)
    return SaintVenantKirchhoff(young * nu / ((1 + nu) * (1 - 2 * nu)), young / (2 * (1 + nu)))


SaintVenantKirchhoff.plane_stress = _svk_plane_stress
SaintVenantKirchhoff.from_young = _svk_from_young


def NeoHookean(lam: float, mu: float) -> Material:
    """Compressible neo-Hookean: W = mu/2 (tr C - d) - mu ln J + lam/2 (ln J)^2 (in 2D: plane strain)."""
    return Material(_neo_hookean, {"lam": lam, "mu": mu}, "NeoHookean",
                    positive=("mu",), nonnegative=("lam",))

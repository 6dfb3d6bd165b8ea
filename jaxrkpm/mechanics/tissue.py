"""Soft-tissue strain energies with a volumetric-deviatoric split, W = W_iso(C̄) + U(J).

They are written on the right Cauchy-Green tensor C = I + 2E, with J = sqrt(det C), the
isochoric C̄ = J^(-2/3) C and its invariants Ī1, Ī2; they are still functions of E, so they
plug into every term, solver and derivative as the other materials do. The volumetric energy
of every one is U(J) = κ/2 (ln J)², which grows without bound as J → 0 (a compressed point
cannot fold flat), so μ is the small-strain shear modulus and κ the bulk modulus of each, in
the stress unit of the model. A 2D body is in plane strain: C is embedded in 3D with C33 = 1,
so the invariants are those of the 3D deformation.

Parameters are given by name: κ directly, or Poisson's ratio ``nu`` (κ = 2μ(1 + ν) / (3(1 − 2ν)),
ν < 1/2); any of them may be a field X (n, d) -> (n,), as for the other materials.
``with_barrier`` adds U(J) to any material (the thesis' Fung and Quadratic energies stay
bounded as J → 0 without it).
"""
from __future__ import annotations

from functools import partial
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from .materials import Material, check_poisson, check_young, det

__all__ = ["HolzapfelGasserOgden", "MooneyRivlin", "NearlyIncompressibleNeoHookean", "Ogden",
           "VerondaWestmann", "Yeoh", "bulk_modulus", "with_barrier"]


# ------------------------------------------------------------------ kinematics
def cauchy_green_3d(E):
    """C = I + 2E as a 3x3 tensor; a 2D strain is embedded in plane strain (C33 = 1)."""
    d = E.shape[-1]
    C = jnp.eye(d) + 2.0 * E
    if d == 3:
        return C
    if d == 2:
        return jnp.zeros((3, 3), C.dtype).at[:2, :2].set(C).at[2, 2].set(1.0)
    raise ValueError(f"tissue energies are for 2D (plane strain) and 3D bodies, got a {d}D strain")


def isochoric_invariants(C):
    """(J, Ī1, Ī2) of a 3x3 right Cauchy-Green tensor."""
    J = jnp.sqrt(det(C))
    I1 = jnp.trace(C)
    I2 = 0.5 * (I1 * I1 - jnp.sum(C * C))      # C is symmetric: tr(C²) = C : C
    scale = J ** (-2.0 / 3.0)
    return J, scale * I1, scale * scale * I2


# ------------------------------------------------------------------ spectral functions
# Ogden's energy is a sum of powers of the principal stretches. Eigenvectors are not
# differentiable where eigenvalues repeat (the undeformed state, any equal stretches), but
# tr f(C) and the matrix function f(C) are: d tr f(C) = f'(C) : dC, and df(C) has the
# Daleckii-Krein form Q (Γ ∘ Qᵀ dC Q) Qᵀ with Γ_ij the divided differences of f, f' at equal
# eigenvalues. Written as custom JVPs, stress and tangent are exact at repeated stretches.


def _power_derivative(lam, a, n: int):
    """(d/dλ)^n λ^a = a (a − 1) ... (a − n + 1) λ^(a − n)."""
    c = 1.0
    for k in range(n):
        c = c * (a - k)
    return c * lam ** (a - n)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def _power_matrix(C, a, n: int):
    """Q diag((d/dλ)^n λ^a) Qᵀ for a symmetric positive definite C = Q diag(λ) Qᵀ (n = 0: C^a)."""
    lam, Q = jnp.linalg.eigh(C)
    return (Q * _power_derivative(lam, a, n)) @ Q.T


def _power_matrix_jvp(n, primals, tangents, rel_gap: float = 1e-6):
    """The Daleckii-Krein derivative; eigenvalues closer than ``rel_gap`` (relative) count as
    equal (Γ takes f' at their midpoint)."""
    C, a = primals
    dC, da = tangents
    lam, Q = jnp.linalg.eigh(C)
    li, lj = lam[:, None], lam[None, :]
    gap = li - lj
    close = jnp.abs(gap) <= rel_gap * jnp.maximum(li, lj)
    fi, fj = _power_derivative(li, a, n), _power_derivative(lj, a, n)
    gamma = jnp.where(close, _power_derivative(0.5 * (li + lj), a, n + 1),
                      (fi - fj) / jnp.where(close, 1.0, gap))
    out = (Q * _power_derivative(lam, a, n)) @ Q.T
    if isinstance(dC, SymbolicZero):
        d_out = jnp.zeros_like(out)
    else:
        d_out = Q @ (gamma * (Q.T @ dC @ Q)) @ Q.T
    if not isinstance(da, SymbolicZero):        # a parameter derivative (calibration)
        dphi = jax.jvp(lambda b: _power_derivative(lam, b, n), (a,), (da,))[1]
        d_out = d_out + (Q * dphi) @ Q.T
    return out, d_out


_power_matrix.defjvp(_power_matrix_jvp, symbolic_zeros=True)


@jax.custom_jvp
def power_trace(C, a):
    """tr(C^a) = Σ λ_i^a over the eigenvalues of a symmetric positive definite C, with stress
    and tangent defined where eigenvalues repeat (d tr C^a = a C^(a−1) : dC)."""
    return jnp.sum(jnp.linalg.eigvalsh(C) ** a)


def _power_trace_jvp(primals, tangents):
    C, a = primals
    dC, da = tangents
    out = power_trace(C, a)
    d_out = jnp.zeros_like(out)
    if not isinstance(dC, SymbolicZero):
        d_out = d_out + jnp.sum(_power_matrix(C, a, 1) * dC)
    if not isinstance(da, SymbolicZero):
        lam = jnp.linalg.eigvalsh(C)
        d_out = d_out + da * jnp.sum(lam ** a * jnp.log(lam))
    return out, d_out


power_trace.defjvp(_power_trace_jvp, symbolic_zeros=True)


def volumetric(J, kappa):
    """U(J) = κ/2 (ln J)²."""
    return 0.5 * kappa * jnp.log(J) ** 2


# ------------------------------------------------------------------ energies
def _neo_hookean(E, p):
    J, I1, _ = isochoric_invariants(cauchy_green_3d(E))
    return 0.5 * p["mu"] * (I1 - 3.0) + volumetric(J, p["kappa"])


def _mooney_rivlin(E, p):
    J, I1, I2 = isochoric_invariants(cauchy_green_3d(E))
    return p["c10"] * (I1 - 3.0) + p["c01"] * (I2 - 3.0) + volumetric(J, p["kappa"])


def _yeoh(E, p):
    J, I1, _ = isochoric_invariants(cauchy_green_3d(E))
    x = I1 - 3.0
    return p["c10"] * x + p["c20"] * x ** 2 + p["c30"] * x ** 3 + volumetric(J, p["kappa"])


def _veronda_westmann(E, p):
    J, I1, I2 = isochoric_invariants(cauchy_green_3d(E))
    return (p["c1"] * jnp.expm1(p["c2"] * (I1 - 3.0)) - 0.5 * p["c1"] * p["c2"] * (I2 - 3.0)
            + volumetric(J, p["kappa"]))


def _ogden(terms: int):
    def W(E, p):
        C = cauchy_green_3d(E)
        J = jnp.sqrt(det(C))
        Cbar = J ** (-2.0 / 3.0) * C
        energy = volumetric(J, p["kappa"])
        for k in range(1, terms + 1):
            mu, alpha = p[f"mu{k}"], p[f"alpha{k}"]
            # Σ_i λ̄_i^α = tr(C̄^(α/2))
            energy = energy + mu / alpha * (power_trace(Cbar, 0.5 * alpha) - 3.0)
        return energy
    return W


def _hgo(families: int):
    def W(E, p):
        C = cauchy_green_3d(E)
        J, I1b, _ = isochoric_invariants(C)
        energy = 0.5 * p["mu"] * (I1b - 3.0) + volumetric(J, p["kappa"])
        I1, kd = jnp.trace(C), p["dispersion"]
        for k in range(families):
            a = jnp.stack([p[f"fibre{k}_x"], p[f"fibre{k}_y"], p[f"fibre{k}_z"]])
            a = a / jnp.linalg.norm(a)
            strain = kd * (I1 - 3.0) + (1.0 - 3.0 * kd) * (a @ C @ a - 1.0)
            # fibres carry tension only; slack at rest too (jnp.maximum's derivative at 0 is ½)
            strain = jnp.where(strain > 0.0, strain, 0.0)
            energy = energy + p["k1"] / (2.0 * p["k2"]) * jnp.expm1(p["k2"] * strain ** 2)
        return energy
    return W


# ------------------------------------------------------------------ parameters
def bulk_modulus(mu, nu):
    """κ = 2μ(1 + ν) / (3(1 − 2ν)) for a shear modulus μ (number or field) and Poisson's ratio
    ν in (−1, 1/2)."""
    nu = check_poisson(nu)
    factor = 2.0 * (1.0 + nu) / (3.0 * (1.0 - 2.0 * nu))
    if not callable(mu):
        arr = np.asarray(mu, float)
        if not np.all(np.isfinite(arr)) or not np.all(arr > 0):
            raise ValueError(f"bulk_modulus: the shear modulus mu must be positive and finite, got {mu!r}")
    if callable(mu):
        return lambda X: factor * np.asarray(mu(X), float)
    return factor * mu


def _kappa(name: str, mu, kappa, nu):
    """κ from exactly one of ``kappa`` and ``nu``."""
    if (kappa is None) == (nu is None):
        raise TypeError(f"{name}: give the bulk modulus kappa or Poisson's ratio nu (one of them), "
                        f"got kappa={kappa!r}, nu={nu!r}")
    return kappa if nu is None else bulk_modulus(mu, nu)


def _shear(name: str, formula: str, mu_of: Callable, **constants):
    """μ = ``mu_of(**constants)`` (written ``formula`` in the error message) where the constants
    are numbers (to check it and to derive κ from ν); a field constant gives a field μ."""
    if any(callable(v) for v in constants.values()):
        return lambda X: mu_of(**{k: np.asarray(v(X), float) if callable(v) else v for k, v in constants.items()})
    mu = mu_of(**constants)
    if not mu > 0:
        raise ValueError(f"{name}: the small-strain shear modulus {formula} must be positive, got {mu:g} "
                         f"from {constants}")
    return mu


def NearlyIncompressibleNeoHookean(mu, kappa=None, *, nu=None) -> Material:
    """W = μ/2 (Ī1 − 3) + κ/2 (ln J)²: shear modulus ``mu``, bulk modulus ``kappa`` (or Poisson's
    ratio ``nu``). ``NearlyIncompressibleNeoHookean.from_young(E, nu)`` takes Young's modulus."""
    k = _kappa("NearlyIncompressibleNeoHookean", mu, kappa, nu)
    return Material(_neo_hookean, {"mu": mu, "kappa": k}, "NearlyIncompressibleNeoHookean",
                    positive=("mu", "kappa"), split=True)


def _from_young(young, nu) -> Material:
    young, nu = check_young(young), check_poisson(nu)
    return NearlyIncompressibleNeoHookean(young / (2.0 * (1.0 + nu)), nu=nu)


NearlyIncompressibleNeoHookean.from_young = _from_young


def MooneyRivlin(c10, c01, kappa=None, *, nu=None) -> Material:
    """W = c10 (Ī1 − 3) + c01 (Ī2 − 3) + κ/2 (ln J)²; small-strain shear modulus μ = 2(c10 + c01)."""
    mu = _shear("MooneyRivlin", "2(c10 + c01)", lambda c10, c01: 2.0 * (c10 + c01), c10=c10, c01=c01)
    return Material(_mooney_rivlin, {"c10": c10, "c01": c01, "kappa": _kappa("MooneyRivlin", mu, kappa, nu)},
                    "MooneyRivlin", positive=("kappa",), split=True)


def Yeoh(c10, c20=0.0, c30=0.0, kappa=None, *, nu=None) -> Material:
    """W = c10 (Ī1 − 3) + c20 (Ī1 − 3)² + c30 (Ī1 − 3)³ + κ/2 (ln J)²; μ = 2 c10."""
    mu = _shear("Yeoh", "2 c10", lambda c10: 2.0 * c10, c10=c10)
    return Material(_yeoh, {"c10": c10, "c20": c20, "c30": c30, "kappa": _kappa("Yeoh", mu, kappa, nu)},
                    "Yeoh", positive=("c10", "kappa"), split=True)


def VerondaWestmann(c1, c2, kappa=None, *, nu=None) -> Material:
    """W = c1 (exp(c2 (Ī1 − 3)) − 1) − c1 c2 / 2 (Ī2 − 3) + κ/2 (ln J)² (Veronda & Westmann 1970,
    used for skin, breast and liver); μ = c1 c2."""
    mu = _shear("VerondaWestmann", "c1 c2", lambda c1, c2: c1 * c2, c1=c1, c2=c2)
    return Material(_veronda_westmann, {"c1": c1, "c2": c2, "kappa": _kappa("VerondaWestmann", mu, kappa, nu)},
                    "VerondaWestmann", positive=("c1", "c2", "kappa"), split=True)


def _evaluated_once(field: Callable) -> Callable:
    """``field`` (X -> (n, 3)) remembering its last points and values, so that its three
    components (three parameter fields) cost one evaluation at the same points."""
    last = {}

    def values(X):
        X = np.asarray(X, float)
        if "X" not in last or last["X"].shape != X.shape or not np.array_equal(last["X"], X):
            last["X"], last["a"] = X.copy(), np.asarray(field(X), float)
        return last["a"]
    return values


def Ogden(mu: Sequence, alpha: Sequence, kappa=None, *, nu=None) -> Material:
    """W = Σ_p μ_p / α_p (λ̄1^α_p + λ̄2^α_p + λ̄3^α_p − 3) + κ/2 (ln J)² on the isochoric
    principal stretches λ̄_i = J^(−1/3) λ_i (Ogden 1972): ``mu`` and ``alpha`` are sequences of
    up to three terms (numbers or fields); small-strain shear modulus μ = Σ_p μ_p α_p / 2, and
    each μ_p α_p must be positive (the usual stability condition). α = 2, μ_1 = μ is the
    neo-Hookean energy. Stress and tangent are exact at equal stretches (the undeformed state
    included): the stretch powers are a trace of a matrix power with its own derivative rule."""
    mu, alpha = (list(mu), list(alpha)) if not (callable(mu) or np.isscalar(mu)) else ([mu], [alpha])
    if not 1 <= len(mu) <= 3 or len(mu) != len(alpha):
        raise ValueError(f"Ogden: mu and alpha must be sequences of the same length, 1 to 3 terms, got "
                         f"{len(mu)} and {len(alpha)}")
    for k, (m, a) in enumerate(zip(mu, alpha), 1):
        if callable(m) or callable(a):
            continue
        if not (np.isfinite(m) and np.isfinite(a) and a != 0 and m * a > 0):
            raise ValueError(f"Ogden: term {k} needs a nonzero alpha and mu * alpha > 0, got mu={m:g}, "
                             f"alpha={a:g}")
    constants = {f"mu{k}": m for k, m in enumerate(mu, 1)} | {f"alpha{k}": a for k, a in enumerate(alpha, 1)}
    terms = len(mu)
    shear = _shear("Ogden", "Σ μ_p α_p / 2",
                   lambda **c: 0.5 * sum(c[f"mu{k}"] * c[f"alpha{k}"] for k in range(1, terms + 1)), **constants)
    return Material(_ogden(terms), {**constants, "kappa": _kappa("Ogden", shear, kappa, nu)}, "Ogden",
                    positive=("kappa",), split=True)


def _fibre_field(field, X, k: int) -> np.ndarray:
    """The (n, 3) directions of fibre field ``k`` at ``X`` (n, d), checked."""
    a = np.asarray(field(X), float)
    if a.shape != (len(X), 3):
        raise ValueError(f"HolzapfelGasserOgden: fibre {k}'s field must return (n, 3) directions (3D vectors, "
                         f"also on a {np.shape(X)[-1]}D body: plane strain keeps the out-of-plane part), "
                         f"got shape {a.shape} for {len(X)} points")
    return a


def HolzapfelGasserOgden(mu, k1, k2, fibres: Sequence, kappa=None, *, nu=None,
                         dispersion: float = 0.0) -> Material:
    """Fibre-reinforced tissue (Holzapfel, Gasser & Ogden 2000; dispersion: Gasser et al. 2006):
    W = μ/2 (Ī1 − 3) + Σ_f k1 / (2 k2) (exp(k2 ⟨E_f⟩²) − 1) + κ/2 (ln J)², with
    E_f = κ_d (I1 − 3) + (1 − 3κ_d)(a_f · C a_f − 1) for each fibre direction a_f; ⟨·⟩ keeps
    the tension only (fibres buckle rather than carry compression). The fibre term uses the
    invariants of C itself, not of C̄, as Nolan et al. (2014) advise for compressible tissue.

    ``fibres``: one or two directions a_f, each a (3,) vector or a field X (n, d) -> (n, 3);
    they are normalised (in a 2D body, in plane strain, a fibre's out-of-plane part keeps its
    length). ``dispersion`` κ_d in [0, 1/3] (1/3: isotropic)."""
    fibres = _fibre_list(fibres)
    if isinstance(dispersion, (str, bytes, bool, np.bool_)) or not isinstance(dispersion, (int, float, np.number)) \
            or not 0.0 <= float(dispersion) <= 1.0 / 3.0:
        raise ValueError(f"HolzapfelGasserOgden: dispersion must lie in [0, 1/3], got {dispersion}")
    params = {"mu": mu, "k1": k1, "k2": k2, "dispersion": float(dispersion),
              "kappa": _kappa("HolzapfelGasserOgden", mu, kappa, nu)}
    for k, a in enumerate(fibres):
        params.update(_fibre_params(k, a))
    return Material(_hgo(len(fibres)), params, "HolzapfelGasserOgden",
                    positive=("mu", "k1", "k2", "kappa"), split=True)


def _fibre_list(fibres) -> list:
    """One or two fibre directions: a single vector or field as a list of one."""
    one = callable(fibres) or (not isinstance(fibres, str) and len(fibres) > 0
                               and all(np.isscalar(x) for x in fibres))
    fibres = [fibres] if one else list(fibres)
    if not 1 <= len(fibres) <= 2:
        raise ValueError(f"HolzapfelGasserOgden: fibres must be one or two directions, got {len(fibres)}")
    return fibres


def _fibre_params(k: int, a) -> dict:
    """The parameters fibre{k}_x, _y, _z of fibre ``k``: numbers for a constant direction, a
    field per component for a field (evaluated once per set of points)."""
    if callable(a):
        field = _evaluated_once(a)
        return {f"fibre{k}_{axis}": (lambda X, field=field, i=i, k=k: _fibre_field(field, X, k)[:, i])
                for i, axis in enumerate("xyz")}
    a = np.asarray(a, float)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or not np.linalg.norm(a) > 0:
        raise ValueError(f"HolzapfelGasserOgden: fibre {k} must be a nonzero finite 3-vector or a field "
                         f"X -> (n, 3), got {a.tolist() if a.size < 10 else a.shape}")
    return {f"fibre{k}_{axis}": float(a[i]) for i, axis in enumerate("xyz")}


def with_barrier(material: Material, kappa=None, *, nu=None, mu=None) -> Material:
    """``material`` plus the volumetric energy κ/2 (ln J)² (2D: plane strain), so that its
    compressed points resist J → 0; e.g. the thesis' Fung energy, which stays bounded there.
    ``kappa``, or ``nu`` with the small-strain shear modulus ``mu`` it refers to."""
    if "kappa" in material.params:
        raise ValueError(f"with_barrier: {material.name} already has a parameter 'kappa'")
    if nu is not None and mu is None:
        raise TypeError("with_barrier: nu needs the shear modulus mu it refers to (or give kappa)")
    k = _kappa(f"with_barrier({material.name})", mu, kappa, nu)
    W = material.W

    def barrier(E, p):
        J = jnp.sqrt(det(cauchy_green_3d(E)))
        return W(E, p) + volumetric(J, p["kappa"])

    return Material(barrier, {**material.params, "kappa": k}, f"{material.name}+barrier",
                    positive=(*material.positive, "kappa"), nonnegative=material.nonnegative,
                    tensors=material.tensors)

"""Small test problems the test files share (import as ``from tests.problems import ...``).

The thesis' objects (the planar square with its paddle, the section 5.3.1 cube, the Figure
6.1 phantom outline) come from :mod:`jaxrkpm.thesis`; the rest are the generic unit
square / cube grids and the "block" (unit square, left edge held, right edge driven) that
several files solve, and two problems with independent references that the tests and the
experiments share: the clamped strip that buckles (``strip_model``, against the extensible
elastica), the shallow arch that snaps through (``shallow_arch``, arc length against
displacement control), and Cook's membrane and a cantilever block, nearly incompressible,
against mixed-FEM references (``cook_membrane``, ``cantilever_block``: volumetric locking).
"""
from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import meshio
import numpy as np
from scipy.optimize import brentq, minimize_scalar
from scipy.special import ellipe, ellipk

import jaxrkpm as jr
from jaxrkpm import thesis
from jaxrkpm.model.continuation import arc_length, point_load

FUNG = jr.Fung(alpha=1.0, beta=1.0)            # eq 5.2, Table 5.2 tensors
PHANTOM = [list(v) for v in thesis.PHANTOM_OUTLINE]   # Figure 6.1 outline


def unit_grid(n: int, dim: int = 2) -> jr.Body:
    """n particles per side on the unit square (dim 2) or cube (dim 3), spacing 1/(n-1)."""
    return jr.Body.grid((n,) * dim, 1.0 / (n - 1))


def annulus(inner: float = 1.0, outer: float = 2.0, rings: int = 4, sectors: int = 32) -> jr.Body:
    """The thick-walled ring inner <= |X| <= outer as a triangle mesh body: ``rings`` + 1
    circles of ``sectors`` vertices (the particles), each quadrilateral cut along alternating
    diagonals (no preferred direction)."""
    r = np.linspace(inner, outer, rings + 1)
    t = 2 * np.pi * np.arange(sectors) / sectors
    R, T = np.meshgrid(r, t, indexing="ij")
    points = np.stack([R * np.cos(T), R * np.sin(T), 0 * R], -1).reshape(-1, 3)
    tris = []
    for i in range(rings):
        for j in range(sectors):
            a, b = i * sectors + j, i * sectors + (j + 1) % sectors
            c, d = b + sectors, a + sectors
            tris += [(a, b, c), (a, c, d)] if (i + j) % 2 else [(a, b, d), (b, c, d)]
    return jr.Body.from_mesh(meshio.Mesh(points, [("triangle", np.array(tris))]), dim=2)


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
    """The 9x9 chapter-5 square (:func:`jaxrkpm.thesis.scenarios.planar_square`) solved with the paddle
    moved by ``paddle``: (model, solution)."""
    model = thesis.planar_square(9, **kw)
    return model, model.solve({"paddle": jnp.asarray(paddle)}, steps=steps)


# ------------------------------------------------------------------ the buckling strip
# Strip 1 x 0.05, 81 x 5 particles, neo-Hookean lam = mu = 1 (plane-strain modulus E' = 8/3),
# both ends clamped, the right end pushed along the axis with no imperfection; the stable-branch
# solve passes the bifurcation and follows the buckled branch. Reference: the clamped
# extensible elastica (four quarter waves; m = k^2 of the pinned elastica of length L / 2):
# P / P_E = (2 K(m) / pi)^2, bending end shortening L (2 - 2 E(m) / K(m)), axial shortening
# P L / (E' h); P_E = 4 pi^2 E' I / L^2 (effective length L / 2, I = h^3 / 12).
L, H, NX, NY = 1.0, 0.05, 81, 5
LAM, MU = 1.0, 1.0
E_PLANE = 4 * MU * (LAM + MU) / (LAM + 2 * MU)
EULER = 4 * np.pi**2 * E_PLANE * (H**3 / 12) / L**2
SHORTENINGS = (0.006, 0.01, 0.02, 0.04, 0.07, 0.10)   # of L; Euler's is 0.0082


def elastica_force(shortening: float) -> float:
    """End force of the clamped extensible elastica at an end shortening (a fraction of L)."""
    def gap(P):
        bend = shortening - P / (E_PLANE * H)
        if bend <= 0:
            return -1.0
        m = brentq(lambda m: 2 - 2 * ellipe(m) / ellipk(m) - bend, 1e-14, 0.999)
        return EULER * (2 * ellipk(m) / np.pi) ** 2 - P
    return brentq(gap, EULER * (1 + 1e-9), 2 * EULER)


def strip_model(nx: int = NX, ny: int = NY) -> jr.Model:
    """The strip with sets "left" (x = 0) and "right" (x = L), both clamped."""
    body = jr.Body.grid((nx, ny), L / (nx - 1))
    sets = {"left": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > L - 1e-9)}
    return jr.Model(body, jr.NeoHookean(lam=LAM, mu=MU), essential=sets)


def path(model: jr.Model, shortenings=SHORTENINGS):
    """Warm-started solves to each end shortening: [(shortening, solution)]."""
    sol, out = model.initial(), []
    for c in shortenings:
        sol = model.solve({"right": jnp.array([-c * L, 0.0])}, initial=sol, stable_branch=True)
        out.append((c, sol))
    return out


# ------------------------------------------------------------------ the snapping arch
# A sinusoidal arch (span 1, thickness 0.05, rise 0.1), both end sections clamped, loaded at the
# crown: arc-length continuation through the limit point, and the same discretisation with
# the crown prescribed (displacement control) as the reference path.


MATERIAL = jr.SaintVenantKirchhoff.plane_stress(1.0, 0.3)
SUPPORT = 2.5          # kernel support in spacings: three particles through the thickness
LIFT = 4e-3            # upward body force (per unit area) of the load model: a load without a limit point


@dataclass(frozen=True)
class Arch:
    body: jr.Body
    ends: dict          # "left", "right": the particles of the clamped end sections
    crown: int          # index of the crown's mid-surface particle (the loaded point)

    @property
    def crown_point(self) -> np.ndarray:
        return self.body.X[self.crown]


def shallow_arch(n_along: int = 41, n_thick: int = 3, span: float = 1.0, thickness: float = 0.05,
                 rise: float = 0.1) -> Arch:
    """A sinusoidal arch y = rise sin(pi x / span), ``thickness`` measured normal to its
    centre line, as a structured triangle mesh body: n_along x n_thick particles (both odd,
    so that the crown is a particle), each quad split by the diagonal mirrored at mid-span
    (the discretisation is symmetric, so a symmetric load gives a symmetric path)."""
    if n_along % 2 == 0 or n_thick % 2 == 0 or n_along < 5 or n_thick < 3:
        raise ValueError(f"n_along >= 5 and n_thick >= 3 must be odd (a crown particle), got {n_along}, {n_thick}")
    s = np.linspace(0.0, span, n_along)
    slope = rise * np.pi / span * np.cos(np.pi * s / span)
    normal = np.stack([-slope, np.ones_like(s)], 1) / np.sqrt(1 + slope**2)[:, None]
    centre = np.stack([s, rise * np.sin(np.pi * s / span)], 1)
    t = np.linspace(-thickness / 2, thickness / 2, n_thick)
    X = (centre[:, None, :] + t[None, :, None] * normal[:, None, :]).reshape(-1, 2)
    idx = np.arange(n_along * n_thick).reshape(n_along, n_thick)
    a, b = idx[:-1, :-1], idx[1:, :-1]        # (n_along - 1, n_thick - 1) quad corners
    c, d = idx[1:, 1:], idx[:-1, 1:]
    left = (np.arange(n_along - 1) < (n_along - 1) // 2)[:, None]
    tri1 = np.where(left[..., None], np.stack([a, b, c], -1), np.stack([a, b, d], -1))
    tri2 = np.where(left[..., None], np.stack([a, c, d], -1), np.stack([b, c, d], -1))
    cells = np.concatenate([tri1.reshape(-1, 3), tri2.reshape(-1, 3)])
    body = jr.Body.from_mesh(meshio.Mesh(X, [("triangle", cells)]), dim=2)
    return Arch(body, {"left": idx[0], "right": idx[-1]}, int(idx[n_along // 2, n_thick // 2]))


def load_model(arch: Arch) -> jr.Model:
    """Ends clamped, the crown free; its own dead load is an upward body force ``LIFT`` (the
    snap-through is driven by ``point_load`` at the crown instead)."""
    return jr.Model(arch.body, MATERIAL, essential=arch.ends, support=SUPPORT, body_force=[0.0, LIFT])


def crown_model(arch: Arch) -> jr.Model:
    """The same discretisation with the crown point prescribed (displacement control)."""
    return jr.Model(arch.body, MATERIAL, essential={**arch.ends, "crown": [arch.crown]}, support=SUPPORT)


def crown_load(model: jr.Model, arch: Arch) -> np.ndarray:
    """A unit downward force at the crown point as nodal loads."""
    return point_load(model, [arch.crown_point], [0.0, -1.0])


def displacement_control(model: jr.Model, depth: float, n: int):
    """The crown pushed down to ``depth`` in n equal steps (each solve warm-started from the
    last): crown deflections (n+1,) and the downward crown force (n+1,) = -reaction_y."""
    v = np.linspace(0.0, depth, n + 1)
    reaction = jax.jit(lambda s: model.reaction(s, "crown"))   # compiled once, not traced per call
    sol, force = model.initial(), [0.0]
    for vk in v[1:]:
        sol = model.solve({"crown": [0.0, -vk]}, initial=sol)
        force.append(-float(reaction(sol)[1]))
    return v, np.asarray(force)


def first_maximum(x, y) -> float:
    """The first local maximum of y(x) (the limit point; past the snap the force rises
    again), between samples: the vertex of the parabola through the sample and its two
    neighbours."""
    peaks = np.flatnonzero((y[1:-1] > y[:-2]) & (y[1:-1] >= y[2:])) + 1
    if not len(peaks):
        raise ValueError("no local maximum inside the samples: sample further")
    k = int(peaks[0])
    c2, c1, c0 = np.polyfit(x[k - 1:k + 2] - x[k], y[k - 1:k + 2], 2)
    return float(c0 - c1 * c1 / (4 * c2))


def snap(arch: Arch, model: jr.Model, ds: float = 0.03, steps: int = 40):
    """The load-driven arch followed by arc length (cylindrical constraint, ds fixed)."""
    return arc_length(model, ds, steps=steps, ds_max=ds, load_pattern=crown_load(model, arch),
                      points=[arch.crown_point])


# ------------------------------------------------------------------ tetrahedral boxes of other tools
BOX = (2.0, 1.0, 1.0)       # the 225-vertex box of issue 35: 9 x 5 x 5 vertices at spacing 0.25


def skfem_box(path) -> str:
    """scikit-fem's ``MeshTet.init_tensor`` box (9 x 5 x 5 vertices, 768 tetrahedra, half of
    them with the opposite vertex order), written with meshio to ``path`` (.vtu)."""
    import skfem
    m = skfem.MeshTet.init_tensor(*(np.linspace(0.0, L, n) for L, n in zip(BOX, (9, 5, 5))))
    meshio.write(path, meshio.Mesh(m.p.T, [("tetra", m.t.T)]))
    return str(path)


def scipy_box(n_inside: int = 120, n_face: int = 12, seed: int = 1) -> meshio.Mesh:
    """A box triangulated by ``scipy.spatial.Delaunay`` (qhull, which orders the vertices of
    about half its simplices the other way): its corners, ``n_face`` random points on each
    face and ``n_inside`` random points inside."""
    from itertools import product

    from scipy.spatial import Delaunay
    rng = np.random.default_rng(seed)
    L = np.asarray(BOX)
    pts = [np.array(list(product(*[(0.0, x) for x in L])))]
    for axis in range(3):
        for side in (0.0, 1.0):
            p = rng.uniform(0.1, 0.9, (n_face, 3)) * L
            p[:, axis] = side * L[axis]
            pts.append(p)
    pts.append(rng.uniform(0.1, 0.9, (n_inside, 3)) * L)
    P = np.concatenate(pts)
    return meshio.Mesh(P, [("tetra", Delaunay(P).simplices)])


# ---------------------------------------------------------- a manufactured 3D solution
MANUFACTURED_AMPLITUDE = 0.05
MANUFACTURED_MATERIAL = jr.NeoHookean(1.0, 1.0)


def manufactured_u(X):
    """A smooth large-deformation field u(X) = A (sin(2x + z), cos(x + y), y sin z), A = 0.05."""
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    return MANUFACTURED_AMPLITUDE * jnp.stack([jnp.sin(2 * x + z), jnp.cos(x + y), y * jnp.sin(z)], -1)


def _manufactured_pk1(X):
    F = jnp.eye(3) + jax.jacfwd(manufactured_u)(X)
    return F @ jr.pk2(MANUFACTURED_MATERIAL.W, jr.green_lagrange(F), {"lam": 1.0, "mu": 1.0})


_manufactured_force = jax.jit(jax.vmap(lambda X: -jnp.trace(jax.jacfwd(_manufactured_pk1)(X), axis1=1, axis2=2)))


def manufactured_body_force(X):
    """The body force -Div P(F(u)) that makes ``manufactured_u`` an equilibrium of
    ``MANUFACTURED_MATERIAL`` (autodiff), as a Model's ``body_force`` takes it."""
    return np.asarray(_manufactured_force(jnp.asarray(X)))



# Cook's membrane (plane strain): clamped on the left, a dead shear traction of total 5 on the right
# edge; the vertical displacement of the top-right corner against FElupe's three-field
# (u-p-J) solution, converged and extrapolated (experiments/cook_reference.py and its JSON,
# which holds the meshes, the extrapolation and its error estimate, a few 1e-5 in 2D and 1e-3 in 3D)
COOK_VERTICES = np.array([[0.0, 0.0], [48.0, 44.0], [48.0, 60.0], [0.0, 44.0]])
COOK_MU = 80.194
COOK_REFERENCE = {0.3: 0.546557, 0.45: 0.438293, 0.49: 0.408384, 0.499: 0.401577}
BLOCK_REFERENCE = {0.3: 0.60756, 0.45: 0.53913, 0.49: 0.52190, 0.499: 0.51806}


def lame(mu: float, nu: float) -> float:
    """lam of Poisson's ratio nu at shear modulus mu."""
    return 2.0 * mu * nu / (1.0 - 2.0 * nu)


def cook_membrane(spacing: float, nu: float, integration: str = "gauss", count: bool = False, **model_kw):
    """u_y of the top-right corner (48, 60) of Cook's membrane, compressible neo-Hookean at
    Poisson's ratio nu, solved in one load step (``count``: and the particles)."""
    body = jr.Body.polygon(COOK_VERTICES, spacing)
    model = jr.Model(body, jr.NeoHookean(lame(COOK_MU, nu), COOK_MU), integration=integration,
                     essential={"left": body.select(lambda X: X[:, 0] < 1e-9)},
                     tractions=[(lambda X: X[:, 0] > 48.0 - 1e-9, [0.0, 5.0 / 16.0])], **model_kw)
    value = float(np.asarray(model.displacement(model.solve(), [[48.0, 60.0]])).ravel()[1])
    return (value, body.n) if count else value


def cantilever_block(spacing: float, nu: float, integration: str = "gauss", count: bool = False, **model_kw):
    """u_z of the point (4, 0.5, 1) of the block [0, 4] x [0, 1]^2, the face x = 0 clamped and
    the face x = 4 under a dead traction (0, 0, 0.5), compressible neo-Hookean (mu = COOK_MU) at
    Poisson's ratio nu, one load step (``count``: and the particles)."""
    body = jr.Body.grid((round(4 / spacing) + 1, round(1 / spacing) + 1, round(1 / spacing) + 1), spacing)
    model = jr.Model(body, jr.NeoHookean(lame(COOK_MU, nu), COOK_MU), integration=integration,
                     essential={"wall": body.select(lambda X: X[:, 0] < 1e-9)},
                     tractions=[(lambda X: X[:, 0] > 4.0 - 1e-9, [0.0, 0.0, 0.5])], **model_kw)
    value = float(np.asarray(model.displacement(model.solve(), [[4.0, 0.5, 1.0]])).ravel()[2])
    return (value, body.n) if count else value


# -------------------------------------------------------------------- Hertz line contact
# A rigid cylinder (a disc, plane strain) pressed into an elastic block, against Hertz's
# half-width a = sqrt(4 P R / (pi E*)) and peak pressure p_max = 2 P / (pi a) (E* = E / (1 - nu^2),
# P the force per unit thickness) at the measured force P: tests/mechanics/test_hertz.py and
# experiments/hertz_contact.py (whose docstring gives the setting's reasons).


def fit_hertz(x, p, w, guess):
    """(a, p_max) of Hertz's profile p_max sqrt(1 - x^2 / a^2) fitted to pressures p at
    points x with weights w (least squares; p_max linear for each a)."""
    def best(a):
        s = np.sqrt(np.clip(1 - (x / a) ** 2, 0.0, None))
        p0 = np.sum(w * p * s) / max(np.sum(w * s * s), 1e-300)
        return p0, np.sum(w * (p - p0 * s) ** 2)

    a = minimize_scalar(lambda a: best(a)[1], bounds=(0.3 * guess, 3.0 * guess), method="bounded",
                        options={"xatol": 1e-10 * guess}).x
    return float(a), float(best(a)[0])


def hertz_line_contact(spacing=0.02, width=1.0, depth=1.0, radius=4.0, young=1.0, nu=0.3, depths=(0.002, 0.0038),
                       gap=None, steps=4, integration="gauss") -> dict:
    """The block's right half (``width`` x ``depth``, particles ``spacing`` apart), its
    symmetry plane held by a frictionless rigid wall (rollers), its bottom clamped, pressed by
    the disc of ``radius`` centred on the symmetry plane to each of ``depths`` (each from the
    unloaded state in ``steps`` load steps): per load, the force, the fitted half-width and
    peak pressure beside Hertz's, the contact's smallest gap and the solve's status."""
    gap = 0.005 * spacing if gap is None else gap
    nx, ny = round(width / spacing) + 1, round(depth / spacing) + 1
    if max(abs((nx - 1) * spacing - width), abs((ny - 1) * spacing - depth)) > 1e-9 * spacing:
        raise ValueError(f"spacing {spacing} must divide the width {width} and the depth {depth}")
    body = jr.Body.grid((nx, ny), spacing, origin=(0.0, -depth))
    mu = young / (2 * (1 + nu))
    lam = young * nu / ((1 + nu) * (1 - 2 * nu))
    p0 = young   # the barrier stiffer than the pressures met: its compliance about 1% of the block's
    tol = 1e-9 * spacing
    disc = jr.Contact(jr.Sphere(radius), position=(0.0, radius + 2 * gap), gap=gap, pressure=p0, name="disc",
                      where=lambda X: (X[:, 1] > -tol) & (X[:, 0] < 0.5 * width))
    wall = jr.Contact(jr.HalfSpace((1.0, 0.0)), position=(-gap, 0.0), gap=gap, pressure=p0, name="wall",
                      where=lambda X: X[:, 0] < tol)
    model = jr.Model(body, jr.SaintVenantKirchhoff(lam, mu), integration=integration,
                     essential={"bottom": body.select(lambda X: X[:, 1] < -depth + tol)}, terms=[disc, wall])
    estar = young / (1 - nu ** 2)
    out = []
    for dd in depths:
        params = {"disc": {"position": jnp.array([0.0, radius + 2 * gap - dd])},
                  "wall": {"position": jnp.array([-gap, 0.0])}}
        sol = model.solve(params=params, steps=steps)   # each load from load 0
        r = jr.contact_forces(model, sol, "disc", params)
        x = np.asarray(r.points)[:, 0]
        p = np.asarray(r.pressure)
        w = np.asarray(model.problem(params).term("disc").w)
        # the half-model's force and moments, mirrored: P = 2 int_0 p dx (per unit thickness)
        P = -2 * float(r.force[1])
        a_moment = 2 * np.sqrt(np.sum(w * p * x ** 2) / np.sum(w * p))
        a_fit, p_fit = fit_hertz(x, p, w, a_moment)
        a_h = np.sqrt(4 * P * radius / (np.pi * estar))
        pmax_h = 2 * P / (np.pi * a_h)
        out.append({"depth": dd, "force": P, "half_width": a_fit, "hertz_half_width": a_h,
                    "half_width_ratio": a_fit / a_h, "peak_pressure": p_fit, "hertz_peak_pressure": pmax_h,
                    "peak_ratio": p_fit / pmax_h, "moment_half_width_ratio": a_moment / a_h,
                    "largest_point_pressure_ratio": float(p.max()) / pmax_h,
                    "active": int(np.sum(np.asarray(r.active))), "min_gap": float(r.min_gap),
                    "block_over_half_width": min(2 * width, depth) / a_h,
                    "status": str(sol.message), "x": x[np.argsort(x)][:24].tolist(),
                    "pressure": p[np.argsort(x)][:24].tolist()})
    return {"spacing": spacing, "integration": integration, "width": width, "depth": depth, "radius": radius,
            "young": young, "nu": nu, "gap": gap, "particles": body.n, "loads": out}

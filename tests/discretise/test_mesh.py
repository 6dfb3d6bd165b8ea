"""Bodies from meshes (meshio, gmsh): shapes, tags, formats, bad meshes; integration on
unstructured bodies (simplex Gauss rules, median-dual SCNI); selections; a manufactured
convergence study on an unstructured tetrahedral body."""
import copy
import itertools

import meshio
import numpy as np
import pytest
from scipy.spatial import Delaunay

import jaxrkpm as jr
from jaxrkpm.discretise import quadrature as integration
from jaxrkpm.discretise import mesh
from jaxrkpm.discretise import scni
from jaxrkpm.discretise import surface as surf
from jaxrkpm.mechanics.loads import nodal_forces
from tests.problems import MANUFACTURED_MATERIAL, manufactured_body_force, manufactured_u

RADII = (1.0, 1.0, 0.6)                  # the half-ellipsoid "breast" on its base z = 0
F0 = np.array([[1.1, 0.05, 0.02], [-0.04, 0.95, 0.03], [0.01, -0.02, 1.05]])
MAT = MANUFACTURED_MATERIAL


@pytest.fixture(scope="module")
def breast_mesh():
    return surf.half_ellipsoid(RADII, 0.25)


@pytest.fixture(scope="module")
def breast(breast_mesh):
    return jr.Body.from_mesh(breast_mesh)


def cube_surface(lo=(0, 0, 0), size=1.0):
    """Outward-oriented triangles of an axis-aligned cube: points (8, 3), triangles (12, 3)."""
    P = np.array(list(itertools.product((0, 1), repeat=3)), float) * size + np.asarray(lo, float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    T = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return P, T


def write_surface(path, P, T):
    meshio.write(path, meshio.Mesh(P, [("triangle", T)]))
    return path


# ================================================================== quadrature, geometry
@pytest.mark.parametrize("d", [1, 2, 3])
def test_simplex_rule_is_exact_to_degree_2n_minus_1(d):
    """Exact monomial integrals on the unit simplex: a! b! c! / (a + b + c + d)!."""
    from math import factorial
    for n in (1, 2, 3, 4):
        lam, w = integration.simplex_rule(n, d)
        x = lam[:, 1:]                                  # Cartesian coordinates on the unit simplex
        assert lam.min() >= 0 and abs(w.sum() - 1) < 1e-14 and len(w) == n ** d
        errors = {}
        for p in itertools.product(range(2 * n + 1), repeat=d):
            if sum(p) > 2 * n:
                continue
            exact = np.prod([factorial(k) for k in p]) / factorial(sum(p) + d) * factorial(d)
            errors[p] = abs(np.sum(w * np.prod(x ** np.array(p), axis=1)) - exact)
        assert max(e for p, e in errors.items() if sum(p) <= 2 * n - 1) < 1e-14
        assert max(e for p, e in errors.items() if sum(p) == 2 * n) > 1e-6   # and no more


def test_half_ellipsoid_body(breast):
    b = breast
    exact = 2 / 3 * np.pi * np.prod(RADII)
    assert b.dim == 3 and b.cells.shape[1] == 4 and np.all(b.volumes > 0)
    assert abs(b.volumes.sum() - b.measure) < 1e-12 * b.measure
    assert abs(b.measure / exact - 1) < 0.05                     # chords of the curved skin
    assert set(b.tags) == {"base", "skin", "volume"} and len(b.tags["volume"]) == b.n
    assert np.abs(b.X[b.tagged("base"), 2]).max() < 1e-12
    skin = b.X[b.tagged("skin")]
    assert np.abs(np.sum((skin / RADII) ** 2, 1) - 1).max() < 1e-6
    assert np.array_equal(np.union1d(b.tagged("base"), b.tagged("skin")), b.surface_particles())
    # surface triangles, outward: closed (sum A n = 0) and the divergence theorem gives the volume
    tri, n = b.boundary_facets()
    assert tri.shape[1:] == (3, 3) and np.allclose(np.linalg.norm(n, axis=1), 1)
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    assert np.abs((area[:, None] * n).sum(0)).max() < 1e-13
    assert abs(np.sum(area * np.einsum("mi,mi->m", tri.mean(1), n)) / 3 - b.measure) < 1e-12
    assert np.allclose(n[np.abs(tri[:, :, 2]).max(1) < 1e-12], [0, 0, -1], atol=1e-12)   # base: down
    # point in mesh
    assert b.contains([[0, 0, 0.3], [0.5, 0.3, 0.1], [0.0, 0.0, 0.0]]).all()
    assert not b.contains([[0, 0, 0.7], [0.9, 0.9, 0.1], [0, 0, -0.01]]).any()
    with pytest.raises(ValueError, match="outside the body"):
        b.check_inside([[0.0, 0.0, 0.65]])


def test_cylinder_and_lobe_shapes():
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(2) as pool:                  # gmsh's global state, off the main thread
        cyl_mesh, again = pool.map(lambda _: surf.cylinder(0.5, 1.0, 0.25), range(2))
    cyl = jr.Body.from_mesh(cyl_mesh)
    assert np.array_equal(jr.Body.from_mesh(again).cells, cyl.cells)
    assert set(cyl.tags) == {"bottom", "top", "side", "volume"}
    assert np.abs(cyl.X[cyl.tagged("bottom"), 2]).max() < 1e-12
    assert np.abs(cyl.X[cyl.tagged("top"), 2] - 1).max() < 1e-12
    side = cyl.X[cyl.tagged("side")]
    assert np.abs(np.hypot(side[:, 0], side[:, 1]) - 0.5).max() < 1e-9
    assert abs(cyl.measure / (np.pi * 0.25) - 1) < 0.05
    lobe = jr.Body.from_mesh(surf.lobe(2.0, 1.0, 0.5, 0.15))
    assert set(lobe.tags) == {"surface", "volume"}
    assert np.array_equal(lobe.tagged("surface"), lobe.surface_particles())
    big, small = 4 / 3 * np.pi * 0.7 * 0.5 * 0.25, 4 / 3 * np.pi * 0.5 * 0.35 * 0.175   # semi-axes
    assert max(big, small) < lobe.measure < big + small        # fused: overlapping lobes


def test_reproducing_conditions_at_random_points(breast):
    """Linear RK reproduction to round-off on the unstructured body: sum Psi = 1,
    sum Psi X = x, sum grad Psi = 0, sum grad Psi X^T = I."""
    rng = np.random.default_rng(0)
    P = rng.uniform(breast.lower, breast.upper, (3000, 3))
    P = P[breast.contains(P)][:400]
    sf = breast.shape_functions(P, 2.01 * breast.spacing)
    XI = breast.X[sf.idx]
    errs = [np.abs(sf.psi.sum(1) - 1).max(), np.abs(np.einsum("pk,pkd->pd", sf.psi, XI) - P).max(),
            np.abs(sf.dpsi.sum(1)).max(), np.abs(np.einsum("pkj,pki->pij", sf.dpsi, XI) - np.eye(3)).max()]
    print(f"reproducing conditions on {breast.n} unstructured particles, {len(P)} points: {errs}")
    assert len(P) == 400 and max(errs) < 1e-12
    with pytest.raises(ValueError, match="support"):
        breast.shape_functions(P, 0.3 * breast.spacing, support_factor=0.3)


# ================================================================== SCNI on meshes
def square_mesh(n=60, seed=1):
    """A 2D Delaunay triangle mesh of the unit square (random interior points)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 7)[:-1]
    edge = np.concatenate([np.c_[t, 0 * t], np.c_[1 + 0 * t, t], np.c_[1 - t, 1 + 0 * t], np.c_[0 * t, 1 - t]])
    P = np.concatenate([edge, rng.uniform(0.08, 0.92, (n, 2))])
    T = Delaunay(P).simplices
    e1, e2 = P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]
    clockwise = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] < 0
    T[clockwise] = T[clockwise][:, ::-1]                 # one orientation (qhull mixes them)
    return meshio.Mesh(np.c_[P, np.zeros(len(P))], [("triangle", T)])


@pytest.mark.parametrize("which", ["breast", "square"])
def test_scni_integration_constraint_on_meshes(which, breast):
    """Every particle: sum_L w_L b_I(X_L) = oint Psi_I n (to round-off), with and without the
    sub-cell stabilisation; the cells are the particles' volumes; linear fields exact."""
    body = breast if which == "breast" else jr.Body.from_mesh(square_mesh())
    a = 2.01 * body.spacing
    for beta in (0.0, 0.5):
        s = scni.build(body, a, stab=beta)
        T = s.table
        lhs = np.zeros((body.n, body.dim))
        np.add.at(lhs, T.idx, T.weights[:, None, None] * T.dpsi)
        err = np.abs(lhs - s.boundary_integral).max()
        print(f"{which} SCNI beta={beta}: constraint error {err:.1e} over {body.n} particles, {len(T.weights)} rows")
        assert err < 1e-12
        assert np.abs(s.areas[:body.n] - body.volumes).max() < 1e-13
        assert abs(T.weights.sum() - body.measure) < 1e-12
        assert np.abs(np.einsum("rkj,rki->rij", T.dpsi, body.X[T.idx]) - np.eye(body.dim)).max() < 1e-11
        B = s.boundary          # the contact points' rule: the same boundary side, exactly
        rhs = np.zeros((body.n, body.dim))
        np.add.at(rhs, B.idx, (B.weights[:, None] * B.psi)[..., None] * B.normals[:, None, :])
        assert np.abs(rhs - s.boundary_integral).max() < 1e-12
        if beta:
            assert len(T.weights) == body.n + body.cells.size      # a piece per particle and cell


# ================================================================== solves
u_exact = manufactured_u


def manufactured_model(spacing, integration_="gauss"):
    body = jr.Body.from_mesh(surf.cylinder(0.5, 1.0, spacing))
    surface = body.surface_particles()
    return jr.Model(body, MAT, integration=integration_, essential={"surface": surface},
                    body_force=manufactured_body_force)


@pytest.fixture(scope="module")
def manufactured():
    return {h: manufactured_model(h) for h in (0.25, 0.18, 0.13)}


def affine_patch_error(model):
    """|u - u_affine| and |F - F0| at the interior particles with u = (F0 - I) X on the
    surface particles and no load."""
    body = model.body
    surface = model.set_indices("surface")
    sol = model.solve({"surface": body.X[surface] @ (F0 - np.eye(3)).T}, loads=0.0)
    inner = np.setdiff1d(np.arange(body.n), surface)
    u = np.asarray(model.particle_displacements(sol))
    F = np.asarray(model.deformation_gradient(sol, body.X[inner]))
    return np.abs(u[inner] - body.X[inner] @ (F0 - np.eye(3)).T).max(), np.abs(F - F0).max(), len(inner)


def test_affine_patch_scni_exact_gauss_bounded(manufactured):
    """SCNI on the unstructured tetrahedral body passes the affine patch test to round-off;
    Gauss on the tetrahedra (no integration constraint) only approximately."""
    eu_s, eF_s, n_in = affine_patch_error(manufactured_model(0.18, "scni"))
    eu_g, eF_g, _ = affine_patch_error(manufactured[0.18])
    print(f"affine patch, {n_in} interior particles: SCNI |u err| {eu_s:.1e} |F err| {eF_s:.1e}; "
          f"Gauss |u err| {eu_g:.1e} |F err| {eF_g:.1e}")
    assert n_in > 30
    assert eu_s < 1e-10 and eF_s < 1e-10
    assert 1e-8 < eF_g < 2e-2 and eu_g < 5e-3


def test_mscni_affine_patch_on_a_2d_triangle_mesh():
    """The sub-cell stabilised SCNI on a 2D unstructured mesh body passes the patch test too
    (every sub-cell satisfies the integration constraint)."""
    body = jr.Body.from_mesh(square_mesh())
    surface = body.surface_particles()
    F2 = np.array([[1.1, 0.2], [-0.1, 0.95]])
    model = jr.Model(body, MAT, integration="mscni", essential={"surface": surface})
    sol = model.solve({"surface": body.X[surface] @ (F2 - np.eye(2)).T})
    inner = np.setdiff1d(np.arange(body.n), surface)
    F = np.asarray(model.deformation_gradient(sol, body.X[inner]))
    u = np.asarray(model.particle_displacements(sol))
    assert len(inner) == 60 and np.abs(F - F2).max() < 1e-10
    assert np.abs(u[inner] - body.X[inner] @ (F2 - np.eye(2)).T).max() < 1e-10


def test_convergence_against_a_manufactured_solution(manufactured):
    """u = A (sin(2x + z), cos(x + y), y sin z) with the body force -Div P(F(u)) (autodiff)
    and u prescribed on the surface particles: the volume-weighted RMS error of the
    particle displacements falls with refinement, at about second order."""
    rows = []
    for h, model in manufactured.items():
        body = model.body
        sol = model.solve({"surface": np.asarray(u_exact(body.X[model.set_indices("surface")]))})
        ref = np.asarray(u_exact(body.X))
        e = np.asarray(model.particle_displacements(sol)) - ref
        err = np.sqrt(np.sum(body.volumes[:, None] * e ** 2) / np.sum(body.volumes[:, None] * ref ** 2))
        rows.append((body.spacing, err, body.n))
    h, err, n = map(np.array, zip(*rows))
    rates = np.diff(np.log(err)) / np.diff(np.log(h))
    print("manufactured solution, Gauss on tetrahedra: particles", n.tolist(), "spacing", h.round(3).tolist(),
          "rel. error", err.round(5).tolist(), "rates", rates.round(2).tolist())
    assert np.all(np.diff(err) < 0) and err[-1] < 5e-3
    assert rates.min() > 1.2


def test_tractions_on_mesh_surface_triangles(breast):
    """Gauss points on the surface triangles: the areas add up, and a uniform traction on the
    base gives nodal forces summing to traction x base area."""
    bp, bw, bn = integration.boundary_points(breast, order=2)
    tri, _ = breast.boundary_facets()
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum() / 2
    assert abs(bw.sum() - area) < 1e-12 and len(bp) == 4 * len(tri)
    a = 2.01 * breast.spacing
    surface = integration.table(breast, bp, bw, a, normals=bn)
    volume = integration.gauss_table(breast, a)
    f = nodal_forces(breast, volume, surface, tractions=[(lambda X: X[:, 2] < 1e-9, [0.0, 0.0, 2.0])])
    base = bw[bp[:, 2] < 1e-9].sum()
    assert abs(base / (np.pi * RADII[0] * RADII[1]) - 1) < 0.05
    assert np.allclose(f.sum(0), [0, 0, 2.0 * base], atol=1e-12)


# ================================================================== files and formats
def test_written_and_read_back_in_four_formats(breast_mesh, breast, tmp_path):
    """The same body (particles, volumes, cells, named tags) from .msh, .vtu, .inp; the same
    geometry from .mesh (Medit keeps integer references only)."""
    for name, fmt in (("b.msh", "gmsh22"), ("b.vtu", None), ("b.inp", None), ("b.mesh", None)):
        m = copy.deepcopy(breast_mesh)
        if name.endswith(".mesh"):
            m = meshio.Mesh(m.points, m.cells)
        path = tmp_path / name
        meshio.write(path, m, file_format=fmt) if fmt else meshio.write(path, m)
        b = jr.Body.from_mesh(path)
        assert np.array_equal(b.cells, breast.cells) and np.abs(b.X - breast.X).max() < 1e-12, name
        assert np.abs(b.volumes - breast.volumes).max() < 1e-15, name
        if not name.endswith(".mesh"):
            assert b.tags.keys() == breast.tags.keys(), name
            assert all(np.array_equal(b.tags[k], breast.tags[k]) for k in b.tags), name


def test_refined_body_keeps_volume_and_tags(breast_mesh, breast):
    """Uniform refinement by gmsh: 8 tetrahedra per tetrahedron, a particle at every edge
    midpoint, the same (chordal) volume, the tags carried to the new particles."""
    fine = jr.Body.from_mesh(breast_mesh, refine=1)
    edges = np.unique(np.sort(breast.cells[:, list(itertools.combinations(range(4), 2))].reshape(-1, 2), 1), axis=0)
    assert len(fine.cells) == 8 * len(breast.cells) and fine.n == breast.n + len(edges)
    assert abs(fine.measure - breast.measure) < 1e-12 and fine.tags.keys() == breast.tags.keys()
    assert np.abs(fine.X[fine.tagged("base"), 2]).max() < 1e-12 and len(fine.tagged("base")) > 3 * len(breast.tagged("base"))
    assert np.array_equal(np.union1d(fine.tagged("base"), fine.tagged("skin")), fine.surface_particles())
    with pytest.raises(ValueError, match="refine must be a whole number"):
        jr.Body.from_mesh(breast_mesh, refine=-1)


def test_from_surface_stl_obj_ply(tmp_path):
    """A closed surface (a sphere triangulated by gmsh, written by meshio) filled with
    tetrahedra at the requested spacing."""
    with mesh.gmsh_session() as gmsh:
        gmsh.model.occ.addSphere(0, 0, 0, 1.0)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.15)
        gmsh.model.mesh.generate(2)
        _, xyz, _ = gmsh.model.mesh.getNodes()
        tags, nodes = gmsh.model.mesh.getElementsByType(2)
    P = xyz.reshape(-1, 3)
    T = nodes.reshape(-1, 3).astype(np.int64) - 1
    sizes = {}
    for ext in ("stl", "obj", "ply"):
        body = jr.Body.from_surface(write_surface(tmp_path / f"sphere.{ext}", P, T), spacing=0.3)
        assert abs(body.measure / (4 / 3 * np.pi) - 1) < 0.05, ext
        assert set(body.tags) == {"surface", "volume"}
        assert np.abs(np.linalg.norm(body.X[body.tagged("surface")], axis=1) - 1).max() < 1e-2
        sizes[ext] = body.n
    fine = jr.Body.from_surface(tmp_path / "sphere.stl", spacing=0.2)
    assert fine.n > 2 * sizes["stl"] and 0.15 < fine.spacing < 0.3


def test_bad_meshes_get_named_errors(breast_mesh, tmp_path):
    P, T = cube_surface()
    open_ = write_surface(tmp_path / "open.stl", P, T[:-2])
    with pytest.raises(ValueError, match="not closed"):
        jr.Body.from_surface(open_, 0.2)
    Q, U = cube_surface((1, 1, 0))                       # a second cube sharing one edge
    touching = write_surface(tmp_path / "edge.stl", np.r_[P, Q], np.r_[T, U + 8])
    with pytest.raises(ValueError, match="not manifold"):
        jr.Body.from_surface(touching, 0.2)
    Q, U = cube_surface((0.5, 0.5, 0.5))                 # a second cube through the first
    crossing = write_surface(tmp_path / "cross.stl", np.r_[P, Q], np.r_[T, U + 8])
    with pytest.raises(ValueError, match="intersects itself"):
        jr.Body.from_surface(crossing, 0.2)
    flipped = write_surface(tmp_path / "flip.obj", P, np.r_[T[:-1], T[-1:, ::-1]])
    with pytest.raises(ValueError, match="not consistently oriented"):
        jr.Body.from_surface(flipped, 0.2)
    with pytest.raises(ValueError, match="too coarse"):
        jr.Body.from_surface(write_surface(tmp_path / "cube.ply", P, T), 0.8)
    with pytest.raises(ValueError, match="too coarse"):
        surf.half_ellipsoid(RADII, 0.4)                   # the breast is 0.6 thick

    tets = breast_mesh.cells_dict["tetra"].copy()       # (mixed vertex orders: test_mesh_hostile.py)
    flat = meshio.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0.0]]),
                       [("tetra", np.array([[0, 1, 2, 3], [0, 1, 4, 2]]))])
    with pytest.raises(ValueError, match="zero-volume"):
        jr.Body.from_mesh(flat)
    twice = meshio.Mesh(np.r_[breast_mesh.points, breast_mesh.points[tets[0, :1]]],
                        [("tetra", np.r_[tets[:7], [[len(breast_mesh.points), *tets[0, 1:]]]])])
    with pytest.raises(ValueError, match="coincide"):
        jr.Body.from_mesh(twice)
    with pytest.raises(ValueError, match="3D body needs tetra cells, but the mesh is a 2D or surface mesh"):
        jr.Body.from_mesh(square_mesh(), dim=3)
    assert jr.Body.from_mesh(square_mesh()).dim == 2          # the same mesh as a 2D body
    with pytest.raises(ValueError, match="2D body needs triangle cells, but the mesh has hexahedron cells"):
        jr.Body.from_mesh(meshio.Mesh(np.eye(8, 3), [("hexahedron", np.arange(8)[None])]))
    with pytest.raises(ValueError, match="does not exist"):
        jr.Body.from_mesh(tmp_path / "missing.vtu")
    body = jr.Body.from_mesh(breast_mesh)
    with pytest.raises(ValueError, match=r"no tag 'nipple'; its tags: \['base', 'skin', 'volume'\]"):
        body.tagged("nipple")


# ================================================================== selections
def test_selections_for_paddles_and_needles(breast):
    b = breast
    apex = np.array([0.0, 0.0, RADII[2]])
    patch = b.surface_near(apex, 0.4)
    d = np.linalg.norm(b.X - apex, axis=1)
    assert set(patch) == set(np.flatnonzero(d <= 0.4)) & set(b.surface_particles())
    assert 3 <= len(patch) and np.all(np.isin(patch, b.tagged("skin")))
    track = b.near_segment([0.0, 0.0, 0.0], [0.0, 0.0, 0.45], 0.25)
    r = np.hypot(b.X[:, 0], b.X[:, 1])
    brute = np.flatnonzero(np.where(b.X[:, 2] > 0.45, np.hypot(r, b.X[:, 2] - 0.45), r) <= 0.25)
    assert np.array_equal(track, brute) and len(track) >= 4
    assert np.array_equal(b.select(lambda X: X[:, 2] < 1e-9), b.tagged("base"))
    with pytest.raises(ValueError, match="radius"):
        b.surface_near(apex, 0.0)
    with pytest.raises(ValueError, match="3 finite coordinates"):
        b.near_segment([0, 0], [0, 0, 1], 0.1)
    grid = jr.Body.grid((4, 4, 4), 1 / 3)
    assert len(grid.surface_particles()) == 64 - 8 and grid.tags == {}
    with pytest.raises(ValueError, match="only mesh bodies carry tags"):
        grid.tagged("base")


def test_embedded_segments_and_mirror_symmetric_shapes():
    """``embed_segments``: mesh vertices along each segment at ``segment_spacing`` (a needle
    track); ``symmetric``: the half meshed and mirrored, vertex for vertex, tags on both halves."""
    a, b = np.array([-0.9, 0.0, 0.2]), np.array([0.3, 0.0, 0.2])
    inside = a + [0.03, 0, 0]                        # a segment in the mirror plane starts inside
    plain, fine, mirror = (jr.Body.from_mesh(surf.half_ellipsoid(RADII, 0.25, **kw)) for kw in (
        {}, {"embed_segments": [(a, b)], "segment_spacing": 0.1},
        {"embed_segments": [(inside, b)], "segment_spacing": 0.1, "symmetric": "y"}))
    assert len(plain.near_segment(a, b, 1e-9)) < 4
    for body, start in ((fine, a), (mirror, inside)):
        on = body.X[body.near_segment(start, b, 1e-9)]
        x = np.sort(on[:, 0])
        assert x[0] == pytest.approx(start[0]) and x[-1] == pytest.approx(b[0])
        assert len(x) >= 12 and np.diff(x).max() < 0.1 * 1.3       # vertices every ~0.1 along it
        assert abs(body.measure / (2 / 3 * np.pi * 0.6) - 1) < 0.05
    X = mirror.X
    image = np.array([np.flatnonzero(np.all(np.abs(X - x * [1, -1, 1]) < 1e-12, axis=1))[0] for x in X])
    assert np.array_equal(image[image], np.arange(len(X)))              # an exact mirror image
    assert np.array_equal(np.sort(image[mirror.tagged("skin")]), mirror.tagged("skin"))
    assert set(mirror.tags) == {"base", "skin", "volume"} and np.any(X[:, 1] > 0.3) and np.any(X[:, 1] < -0.3)
    assert np.array_equal(mirror.tagged("skin"), np.intersect1d(mirror.surface_particles(), mirror.tagged("skin")))
    assert np.all(np.isin(mirror.surface_particles(), np.union1d(mirror.tagged("skin"), mirror.tagged("base"))))
    with pytest.raises(ValueError, match="leaves the half-ellipsoid"):
        surf.half_ellipsoid(RADII, 0.25, embed_segments=[(a, [1.5, 0, 0.2])])
    with pytest.raises(ValueError, match="mirrored half"):
        surf.half_ellipsoid(RADII, 0.25, embed_segments=[([0, -0.2, 0.2], b)], symmetric="y")
    with pytest.raises(ValueError, match="pairs of 3D points"):
        surf.half_ellipsoid(RADII, 0.25, embed_segments=[(0, 1)])
    with pytest.raises(ValueError, match="symmetric"):
        surf.half_ellipsoid(RADII, 0.25, symmetric="z")

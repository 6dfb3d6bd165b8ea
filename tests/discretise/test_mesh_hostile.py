"""Meshes from other tools and hostile mesh input (issue 35): tetrahedral boxes of scipy's
Delaunay and scikit-fem (half their cells in the other vertex order) load and pass the affine
patch test with SCNI; every defect is refused with an error naming it, before any geometry
(finite coordinates, cells, connectivity) or before meshing (the spacing of a surface)."""
import logging

import meshio
import numpy as np
import pytest

import jaxrkpm as jr
from tests.problems import BOX, scipy_box, skfem_box

F0 = np.array([[1.1, 0.05, 0.02], [-0.04, 0.95, 0.03], [0.01, -0.02, 1.05]])
MAT = jr.NeoHookean(1.0, 1.0)
LOGGER = "jaxrkpm.discretise.mesh"


def signed_volumes(points, cells):
    V = np.asarray(points, float)[np.asarray(cells)]
    return np.linalg.det(V[:, 1:] - V[:, :1]) / 6


def scni_patch_error(body):
    """max |u - (F0 - I) X| and |F - F0| at the interior particles, the surface particles
    moved by the affine map, no load, SCNI (exact for affine fields on any particle set)."""
    surface = body.surface_particles()
    model = jr.Model(body, MAT, integration="scni", essential={"surface": surface})
    sol = model.solve({"surface": body.X[surface] @ (F0 - np.eye(3)).T})
    inner = np.setdiff1d(np.arange(body.n), surface)
    u = np.asarray(model.particle_displacements(sol))
    F = np.asarray(model.deformation_gradient(sol, body.X[inner]))
    return np.abs(u[inner] - body.X[inner] @ (F0 - np.eye(3)).T).max(), np.abs(F - F0).max(), len(inner)


@pytest.mark.parametrize("tool", ["scipy", "skfem"])
def test_meshes_of_other_tools_load_and_pass_the_scni_patch_test(tool, tmp_path, caplog):
    if tool == "skfem":
        pytest.importorskip("skfem")
        source = skfem_box(tmp_path / "box.vtu")
        raw = meshio.read(source)
    else:
        source = raw = scipy_box()
    vol = signed_volumes(raw.points, raw.cells_dict["tetra"])
    assert (vol < 0).sum() > 0.3 * len(vol) and (vol > 0).sum() > 0.3 * len(vol)   # mixed orientation
    with caplog.at_level(logging.INFO, logger=LOGGER):
        body = jr.Body.from_mesh(source)
    said = [r for r in caplog.records if r.name == LOGGER]
    assert len(said) == 1 and said[0].levelno == logging.INFO                        # said once
    assert f"{(vol < 0).sum()} of {len(vol)} tetra cells had the opposite vertex order" in said[0].getMessage()
    assert np.all(signed_volumes(body.X, body.cells) > 0)
    assert body.measure == pytest.approx(np.prod(BOX), rel=1e-12)
    eu, eF, n_in = scni_patch_error(body)
    print(f"{tool} box: {body.n} particles, {len(body.cells)} tetrahedra; SCNI affine patch |u err| {eu:.1e} "
          f"|F err| {eF:.1e} over {n_in} interior particles")
    assert n_in >= 27 and eu < 1e-10 and eF < 1e-10


def test_reordering_a_cell_changes_nothing():
    """One cell in the other vertex order: the same body as before (a convention)."""
    mesh = scipy_box()
    tets = mesh.cells_dict["tetra"]
    body = jr.Body.from_mesh(mesh)
    flipped = tets.copy()
    flipped[7, [0, 1]] = flipped[7, [1, 0]]
    again = jr.Body.from_mesh(meshio.Mesh(mesh.points, [("tetra", flipped)]))
    assert np.array_equal(np.sort(again.cells, 1), np.sort(body.cells, 1))
    assert np.array_equal(again.volumes, body.volumes) and np.all(signed_volumes(again.X, again.cells) > 0)


def test_folded_cells_are_refused_naming_them():
    """Two cells on the same side of their shared face overlap: reordering cannot mend it."""
    P3 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.2, 1], [0.3, 0.3, 0.5]], float)
    with pytest.raises(ValueError, match=r"1 interior faces have both their tetra cells on the same side .*"
                                         r"cells 0 and 1 across the face with vertices \[0, 1, 2\]"):
        jr.Body.from_mesh(meshio.Mesh(P3, [("tetra", np.array([[0, 1, 2, 3], [0, 1, 2, 4]]))]))
    P2 = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0.5, 0]], float)
    with pytest.raises(ValueError, match="both their triangle cells on the same side"):
        jr.Body.from_mesh(meshio.Mesh(P2, [("triangle", np.array([[0, 1, 2], [1, 0, 3]]))]))


@pytest.fixture(scope="module")
def box():
    return scipy_box()


def hostile(box, points=None, cells=None):
    return meshio.Mesh(box.points if points is None else points,
                       [("tetra", box.cells_dict["tetra"] if cells is None else cells)])


def test_non_finite_coordinates_are_refused_before_any_geometry(box):
    for bad in (np.nan, np.inf):
        P = box.points.copy()
        P[5, 1] = bad
        with pytest.raises(ValueError, match=r"1 points have non-finite coordinates \(NaN or inf\), e.g. point 5"):
            jr.Body.from_mesh(hostile(box, points=P))


def test_connectivity_is_checked(box):
    tets = box.cells_dict["tetra"]
    n = len(box.points)
    with pytest.raises(ValueError, match="has no tetra cells: its tetra blocks are empty"):
        jr.Body.from_mesh(hostile(box, cells=np.zeros((0, 4), np.int64)))
    past = tets.copy()
    past[3, 2] = n
    with pytest.raises(ValueError, match=rf"1 tetra cells index past the {n} points \(valid 0..{n - 1}\), e.g. cell 3"):
        jr.Body.from_mesh(hostile(box, cells=past))
    missing = tets.copy()
    missing[4, 0] = -1                       # NumPy would take the last point
    with pytest.raises(ValueError, match=r"e.g. cell 4 .* \(a negative index: a missing vertex\)"):
        jr.Body.from_mesh(hostile(box, cells=missing))
    fractional = tets.astype(float)
    fractional[2, 1] += 0.5                  # astype(int) would truncate it
    with pytest.raises(ValueError, match=r"must be integer vertex indices, got float64: cell 2 holds"):
        jr.Body.from_mesh(hostile(box, cells=fractional))
    with pytest.raises(ValueError, match="must be integer vertex indices, got float64"):
        jr.Body.from_mesh(hostile(box, cells=tets.astype(float)))


def test_points_no_cell_uses_are_dropped_and_said(box, caplog):
    P = np.concatenate([box.points, [[5.0, 5.0, 5.0]]])
    with caplog.at_level(logging.INFO, logger=LOGGER):
        body = jr.Body.from_mesh(hostile(box, points=P))
    said = [r for r in caplog.records if r.name == LOGGER]
    assert len(said) == 1 and said[0].levelno == logging.WARNING
    assert f"1 of {len(P)} points are no tetra vertex and were dropped (1 belong to no cell at all, e.g. point " \
           f"{len(P) - 1}" in said[0].getMessage()
    assert body.n == len(box.points) and np.array_equal(body.X, box.points)


def test_unreadable_file_is_a_named_error_not_an_exit(tmp_path):
    text = tmp_path / "notes.vtu"
    text.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match=r"meshio cannot read .*notes.vtu': not a valid .vtu file"):
        jr.Body.from_mesh(text)
    with pytest.raises(ValueError, match="meshio cannot read"):
        jr.Body.from_surface(text, 0.3)


def test_surface_input_is_checked_before_meshing(tmp_path, monkeypatch):
    from jaxrkpm.discretise import surface
    from tests.discretise.test_mesh import cube_surface, write_surface

    P, T = cube_surface()
    path = write_surface(tmp_path / "cube.stl", P, T)

    def no_meshing(*a, **k):
        raise AssertionError("gmsh was started")
    monkeypatch.setattr(surface, "gmsh_session", no_meshing)
    with pytest.raises(TypeError, match=r"spacing must be a positive number, got '0.3' \(str\)"):
        jr.Body.from_surface(path, spacing="0.3")
    with pytest.raises(ValueError, match="spacing 0.002 is too fine for "):
        jr.Body.from_surface(path, spacing=0.002)
    with pytest.raises(ValueError, match=r"about 8.1e\+08 tetrahedra .* more than the bound of 1,000,000 "
                                         r"\(max_cells\); use a spacing of at least 0.0187"):
        jr.Body.from_surface(path, spacing=0.002)
    with pytest.raises(ValueError, match="more than the bound of 100"):
        jr.Body.from_surface(path, spacing=0.2, max_cells=100)
    Q = P.copy()
    Q[3, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite coordinates"):
        surface.tetrahedralise(Q, T, 0.3)
    with pytest.raises(ValueError, match="index past"):
        surface.tetrahedralise(P, np.r_[T, [[0, 1, 8]]], 0.3)


def test_refining_past_the_bound_is_refused(box):
    with pytest.raises(ValueError, match=r"refine=6 would split the .* cells into .* more than the bound"):
        jr.Body.from_mesh(box, refine=6)


def test_the_default_integration_of_a_mesh_body_is_the_accurate_one(tmp_path):
    """Why Model's default stays "gauss" for mesh bodies (experiments/bench_mesh_integration.py
    measures it with timings): on the tetrahedral box, a smooth large deformation (the
    manufactured solution of test_mesh.py) is several times more accurate with Gauss points
    than with SCNI, which is exact only for affine fields."""
    pytest.importorskip("skfem")
    from tests.problems import MANUFACTURED_MATERIAL, manufactured_body_force, manufactured_u

    body = jr.Body.from_mesh(skfem_box(tmp_path / "box.vtu"))
    surface = body.surface_particles()
    errors = {}
    for integration in (None, "scni"):
        kw = {} if integration is None else {"integration": integration}
        model = jr.Model(body, MANUFACTURED_MATERIAL, essential={"surface": surface},
                         body_force=manufactured_body_force, **kw)
        sol = model.solve({"surface": np.asarray(manufactured_u(body.X[surface]))})
        ref = np.asarray(manufactured_u(body.X))
        e = np.asarray(model.particle_displacements(sol)) - ref
        errors[model.integration] = np.sqrt(np.sum(body.volumes[:, None] * e ** 2)
                                            / np.sum(body.volumes[:, None] * ref ** 2))
    print(f"manufactured solution on the {body.n}-particle box: relative errors {errors}")
    assert set(errors) == {"gauss", "scni"} and errors["gauss"] < 3e-3 and errors["scni"] > 5 * errors["gauss"]


def test_delaunay_slivers_are_named_and_dropped_on_request(caplog):
    """scipy's Delaunay of a lattice cube holds zero-volume slivers: refused with the count and
    the option that drops them; dropped, the body has the cube's volume and its surface (the
    faces the slivers left inside are not boundary), said in the log line."""
    from scipy.spatial import Delaunay
    from jaxrkpm.discretise import mesh
    g = np.linspace(0.0, 1.0, 4)
    P = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    cells = Delaunay(P).simplices
    lattice = meshio.Mesh(P, [("tetra", cells)])
    flat = int(np.sum(np.abs(signed_volumes(P, cells)) < 1e-12))
    assert flat > 0
    with pytest.raises(ValueError, match=rf"{flat} of {len(cells)} tetra cells are zero-volume.*"
                                         r"drop_degenerate=True\) drops them"):
        jr.Body.from_mesh(lattice)
    with caplog.at_level(logging.INFO, logger=LOGGER):
        body = jr.Body.from_mesh(lattice, drop_degenerate=True)
    assert f"{flat} zero-volume tetra cells were dropped" in caplog.text
    assert len(body.cells) == len(cells) - flat and body.volumes.sum() == pytest.approx(1.0, abs=1e-12)
    faces = mesh.boundary_faces(body.X, body.cells)[0]
    normals, areas = mesh.facet_normals(body.X[faces])
    assert areas.sum() == pytest.approx(6.0, abs=1e-12)                # the cube's surface, no inner faces
    assert np.all(np.sum(normals * (body.X[faces].mean(1) - 0.5), 1) > 0)
    with pytest.raises(ValueError, match="drop_degenerate must be True or False"):
        jr.Body.from_mesh(lattice, drop_degenerate="yes")

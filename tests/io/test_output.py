"""Mesh output (jaxrkpm.io.output, meshio): a written .vtu read back has the right points, cells and
arrays on the right points; a .pvd series lists its frames; the 3D PNG view is drawn."""
import dataclasses

import jax

import jax.numpy as jnp
import matplotlib.image
import meshio
import numpy as np
import pytest
from scipy.spatial import Delaunay

import jaxrkpm as jr
from jaxrkpm.io import output
from jaxrkpm.io import plot
from jaxrkpm import thesis
from tests.problems import block, phantom_body

PAD = (0.1, 0.05)


@pytest.fixture(scope="module")
def solved2d():
    _, _, model = block(5, right="pad")
    return model, model.solve({"pad": jnp.array(PAD)}, steps=2)


@pytest.fixture(scope="module")
def solved3d():
    model = thesis.cube("reduced")
    return model, model.solve({"paddle": jnp.array([-0.3, 0.0, 0.3])}, steps=2)


def areas(X, tri):
    """Signed areas of triangles (C, 3) of 2D points."""
    a, b, c = X[tri[:, 0]], X[tri[:, 1]], X[tri[:, 2]]
    return 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])


def enclosed_volume(X, faces):
    """(volume, |sum of area vectors|) of a closed surface of triangles / planar quads
    (divergence theorem: positive volume iff the faces point outward)."""
    P = X[faces]
    tris = [P[:, [0, i, i + 1]] for i in range(1, faces.shape[1] - 1)]   # fan split
    vol, area = 0.0, np.zeros(3)
    for T in tris:
        n = 0.5 * np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0])
        vol += np.sum(np.einsum("ij,ij->i", T.mean(axis=1), n)) / 3.0
        area += n.sum(axis=0)
    return vol, np.linalg.norm(area)


def test_vtu_2d_roundtrip_right_arrays_on_right_points(solved2d, tmp_path):
    model, sol = solved2d
    path = output.write_solution(tmp_path / "s.vtu", model, sol)
    back = meshio.read(path)
    X = np.asarray(model.body.X)
    n = len(X)
    np.testing.assert_array_equal(back.points, np.c_[X, np.zeros(n)])      # reference positions, z = 0
    # cells: the 4x4 lattice quads, counter-clockwise, each a spacing x spacing square
    (block_,) = back.cells
    assert block_.type == "quad" and block_.data.shape == (16, 4)
    q = block_.data
    quad_area = areas(X, q[:, :3]) + areas(X, q[:, [0, 2, 3]])
    np.testing.assert_allclose(quad_area, 0.25 ** 2)
    assert len({tuple(sorted(c)) for c in q}) == 16
    pd = back.point_data
    assert set(pd) == {"displacement", "cauchy_stress", "von_mises", "det_F", "volume", "set_wall", "set_pad", "reaction"}
    assert pd["displacement"].shape == (n, 3) and pd["cauchy_stress"].shape == (n, 9)
    u = np.asarray(model.particle_displacements(sol))
    np.testing.assert_allclose(pd["displacement"][:, :2], u, rtol=1e-13, atol=1e-15)
    assert np.all(pd["displacement"][:, 2] == 0)
    pad = model.set_indices("pad")
    np.testing.assert_allclose(pd["displacement"][pad, :2], np.tile(PAD, (len(pad), 1)), atol=1e-10)
    np.testing.assert_array_equal(np.flatnonzero(pd["set_pad"]), np.sort(pad))
    np.testing.assert_array_equal(np.flatnonzero(pd["set_wall"]), np.flatnonzero(X[:, 0] == 0))
    np.testing.assert_allclose(pd["reaction"][pad, :2].sum(0), model.reaction(sol, "pad"), rtol=1e-12, atol=1e-14)
    assert np.all(pd["reaction"][(pd["set_pad"] == 0) & (pd["set_wall"] == 0)] == 0)
    s = np.asarray(model.stress(sol, X, kind="cauchy"))
    s33 = pd["cauchy_stress"].reshape(n, 3, 3)
    np.testing.assert_allclose(s33[:, :2, :2], s, rtol=1e-12, atol=1e-14)
    assert np.all(s33[:, 2, :] == 0) and np.abs(s).max() > 1e-3
    # von Mises of the plane-stress state, written out from its 2D formula
    vm = np.sqrt(s[:, 0, 0] ** 2 - s[:, 0, 0] * s[:, 1, 1] + s[:, 1, 1] ** 2 + 3 * s[:, 0, 1] ** 2)
    np.testing.assert_allclose(pd["von_mises"], vm, rtol=1e-12)
    detF = np.linalg.det(np.asarray(model.deformation_gradient(sol, X)))
    np.testing.assert_allclose(pd["det_F"], detF, rtol=1e-13)
    assert detF.min() > 0 and np.ptp(detF) > 1e-3          # stretched, not uniform
    np.testing.assert_allclose(pd["volume"].sum(), 1.0, rtol=1e-12)
    # deformed=True: the points are x = X + u, the data unchanged
    moved = meshio.read(output.write_solution(tmp_path / "d.vtu", model, sol, deformed=True))
    np.testing.assert_allclose(moved.points[:, :2], X + u, rtol=1e-13)
    np.testing.assert_array_equal(moved.point_data["von_mises"], pd["von_mises"])


def test_vtu_3d_hexahedra_and_fields(solved3d, tmp_path):
    model, sol = solved3d
    back = meshio.read(output.write_solution(tmp_path / "c.vtu", model, sol))
    X = np.asarray(model.body.X)
    np.testing.assert_array_equal(back.points, X)
    (cells,) = back.cells
    assert cells.type == "hexahedron" and cells.data.shape == (8, 8)
    vol, open_area = enclosed_volume(X, output.surface_faces("hexahedron", cells.data))
    assert vol == pytest.approx(1.0, rel=1e-12) and open_area < 1e-12    # closed, outward, the unit cube
    F = np.asarray(model.deformation_gradient(sol, X))
    np.testing.assert_allclose(back.point_data["det_F"], np.linalg.det(F), rtol=1e-13)
    np.testing.assert_allclose(back.point_data["cauchy_stress"].reshape(-1, 3, 3),
                               np.asarray(model.stress(sol, X)), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(back.point_data["displacement"],
                               np.asarray(model.particle_displacements(sol)), rtol=1e-13, atol=1e-15)


def test_pyvista_opens_vtu_and_series(solved3d, tmp_path):
    pv = pytest.importorskip("pyvista")
    model, sol = solved3d
    grid = pv.read(output.write_solution(tmp_path / "c.vtu", model, sol))
    assert grid.n_points == 27 and grid.n_cells == 8 and set(grid.celltypes) == {pv.CellType.HEXAHEDRON}
    np.testing.assert_allclose(grid["von_mises"], output.point_fields(model, sol)["von_mises"])
    reader = pv.get_reader(output.write_series(tmp_path / "run.pvd", model, [model.initial(), sol], [0, 5]))
    assert reader.time_values == [0.0, 5.0]
    reader.set_active_time_value(5.0)
    np.testing.assert_allclose(reader.read()[0]["displacement"], grid["displacement"])


def test_series_index_lists_the_frames(solved2d, tmp_path):
    model, sol = solved2d
    path = output.write_series(tmp_path / "out" / "run.pvd", model, [model.initial(), sol], [0.0, 2.5])
    frames = output.read_series(path)
    assert [t for t, _ in frames] == [0.0, 2.5]
    assert [f.relative_to(tmp_path / "out").as_posix() for _, f in frames] == \
        ["run/frame_0000.vtu", "run/frame_0001.vtu"]
    first, last = (meshio.read(f) for _, f in frames)
    assert np.all(first.point_data["displacement"] == 0)
    np.testing.assert_allclose(last.point_data["displacement"][:, :2],
                               np.asarray(model.particle_displacements(sol)), rtol=1e-13, atol=1e-15)


def test_polygon_body_triangulated_inside():
    body = phantom_body(0.1)
    kind, tri = output.body_cells(body)
    a = areas(body.X, tri)
    assert kind == "triangle" and a.min() > 0
    assert a.sum() == pytest.approx(body.measure, rel=1e-12)           # covers the polygon exactly
    # the cut corner x + y < 0.5 stays empty
    assert np.all(body.X[tri].mean(axis=1).sum(axis=1) > 0.5)
    assert set(np.unique(tri)) == set(range(body.n))                   # every particle is a vertex


def test_mesh_body_cells_are_used_and_oriented():
    grid = jr.Body.grid((3, 3, 3), 0.5)
    tets = Delaunay(grid.X).simplices
    P = grid.X[tets]
    tets = tets[np.abs(np.linalg.det(P[:, 1:] - P[:, :1])) > 1e-9]    # qhull's flat tets on the faces
    tets[::2] = tets[::2, [0, 2, 1, 3]]        # half of them negatively oriented
    kind, cells = output.body_cells(dataclasses.replace(grid, cells=tets))
    assert kind == "tetra"
    assert {tuple(sorted(c)) for c in cells} == {tuple(sorted(c)) for c in tets}
    vol, open_area = enclosed_volume(grid.X, output.surface_faces(kind, cells))
    assert vol == pytest.approx(1.0, rel=1e-12) and open_area < 1e-12
    with pytest.raises(ValueError, match=r"body.cells must be .*\(C, 4\)"):
        output.body_cells(dataclasses.replace(grid, cells=tets[:, :3]))


def test_lattice_cells_in_any_particle_order():
    grid = jr.Body.grid((4, 3), 0.5)
    perm = np.random.default_rng(0).permutation(grid.n)
    shuffled = dataclasses.replace(grid, X=grid.X[perm], volumes=grid.volumes[perm])
    kind, q = output.body_cells(shuffled)
    _, q0 = output.body_cells(grid)
    assert kind == "quad"
    assert {tuple(perm[c]) for c in q} == {tuple(c) for c in q0}        # the same quads, same order


def test_von_mises_of_uniaxial_and_pure_shear():
    s = np.zeros((2, 3, 3))
    s[0, 0, 0] = 2.0                  # uniaxial: sigma_vm = |sigma|
    s[1, 0, 1] = s[1, 1, 0] = 1.0     # pure shear: sqrt(3) tau
    np.testing.assert_allclose(output.von_mises(s), [2.0, np.sqrt(3.0)])


def test_bad_arguments(solved2d, tmp_path):
    model, sol = solved2d
    with pytest.raises(ValueError, match=r"must end with '\.vtu'"):
        output.write_solution(tmp_path / "a.vtk", model, sol)
    with pytest.raises(ValueError, match=r"must end with '\.pvd'"):
        output.write_series(tmp_path / "a.vtu", model, [sol], [0.0])
    with pytest.raises(ValueError, match="one value per solution"):
        output.write_series(tmp_path / "a.pvd", model, [sol, sol], [0.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        output.write_series(tmp_path / "a.pvd", model, [sol, sol], [1.0, 1.0])
    with pytest.raises(ValueError, match="empty"):
        output.write_series(tmp_path / "a.pvd", model, [], [])
    quad = ("quad", np.array([[0, 1, 2, 3]]))
    with pytest.raises(ValueError, match=r"points must have shape \(N, 2\) or \(N, 3\)"):
        output.write_vtu(tmp_path / "a.vtu", np.zeros((4, 4)), quad)
    with pytest.raises(ValueError, match="point data 'u' has shape"):
        output.write_vtu(tmp_path / "a.vtu", np.zeros((4, 2)), quad, {"u": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="cells index points outside 0..2"):
        output.write_vtu(tmp_path / "a.vtu", np.zeros((3, 2)), quad)
    with pytest.raises(ValueError, match="cells must be"):
        output.write_vtu(tmp_path / "a.vtu", np.zeros((4, 2)), ("quad", np.array([[0, 1, 2]])))
    assert not list(tmp_path.iterdir())        # nothing half-written


def test_deformed_body_png(solved3d, solved2d, tmp_path):
    model, sol = solved3d
    path = plot.deformed_body_png(tmp_path / "cube.png", model, sol, title="cube", stress_unit="kPa")
    img = matplotlib.image.imread(path)
    assert img.shape[0] > 500 and img.shape[1] > 600
    assert img[..., :3].std() > 0.1                       # drawn, not blank
    # the view's outline: the reference cube's 12 edges, each split at the middle particle
    faces = output.surface_faces(*output.body_cells(model.body))
    assert len(plot.feature_edges(model.body.X, faces)) == 24
    with pytest.raises(ValueError, match="3D bodies"):
        plot.deformed_body_png(tmp_path / "sq.png", *solved2d)


# --------------------------------------------------------------------------- hostile input (issue 35)
def test_the_file_says_whether_the_solve_converged(solved2d, tmp_path):
    """The solve's outcome is field data of the .vtu: a failed solve's last converged state is
    written and marked (meshio and VTK both read it)."""
    model, sol = solved2d
    ok = meshio.read(output.write_solution(tmp_path / "ok.vtu", model, sol)).field_data
    assert ok["solve_status"].tolist() == [0] and ok["converged"].tolist() == [1] and ok["t"].tolist() == [1.0]
    failed = sol._replace(status=jnp.asarray(int(jr.Status.INVERTED), jnp.int32), t=jnp.asarray(0.4))
    back = meshio.read(output.write_solution(tmp_path / "failed.vtu", model, failed))
    assert back.field_data["solve_status"].tolist() == [int(jr.Status.INVERTED)]
    assert back.field_data["converged"].tolist() == [0] and back.field_data["t"].tolist() == [0.4]
    np.testing.assert_allclose(back.point_data["displacement"][:, :2], np.asarray(model.particle_displacements(sol)))
    pv = pytest.importorskip("pyvista")
    assert pv.read(tmp_path / "failed.vtu").field_data["converged"].tolist() == [0]


def test_non_finite_fields_and_foreign_solutions_write_nothing(solved2d, solved3d, tmp_path):
    model, sol = solved2d
    broken = sol._replace(u=sol.u.at[3, 0].set(jnp.nan))
    with pytest.raises(ValueError, match=r"non-finite fields \(displacement: \d+ particles.*nothing written"):
        output.write_solution(tmp_path / "nan.vtu", model, broken)
    with pytest.raises(ValueError, match="does not belong to this model"):
        output.write_solution(tmp_path / "other.vtu", model, solved3d[1])
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), sol)
    with pytest.raises(ValueError, match="a batch of 2 solves"):
        output.write_solution(tmp_path / "batch.vtu", model, batch)
    assert not list(tmp_path.iterdir())


def test_a_bad_series_leaves_the_earlier_one_as_it_was(solved2d, solved3d, tmp_path):
    model, sol = solved2d
    index = output.write_series(tmp_path / "run.pvd", model, [model.initial(), sol, sol], [0, 1, 2])
    before = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert len(before) == 4
    for bad in ([sol, solved3d[1]], [sol, sol._replace(u=sol.u * jnp.nan)]):
        with pytest.raises(ValueError, match=r"solutions\[1\]"):
            output.write_series(index, model, bad, [0, 1])
        after = {p.relative_to(tmp_path): p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
        assert after == before                                 # index and frames untouched, no temporaries
    output.write_series(index, model, [sol], [7.0])              # a shorter series replaces it whole
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == ["frame_0000.vtu"]
    assert [t for t, _ in output.read_series(index)] == [7.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "run.pvd"]


@pytest.mark.parametrize("body, error", [
    ('<DataSet timestep="0" file="/etc/passwd"/>', "must be a path relative to the index's folder"),
    ('<DataSet timestep="0" file="../elsewhere/frame.vtu"/>', r"no absolute path, no '\.\.'"),
    ('<DataSet timestep="nan" file="run/frame_0000.vtu"/>', "frame 0 has no finite time"),
    ('<DataSet file="run/frame_0000.vtu"/>', "frame 0 has no finite time"),
])
def test_read_series_refuses_what_it_would_return_wrongly(body, error, tmp_path):
    index = tmp_path / "run.pvd"
    index.write_text(f'<VTKFile type="Collection"><Collection>{body}</Collection></VTKFile>')
    with pytest.raises(ValueError, match=error):
        output.read_series(index)


def test_read_series_names_a_garbage_index(tmp_path):
    garbage = tmp_path / "garbage.pvd"
    garbage.write_bytes(b"\x00\x01 not xml at all")
    with pytest.raises(ValueError, match="is not a ParaView collection: not XML"):
        output.read_series(garbage)
    other = tmp_path / "other.pvd"
    other.write_text('<VTKFile type="UnstructuredGrid"/>')
    with pytest.raises(ValueError, match=r"not a VTK collection file \(<VTKFile type='UnstructuredGrid'>\)"):
        output.read_series(other)
    with pytest.raises(ValueError, match="does not exist"):
        output.read_series(tmp_path / "missing.pvd")


def test_the_particle_plot_says_what_its_colours_mean():
    """``deformed_particles`` draws a colour bar of |u| (a figure without one left the colours
    unexplained), none with ``colorbar=False`` (axes that share one)."""
    X = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    u = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.2]])
    for colorbar, bars in ((True, ["|u| (model units)"]), (False, [])):
        fig, ax = plot.plt.subplots()
        plot.deformed_particles(ax, X, u, colorbar=colorbar)
        assert [a.get_ylabel() for a in fig.axes[1:]] == bars
        plot.plt.close(fig)

"""VTK export: write a solved model, parse the file back, compare with the model's own fields."""
import numpy as np
import jax.numpy as jnp
import pytest

from jaxrkpm import vtk
from tests.problems import block


@pytest.fixture(scope="module")
def solved():
    _, _, model = block(5, right="pad")
    sol = model.solve({"pad": jnp.array([0.1, 0.05])}, steps=2)
    return model, sol


def test_vtu_roundtrip_matches_model(solved, tmp_path):
    model, sol = solved
    path = vtk.write_solution(tmp_path / "s.vtu", model, sol)
    back = vtk.read_vtu(path)
    X = np.asarray(model.body.X)
    n = X.shape[0]
    assert back["points"].shape == (n, 3)
    np.testing.assert_allclose(back["points"][:, :2], X)
    np.testing.assert_array_equal(back["cell_types"], np.ones(n, dtype=int))
    u = np.asarray(model.particle_displacements(sol))
    np.testing.assert_allclose(back["displacement"][:, :2], u, rtol=1e-14, atol=1e-15)
    assert np.all(back["displacement"][:, 2] == 0)
    # the driven edge moved by the prescribed translation (exact by the BC transformation)
    pad = model.set_indices("pad")
    np.testing.assert_allclose(back["displacement"][pad, :2], np.tile([0.1, 0.05], (len(pad), 1)),
                               atol=1e-10)
    s = np.asarray(model.stress(sol, X, kind="cauchy"))
    s9 = back["stress_cauchy"].reshape(n, 3, 3)
    np.testing.assert_allclose(s9[:, :2, :2], s, rtol=1e-12, atol=1e-14)
    assert np.abs(s).max() > 1e-3  # a real, non-trivial stress field went through
    np.testing.assert_allclose(back["volume"].sum(), 1.0, rtol=1e-12)


def test_von_mises_of_uniaxial_and_pure_shear():
    s = np.zeros((2, 3, 3))
    s[0, 0, 0] = 2.0            # uniaxial: sigma_vm = |sigma|
    s[1, 0, 1] = s[1, 1, 0] = 1.0  # pure shear: sqrt(3) tau
    np.testing.assert_allclose(vtk.von_mises(s), [2.0, np.sqrt(3.0)])


def test_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match="must end with '.vtu'"):
        vtk.write_points_vtu(tmp_path / "a.vtk", np.zeros((2, 2)))
    with pytest.raises(ValueError, match="point data 'u'"):
        vtk.write_points_vtu(tmp_path / "a.vtu", np.zeros((2, 2)), {"u": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="points must be"):
        vtk.write_points_vtu(tmp_path / "a.vtu", np.zeros((2, 4)))

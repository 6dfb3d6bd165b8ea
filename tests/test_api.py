"""The public API is the API: nothing outside jaxrkpm/model.py touches a private member of
Model, and outcomes print as names."""
import ast
import json
import re
from pathlib import Path

import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.base.outcome import Outcome

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "jaxrkpm" / "model" / "model.py"
MAGIC = re.compile(r"^\s*(%%?[A-Za-z]|!)")


def private_members_of_model() -> set:
    """Private (single underscore) methods and attributes of class Model, from its source."""
    tree = ast.parse(MODEL.read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Model")
    names = set()
    for node in ast.walk(cls):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            names.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
            names.add(node.attr)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names.add(node.value)   # self.__dict__.setdefault("_cache", ...)
    return {n for n in names if n.startswith("_") and not n.startswith("__")}


def uses(source: str, private: set) -> list:
    """(line, name) of every attribute access ``x._name`` with a name in ``private``."""
    return [(n.lineno, n.attr) for n in ast.walk(ast.parse(source))
            if isinstance(n, ast.Attribute) and n.attr in private]


def sources():
    """Every Python source of the repository outside model.py, notebooks' code cells too."""
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if path == MODEL or rel.parts[0] in (".venv", "build", ".git") or "site-packages" in rel.parts:
            continue
        yield str(rel), path.read_text()
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        code = "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")
        code = "\n".join(l for l in code.splitlines() if not MAGIC.match(l))   # IPython magics
        yield str(path.relative_to(ROOT)), code


def test_the_checker_finds_private_uses():
    private = private_members_of_model()
    assert {"_problem"} <= private
    assert uses("model._problem.terms\ncfg = m.problem()", private) == [(1, "_problem")]
    assert uses("model.solver()\nx = y.public", private) == []


RETIRED = {"_config", "_jacobian_tables", "_sparse_solver",   # private once; public now or gone
           "_springs", "_terms", "_constraints", "_check_set", "_check_g", "_driver", "_kept_linear",
           "_ramped_from", "_point_tables", "_point_cache", "_check_penetration"}


def test_nothing_outside_model_uses_a_private_member_of_model():
    private = private_members_of_model() | RETIRED
    found = {name: hits for name, src in sources() if (hits := uses(src, private))}
    assert not found, f"private members of Model used outside model.py: {found}"


def test_outcomes_print_as_names_and_carry_messages():
    model = jr.Model(jr.Body.grid((3, 3), 0.5), jr.NeoHookean(1.0, 1.0), essential={"l": [0, 1, 2]})
    sol = model.solve()
    assert str(sol.outcome) == "CONVERGED" and f"{sol.outcome}" == "CONVERGED"
    from jaxrkpm.control.tracking import TrackStatus
    from jaxrkpm.solvers.linalg.base import Stability
    for kind in (jr.Status, TrackStatus, Stability):
        assert issubclass(kind, Outcome)
        for member in kind:
            assert str(member) == member.name and member.message and kind.of(int(member)) is member
    with pytest.raises(ValueError, match="one code"):
        jr.Status.of(np.zeros(3))
    # an arc-length path's status is its PathStatus (it was the bare code: printed 0)
    path = jr.arc_length(model, 0.05, steps=2, load_max=0.01, prescribed={"l": np.array([0.01, 0.0])})
    assert str(path.status) == path.status.name == "COMPLETED" and f"{path.status}" == "COMPLETED"


def test_bodies_and_models_print_as_a_summary():
    body = jr.Body.grid((40, 40), 1 / 39)
    model = jr.Model(body, jr.Fung(), essential={"wall": body.select(lambda X: X[:, 0] < 1e-9)})
    assert repr(body) == "Body(2D box, 1600 particles, spacing 0.02564, [0, 1] x [0, 1])"
    assert str(model) == ("Model(2D, 1600 particles, Fung, gauss, support 2.01, essential {'wall': 40}, "
                          f"{type(model.linear).__name__})")


def test_unknown_inertia_is_reported_as_unknown(monkeypatch):
    """A factorisation that cannot tell the inertia (PARDISO with perturbed pivots, SuperLU
    with pivoting) gives STABILITY_UNKNOWN, never CONVERGED on a claimed positive definite
    tangent; the equilibrium is still returned (no SolveError)."""
    from jaxrkpm.solvers.linalg import factorisations as sparse
    body = jr.Body.grid((4, 4), 1 / 3)
    sets = {"l": body.select(lambda X: X[:, 0] < 1e-9), "r": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(1.0, 1.0), essential=sets, solver="sparse", factorisation="superlu")
    monkeypatch.setattr(sparse.SuperLU, "factor", _unknown)
    sol = model.solve({"r": [-0.05, 0.0]})
    assert sol.outcome == jr.Status.STABILITY_UNKNOWN and sol.converged
    assert "could not tell" in sol.message
    state = model.linear.state_at(model.problem(), sol.u, sol.g)
    assert jr.Stability.of(model.linear.stability(state)) == jr.Stability.UNKNOWN
    # with the check off there is nothing to report
    assert model.solve({"r": [-0.05, 0.0]}, check_stability=False).outcome == jr.Status.CONVERGED


def _unknown(self, data):
    """SuperLU.factor that factorises but reports the inertia as unknown."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla
    A = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
    self.lu = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))
    return None


class FakeDevice:
    def __init__(self, platform, bytes_limit=None):
        self.platform, self.bytes_limit = platform, bytes_limit

    def memory_stats(self):
        return None if self.bytes_limit is None else {"bytes_limit": self.bytes_limit}


def test_auto_goes_dense_on_an_accelerator_while_the_matrices_fit():
    """solver="auto": the measured CPU crossover on a CPU; on a GPU, dense (no host callback)
    up to ``dense_copies`` n^2 doubles of device memory."""
    choice = jr.internal.SolverChoice()
    assert choice.dense_limit(3, FakeDevice("cpu")) == choice.dense_3d
    assert choice.dense_limit(2, FakeDevice("cpu")) == choice.dense_2d
    n = choice.dense_limit(3, FakeDevice("gpu", 80 * 2**30))
    assert 8 * choice.dense_copies * n**2 <= 80 * 2**30 < 8 * choice.dense_copies * (n + 1) ** 2
    assert n > 21_600                                   # the 20^3 cube is dense on an 80 GB GPU
    assert choice.dense_limit(3, FakeDevice("gpu")) >= 20_000    # memory not reported
    assert choice.dense_limit(3, FakeDevice("gpu", 2**20)) == choice.dense_3d   # never below the CPU's
    assert choice.dense_limit(3) == choice.dense_3d                # this test machine: a CPU


def test_precision_is_chosen_by_size_and_mixed_solves_equal_double():
    """Model(precision=...): "auto" factorises in mixed precision from ``mixed_min`` free DOFs;
    a mixed-precision solve and Jacobian equal the double ones to the solver's tolerance;
    an unknown precision is refused with the choices."""
    import jax.numpy as jnp

    body = jr.Body.grid((5, 5), 0.25)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "push": body.select(lambda X: X[:, 0] > 1 - 1e-9)}

    def make(precision, **kw):
        return jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, precision=precision, **kw)

    assert not make("auto").linear.mixed and make("mixed").linear.mixed and not make("double").linear.mixed
    assert make("auto", choice=jr.internal.SolverChoice(mixed_min=10)).linear.mixed
    with pytest.raises(ValueError, match="unknown precision 'half'.*'mixed'"):
        make("half")
    g = jnp.array([-0.2, 0.05])
    solved = {p: (m, m.solve({"push": g}, steps=2)) for p, m in (("double", make("double")), ("mixed", make("mixed")))}
    (md, sd), (mm, sm) = solved["double"], solved["mixed"]
    assert sm.outcome.name == "CONVERGED" and sm.iterations == sd.iterations
    assert np.abs(np.asarray(sm.u - sd.u)).max() < 1e-10 * np.abs(np.asarray(sd.u)).max()
    centre = np.array([[0.5, 0.5]])
    Jd, Jm = np.asarray(md.jacobian(sd, "push", centre)), np.asarray(mm.jacobian(sm, "push", centre))
    assert np.abs(Jm - Jd).max() < 1e-9 * np.abs(Jd).max()

"""The term protocol: the example of a new term in jaxrkpm.mechanics.term's docstring works as
written. Added with ``Model(terms=...)``, it is the built-in springs it imitates, its parameter
is overridden by its name, a term that forgets its tangent is refused, and models whose terms
differ are not batched. (A solve's derivative in a new term's parameter: the pressure's,
tests/mechanics/test_pressure.py.)"""
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.mechanics import term as term_module
from tests.problems import unit_grid

POINTS = np.array([[1.0, 0.5], [0.5, 1.0]])
MATERIAL = jr.NeoHookean(1.0, 1.0)


def docstring_example() -> dict:
    """The namespace the docstring's example code defines (executed as written)."""
    doc = term_module.__doc__
    lines = doc[doc.index("Writing a new term"):].split("::\n", 1)[1].splitlines()
    code = []
    for line in lines:
        if line.strip() and not line.startswith("    "):
            break
        code.append(line)
    namespace = {}
    exec(textwrap.dedent("\n".join(code)), namespace)
    return namespace


@pytest.fixture(scope="module")
def models():
    ex = docstring_example()
    body = unit_grid(5)
    common = dict(essential={"wall": body.select(lambda X: X[:, 0] < 1e-9)}, body_force=[0.0, -0.1])
    springs = jr.Model(body, MATERIAL, springs=jr.Springs(POINTS, 3.0), **common)
    tether = jr.Model(body, MATERIAL, terms=[ex["TetherSpec"](POINTS, 3.0)], **common)
    return springs, tether


residual = jax.jit(lambda prob, u, g: prob.residual(u, g))
tangent = jax.jit(lambda prob, u, g: prob.tangent(u, g))


def test_the_docstring_term_is_the_springs_it_imitates(models):
    """Its residual and tangent (through the essential constraint) are the built-in springs'
    at a deformed state, so it solves like them: the solver sees nothing else. Its parameter
    is overridden by its name, checked by the protocol's default ``check_params``."""
    springs, tether = models
    a, b = springs.problem(), tether.problem()
    a, b = a.replace(terms=(a.term("springs"),)), b.replace(terms=(b.term("tether"),))
    rng = np.random.default_rng(5)
    u = jnp.asarray(0.05 * rng.standard_normal((a.n_free, 2)))
    g = jnp.asarray(0.05 * rng.standard_normal((len(springs.sets.bnd), 2)))
    ra, rb = np.asarray(residual(a, u, g)), np.asarray(residual(b, u, g))
    Ka, Kb = np.asarray(tangent(a, u, g)), np.asarray(tangent(b, u, g))
    print("residual", np.abs(ra - rb).max() / np.abs(ra).max(), "tangent", np.abs(Ka - Kb).max() / np.abs(Ka).max())
    assert np.abs(ra).max() > 0 and np.abs(Ka).max() > 0
    assert np.abs(ra - rb).max() < 1e-12 * np.abs(ra).max()
    assert np.abs(Ka - Kb).max() < 1e-12 * np.abs(Ka).max()
    soft = tether.problem({"tether": {"k": 0.3}})
    assert float(soft.term("tether").k) == 0.3
    with pytest.raises(ValueError, match=r"params\['tether'\] must be a dict of 'k' \(shape \(\)\)"):
        tether.problem({"tether": 0.3})


def test_models_with_different_terms_are_not_batched(models):
    with pytest.raises(ValueError, match="same terms"):
        jr.internal.stack_models(list(models))


def test_a_term_that_forgets_its_tangent_is_refused():
    """A term with a nonlinear energy and no tangent blocks would leave K_ff short (slower
    Newton, wrong implicit derivatives): the model refuses it."""
    ex = docstring_example()

    @term_module.term
    class Careless(ex["Tether"]):
        def lists(self):
            return None

    class CarelessSpec(ex["TetherSpec"]):
        def build(self, ctx):
            t = super().build(ctx)
            return Careless(t.idx, t.psi, t.k, name=self.name)

    body = unit_grid(3)
    with pytest.raises(TypeError, match="'tether' has no tangent blocks"):
        jr.Model(body, MATERIAL, essential={"wall": [0, 1, 2]}, terms=[CarelessSpec(POINTS)])

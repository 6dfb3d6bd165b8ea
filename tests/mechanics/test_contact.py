"""Contact with rigid tools (jaxrkpm.mechanics.contact): the barrier keeps the body out of the
tool, a flat plate gives a uniform state, and the solution is differentiable in the tool's
pose (implicit Jacobian against central differences), frictionless and frictional."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.mechanics.contact import barrier, near_seam, rotation

GAP = 1e-3
MAT = jr.NeoHookean(lam=1.0, mu=1.0)


def test_barrier_is_c2_at_its_range_and_finite_below_the_floor():
    kappa, ghat, floor = 2.0, 1e-3, 0.1
    db = jax.jit(jax.grad(barrier))
    d2b = jax.jit(jax.grad(jax.grad(barrier)))
    for f in (barrier, db, d2b):    # b, b', b'' vanish at ghat (C2)
        assert abs(float(f(ghat * (1 - 1e-9), kappa, ghat, floor))) < 1e-6 * kappa
        assert float(f(ghat * 1.5, kappa, ghat, floor)) == 0.0
    g = jnp.linspace(-ghat, ghat, 101)
    b = jax.jit(jax.vmap(barrier, (0, None, None, None)))(g, kappa, ghat, floor)
    p = -jax.jit(jax.vmap(db, (0, None, None, None)))(g, kappa, ghat, floor)
    assert np.all(np.isfinite(np.asarray(b))) and np.all(np.diff(np.asarray(p)) <= 0)   # p falls with g
    # the spec's p0: the pressure at half the gap
    spec = jr.Contact(jr.Sphere(1.0), position=(0.0, 0.0), gap=ghat, pressure=3.0)
    k = spec.pressure / (ghat * (np.log(2) + 0.5))
    assert float(-db(ghat / 2, k, ghat, floor)) == pytest.approx(3.0, rel=1e-12)


def test_seams_of_the_tools_are_found():
    """Where a box's flat face meets its rounded edge, or a capsule's side its end, the
    curvature jumps (the implicit Jacobian is one-sided there): found within the distance
    asked, and nowhere on a face, a sphere or a plane."""
    box, cap = jr.Box((0.5, 0.1), 0.2), jr.Capsule(0.4, 0.1)
    seam = jax.jit(near_seam, static_argnums=0)
    for shape, y, near in ((box, [0.5, 0.35], True), (box, [0.5 + 2e-3, 0.35], False),
                           (box, [0.2, 0.35], False), (box, [0.6, 0.4], False),
                           (jr.Sphere(1.0), [0.3, 1.2], False), (jr.HalfSpace((0.0, 1.0)), [0.3, 0.1], False)):
        assert bool(seam(shape, jnp.asarray(y), 1e-3)) == near, (shape, y)
    for x in (0.4, -0.4):     # the capsule's segment ends at x = +-0.4 along its first axis
        assert bool(seam(cap, jnp.asarray([x, 0.15]), 1e-3))
    assert not bool(seam(cap, jnp.asarray([0.0, 0.15]), 1e-3))


def test_rotation_is_smooth_at_the_identity():
    J = jax.jacfwd(lambda w: rotation(w, 3))(jnp.zeros(3))
    W = np.zeros((3, 3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = 1
        W[:, :, a] = np.cross(e, np.eye(3)).T     # d R / d w_a = [e_a]x
    assert np.allclose(np.asarray(J), W, atol=1e-14)
    R = rotation(jnp.array([0.3, -0.2, 0.5]), 3)
    assert np.allclose(np.asarray(R @ R.T), np.eye(3), atol=1e-14)


# ---------------------------------------------------------------------- patch test
@pytest.fixture(scope="module")
def pressed_block():
    """A 1 x 1 block (SCNI) pressed over its whole top by a rigid frictionless plate, its
    bottom on rollers (a second frictionless plate: it lets the bottom slide freely); both
    plates move in by ``d`` so that the centre particle, held against rigid motion, carries no
    load by symmetry."""
    n = 5
    body = jr.Body.grid((n, n), 1.0 / (n - 1), origin=(-0.5, -0.5))
    centre = body.select(lambda X: np.hypot(*X.T) < 1e-9)
    top = jr.Contact(jr.HalfSpace((0.0, -1.0)), position=(0.0, 0.5 + GAP), gap=GAP, pressure=0.3, name="top",
                     where=lambda X: X[:, 1] > 0.5 - 1e-9)
    bot = jr.Contact(jr.HalfSpace((0.0, 1.0)), position=(0.0, -0.5 - GAP), gap=GAP, pressure=0.3, name="bot",
                     where=lambda X: X[:, 1] < -0.5 + 1e-9)
    model = jr.Model(body, MAT, integration="scni", essential={"c": centre}, terms=[top, bot])
    d = 0.05
    params = {"top": {"position": jnp.array([0.0, 0.5 + GAP - d])},
              "bot": {"position": jnp.array([0.0, -0.5 - GAP + d])}}
    return model, model.solve(params=params, steps=4), params


def test_contact_patch(pressed_block):
    model, sol, params = pressed_block
    body = model.body
    res = jr.contact_forces(model, sol, "top", params)
    bot = jr.contact_forces(model, sol, "bot", params)
    S = np.asarray(model.stress(sol, 0.9 * body.X))
    syy = S[:, 1, 1]
    spread = np.ptp(syy) / abs(syy.mean())
    p = np.asarray(res.pressure)
    print(f"contact patch: sigma_yy {syy.mean():.6f}, spread {spread:.2e}; pressure {p.min():.6f} .. "
          f"{p.max():.6f}; gaps {float(res.min_gap):.3e} .. {float(np.max(res.gap)):.3e} (ghat {GAP}); "
          f"|sigma_xx|, |sigma_xy| <= {np.abs(S[:, 0, 0]).max():.2e}, {np.abs(S[:, 0, 1]).max():.2e}")
    # no interpenetration, within the barrier's range, all points touch
    assert 0 < float(res.min_gap) and float(np.max(res.gap)) < GAP and bool(np.all(res.active))
    # the plates' forces balance, are normal and compressive
    assert float(res.force[1]) < 0 and np.allclose(np.asarray(res.force), -np.asarray(bot.force), rtol=1e-8)
    assert abs(float(res.tangential[0])) < 1e-10 * abs(float(res.force[1]))
    assert np.allclose(np.asarray(model.reaction(sol, "c")), 0.0, atol=1e-9 * abs(float(res.force[1])))
    # the resultant is the stress times the face (deformed width x sigma_yy, 2D)
    width = 1.0 + float(np.ptp(np.asarray(model.displacement(sol, np.array([[-0.5, 0.5], [0.5, 0.5]]))[:, 0])))
    assert float(res.force[1]) == pytest.approx(syy.mean() * width, rel=1e-6)
    # uniform: the contact points are SCNI's boundary quadrature points, so that the uniform
    # pressure balances a uniform stress exactly (lumped nodal weights do not)
    assert spread < 1e-6 and np.abs(S[:, 0, :]).max() < 1e-6 * abs(syy.mean())
    assert np.ptp(p) / p.mean() < 1e-6


def test_contact_in_the_vtu_and_the_figure(pressed_block, tmp_path):
    import meshio

    from jaxrkpm.io import output, plot
    model, sol, params = pressed_block
    res = jr.contact_forces(model, sol, "top", params)
    back = meshio.read(output.write_solution(tmp_path / "pressed.vtu", model, sol, params=params))
    top = model.body.X[:, 1] > 0.5 - 1e-9
    force = back.point_data["contact_top_force"]
    # the particles' shares add up to the tool's force; the top row carries it all, uniformly
    assert np.allclose(force.sum(0)[:2], np.asarray(res.force), rtol=1e-12)
    assert np.all(force[~top] == 0) and np.all(back.point_data["contact_top_active"][top] == 1)
    assert np.allclose(back.point_data["contact_top_pressure"][top], np.asarray(res.pressure)[0], rtol=1e-9)
    gap = back.point_data["contact_top_gap"]
    assert np.all(gap[top] > 0) and np.all(gap[top] < GAP) and np.all(gap[~top] > 0.2)
    f = back.field_data
    assert np.allclose(f["contact_top_resultant"][:2], np.asarray(res.force)) and f["contact_top_active"][0] == len(res.gap)
    assert f["contact_top_min_gap"][0] == pytest.approx(float(res.min_gap))
    assert abs(f["contact_top_tangential"]).max() < 1e-10 * abs(f["contact_top_normal"]).max()
    fig, ax = plot.plt.subplots()
    plot.deformed_particles(ax, model.body.X, model.particle_displacements(sol), colorbar=False)
    sc = jr.contact_pressures(ax, model, sol, params)
    assert [a.get_ylabel() for a in fig.axes[1:]] == ["contact pressure"]          # its colour bar
    assert sc.get_offsets().shape == (len(res.gap), 2) and np.allclose(sc.get_array(), np.asarray(res.pressure))
    plot.save(fig, tmp_path / "pressed.png")
    assert (tmp_path / "pressed.png").stat().st_size > 10_000


# -------------------------------------------------------------------- derivatives
def _fd_vs_implicit(model, sol, params, name, keys, points, eps, fd=True):
    """(implicit Jacobian d u(points) / d (params[name][keys]), central differences (None
    without ``fd``))."""
    base = {k: jnp.asarray(v) for k, v in params[name].items()}
    flat0 = jnp.concatenate([jnp.atleast_1d(base[k]) for k in keys])
    sizes = [jnp.atleast_1d(base[k]).size for k in keys]

    def unflat(x):
        out, i = dict(base), 0
        for k, s in zip(keys, sizes):
            out[k] = x[i:i + s].reshape(jnp.shape(base[k]))
            i += s
        return out

    def u(x, initial=None):
        p = {**params, name: unflat(x)}
        s = model.solve(params=p, steps=4, rtol=1e-12) if initial is None else \
            model.solve(params=p, initial=initial, rtol=1e-12)
        return model.displacement(s, points).ravel()

    J = jax.jacfwd(lambda x: u(x, sol))(flat0)
    if not fd:
        return np.asarray(J), None
    cols = []
    for i in range(flat0.size):
        e = jnp.zeros_like(flat0).at[i].set(eps)
        cols.append((u(flat0 + e, sol) - u(flat0 - e, sol)) / (2 * eps))
    return np.asarray(J), np.asarray(jnp.stack(cols, 1))


@pytest.fixture(scope="module")
def paddle_2d():
    """A 1 x 1 block held at its bottom, pressed by a tilted box paddle with rounded edges."""
    body = jr.Body.grid((5, 5), 0.25, origin=(-0.5, -0.5))
    paddle = jr.Contact(jr.Box((0.2, 0.05), 0.15), position=(0.1, 0.75), rotation=0.1,
                        gap=GAP, pressure=0.1, name="paddle", where=lambda X: X[:, 1] > 0.5 - 1e-9)
    model = jr.Model(body, MAT, essential={"bottom": body.select(lambda X: X[:, 1] < -0.5 + 1e-9)},
                     terms=[paddle])
    start = model.params["paddle"]
    # every friction parameter given (frictionless: mu = 0), so that the frictional solves
    # and their Jacobians below reuse these compiled programs
    params = {"paddle": {**start, "position": start["position"] + jnp.array([0.0, -0.06]),
                         "rotation": jnp.asarray(0.12)}}
    return model, model.solve(params=params, steps=4, rtol=1e-12), params


def test_pose_jacobian_2d_frictionless(paddle_2d):
    model, sol, params = paddle_2d
    res = jr.contact_forces(model, sol, "paddle", params)
    assert int(np.sum(res.active)) >= 1 and float(res.min_gap) > 0
    J, fd = _fd_vs_implicit(model, sol, params, "paddle", ("position", "rotation"),
                            np.array([[0.1, 0.5], [0.0, 0.0]]), 1e-5)
    err = np.abs(J - fd).max() / np.abs(J).max()
    print(f"2D pose Jacobian, frictionless: |J| {np.abs(J).max():.3e}, rel. difference to central FD {err:.2e}")
    assert np.abs(J).max() > 0.1 and err < 1e-6


def test_pose_jacobian_2d_frictional(paddle_2d):
    model, sol, params = paddle_2d
    lag = jr.contact_forces(model, sol, "paddle", params).lag
    p = {"paddle": {**params["paddle"], "mu": jnp.asarray(0.3), **lag}}
    fr = model.solve(params=p, initial=sol, rtol=1e-12)
    res = jr.contact_forces(model, fr, "paddle", p)
    # the lag's anchors are the state itself: no slip, no friction until the tool moves
    assert np.abs(np.asarray(res.tangential)).max() < 1e-8 * np.abs(np.asarray(res.normal)).max()
    J, fd = _fd_vs_implicit(model, fr, p, "paddle", ("position", "rotation"), np.array([[0.1, 0.5], [0.0, 0.0]]),
                            1e-5)
    err = np.abs(J - fd).max() / np.abs(J).max()
    print(f"2D pose Jacobian, mu = 0.3 (lagged): rel. difference to central FD {err:.2e}")
    assert err < 1e-6
    # friction stiffens the tangential response to the paddle's sideways motion
    J0, _ = _fd_vs_implicit(model, sol, params, "paddle", ("position", "rotation"),
                            np.array([[0.1, 0.5], [0.0, 0.0]]), 1e-5, fd=False)
    assert abs(J[0, 0]) > abs(J0[0, 0])


@pytest.fixture(scope="module")
def ball_3d():
    """A 2 x 2 x 2 cube held at its bottom, pressed off-centre by a sphere."""
    body = jr.Body.grid((3, 3, 3), 0.5, origin=(-0.5, -0.5, -0.5))
    ball = jr.Contact(jr.Sphere(0.4), position=(0.05, 0.0, 0.5 + 0.4 + 2 * GAP), gap=GAP, pressure=0.1,
                      name="ball", where=lambda X: X[:, 2] > 0.5 - 1e-9)
    model = jr.Model(body, MAT, essential={"bottom": body.select(lambda X: X[:, 2] < -0.5 + 1e-9)},
                     terms=[ball])
    # every friction parameter given (frictionless: mu = 0): the frictional solve below
    # reuses the compiled programs
    params = {"ball": {**model.params["ball"],
                       "position": model.params["ball"]["position"] + jnp.array([0.0, 0.0, -0.05])}}
    return model, model.solve(params=params, steps=4, rtol=1e-12), params


def test_3d_figures_show_the_contact_and_say_what_the_colours_mean(ball_3d):
    """On 3D axes the contact points are drawn inside the view, over the body, with colour
    bars for the pressure and (deformed_surface) the stress."""
    from jaxrkpm.io import plot
    model, sol, params = ball_3d
    fig = plot.plt.figure()
    ax = fig.add_subplot(projection="3d")
    jr.deformed_surface(ax, model, sol)
    sc = jr.contact_pressures(ax, model, sol, params)
    res = jr.contact_forces(model, sol, "ball", params)
    pts = np.asarray(res.points)[np.asarray(res.active)]
    assert len(pts) > 0 and np.asarray(sc.get_array()).shape == (len(pts),)
    for lim, c in zip((ax.get_xlim(), ax.get_ylim(), ax.get_zlim()), pts.T):
        assert lim[0] < c.min() and c.max() < lim[1]
    assert [a.get_ylabel() for a in fig.axes[1:]] == ["von Mises (Cauchy) stress", "contact pressure"]
    plot.plt.close(fig)


def test_pose_jacobian_3d(ball_3d):
    model, sol, params = ball_3d
    J, fd = _fd_vs_implicit(model, sol, params, "ball", ("position",), np.array([[0.0, 0.0, 0.5]]), 1e-5)
    err = np.abs(J - fd).max() / np.abs(J).max()
    print(f"3D pose Jacobian (sphere): rel. difference to central FD {err:.2e}")
    assert np.abs(J).max() > 0.1 and err < 1e-6


def test_pose_jacobian_3d_frictional(ball_3d):
    """mu = 0.3, one lagged step from the frictionless state: the tool then moves sideways,
    the Jacobian of the lagged solve against central differences."""
    model, sol, params = ball_3d
    lag = jr.contact_forces(model, sol, "ball", params).lag
    p = {"ball": {**params["ball"], "mu": jnp.asarray(0.3), **lag,
                  "position": params["ball"]["position"] + jnp.array([0.02, 0.0, 0.0])}}
    fr = model.solve(params=p, initial=sol, rtol=1e-12)
    res = jr.contact_forces(model, fr, "ball", p)
    assert np.abs(np.asarray(res.tangential)).max() > 1e-3 * np.abs(np.asarray(res.normal)).max()  # friction acts
    J, fd = _fd_vs_implicit(model, fr, p, "ball", ("position",), np.array([[0.0, 0.0, 0.5]]), 1e-5)
    err = np.abs(J - fd).max() / np.abs(J).max()
    print(f"3D pose Jacobian, mu = 0.3 (lagged): rel. difference to central FD {err:.2e}")
    assert np.abs(J).max() > 0.1 and err < 1e-6


def test_bad_input_is_named():
    body = jr.Body.grid((3, 3), 0.5)
    with pytest.raises(ValueError, match="overlaps"):
        jr.Model(body, MAT, essential={"b": [0]}, terms=[jr.Contact(jr.Sphere(0.3), position=(0.5, 1.0))])
    with pytest.raises(ValueError, match="shape"):
        jr.Contact(object(), position=(0, 0))
    with pytest.raises(ValueError, match="gap"):
        jr.Contact(jr.Sphere(0.3), position=(0, 2), gap=0.0)


@pytest.mark.parametrize("make, match", [
    (lambda: jr.Sphere(-0.5), r"Sphere.radius must be a finite number > 0, got -0.5"),
    (lambda: jr.Sphere(float("nan")), r"Sphere.radius must be a finite number > 0, got nan"),
    (lambda: jr.Box((0.2, -0.05)), r"Box.half must be finite half extents >= 0"),
    (lambda: jr.Box((0.2, 0.0)), r"a half extent of 0 needs radius > 0"),
    (lambda: jr.Box((0.2, 0.1), -0.1), r"Box.radius must be a finite number >= 0"),
    (lambda: jr.Capsule(-0.1, 0.2), r"Capsule.half_length must be a finite number >= 0"),
    (lambda: jr.Capsule(0.1, 0.0), r"Capsule.radius must be a finite number > 0"),
    (lambda: jr.HalfSpace((0.0, 0.0)), r"HalfSpace.normal must be a finite, non-zero vector"),
    (lambda: jr.HalfSpace((float("nan"), 1.0)), r"HalfSpace.normal must be a finite, non-zero vector"),
])
def test_tools_of_no_size_are_refused_when_built(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_a_nan_rotation_or_a_float_predicate_is_named():
    body = jr.Body.grid((3, 3), 0.5)
    with pytest.raises(ValueError, match="contact 'disc': rotation must be a finite angle"):
        jr.Model(body, MAT, essential={"b": [0]},
                 terms=[jr.Contact(jr.Sphere(0.3), position=(0.5, 1.5), rotation=float("nan"), name="disc")])
    with pytest.raises(ValueError, match="contact 'disc': where must return booleans, got float64"):
        jr.Model(body, MAT, essential={"b": [0]},
                 terms=[jr.Contact(jr.Sphere(0.3), position=(0.5, 1.5), where=lambda X: X[:, 1] * 1.0, name="disc")])
    with pytest.raises(ValueError, match="pressure 'p': where must return booleans, got float64"):
        jr.Model(body, MAT, essential={"b": [0]}, terms=[jr.Pressure(lambda X: X[:, 1] - 0.5, name="p")])


def test_a_converged_solve_inside_the_tool_says_so():
    """A barrier far too soft for the load lets the points pass into the tool: the solve
    converges, and warns, naming the tool and the gap; a solve that stays clear says nothing."""
    import warnings
    gap = 1e-2
    body = jr.Body.grid((3, 3), 0.5, origin=(-0.5, -0.5))
    plate = jr.Contact(jr.HalfSpace((0.0, -1.0)), position=(0.0, 0.5 + gap), gap=gap, pressure=1e-6, name="plate",
                       where=lambda X: X[:, 1] > 0.5 - 1e-9)
    model = jr.Model(body, jr.NeoHookean(lam=1e3, mu=1e3), essential={"w": body.select(lambda X: X[:, 1] < -0.4)},
                     terms=[plate])
    with pytest.warns(jr.ContactPenetrationWarning, match=r"contact 'plate' inside the tool \(min gap -0.0\d+ < 0\)"):
        sol = model.solve(params={"plate": {"position": jnp.array([0.0, 0.5 + gap - 0.1])}})
    assert jr.Status.of(sol.status) == jr.Status.CONVERGED
    with warnings.catch_warnings():
        warnings.simplefilter("error", jr.ContactPenetrationWarning)
        model.solve(params={"plate": {"position": jnp.array([0.0, 0.5 + gap])}})


# ------------------------------------------------------------- friction vs glued
@pytest.fixture(scope="module")
def clamped_block():
    """A 1 x 1 block, bottom clamped, its top pressed down by ``D``: by a rigid plate
    (frictionless, and with mu = 0.3 as one lagged step from load 0: the anchors at the start,
    the normal pressure lagged and iterated twice) and by a glued plate (the top held by an
    essential set)."""
    body = jr.Body.grid((5, 5), 0.25)
    bottom = body.select(lambda X: X[:, 1] < 1e-9)
    plate = jr.Contact(jr.HalfSpace((0.0, -1.0)), position=(0.0, 1.0 + GAP), gap=GAP, pressure=0.3, name="plate",
                       where=lambda X: X[:, 1] > 1 - 1e-9, slip=2e-3)
    contact = jr.Model(body, MAT, integration="scni", essential={"bottom": bottom}, terms=[plate])
    glued = jr.Model(body, MAT, integration="scni",
                     essential={"bottom": bottom, "top": body.select(lambda X: X[:, 1] > 1 - 1e-9)})
    return body, contact, glued


D = 0.05
CORNER = np.array([[1.0, 1.0]])


@pytest.mark.parametrize("lam", [0.0, 1.0])
def test_friction_against_a_glued_plate(clamped_block, lam):
    body, contact, glued = clamped_block
    anchors = contact.params["plate"]["anchor"]          # the start of the step: no slip yet
    # frictionless: mu = 0 (every friction parameter given: one compiled solve for all)
    pose = {"position": jnp.array([0.0, 1.0 + GAP - D]), "mu": jnp.asarray(0.0),
            "pressure": jnp.zeros(len(anchors)), "anchor": anchors}
    free = contact.solve(params={"plate": pose, "lam": lam}, steps=4, max_iter=60)
    res = jr.contact_forces(contact, free, "plate", {"plate": pose})
    sol, pressure = free, res.pressure
    for _ in range(2):                                   # the lagged normal pressure, iterated
        p = {"plate": {**pose, "mu": jnp.asarray(0.3), "pressure": pressure, "anchor": anchors}, "lam": lam}
        sol = contact.solve(params=p, steps=4, max_iter=60)   # one lagged step: from load 0
        fr = jr.contact_forces(contact, sol, "plate", p)
        pressure = fr.pressure
    # the glued plate at the same top displacement
    top = float(np.mean(np.asarray(contact.displacement(sol, body.X[body.X[:, 1] > 1 - 1e-9])[:, 1])))
    gl = glued.solve({"top": (0.0, top)}, params={"lam": lam}, steps=2)
    ux = [abs(float(m.displacement(s, CORNER)[0, 0])) for m, s in ((contact, free), (contact, sol), (glued, gl))]
    fy = [float(res.force[1]), float(fr.force[1]), float(glued.reaction(gl, "top", params={"lam": lam})[1])]   # on the body
    ratio = float(np.max(np.abs(np.asarray(fr.tangential)))) / abs(float(fr.force[1]))
    print(f"lam {lam}: top corner |u_x| frictionless {ux[0]:.3e}, mu 0.3 {ux[1]:.3e}, glued {ux[2]:.3e}; "
          f"force {fy[0]:.6f} / {fy[1]:.6f} / {fy[2]:.6f}; friction / normal {ratio:.3f}")
    # every point within the friction cone (the regularised law's force is at most mu p)
    f = np.asarray(fr.point_force)
    n = np.asarray(fr.normals)
    fn = np.sum(f * n, 1)
    ft = np.linalg.norm(f - fn[:, None] * n, axis=1)
    assert np.all(fn >= 0) and np.all(ft <= 0.3 * np.asarray(fr.pressure) * np.asarray(
        contact.problem(p).term("plate").w) * (1 + 1e-9) + 1e-15)
    if lam == 0.0:   # no lateral tendency: friction changes nothing, nothing slides
        assert max(ux) < 1e-4 * D and ux[2] < 1e-8
        assert fy[1] == pytest.approx(fy[0], rel=1e-6) and fy[1] == pytest.approx(fy[2], rel=1e-2)
    else:            # the top wants to spread: friction holds it partly, the glue wholly
        assert ux[0] > 2 * ux[1] and ux[1] > 10 * ux[2] and ux[2] < 1e-8
        assert abs(fy[1] - fy[2]) > 1e-3 * abs(fy[2]) and abs(fy[1] - fy[0]) > 1e-3 * abs(fy[0])


# ------------------------------------------------------------- frictional restarts
def test_frictional_slides_restart_from_the_previous_solution():
    """A block pressed by a frictional plate (mu = 0.3) over its whole top (contact width 1),
    then slid along it in steps of 0.1% to 10% of that width, each solve started from the
    previous Solution with the lag of that state, at the default settings: the pose change is
    ramped along the solve's path (so step cutting shrinks it) and predicted from the
    converged state's tangent. The friction builds up to mu times the normal force."""
    body = jr.Body.grid((5, 5), 0.25)
    plate = jr.Contact(jr.HalfSpace((0.0, -1.0)), position=(0.0, 1.0 + GAP), gap=GAP, pressure=0.3, name="plate",
                       where=lambda X: X[:, 1] > 1 - 1e-9)
    model = jr.Model(body, MAT, integration="scni", essential={"bottom": body.select(lambda X: X[:, 1] < 1e-9)},
                     terms=[plate])
    pose = {**model.params["plate"], "position": jnp.array([0.0, 1.0 + GAP - 0.05]), "mu": jnp.asarray(0.3)}
    sol = model.solve(params={"plate": pose}, steps=4)
    x, ratios, iterations = 0.0, [], []
    for slide in (0.001, 0.003, 0.01, 0.03, 0.1):
        lag = jr.contact_forces(model, sol, "plate", {"plate": pose}).lag
        x += slide
        pose = {**pose, **lag, "position": jnp.array([x, 1.0 + GAP - 0.05])}
        sol = model.solve(params={"plate": pose}, initial=sol)     # raises if it does not converge
        res = jr.contact_forces(model, sol, "plate", {"plate": pose})
        ratios.append(-float(res.force[0]) / (0.3 * float(res.force[1])))
        iterations.append(int(sol.iterations))
    print("slides 0.001 .. 0.1: F_t / (mu F_n)", np.round(ratios, 4), "Newton iterations", iterations)
    assert all(0 < a < b for a, b in zip(ratios, ratios[1:]))
    assert ratios[-1] == pytest.approx(1.0, abs=0.01)

"""The 3D needle-insertion phantom (chapter 6 lifted to 3D; jaxrkpm.thesis.phantom3d.Phantom3D).

A half-ellipsoid on a fixed chest-wall base, a horizontal needle entering from x < 0 along
+x towards an interior target at 40% of its chord; the target's lateral (y, z) deviation is
what a paddle holding a patch of the skin must prevent.

``--mode static``: every candidate paddle patch (an angle grid over the accessible skin,
20 by default) x every insertion increment in one batched, compiled call, plus the
no-paddle run; the final lateral deviation per patch, the best patch and its reduction
against no paddle; the controllability delta x_min per patch (the largest paddle travel
per unit lateral correction, 1/sigma_min of the lateral rows of J^-1) as a map over the skin.

``--mode dynamic``: the closed loop moving the most controllable patch during insertion so
the target stays on the needle line (|lateral deviation| below ``--tol`` at every
increment; the summary also states it against 1e-4 of the object size).

``--mode optimize``: the best discrete patch's contact points as stiff springs, slid over
the skin by two surface coordinates (theta, phi) and optimised with Adam (optax) through
the differentiable solve from that patch's centre (where the spring paddle is the held
patch again), against that patch.

Writes summary.json, PNG figures and a .vtu of the final state to --out.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import Command, lazy
from jaxrkpm.thesis.studies.needle import (contact_legend, contact_options, contact_params, contact_result,
                                           contact_state, deviation_panel, glued_curves, needle_options,
                                           optimize_result, paddle_pose, tool_outline)

nd = lazy("jaxrkpm.thesis.needle")
output = lazy("jaxrkpm.io.output")
plot = lazy("jaxrkpm.io.plot")
phantom3d = lazy("jaxrkpm.thesis.phantom3d")
contact = lazy("jaxrkpm.mechanics.contact")

INCREMENTS_3D_MAX = 100         # insertion increments (each a 3D solve of every patch)


def object_size(phantom: phantom3d.Phantom3D) -> float:
    """The phantom's largest extent (its long axis, 2a): the scale of the hold bound."""
    return float(2 * max(phantom.semi_axes[:2]))


def draw_deformed(ax, phantom: phantom3d.Phantom3D, model, sol, title: str, vmax=None, patch=None):
    """Deformed particles, the x-z view (the needle runs along x, the base is z = 0), with the
    needle particles, the patch and the target marked."""
    X = model.body.X
    u = np.asarray(model.particle_displacements(sol))
    sc = plot.deformed_particles(ax, X, u, vmax=vmax, size=10, colorbar=False)
    x = X + u
    n = model.set_indices("needle")
    ax.plot(x[n, 0], x[n, 2], "r^", ms=6, label="needle")
    if patch is not None:
        p = model.set_indices("paddle")
        ax.plot(x[p, 0], x[p, 2], "gs", ms=7, mfc="none", mew=2, label=f"patch {patch}")
    t = np.asarray(phantom.target)
    tu = t + np.asarray(model.displacement(sol, np.atleast_2d(t)))[0]
    ax.axhline(phantom.entry[2], color="r", ls="--", lw=0.8)
    ax.plot(t[0], t[2], "k+", ms=10, label="target (rest)")
    ax.plot(tu[0], tu[2], "m*", ms=12, label="target")
    ax.set_title(title, fontsize=10)
    return sc


def skin_map(ax, phantom: phantom3d.Phantom3D, values, label: str, log=True, best=None, best_label="best patch"):
    """Patch centres seen from above (x-y), coloured by ``values`` (one per patch); ``best``
    (1-based) ringed and named ``best_label`` in the legend."""
    c = phantom.paddles
    v = np.asarray(values, float)
    from matplotlib.colors import LogNorm
    norm = LogNorm(vmin=np.nanmin(v), vmax=np.nanmax(v)) if log and np.nanmin(v) > 0 else None
    a, b, _ = phantom.semi_axes
    t = np.linspace(0, 2 * np.pi, 200)
    ax.plot(a * np.cos(t), b * np.sin(t), color="0.6", lw=0.8)
    ax.plot([phantom.entry[0], phantom.target[0]], [phantom.entry[1], phantom.target[1]], "r-", lw=1.5,
            label="needle track")
    sc = ax.scatter(c[:, 0], c[:, 1], c=v, s=120, cmap="viridis_r", norm=norm, edgecolors="k")
    for i, p in enumerate(c):
        ax.annotate(str(i + 1), p[:2], fontsize=6, ha="center", va="center", color="w")
    if best is not None:
        ax.plot(*c[best - 1, :2], "o", ms=16, mfc="none", mec="r", mew=2, label=f"{best_label} {best}")
    ax.plot(*phantom.target[:2], "m*", ms=12, label="target")
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({plot.UNITS})")
    ax.set_ylabel(f"y ({plot.UNITS})")
    ax.legend(fontsize=7, loc="lower left")
    ax.figure.colorbar(sc, ax=ax, label=label, shrink=0.8)
    return sc


def final_state(phantom, inclusion, paddle, increments):
    return nd.static_state(phantom, inclusion, paddle, increments)


def write_vtu(out: Path, name: str, model, sol) -> str:
    """Write ``out/name.vtu``; returns its name (relative to the results folder)."""
    return output.write_solution(out / f"{name}.vtu", model, sol).name


def run_static(phantom, inclusion, increments, out: Path, n_devices=None):
    t0 = time.perf_counter()
    sw = nd.static_sweep(phantom, inclusion, increments, n_devices=n_devices)
    return static_report(phantom, sw, out, wall=time.perf_counter() - t0)


def static_report(phantom, sw, out: Path, wall=None):
    """The static mode's summary, figures and .vtu files from a sweep ``sw``."""
    inclusion, increments = sw.inclusion, len(sw.depths)
    free = float(sw.no_paddle[-1])
    final = sw.final
    best = sw.best
    ctrl = sw.controllability[:, 0]
    summary = {
        "mode": "static", "inclusion": inclusion, "increments": increments,
        "particles": phantom.body.n, "spacing": phantom.spacing, "insertion": phantom.insertion,
        "material": phantom.material_law, "patches": len(final), "patch_size": phantom.patch_size,
        "patch_coordinates": phantom.patch_coordinates.tolist(),
        "no_paddle_deviation": free, "no_paddle_lateral": phantom.lateral_components(sw.no_paddle_u[-1]).tolist(),
        "deviation": final.tolist(), "best": best,
        "best_reduction": abs(free) / max(abs(final[best - 1]), 1e-300),
        "reduction": (abs(free) / np.maximum(np.abs(final), 1e-300)).tolist(),
        "controllability": ctrl.tolist(), "most_controllable": int(np.argmin(ctrl)) + 1,
        "status": [[nd.Status(int(s)).name.lower() for s in row] for row in sw.status],
        "converged": sw.converged, "wall_s": wall,
    }
    fig, (a1, a2) = plot.plt.subplots(1, 2, figsize=(13, 4.8), layout="constrained")
    skin_map(a1, phantom, np.abs(final), f"|lateral deviation| at full insertion ({plot.UNITS})", best=best)
    a1.set_title(f"inclusion {inclusion}: no paddle {abs(free):.2e}; best patch {best} "
                 f"({summary['best_reduction']:.0f}x less)", fontsize=10)
    skin_map(a2, phantom, ctrl, r"controllability $\delta x_{min}$ (paddle travel / lateral correction, -)",
             best=summary["most_controllable"], best_label="most controllable patch")
    a2.set_title("controllability after the first increment (smaller: more controllable)", fontsize=10)
    fig.savefig(out / f"patches_{inclusion}.png", dpi=120)
    plot.plt.close(fig)

    fig, ax = plot.plt.subplots(figsize=(9, 4))
    ok = sw.converged_paddles
    idx = np.arange(1, len(final) + 1)
    ax.bar(idx, np.abs(final), color=["C0" if o else "0.6" for o in ok])
    ax.axhline(abs(free), color="r", ls="--", label="no paddle")
    ax.set_yscale("log")
    ax.set_xticks(idx)             # one tick per patch: patches are numbered, not a continuum
    ax.set_xlabel("paddle patch")
    ax.set_ylabel(f"|lateral target deviation| ({plot.UNITS})")
    ax.set_title(f"3D phantom, inclusion {inclusion}: final deviation per patch", fontsize=10)
    ax.legend(fontsize=8)
    plot.save(fig, out / f"deviation_{inclusion}.png")

    m0, s0 = final_state(phantom, inclusion, None, increments)
    m1, s1 = final_state(phantom, inclusion, best, increments)
    vmax = float(max(np.linalg.norm(m.particle_displacements(s), axis=1).max() for m, s in ((m0, s0), (m1, s1))))
    fig, axes = plot.plt.subplots(1, 2, figsize=(12, 3.3), layout="constrained")
    draw_deformed(axes[0], phantom, m0, s0, "no paddle (x-z view)", vmax)
    sc = draw_deformed(axes[1], phantom, m1, s1, f"static patch {best} (x-z view)", vmax, patch=best)
    axes[1].legend(fontsize=7, loc="upper right")
    fig.colorbar(sc, ax=axes, label=f"|u| ({plot.UNITS})", shrink=0.8)
    fig.savefig(out / f"phantom_static_{inclusion}.png", dpi=120)
    plot.plt.close(fig)
    summary["vtu"] = [write_vtu(out, f"no_paddle_{inclusion}", m0, s0),
                      write_vtu(out, f"patch{best}_{inclusion}", m1, s1)]
    return summary


def run_dynamic(phantom, inclusion, increments, out: Path, paddle=None, tol=1e-5, n_devices=None):
    t0 = time.perf_counter()
    sw = nd.static_sweep(phantom, inclusion, increments, n_devices=n_devices)
    ctrl = sw.controllability[:, 0]
    chosen = int(np.argmin(ctrl)) + 1 if paddle is None else paddle
    run = nd.dynamic_paddle(phantom, chosen, inclusion, increments, tol=tol)
    wall = time.perf_counter() - t0
    size = object_size(phantom)
    dev = np.abs(run.deviation)
    summary = {
        "mode": "dynamic", "inclusion": inclusion, "increments": increments,
        "particles": phantom.body.n, "controllability": ctrl.tolist(), "paddle": chosen,
        "object_size": size, "bound": 1e-4 * size, "tol": tol,
        "max_deviation": float(dev.max()) if len(dev) else None,
        "held": bool(len(dev) == increments and dev.max() < 1e-4 * size),
        "paddle_travel": run.travel, "deviation": run.deviation.tolist(),
        "feed_forward_deviation": run.uncorrected.tolist(), "paddle_u": run.paddle_u.tolist(),
        "corrections": run.iterations.tolist(), "depths": run.depths.tolist(),
        "static_deviation": sw.deviation[chosen - 1].tolist(), "no_paddle_per_increment": sw.no_paddle.tolist(),
        "status": run.status.name.lower(), "message": run.message, "wall_s": wall,
    }
    fig, (a1, a2) = plot.plt.subplots(1, 2, figsize=(12, 4.3), layout="constrained")
    d = 100 * np.asarray(run.depths) / phantom.chord
    a1.semilogy(100 * sw.depths / phantom.chord, np.abs(sw.no_paddle), "k--", label="no paddle")
    a1.semilogy(100 * sw.depths / phantom.chord, np.abs(sw.deviation[chosen - 1]), "s-", ms=3,
                label=f"static patch {chosen}")
    a1.semilogy(d, np.abs(run.uncorrected), "^-", ms=3, label="feed-forward move only")
    a1.semilogy(d, np.maximum(dev, 1e-16), "o-", ms=3, label="closed loop")
    a1.axhline(1e-4 * size, color="r", ls=":", label="1e-4 x object size")
    a1.set_xlabel("needle insertion (% of the chord)")
    a1.set_ylabel(f"|lateral target deviation| ({plot.UNITS})")
    a1.legend(fontsize=7)
    a1.grid(alpha=0.3, which="both")
    if run.solution is not None:
        model = phantom.model(inclusion, chosen)
        sc = draw_deformed(a2, phantom, model, run.solution, f"dynamic patch {chosen}, final state", patch=chosen)
        a2.legend(fontsize=7, loc="upper right")
        fig.colorbar(sc, ax=a2, label=f"|u| ({plot.UNITS})", shrink=0.8)
        summary["vtu"] = write_vtu(out, f"dynamic_patch{chosen}_{inclusion}", model, run.solution)
    fig.savefig(out / f"dynamic_{inclusion}.png", dpi=120)
    plot.plt.close(fig)
    return summary


def run_optimize(phantom, inclusion, increments, out: Path, iterations=12, stiffness=1e6, n_devices=None):
    """The best discrete patch's contact points as a spring paddle (``with_footprint``),
    slid over the skin by Adam from that patch's centre: its first iterate is the held
    patch again (to the penalty error), so the optimum compares with it like for like."""
    t0 = time.perf_counter()
    sw = nd.static_sweep(phantom, inclusion, increments, n_devices=n_devices)
    best = sw.best
    start = phantom.patch_coordinates[best - 1]
    sliding = phantom.with_footprint(best)
    opt = nd.optimize_paddle(sliding, inclusion, start=start, increments=increments, iterations=iterations,
                             learning_rate=0.05, stiffness=stiffness)
    wall = time.perf_counter() - t0
    best_dev = float(sw.final[best - 1])
    summary = {
        "mode": "optimize", "inclusion": inclusion, "increments": increments, "particles": phantom.body.n,
        "optimum": {"theta": float(opt.q[0]), "phi": float(opt.q[1]), "deviation": opt.deviation,
                    "point": np.asarray(phantom3d.ellipsoid_point(phantom.semi_axes, *opt.q)).tolist()},
        "best_discrete": best, "best_discrete_deviation": best_dev,
        "best_discrete_coordinates": start.tolist(),
        "spring_paddle_at_best_discrete": opt.start_deviation,
        "no_paddle_deviation": float(sw.no_paddle[-1]),
        "improvement_over_discrete": abs(best_dev) / max(abs(opt.deviation), 1e-300),
        "status": opt.status.name.lower(), "message": opt.message, "rejected_steps": opt.rejected,
        "history": opt.history.tolist(), "paddle_stiffness": stiffness, "wall_s": wall,
    }
    fig, (a1, a2) = plot.plt.subplots(1, 2, figsize=(12, 4.6), layout="constrained")
    skin_map(a1, phantom, np.abs(sw.final), f"|lateral deviation| (discrete patches, {plot.UNITS})", best=best)
    h = opt.history
    path = np.array([np.asarray(phantom3d.ellipsoid_point(phantom.semi_axes, *q)) for q in h[:, :2]])
    a1.plot(path[:, 0], path[:, 1], "o-", color="C3", ms=3, label="Adam iterates")
    a1.plot(*path[np.argmin(np.abs(h[:, 2])), :2], "*", color="C3", ms=14, label="optimum")
    a1.legend(fontsize=7, loc="lower left")
    a1.set_title(f"optimised patch: {abs(opt.deviation):.2e} vs best discrete {abs(best_dev):.2e}", fontsize=10)
    a2.semilogy(np.abs(h[:, 2]), "o-", label="continuous paddle (Adam)")
    a2.axhline(abs(best_dev), color="k", ls="--", label=f"best discrete patch {best}")
    a2.axhline(abs(summary["no_paddle_deviation"]), color="r", ls=":", label="no paddle")
    a2.set_xlabel("iteration")
    a2.set_ylabel(f"|lateral deviation| at full insertion ({plot.UNITS})")
    a2.legend(fontsize=8)
    a2.grid(alpha=0.3, which="both")
    fig.savefig(out / f"optimize_{inclusion}.png", dpi=120)
    plot.plt.close(fig)
    return summary


CONTACT_START = 0.1   # the contact paddle's default indentation, in particle spacings: a light press


def run_contact(phantom, a, out: Path) -> dict:
    """The study of ``a.mode`` with a contact (push-only) paddle at patch ``a.paddle`` (default:
    the best glued patch of the static sweep): static, pressed ``a.indentation`` in; dynamic,
    its pose (indentation, two shifts) moved during the insertion; optimize, Adam on that pose
    (``jaxrkpm.thesis.contact_paddle``); beside the glued patch and no paddle. Writes the
    figure and a .vtu of the final state."""
    from jaxrkpm.thesis import contact_paddle as cp
    t0 = time.perf_counter()
    spec = cp.ContactPaddle(mu=a.friction)
    sw = nd.static_sweep(phantom, a.inclusion, a.increments, paddles=None if a.paddle is None else [a.paddle],
                         n_devices=a.devices)
    paddle = sw.best if a.paddle is None else a.paddle
    k = 0 if a.paddle is not None else paddle - 1            # the chosen patch's row of the sweep
    delta = CONTACT_START * phantom.spacing if a.indentation is None else a.indentation
    s = {"mode": a.mode, "paddle_model": "contact", "friction": a.friction, "inclusion": a.inclusion,
         "increments": a.increments, "particles": phantom.body.n, "spacing": phantom.spacing,
         "material": phantom.material_law, "paddle": paddle, "indentation": delta,
         "no_paddle_deviation": float(sw.no_paddle[-1]), "glued_deviation": float(sw.final[k]),
         "no_paddle_per_increment": sw.no_paddle.tolist(), "glued_per_increment": sw.deviation[k].tolist(),
         "depths": sw.depths.tolist()}
    start = [delta, 0.0, 0.0]
    uncorrected = None
    if a.mode == "static":
        r = cp.contact_insertion(phantom, paddle, start, a.inclusion, a.increments, spec)
        control, sol, lag, depths, dev, checks = r.control, r.solution, r.lag, r.depths, r.deviation, r.checks
        s.update(status=r.status.name.lower(), message=r.status.message)
    elif a.mode == "dynamic":
        r = cp.dynamic_contact_paddle(phantom, paddle, a.inclusion, a.increments, spec, tol=a.tol, start=start)
        control = r.control[-1] if len(r.control) else None
        sol, lag, depths, dev, checks, uncorrected = r.solution, r.lag, r.depths, r.deviation, r.checks, r.uncorrected
        s.update(status=r.status.name.lower(), message=r.message, control_per_increment=r.control.tolist(),
                 corrections=r.iterations.tolist(), feed_forward_deviation=r.uncorrected.tolist())
    else:
        o = cp.optimize_contact_paddle(phantom, paddle, a.inclusion, a.increments, spec, start=start,
                                       iterations=a.iterations, learning_rate=0.03 * phantom.spacing)
        r = o.run
        control, sol, lag, depths, dev, checks = o.control, r.solution, r.lag, r.depths, r.deviation, r.checks
        s.update(status=o.status.name.lower(), message=o.message, history=o.history.tolist())
    s.update(control=None if control is None else np.asarray(control).tolist(), final=float(dev[-1]) if len(dev) else None,
             deviation=np.asarray(dev).tolist(), contact_depths=np.asarray(depths).tolist(),
             contact_ok=all(c.ok() for c in checks), contact_ok_per_increment=[c.ok() for c in checks],
             active_points=[c.active for c in checks], cone_ratio=[c.cone for c in checks],
             min_point_normal_force=[c.min_normal for c in checks], wall_s=time.perf_counter() - t0)
    if sol is not None and control is not None and len(dev):
        what = {"static": "static", "dynamic": "dynamic", "optimize": "optimised"}[a.mode]
        state = contact_state(paddle, control, sol, lag, depths, dev, f"{what} contact paddle at patch {paddle}",
                              uncorrected)
        model, params = contact_params(phantom, a.inclusion, spec, state)
        s["figure"] = contact_figure(out / f"contact_{a.mode}_{a.inclusion}.png", phantom, model, params, spec,
                                     state, glued_curves(sw, k))
        s["vtu"] = output.write_solution(out / f"contact_{a.mode}_{a.inclusion}.vtu", model, sol, params=params).name
    return s


def contact_figure(path: Path, phantom, model, params, spec, state, curves) -> str:
    """The contact paddle's final state in the x-z view (the paddle's outline, the contact
    points coloured by pressure with the paddle's force on each, the needle and the target),
    the paddle's face seen along its normal (the contact points by pressure and their
    friction), and the lateral deviation against depth with no paddle and the glued patch.
    Returns the file name."""
    from jaxrkpm.thesis import contact_paddle as cp
    sol = state["solution"]
    res = contact.contact_forces(model, sol, cp.NAME, params)
    on = np.asarray(res.active)
    pts, pr, f = np.asarray(res.points)[on], np.asarray(res.pressure)[on], np.asarray(res.point_force)[on]
    vmax = float(pr.max()) if len(pr) else 1.0
    fig, (a1, a2, a3) = plot.plt.subplots(1, 3, figsize=(17, 5.4), layout="constrained",
                                          gridspec_kw={"width_ratios": [1.5, 1, 1.2]})
    sc = draw_deformed(a1, phantom, model, sol, state["title"] + " (x-z view)")
    hull = tool_outline(model, params, lambda P: P[:, [0, 2]])
    a1.fill(*np.vstack([hull, hull[:1]]).T, facecolor="0.8", edgecolor="0.3", lw=1, zorder=3, label="contact paddle")
    pc = None
    if len(pts):
        a1.quiver(pts[:, 0], pts[:, 2], f[:, 0], f[:, 2], color="0.2", width=0.003, zorder=4)
        pc = a1.scatter(pts[:, 0], pts[:, 2], c=pr, s=25, cmap="magma", vmin=0, vmax=vmax, zorder=5,
                        edgecolors="k", linewidths=0.3)
    contact_legend(a1, paddle=False)
    a1.set_aspect("equal")
    X = model.body.X + np.asarray(model.particle_displacements(sol))
    lo = np.minimum(X[:, [0, 2]].min(0), hull.min(0)) - 0.05
    hi = np.maximum(X[:, [0, 2]].max(0), hull.max(0)) + 0.05
    a1.set_xlim(lo[0], hi[0])
    a1.set_ylim(lo[1], hi[1])
    a1.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=3)
    fig.colorbar(sc, ax=a1, label=f"|u| ({plot.UNITS})", shrink=0.7)

    # the face seen from outside along the paddle's normal: tool-frame tangential coordinates
    tool, c, R = paddle_pose(model, params)
    local = (X - c) @ R
    near = np.abs(local[:, 2] + float(tool.shape.half[2])) < phantom.spacing     # skin particles by the face
    a2.scatter(local[near, 0], local[near, 1], s=12, color="0.7", label="particles by the face")
    h = np.asarray(tool.shape.half[:2], float)
    a2.add_patch(plot.plt.Rectangle(-h, *(2 * h), facecolor="0.92", edgecolor="0.3", lw=1, zorder=0,
                                    label="paddle face"))
    if len(pts):
        lp, lf = (pts - c) @ R, f @ R
        a2.quiver(lp[:, 0], lp[:, 1], lf[:, 0], lf[:, 1], color="C0", width=0.005, zorder=4)
        a2.scatter(lp[:, 0], lp[:, 1], c=pr, s=60, cmap="magma", vmin=0, vmax=vmax, zorder=5, edgecolors="k",
                   linewidths=0.3)
        contact_legend(a2, paddle=False, arrow="friction on it", colour="C0")
    a2.set_aspect("equal")
    m = 1.3 * float(np.max(np.r_[h, np.abs(local[near, :2]).max() if near.any() else 0.0]))
    a2.set_xlim(-m, m)
    a2.set_ylim(-m, m)
    a2.set_xlabel(f"along the face, first tangent ({plot.UNITS})")
    a2.set_ylabel(f"second tangent ({plot.UNITS})")
    a2.set_title(f"paddle face, seen along its normal (mu {spec.mu:g})", fontsize=10)
    a2.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    if pc is not None:
        fig.colorbar(pc, ax=a2, label="contact pressure (units of the material constants)", shrink=0.7)

    scale = 100.0 / phantom.chord
    deviation_panel(a3, curves, state, scale, magnitude=True)
    a3.set_xlabel("needle insertion (% of the chord)")
    a3.set_ylabel(f"|lateral target deviation| ({plot.UNITS})")
    final = abs(state["deviation"][-1])
    a3.set_title(f"final {final:.2e}: no paddle {abs(curves['no_paddle'][-1]):.2e}, "
                 f"glued {abs(curves['glued'][-1]):.2e}",
                 fontsize=10)
    fig.savefig(path, dpi=120)
    plot.plt.close(fig)
    return path.name


def result(s: dict) -> tuple[bool, str]:
    """(goal reached, the result in words) of a needle3d summary. Static: every patch and the
    no-paddle run reach full insertion; dynamic: the target held within the bound at every
    increment; optimize: the optimiser converged."""
    if s.get("paddle_model") == "contact":
        return contact_result(s, "needle3d")
    mode, inc, n = s["mode"], s["inclusion"], s["particles"]
    if mode == "static":
        failed = [i + 1 for i, row in enumerate(s["status"]) if any(x != "converged" for x in row)]
        words = (f"needle3d static ({inc}, {n} particles): no paddle {abs(s['no_paddle_deviation']):.2e}, best "
                 f"patch {s['best']} of {s['patches']} {abs(s['deviation'][s['best'] - 1]):.2e} "
                 f"({s['best_reduction']:.0f}x less), most controllable patch {s['most_controllable']}")
        if failed:
            words += f"; patches {', '.join(map(str, failed))} stopped before full insertion"
        return bool(s["converged"]), words
    if mode == "dynamic":
        dev = "none" if s["max_deviation"] is None else f"{s['max_deviation']:.1e}"
        words = (f"needle3d dynamic ({inc}, {n} particles): patch {s['paddle']}, max |lateral deviation| {dev} "
                 f"(bound {s['bound']:.0e}), paddle travel {s['paddle_travel']:.4f}; "
                 f"{s['status']}: {s['message']}")
        return bool(s["held"]), words
    o = s["optimum"]
    return optimize_result(s, "needle3d optimize", f"{n} particles, patch at theta {o['theta']:.3f}, phi {o['phi']:.3f}", "patch")


def _patch_in_range(a, given):
    """--paddle names one of the candidate patches (the angle grid: no mesh needed)."""
    if a.paddle is None:
        return None
    patches = len(phantom3d.Phantom3D(spacing=a.spacing, material_law=a.material).patch_coordinates)
    if a.paddle > patches:
        return f"argument --paddle: must be an integer in [1, {patches}] (the candidate patches), got {a.paddle}"
    return None


def _deepest(a) -> tuple:
    from jaxrkpm.thesis.contact_paddle import max_indentation
    phantom = phantom3d.Phantom3D(spacing=a.spacing, material_law=a.material)
    return phantom.spacing, max_indentation(phantom)


def parser() -> interface.Parser:
    from jaxrkpm.thesis.data import INCLUSIONS_3D
    number = interface.number
    p = needle_options("needle3d", __doc__, INCLUSIONS_3D)
    p.add_argument("--material", choices=("neo-hookean", "neohookean", "fung", "fung-barrier"),
                   default="neo-hookean",
                   help="neo-hookean (default): nearly incompressible neo-Hookean tissue, mu = 1, nu = 0.45; "
                        "neohookean: compressible neo-Hookean, lam = 4, mu = 1 (nu = 0.4, the default before); "
                        "fung: chapter 6's Fung with the 3D Table 5.2 pattern; fung-barrier: the same plus the "
                        "volumetric barrier kappa/2 (ln J)^2")
    p.add_argument("--spacing", type=number(float, 0.05, 0.4), default=0.2,
                   help="mesh size of the phantom (0.3: 231 particles; 0.2: 390; 0.1: 1,332)")
    p.add_argument("--increments", type=number(int, 1, INCREMENTS_3D_MAX), default=4,
                   help=f"insertion increments, 1..{INCREMENTS_3D_MAX}")
    p.add_argument("--paddle", type=interface.COUNT, default=None,
                   help="dynamic mode: patch to move, 1..the number of patches (default: the most controllable); "
                        "contact paddle: its patch in every mode (default: the best glued patch)")
    p.add_argument("--tol", type=interface.POSITIVE, default=1e-5, help="dynamic mode: |lateral deviation| to hold")
    p.add_argument("--iterations", type=number(int, 1, interface.ADAM_MAX), default=12,
                   help=f"optimize mode: Adam iterations, 1..{interface.ADAM_MAX}")
    p.add_argument("--devices", type=number(int, 1, interface.DEVICES_MAX), default=None,
                   help="shard the sweep over this many devices (default: one)")
    p.check(_patch_in_range)
    contact_options(p, "the patch, default the best glued one", "a tenth of a particle spacing", _deepest)
    return p


def main(argv=None):
    a = parser().parse_args(argv)
    phantom = phantom3d.Phantom3D(spacing=a.spacing, material_law=a.material)
    results = interface.results("needle3d", a, a.out or f"results/needle3d/{a.mode}_{a.inclusion}")
    with results as out:
        stages = interface.progress(total=2, desc=f"needle3d {a.mode} {a.inclusion}", unit="stage")
        stages.set_postfix_str("mesh and models")
        phantom.body
        stages.update()
        stages.set_postfix_str("sweep and solves")
        if a.paddle_model == "contact":
            summary = run_contact(phantom, a, out)
        elif a.mode == "static":
            summary = run_static(phantom, a.inclusion, a.increments, out, a.devices)
        elif a.mode == "dynamic":
            summary = run_dynamic(phantom, a.inclusion, a.increments, out, a.paddle, a.tol, a.devices)
        else:
            summary = run_optimize(phantom, a.inclusion, a.increments, out, a.iterations, n_devices=a.devices)
        stages.update()
        stages.close()
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        results.finish(summary, *result(summary), a.json)
    return summary


COMMAND = Command("needle3d", "chapter 6 lifted to 3D: a half-ellipsoid phantom from a mesh, paddle patches on its "
                              "skin", parser, main, result, order=50)

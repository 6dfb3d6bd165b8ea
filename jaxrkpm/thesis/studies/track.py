"""Chapter-5 Jacobian path tracking (thesis Algorithm 3, section 5.3).

2D (``--dim 2``, default): the 9x9 Fung unit square (left edge immobile, the three
right-edge particles nearest (1, 0.5) moved rigidly, control point (0.5, 0.5)); paths
``setpoint`` (0,0)->(0.05,0.05), ``box`` (Table 5.3), ``figure8`` (Table 5.4), ``line``
(Table 5.5), all control point displacements.

3D (``--dim 3``): the cube of section 5.3.1 (x in [-2.5,-1.5], y in [-0.5,0.5], z in [1.5,2.5],
face x=-1.5 immobile, paddle on face x=-2.5, control point (-2, 0, 2.5)), path Table 5.1,
material eq 5.1. ``--model reduced`` (3x3x3, paddle on the bottom two layers) or ``refined``
(5x5x5, paddle on the whole face); ``--scheme reduced-to-refined`` computes the Jacobian on
the reduced model and moves the refined one (the thesis' reduced->refined control).

Writes ``summary.json``, ``history.npz`` and figures (desired vs achieved control point path,
error per iteration on a log axis, manipulation point path, deformed snapshots at waypoints)
to ``--out``. Lengths are in model units (the square's side is 1, the cube's edge 1).
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import jaxrkpm as jr
from jaxrkpm.thesis.data import CP_2D, CP_3D, CUBE_MAX_ERROR, PATHS, TRACKING_MINUTES
from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import Command, lazy
from jaxrkpm.thesis.studies.experiments import AGREES, COLL, DIFFERS, IN_KIND, Entry

jnp = lazy("jax.numpy")
output = lazy("jaxrkpm.io.output")
plot = lazy("jaxrkpm.io.plot")
tracking = lazy("jaxrkpm.control.tracking")
scenarios = lazy("jaxrkpm.thesis.scenarios")

PATH_NAMES_2D = tuple(PATHS)
PATH_3D = "table5.1"
REPEATS_MAX = 100               # timed warm runs


# --------------------------------------------------------------------------- models
def planar_model(n: int = 9, integration: str = "gauss", alpha: float = 1.0, beta: float = 1.0,
                 solver: str = "auto") -> jr.Model:
    """The chapter-5 tracking model: :func:`jaxrkpm.thesis.scenarios.planar_square` with Fung(alpha,
    beta) and the paddle on the three right-edge particles nearest (1, 0.5)."""
    return scenarios.planar_square(n, integration, jr.Fung(alpha=alpha, beta=beta), paddle="three", solver=solver)


@dataclass
class Experiment:
    """A configured tracking run: the controller model (its Jacobian drives the paddle), the
    plant (moved and measured; None = the controller itself), the path of control point
    displacements (W, d) and the control point (1, d)."""

    name: str
    dim: int
    path_name: str
    path: np.ndarray
    model: jr.Model
    cp: np.ndarray
    plant: jr.Model | None = None
    kind: str | None = None        # 3D: reduced | refined
    scheme: str = "self"
    meta: dict = field(default_factory=dict)

    @property
    def measured(self) -> jr.Model:
        return self.model if self.plant is None else self.plant


def build(path: str | None = None, dim: int = 2, integration: str = "gauss", model: str = "reduced",
          scheme: str = "self", n: int = 9, alpha: float = 1.0, beta: float = 1.0) -> Experiment:
    """Build the models of one experiment (raises ValueError on a bad combination, and lets
    the Model's own ValueError through, e.g. for an integration it does not know)."""
    if scheme not in ("self", "reduced-to-refined"):
        raise ValueError(f"unknown scheme {scheme!r}: choose 'self' or 'reduced-to-refined'")
    if dim == 2:
        path = path or "box"
        if path not in PATHS:
            raise ValueError(f"unknown 2D path {path!r}: choose {list(PATHS)}")
        if scheme != "self":
            raise ValueError("the reduced-to-refined scheme is the 3D cube's (--dim 3 --model refined)")
        m = planar_model(n, integration, alpha, beta)
        return Experiment(f"{path}-{integration}" + ("" if n == 9 else f"-{n}x{n}"), 2, path,
                          np.asarray(PATHS[path], float), m, CP_2D)
    if dim != 3:
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    path = path or PATH_3D
    if path != PATH_3D:
        raise ValueError(f"the 3D cube tracks Table 5.1 (--path {PATH_3D}), got {path!r}")
    if scheme == "reduced-to-refined":
        if model != "refined":
            raise ValueError("--scheme reduced-to-refined needs --model refined (the plant)")
        ctrl, plant = scenarios.cube("reduced", integration, alpha), scenarios.cube("refined", integration, alpha)
    else:
        ctrl, plant = scenarios.cube(model, integration, alpha), None
    return Experiment(f"cube-{model}-{scheme}-{integration}", 3, path, scenarios.cube_path(),
                      ctrl, CP_3D, plant, model, scheme)


# --------------------------------------------------------------------------- running
def execute(exp: Experiment, *, gain=0.05, clamp=0.01, tol=1e-4, max_iter=2000, max_steps=20000,
            window=300, repeats: int = 1):
    """Compile, then run the tracking ``repeats`` times (>= 1). Returns (TrackResult, timing).

    The compile time is measured by a probe with the same shapes and static settings but a
    huge tolerance (every waypoint counts as reached at once, no solve runs): the tolerance
    is a traced argument, so the probe compiles exactly the loop that the real runs reuse.
    wall_s is the median of the warm runs."""
    kw = dict(plant=exp.plant, gain=gain, clamp=clamp, max_iter=max_iter, max_steps=max_steps,
              window=window)
    t0 = time.perf_counter()
    tracking.track(exp.model, exp.path, "paddle", exp.cp, tol=1e30, **kw)
    compile_s = time.perf_counter() - t0
    warm = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        res = tracking.track(exp.model, exp.path, "paddle", exp.cp, tol=tol, **kw)
        warm.append(time.perf_counter() - t0)
    w = float(np.median(warm))
    return res, {"wall_s": w, "compile_s": compile_s, "first_run_s": compile_s + warm[0],
                 "warm_runs_s": warm}


def snapshot_waypoints(exp: Experiment, res: tracking.TrackResult) -> list[int]:
    """Waypoints to draw: all six of Table 5.1 in 3D; about five evenly spaced in 2D
    (the corners of the box)."""
    W = len(res.desired)
    pick = list(range(W)) if (exp.dim == 3 or W <= 5) else \
        sorted(set(int(round(x)) for x in np.linspace(0, W - 1, 5)))
    return [i for i in pick if res.reached[i] >= 0]


def snapshots(exp: Experiment, res: tracking.TrackResult, which: list[int]):
    """Re-solve the measured model at the manipulation point recorded when each waypoint was
    reached (sequentially, each warm-started from the previous: the same branch as the
    tracking run). Returns [(waypoint, iteration, Solution)], plus the final state if the
    run stopped early."""
    m = exp.measured
    sol, out = m.initial(), []
    for i in which:
        k = int(res.reached[i])
        sol = m.solve({"paddle": jnp.asarray(res.mp[k])}, initial=sol, steps=4, throw=False)
        out.append((i, k, sol))
    if res.status.name != "DONE":
        out.append((None, len(res.error) - 1, res.plant_solution))
    return out


def write_mesh_outputs(exp: Experiment, res: tracking.TrackResult, out: Path) -> dict:
    """ParaView / PyVista files of the run (jaxrkpm.io.output): ``final.vtu``, the measured model's
    last state, and ``series.pvd``, one frame per reached waypoint (plus the final state if the
    run stopped early), re-solved as in :func:`snapshots`, time = the control step."""
    reached = [i for i in range(len(res.desired)) if res.reached[i] >= 0]
    frames = {}
    for _, k, sol in snapshots(exp, res, reached):
        frames[k] = sol                      # one frame per control step (the later state wins)
    output.write_solution(out / "final.vtu", exp.measured, res.plant_solution)
    output.write_series(out / "series.pvd", exp.measured, list(frames.values()), list(frames))
    return {"vtu": "final.vtu", "series": "series.pvd", "series_frames": len(frames)}


def summarize(exp: Experiment, res: tracking.TrackResult, timing: dict, settings: dict, snaps=()) -> dict:
    m, plant = exp.model, exp.measured
    dev = tracking.path_deviation(res)
    rows = tracking.waypoint_table(res)
    shape = lambda mod: [int(len(np.unique(np.round(mod.body.X[:, a], 9)))) for a in range(mod.dim)]
    s = {
        "experiment": exp.name, "dim": exp.dim, "path": exp.path_name,
        "status": res.status.name, "message": res.message,
        "max_waypoint_error": res.max_waypoint_error,
        "waypoints_reached": int(np.sum(res.reached >= 0)), "waypoints_total": len(res.desired),
        "waypoints": rows,
        "iterations": int(len(res.error) - 1),
        "newton_iterations": int(np.sum(res.newton)),
        "max_path_deviation": float(dev.max()),
        "final_error": float(res.error[-1]),
        "final_manipulation_point": res.mp[-1].tolist(),
        "wall_s": timing["wall_s"], "compile_s": timing["compile_s"],
        "first_run_s": timing["first_run_s"], "warm_runs_s": timing["warm_runs_s"],
        **settings,
        "material": m.material.describe(),
        "integration": m.integration,
        "particles": shape(plant),
        "n_particles": int(plant.body.n),
        "control_point": exp.cp.ravel().tolist(),
        "paddle_particles": plant.body.X[plant.set_indices("paddle")].tolist(),
        "linear_solver": plant.linear.name,
    }
    if exp.dim == 3:
        s["model"] = exp.kind
        s["scheme"] = exp.scheme
        s["controller_particles"] = shape(m)
        s["desired_positions"] = (res.desired + exp.cp.ravel()).tolist()
        s["thesis_max_error"] = CUBE_MAX_ERROR[exp.kind]
    else:
        ref = TRACKING_MINUTES["gauss"].get(exp.path_name)
        if ref is not None:
            s["thesis_minutes_gauss"] = ref
            s["thesis_minutes_collocated"] = TRACKING_MINUTES["collocated"][exp.path_name]
            s["speedup_vs_thesis_gauss"] = ref * 60 / timing["wall_s"]
    s["snapshots"] = []
    for i, k, sol in snaps:
        cp_now = np.asarray(plant.displacement(sol, exp.cp)).ravel()
        u = np.asarray(plant.particle_displacements(sol))
        s["snapshots"].append({
            "waypoint": i, "iteration": k, "manipulation_point": res.mp[k].tolist(),
            "control_point": cp_now.tolist(),
            "resolve_mismatch": float(np.linalg.norm(cp_now - res.cp[k])),
            "max_displacement": float(np.linalg.norm(u, axis=1).max()),
            "paddle_force": np.asarray(plant.reaction(sol, "paddle")).tolist(),
            "solve_status": jr.Status(int(sol.status)).name})
    return s


# --------------------------------------------------------------------------- figures
def _labels(dim):
    return ("x", "y") if dim == 2 else ("x", "z")


def fig_cp_path(exp, res, out):
    plt = plot.plt
    d = exp.dim
    off = np.zeros(d) if d == 2 else exp.cp.ravel()   # 3D: object coordinates (Table 5.1)
    D, C = res.desired + off, res.cp + off
    i, j = (0, 1) if d == 2 else (0, 2)
    ok = res.reached >= 0
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1, 1.3]})
    a.plot(D[:, i], D[:, j], "k--", lw=1, zorder=1)
    a.plot(D[:, i], D[:, j], "ks", ms=7, mfc="none", label="desired waypoints", zorder=2)
    a.plot(C[:, i], C[:, j], "-", color="tab:blue", lw=1.5, label="control point (achieved)", zorder=3)
    a.plot(res.achieved[ok, i] + off[i], res.achieved[ok, j] + off[j], "o", color="tab:red", ms=4,
           label="waypoint reached", zorder=4)
    seen = {}
    for w, p in enumerate(D):
        key = (round(p[i], 9), round(p[j], 9))
        seen[key] = seen.get(key, []) + [str(w + 1)]
    for (x, y), names in seen.items():
        a.annotate(",".join(names), (x, y), textcoords="offset points", xytext=(6, 5), fontsize=8)
    a.set_xlabel(f"{_labels(d)[0]}" + (" displacement" if d == 2 else " position") + f" ({plot.UNITS})")
    a.set_ylabel(f"{_labels(d)[1]}" + (" displacement" if d == 2 else " position") + f" ({plot.UNITS})")
    a.set_aspect("equal", adjustable="datalim")
    a.grid(alpha=0.3)
    a.legend(fontsize=8, loc="best")
    a.set_title("control point path" + (" (x-z plane, object coordinates)" if d == 3 else ""))
    it = np.arange(len(C))
    names = "xyz"[:d]
    colors = ["tab:blue", "tab:orange", "tab:green"]
    target = res.desired[np.clip(res.waypoint, 0, len(res.desired) - 1)]
    for c in range(d):
        b.plot(it, res.cp[:, c], color=colors[c], lw=1.5, label=f"{names[c]} achieved")
        b.step(it, target[:, c], where="post", color=colors[c], ls="--", lw=1, label=f"{names[c]} desired")
    b.set_xlabel("iteration")
    b.set_ylabel(f"control point displacement ({plot.UNITS})")
    b.grid(alpha=0.3)
    b.legend(fontsize=8, ncol=d)
    b.set_title("control point coordinates per iteration")
    fig.suptitle(_title(exp, res))
    plot.save(fig, out / "cp_path.png")


def fig_cp_error(exp, res, tol, out):
    plt = plot.plt
    fig, ax = plt.subplots(figsize=(9, 4.5))
    it = np.arange(len(res.error))
    err = np.where(res.error > 0, res.error, np.nan)   # an exact hit (iteration 0) has no log
    ax.semilogy(it, err, color="tab:blue", lw=1.2, label="|desired - achieved|")
    pos = res.error[res.error > 0]
    if pos.size:
        ax.set_ylim(bottom=0.5 * min(tol / 10, pos.min()))
    ax.axhline(tol, color="tab:red", ls="--", lw=1, label=f"tolerance {tol:g}")
    for k in res.reached[res.reached > 0]:
        ax.axvline(k, color="0.8", lw=0.6, zorder=0)
    ax.set_xlabel("iteration (vertical lines: a waypoint reached)")
    ax.set_ylabel(f"control point error ({plot.UNITS})")
    ax.set_title(f"control point error per iteration; max error at the waypoints "
                 f"{res.max_waypoint_error:.2e}\n{_title(exp, res)}", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    plot.save(fig, out / "cp_error.png")


def fig_mp_path(exp, res, out):
    plt = plot.plt
    d = exp.dim
    i, j = (0, 1) if d == 2 else (0, 2)
    M = res.mp
    ok = res.reached >= 0
    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [1, 1.3]})
    a.plot(M[:, i], M[:, j], "-", color="tab:purple", lw=1.5, label="manipulation point")
    r = res.reached[ok]
    a.plot(M[r, i], M[r, j], "o", color="tab:red", ms=4, label="at a reached waypoint")
    for w, k in enumerate(res.reached):
        if k >= 0:
            a.annotate(str(w + 1), (M[k, i], M[k, j]), textcoords="offset points", xytext=(5, 4), fontsize=8)
    a.plot([0], [0], "k+", ms=10, label="start")
    a.set_xlabel(f"paddle {_labels(d)[0]} displacement ({plot.UNITS})")
    a.set_ylabel(f"paddle {_labels(d)[1]} displacement ({plot.UNITS})")
    a.set_aspect("equal", adjustable="datalim")
    a.grid(alpha=0.3)
    a.legend(fontsize=8)
    a.set_title("manipulation point (paddle) path")
    it = np.arange(len(M))
    for c in range(d):
        b.plot(it, M[:, c], lw=1.5, label="xyz"[c])
    b.set_xlabel("iteration")
    b.set_ylabel(f"paddle displacement ({plot.UNITS})")
    b.grid(alpha=0.3)
    b.legend(fontsize=8)
    b.set_title("manipulation point coordinates per iteration")
    fig.suptitle(_title(exp, res))
    plot.save(fig, out / "mp_path.png")


def fig_deformed_2d(exp, res, snaps, out):
    plt = plot.plt
    m = exp.measured
    X = m.body.X
    us = [np.asarray(m.particle_displacements(sol)) for _, _, sol in snaps]
    vmax = max(float(np.linalg.norm(u, axis=1).max()) for u in us) or None
    allx = np.concatenate([X] + [X + u for u in us])
    lo, hi = allx.min(0), allx.max(0)
    n = len(snaps)
    cols = n if n <= 5 else 3
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols + 1.0, 3.9 * rows + 0.6), squeeze=False,
                             layout="constrained")
    pad = m.set_indices("paddle")
    sc = None
    for ax, (w, k, sol), u in zip(axes.flat, snaps, us):
        sc = plot.deformed_particles(ax, X, u, vmax=vmax, size=28, colorbar=False)
        ax.plot(*(X[pad] + u[pad]).T, "s", mfc="none", mec="tab:red", ms=9, mew=1.2, label="paddle")
        cp = exp.cp[0] + np.asarray(m.displacement(sol, exp.cp))[0]
        ax.plot(*cp, "*", color="tab:red", ms=12, mec="k", mew=0.5, label="control point")
        if w is not None:
            ax.plot(*(exp.cp[0] + res.desired[w]), "x", color="k", ms=9, mew=1.5, label="desired")
            ttl = f"waypoint {w + 1} (iteration {k})"
        else:
            ttl = f"final state (iteration {k})"
        ax.set_title(ttl, fontsize=10)
        ax.set_xlim(lo[0] - 0.06, hi[0] + 0.06)
        ax.set_ylim(lo[1] - 0.06, hi[1] + 0.06)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.colorbar(sc, ax=axes.ravel().tolist(), label=f"|u| ({plot.UNITS})", shrink=0.85)
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="outside lower center", ncol=5, fontsize=9)
    fig.suptitle(_title(exp, res))
    fig.savefig(out / "deformed.png", dpi=120)
    plt.close(fig)


def _grid_shape(X):
    return tuple(len(np.unique(np.round(X[:, a], 9))) for a in range(X.shape[1]))


def fig_layers_3d(exp, res, snaps, out, sub: int = 4):
    """Figs 5.3-5.8: the horizontal particle layers z = const of the deformed cube, each a
    surface coloured by the displacement magnitude (the RK field sampled ``sub`` times finer
    than the particles within each layer)."""
    plt = plot.plt
    from matplotlib import cm, colors
    m = exp.measured
    X = m.body.X
    nx, ny, nz = _grid_shape(X)
    h = m.body.spacing
    lo, hi = m.body.lower, m.body.upper
    s1 = np.linspace(lo[0], hi[0], (nx - 1) * sub + 1)
    s2 = np.linspace(lo[1], hi[1], (ny - 1) * sub + 1)
    zs = lo[2] + h * np.arange(nz)
    A, B = np.meshgrid(s1, s2, indexing="ij")
    fields = []
    for w, k, sol in snaps:
        layers = []
        for z in zs:
            P = np.stack([A.ravel(), B.ravel(), np.full(A.size, z)], 1)
            P = np.clip(P, lo, hi)
            u = np.asarray(m.displacement(sol, P)).reshape(A.shape + (3,))
            layers.append((P.reshape(A.shape + (3,)), u))
        up = np.asarray(m.particle_displacements(sol))
        cp = exp.cp[0] + np.asarray(m.displacement(sol, exp.cp))[0]
        fields.append((layers, up, cp))
    vmax = max(float(max(np.linalg.norm(u, axis=-1).max() for _, u in L)) for L, _, _ in fields) or 1.0
    norm = colors.Normalize(0, vmax)
    cmap = plt.get_cmap("jet")
    allx = np.concatenate([np.concatenate([(P + u).reshape(-1, 3) for P, u in L]) for L, _, _ in fields])
    allx = np.concatenate([allx, X])
    bl, bh = allx.min(0), allx.max(0)
    n = len(snaps)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = plt.figure(figsize=(5.6 * cols, 5.0 * rows))
    pad = m.set_indices("paddle")
    wall = m.set_indices("wall")
    for a, ((w, k, sol), (L, up, cp)) in enumerate(zip(snaps, fields)):
        ax = fig.add_subplot(rows, cols, a + 1, projection="3d", computed_zorder=False)
        for P, u in L:
            x = P + u
            mag = np.linalg.norm(u, axis=-1)
            # face (i, j) coloured by the mean of its corners (plot_surface reads [i, j])
            fm = 0.25 * (mag[:-1, :-1] + mag[1:, :-1] + mag[:-1, 1:] + mag[1:, 1:])
            fc = np.zeros(mag.shape + (4,))
            fc[:-1, :-1] = cmap(norm(fm))
            ax.plot_surface(x[..., 0], x[..., 1], x[..., 2], facecolors=fc, shade=False,
                            rstride=1, cstride=1, linewidth=0.2, edgecolor=(0, 0, 0, 0.15),
                            antialiased=False, zorder=1)
        xp = X + up
        ax.scatter(*xp[pad].T, color="tab:red", s=22, depthshade=False, label="paddle particles", zorder=4)
        ax.scatter(*xp[wall].T, color="0.3", s=10, depthshade=False, label="immobile face", zorder=4)
        ax.scatter(*cp, marker="*", color="magenta", s=260, edgecolor="k", depthshade=False,
                   label="control point", zorder=6)
        if w is not None:
            ax.scatter(*(exp.cp[0] + res.desired[w]), marker="x", color="k", s=110, linewidths=2,
                       depthshade=False, label="desired control point", zorder=7)
            ttl = f"step {w + 1} of Table 5.1 (iteration {k})"
        else:
            ttl = f"final state (iteration {k})"
        ax.set_title(ttl, fontsize=10)
        ax.set_xlim(bl[0], bh[0])
        ax.set_ylim(bl[1], bh[1])
        ax.set_zlim(bl[2], bh[2])
        ax.set_box_aspect(bh - bl)
        plot.tidy_3d_axes(ax)
        ax.view_init(elev=24, azim=-55)
        if a == 0:
            handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=9)
    fig.subplots_adjust(left=0.0, right=0.9, bottom=0.06, top=0.9, wspace=0.02, hspace=0.08)
    sm = cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, cax=fig.add_axes([0.92, 0.25, 0.015, 0.5]), label=f"|u| ({plot.UNITS})")
    fig.suptitle(_title(exp, res) + f"\nlayers z = const ({nz} layers) coloured by |u|")
    fig.savefig(out / "layers.png", dpi=110)
    plt.close(fig)


def _title(exp, res):
    m = exp.measured
    mat = m.material.describe()
    mat_s = ", ".join(f"{k}={v}" for k, v in mat.items() if k != "name" and np.ndim(v) == 0)
    shape = "x".join(str(s) for s in _grid_shape(m.body.X))
    if exp.dim == 2:
        what = f"{exp.path_name} path, {shape} {m.integration}, {mat['name']} ({mat_s})"
    else:
        what = f"Table 5.1, {exp.kind} cube {shape}" + \
               (" (Jacobian from the reduced 3x3x3 model)" if exp.scheme != "self" else "") + \
               f", {m.integration}, {mat['name']} ({mat_s})"
    return f"{what} - {res.status.name}"


def figures(exp: Experiment, res: tracking.TrackResult, snaps, out: Path, tol: float) -> list[str]:
    fig_cp_path(exp, res, out)
    fig_cp_error(exp, res, tol, out)
    fig_mp_path(exp, res, out)
    names = ["cp_path.png", "cp_error.png", "mp_path.png"]
    if snaps:
        if exp.dim == 2:
            fig_deformed_2d(exp, res, snaps, out)
            names.append("deformed.png")
        else:
            fig_layers_3d(exp, res, snaps, out)
            plot.deformed_body_png(out / "deformed_3d.png", exp.measured, res.plant_solution,
                                   title=_title(exp, res) + "\nfinal state, faces coloured by von Mises stress")
            names += ["layers.png", "deformed_3d.png"]
    return names


# --------------------------------------------------------------------------- entry points
def run(out: Path, path: str | None = None, *, dim: int = 2, integration: str = "gauss",
        model: str = "reduced", scheme: str = "self", n: int = 9, alpha: float = 1.0,
        beta: float = 1.0, gain: float = 0.05, clamp: float = 0.01, tol: float = 1e-4,
        max_iter: int = 2000, max_steps: int = 20000, window: int = 300, repeats: int = 1,
        make_figures: bool = True, mesh_output: bool = True,
        experiment: Experiment | None = None) -> dict:
    """Build (or reuse ``experiment``), track, write summary.json (+ figures), history.npz
    (+ final.vtu and series.pvd, :func:`write_mesh_outputs`); return the summary. ``repeats``
    warm runs are timed (wall_s: their median; compile_s: see ``execute``)."""
    start = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    exp = experiment or build(path, dim, integration, model, scheme, n, alpha, beta)
    settings = {"gain": gain, "clamp": clamp, "tol": tol, "max_iter": max_iter,
                "max_steps": max_steps, "window": window}
    # the tracking loop is one compiled call: the bar counts its stages, and shows the time
    stages = interface.progress(total=3 if make_figures else 1, desc=f"track {exp.name}", unit="stage")
    stages.set_postfix_str("compile and track")
    res, timing = execute(exp, repeats=repeats, **settings)
    stages.update()
    stages.set_postfix_str("snapshots")
    snaps = snapshots(exp, res, snapshot_waypoints(exp, res)) if make_figures else []
    s = summarize(exp, res, timing, settings, snaps)
    if make_figures:
        stages.update()
        stages.set_postfix_str("figures")
        s["figures"] = figures(exp, res, snaps, out, tol)
        stages.update()
    stages.close()
    if mesh_output:
        s.update(write_mesh_outputs(exp, res, out))
    np.savez_compressed(out / "history.npz", mp=res.mp, cp=res.cp, error=res.error,
                        waypoint=res.waypoint, newton=res.newton, solve_status=res.solve_status,
                        reached=res.reached, achieved=res.achieved, desired=res.desired)
    # the whole run (model, snapshots, figures, files): the line's warm and compile times are only the tracking's
    s["total_s"] = time.perf_counter() - start
    (out / "summary.json").write_text(json.dumps(s, indent=2))
    return s


def result(s: dict) -> tuple[bool, str]:
    """(every waypoint reached, the result in words) of a tracking summary."""
    what = (f"{s['path']} path ({s['integration']}, {'x'.join(map(str, s['particles']))})" if s["dim"] == 2
            else f"Table 5.1 on the {s['model']} cube" + (" (Jacobian from the reduced model)"
                                                           if s.get("scheme") == "reduced-to-refined" else ""))
    words = (f"{what}: {s['waypoints_reached']}/{s['waypoints_total']} waypoints reached, max waypoint error "
             f"{s['max_waypoint_error']:.1e} (tolerance {s['tol']:.0e}), {s['iterations']} iterations, "
             f"{s['wall_s']:.1f} s warm + {s['compile_s']:.1f} s compile"
             + (f", {s['total_s']:.1f} s in all with the model, figures and files" if "total_s" in s else ""))
    if s.get("thesis_minutes_gauss"):
        words += f" (thesis: {s['thesis_minutes_gauss']} min)"
    if s.get("thesis_max_error") is not None:
        words += f" (thesis max error {s['thesis_max_error']})"
    if s["status"] != "DONE":
        words += f"; stopped: {s['status']}: {s['message']}"
    return s["status"] == "DONE", words


ONLY_2D = ("n", "beta")              # options of the 2D square only
ONLY_3D = ("model", "scheme")         # options of the 3D cube only


def _other_dimension(a, given):
    """An option of the other dimension would be ignored: refused."""
    wrong = [o for o in (ONLY_3D if a.dim == 2 else ONLY_2D) if o in given]
    if wrong:
        return (f"{', '.join('--' + o for o in wrong)} {'applies' if len(wrong) == 1 else 'apply'} to "
                f"--dim {3 if a.dim == 2 else 2} only (this run is --dim {a.dim})")
    return None


def _path_of_the_dimension(a, given):
    if (a.scheme or "self") == "reduced-to-refined" and (a.dim != 3 or (a.model or "reduced") != "refined"):
        return "--scheme reduced-to-refined needs --dim 3 --model refined"
    if a.dim == 3 and a.path not in (None, PATH_3D):
        return f"--dim 3 tracks Table 5.1 (--path {PATH_3D})"
    if a.dim == 2 and a.path == PATH_3D:
        return "--path table5.1 is the 3D cube's (--dim 3)"
    return None


def parser() -> interface.Parser:
    from jaxrkpm.thesis.data import CUBES
    p = interface.parser("track", __doc__, "results/track/<experiment>")
    p.add_argument("--path", choices=[*PATHS, PATH_3D], default=None,
                   help="2D: " + "|".join(PATHS) + " (default box); 3D: table5.1 (default)")
    p.add_argument("--integration", choices=("gauss", "scni", "mscni"), default="gauss")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2)
    p.add_argument("--model", choices=tuple(CUBES), default=None,
                   help="3D only: the cube's discretisation (default reduced)")
    p.add_argument("--scheme", choices=("self", "reduced-to-refined"), default=None,
                   help="3D refined only: Jacobian from the model itself or from the reduced model (default self)")
    p.add_argument("--n", type=interface.number(int, 3), default=None,
                   help="2D only: particles per side (default 9, the thesis'; bounded by the memory available)")
    p.add_argument("--alpha", type=interface.POSITIVE, default=1.0, help="material alpha (Fung 2D, eq 5.1 in 3D)")
    p.add_argument("--beta", type=interface.POSITIVE, default=None, help="2D only: Fung beta (default 1)")
    p.add_argument("--gain", type=interface.POSITIVE, default=0.05)
    p.add_argument("--clamp", type=interface.POSITIVE, default=0.01, help="largest paddle increment per component")
    p.add_argument("--tol", type=interface.POSITIVE, default=1e-4, help="control point tolerance per waypoint")
    p.add_argument("--max-iter", type=interface.iterations(), default=2000, help="iterations per waypoint, 1..1e6")
    p.add_argument("--max-steps", type=interface.iterations(), default=20000, help="iterations in all, 1..1e6")
    p.add_argument("--window", type=interface.iterations(), default=300,
                   help="iterations without progress before giving up, 1..1e6")
    p.add_argument("--repeats", type=interface.number(int, 1, REPEATS_MAX), default=1,
                   help=f"timed warm runs (wall_s: their median), 1..{REPEATS_MAX}")
    p.add_argument("--no-figures", action="store_true")
    p.add_argument("--no-mesh", action="store_true", help="skip final.vtu and series.pvd (ParaView)")
    p.check(_other_dimension)
    p.check(_path_of_the_dimension)
    p.check(interface.memory_check("--n", lambda k: k * k, when=lambda a: a.dim == 2))
    return p


def main(argv=None):
    p = parser()
    a = p.parse_args(argv)
    try:
        exp = build(a.path, a.dim, a.integration, a.model or "reduced", a.scheme or "self", a.n or 9, a.alpha,
                    a.beta or 1.0)
    except ValueError as e:
        p.error(f"cannot build the model: {e}")
    results = interface.results("track", a, a.out or f"results/track/{exp.name}")
    with results as out:
        s = run(out, gain=a.gain, clamp=a.clamp, tol=a.tol, max_iter=a.max_iter, max_steps=a.max_steps,
                window=a.window, repeats=a.repeats, make_figures=not a.no_figures,
                mesh_output=not a.no_mesh, experiment=exp)
        results.finish(s, *result(s), a.json)
    return s


# ------------------------------------------------------------------ the experiments of reproduce
def _run(path=None, integration="gauss", dim=2, model="reduced", scheme="self"):
    """(out dir, quick) -> ("track", its options): the experiment's command line."""
    def run(out: Path, quick: bool) -> tuple[str, list]:
        argv = ["--dim", str(dim), "--integration", integration, "--out", str(out)]
        if path:
            argv += ["--path", path]
        if dim == 3:
            argv += ["--model", model, "--scheme", scheme]
        elif quick:
            argv += ["--n", "5"]
        return "track", argv
    return run


def _ours(s):
    return (f"{s['waypoints_reached']}/{s['waypoints_total']} waypoints to 1e-4, max waypoint error "
            f"{s['max_waypoint_error']:.2e}, {s['iterations']} iterations; "
            f"{s['wall_s']:.1f} s warm ({s['first_run_s']:.1f} s with compile) = "
            f"{s['wall_s'] / 60:.3f} min")


def _ours_vs(minutes):
    """Tracking row with the speed-up against the thesis' reported minutes (warm run)."""
    def fmt(s):
        return _ours(s) + f" (thesis / ours: {60 * minutes / max(s['wall_s'], 1e-9):,.0f}x)"
    return fmt


def _ours_3d(s):
    return (f"max error at the waypoints {s['max_waypoint_error']:.2e} "
            f"({s['waypoints_reached']}/{s['waypoints_total']} reached), max path deviation "
            f"{s['max_path_deviation']:.4f}; {s['wall_s']:.1f} s warm")


def _judge(scheme="gauss"):
    """Every waypoint within the tolerance: the thesis' result (with SCNI for its
    collocation: the same result by another scheme)."""
    def judge(s):
        if s["waypoints_reached"] != s["waypoints_total"]:
            return DIFFERS, "stopped"
        return (AGREES if scheme == "gauss" else IN_KIND), ("tolerance" if scheme == "gauss" else "scheme")
    return judge


def _judge_3d(max_error):
    def judge(s):
        if s["waypoints_reached"] != s["waypoints_total"]:
            return DIFFERS, "stopped"
        return (AGREES, "error") if s["max_waypoint_error"] <= max_error else (DIFFERS, "error")
    return judge


GAUSS_TIME = "{m} minutes (section 5.3.2, Gaussian Quadrature)"


def _entries_2d(MIN) -> list:
    return [
        Entry("track_setpoint_gauss", "Fig 5.19", '"within 0.0001 of the desired position"; '
              + GAUSS_TIME.format(m=MIN["gauss"]["setpoint"]), _run("setpoint"),
              _ours_vs(MIN["gauss"]["setpoint"]), quick=True, judge=_judge()),
        Entry("track_setpoint_scni", "Fig 5.20",
              f'"The Collocated model time was approximately {MIN["collocated"]["setpoint"]} minutes"',
              _run("setpoint", "scni"), _ours_vs(MIN["collocated"]["setpoint"]), note=COLL, judge=_judge("scni")),
        Entry("track_box_gauss", "Figs 5.21-5.22 (Table 5.3)", GAUSS_TIME.format(m=MIN["gauss"]["box"]),
              _run("box"), _ours_vs(MIN["gauss"]["box"]), judge=_judge()),
        Entry("track_figure8_gauss", "Figs 5.23-5.24 (Table 5.4)", GAUSS_TIME.format(m=MIN["gauss"]["figure8"]),
              _run("figure8"), _ours_vs(MIN["gauss"]["figure8"]), judge=_judge()),
        Entry("track_line_gauss", "Figs 5.25-5.26 (Table 5.5)", "tracked (no time given)",
              _run("line"), _ours, judge=_judge()),
        Entry("track_box_scni", "Figs 5.27-5.28 (Table 5.3)",
              f'"the Collocated model took {MIN["collocated"]["box"]} ... minutes"',
              _run("box", "scni"), _ours_vs(MIN["collocated"]["box"]), note=COLL, judge=_judge("scni")),
        Entry("track_figure8_scni", "Figs 5.29-5.30 (Table 5.4)", f'"... and {MIN["collocated"]["figure8"]} minutes"',
              _run("figure8", "scni"), _ours_vs(MIN["collocated"]["figure8"]), note=COLL, judge=_judge("scni")),
        Entry("track_line_scni", "Figs 5.31-5.32 (Table 5.5)", "tracked (no time given)",
              _run("line", "scni"), _ours, note=COLL, judge=_judge("scni")),
    ]


def _entries_3d(ERR) -> list:
    return [
        Entry("track3d_reduced", "Fig 5.2 (Table 5.1)", f'"{ERR["reduced"]} for the reduced model object" '
              "(maximum absolute error)", _run(dim=3, model="reduced"), _ours_3d, judge=_judge_3d(ERR["reduced"])),
        Entry("track3d_refined", "Fig 5.6 (Table 5.1)", f'"{ERR["refined"]} for the refined model object"',
              _run(dim=3, model="refined"), _ours_3d, judge=_judge_3d(ERR["refined"])),
        Entry("track3d_reduced_to_refined", "Figs 5.6-5.8 (Table 5.1)", f'"{ERR["refined"]} for the refined model '
              'object" (Jacobian from the reduced model)', _run(dim=3, model="refined", scheme="reduced-to-refined"),
              _ours_3d, judge=_judge_3d(ERR["refined"])),
    ]


def entries() -> list:
    """The 2D paths of section 5.3.2 (Gauss and SCNI) and the 3D cube of Table 5.1."""
    return _entries_2d(TRACKING_MINUTES) + _entries_3d(CUBE_MAX_ERROR)


COMMAND = Command("track", "chapter-5 Jacobian path tracking: 2D paths, the 3D cube of Table 5.1",
                  parser, main, result, order=20, reproduce=entries)

"""Figures in the manner of the thesis: deformed particles coloured by displacement magnitude
(2D, or a projection of 3D), a 3D body's deformed surface coloured by von Mises stress, and
the rigid tools with their contact pressures."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.colors  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection  # noqa: E402

from ..mechanics.contact import ContactTerm  # noqa: E402
from . import output  # noqa: E402

# the thesis' objects are dimensionless: lengths in units of the square's side (the cube's
# edge), forces per unit thickness in units of the material constants times a length
UNITS = "model units"


def _colorbar(ax, mappable, label: str):
    """A colour bar beside ``ax`` saying what the colours mean."""
    return ax.figure.colorbar(mappable, ax=ax, label=label, shrink=0.8)


def deformed_particles(ax, X, u, title=None, vmax=None, cmap="viridis", size=30, show_reference=True,
                       colorbar: bool = True):
    """Scatter the deformed particles x = X + u (2D, or the x-z projection in 3D),
    coloured by |u|, with a colour bar (``colorbar=False``: none, e.g. where several axes
    share one). Returns the scatter artist."""
    X, u = np.asarray(X), np.asarray(u)
    x = X + u
    mag = np.linalg.norm(u, axis=1)
    i, j = (0, 1) if X.shape[1] == 2 else (0, 2)
    if show_reference:
        ax.scatter(X[:, i], X[:, j], s=size / 3, facecolors="none", edgecolors="0.75", lw=0.6,
                   label="reference")
    sc = ax.scatter(x[:, i], x[:, j], c=mag, s=size, cmap=cmap, vmin=0, vmax=vmax,
                    edgecolors="k", linewidths=0.3, label="deformed")
    ax.set_aspect("equal")
    ax.set_xlabel(f"x ({UNITS})")
    ax.set_ylabel(f"{'xyz'[j]} ({UNITS})")
    if title:
        ax.set_title(title)
    if colorbar:
        _colorbar(ax, sc, f"|u| ({UNITS})")
    return sc


def save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def deformed_surface(ax, model, sol, *, norm=None, cmap="viridis", show_reference=True, colorbar: bool = True):
    """Draw a solved 3D body on the mplot3d axes ``ax``: the surface of its viewing cells
    (:func:`jaxrkpm.io.output.body_cells`) at the deformed particles X + u, each face coloured by
    the mean von Mises (Cauchy) stress of its vertices, and the reference surface's edges
    faint, and a colour bar (``colorbar=False``: none). Sets equal aspect over both. Returns
    the face collection."""
    if model.dim != 3:
        raise ValueError(f"deformed_surface draws 3D bodies, this model is {model.dim}D: "
                         "use deformed_particles for 2D")
    X = np.asarray(model.body.X, float)
    fields = output.point_fields(model, sol)
    x = X + fields["displacement"]
    faces = output.surface_faces(*output.body_cells(model.body))
    value = fields["von_mises"][faces].mean(axis=1)
    norm = norm or matplotlib.colors.Normalize(0.0, max(float(value.max()), 1e-300))
    polys = Poly3DCollection(x[faces], cmap=cmap, norm=norm, edgecolors=(0, 0, 0, 0.35), linewidths=0.3)
    polys.set_array(value)
    ax.add_collection3d(polys)
    if show_reference:   # drawn after (over) the body: a faint wireframe of where it was
        ax.add_collection3d(Line3DCollection(X[feature_edges(X, faces)], colors=(0, 0, 0, 0.3),
                                             linewidths=0.8, linestyles="--", zorder=polys.get_zorder() + 1))
    both = np.concatenate([X, x])
    lo, hi = both.min(axis=0), both.max(axis=0)
    pad = 0.02 * float((hi - lo).max())
    ax.set(xlim=(lo[0] - pad, hi[0] + pad), ylim=(lo[1] - pad, hi[1] + pad),
           zlim=(lo[2] - pad, hi[2] + pad))
    ax.set_box_aspect(hi - lo + 2 * pad)
    tidy_3d_axes(ax)
    if colorbar:
        _colorbar(ax, polys, "von Mises (Cauchy) stress")
    return polys


def contact_pressures(ax, model, sol, params=None, *, cmap="magma", vmax=None, colorbar: bool = True):
    """Draw the rigid tools (``jaxrkpm.Contact``) of a solved model at the poses in ``params``
    (the solve's) and their contact: in 2D each tool's outline, filled grey where it is solid,
    and the active contact points at their deformed positions coloured by the contact
    pressure, with arrows of the tool's force on each point; in 3D (mplot3d axes) the
    deformed particles faint and the active points coloured by pressure (the tools' surfaces
    are not drawn), the axes fitted to the body. A colour bar of the pressure
    (``colorbar=False``: none). Returns the scatter of the last tool with active points, or
    None."""
    problem = model.problem(params)
    tools = [t for t in problem.terms if isinstance(t, ContactTerm)]
    if not tools:
        raise ValueError("this model has no rigid tool: add jaxrkpm.Contact(...) to its terms")
    d, load = model.coefficients(sol), np.asarray(sol.load, float)
    X = np.asarray(model.body.X, float)
    x = X + np.asarray(model.particle_displacements(sol))
    lo, hi = np.minimum(X.min(0), x.min(0)), np.maximum(X.max(0), x.max(0))
    span = float((hi - lo).max())
    res = [(t, t.results(d, load)) for t in tools]
    vmax = vmax or max(float(np.max(np.asarray(r.pressure))) for _, r in res) or 1.0
    sc = None
    for t, r in res:
        draw = _tool_2d if model.dim == 2 else _tool_3d
        drawn = draw(ax, t, r, load, lo - 0.25 * span, hi + 0.25 * span, cmap, vmax)
        sc = sc if drawn is None else drawn
    if model.dim == 2:
        ax.set_xlim(lo[0] - 0.25 * span, hi[0] + 0.25 * span)
        ax.set_ylim(lo[1] - 0.25 * span, hi[1] + 0.25 * span)
        ax.set_aspect("equal")
    else:
        _fit_3d(ax, x, lo, hi, span)
    if colorbar and sc is not None:
        _colorbar(ax, sc, "contact pressure")
    return sc


def _tool_3d(ax, t, r, load, lo, hi, cmap, vmax):
    """A 3D tool's active points coloured by pressure (its surface is not drawn); their
    scatter, or None."""
    on = np.asarray(r.active)
    pts, p = np.asarray(r.points)[on], np.asarray(r.pressure)[on]
    if not len(pts):
        return None
    return ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=p, s=30, cmap=cmap, vmin=0, vmax=vmax,
                      edgecolors="k", linewidths=0.3, depthshade=False)


def _tool_2d(ax, t, r, load, lo, hi, cmap, vmax):
    """A 2D tool's outline, filled grey where it is solid (its gap sampled over the box lo,
    hi), and its active points with their forces; the points' scatter, or None."""
    on = np.asarray(r.active)
    g = np.linspace(lo, hi, 160)
    G = np.stack(np.meshgrid(g[:, 0], g[:, 1], indexing="ij"), -1)
    sdf = np.asarray(t.gaps(G.reshape(-1, 2), load)).reshape(G.shape[:2])
    ax.contourf(G[..., 0], G[..., 1], sdf, levels=[sdf.min() - 1.0, 0.0], colors=["0.8"], zorder=0)
    ax.contour(G[..., 0], G[..., 1], sdf, levels=[0.0], colors="0.3", linewidths=1.0, zorder=1)
    pts, p = np.asarray(r.points)[on], np.asarray(r.pressure)[on]
    if not len(pts):
        return None
    f = np.asarray(r.point_force)[on]
    ax.quiver(pts[:, 0], pts[:, 1], f[:, 0], f[:, 1], color="0.2", width=0.003, zorder=3)
    return ax.scatter(pts[:, 0], pts[:, 1], c=p, s=12, cmap=cmap, vmin=0, vmax=vmax, zorder=4)


def _fit_3d(ax, x, lo, hi, span):
    """The deformed body faint for context, and the axes fitted to it (mplot3d does not
    autoscale to a scatter added alone, which left the points outside the view)."""
    ax.scatter(x[:, 0], x[:, 1], x[:, 2], s=4, color="0.6", alpha=0.4, depthshade=False)
    pad = 0.05 * span
    ax.set(xlim=(lo[0] - pad, hi[0] + pad), ylim=(lo[1] - pad, hi[1] + pad), zlim=(lo[2] - pad, hi[2] + pad))
    ax.set_box_aspect(hi - lo + 2 * pad)


def tidy_3d_axes(ax, units: str = UNITS, ticks: int = 4):
    """Readable mplot3d axes: at most ``ticks`` ticks per axis (the default crowds a short
    axis until its labels collide), small tick labels, and the axis labels with units set
    off from them."""
    from matplotlib.ticker import MaxNLocator
    for axis, name in ((ax.xaxis, "x"), (ax.yaxis, "y"), (ax.zaxis, "z")):
        axis.set_major_locator(MaxNLocator(ticks))
        axis.set_tick_params(labelsize=7, pad=0)
        axis.set_label_text(f"{name} ({units})", fontsize=8)
        axis.labelpad = 2


def feature_edges(X, faces, angle: float = 30.0) -> np.ndarray:
    """(E, 2) vertex pairs of the surface edges where the faces meet at more than ``angle``
    degrees (a box's 12 edges; the outline of a body), and of open edges."""
    nrm = np.cross(X[faces[:, 1]] - X[faces[:, 0]], X[faces[:, 2]] - X[faces[:, 0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    edges = np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    owner = np.repeat(np.arange(len(faces)), faces.shape[1])
    key = np.sort(edges, axis=1)
    order = np.lexsort(key.T[::-1])
    key, owner = key[order], owner[order]
    same = np.all(key[1:] == key[:-1], axis=1)                  # consecutive pairs: shared edges
    shared = np.flatnonzero(same)
    bent = np.einsum("ij,ij->i", nrm[owner[shared]], nrm[owner[shared + 1]]) < np.cos(np.radians(angle))
    counts = np.diff(np.flatnonzero(np.r_[True, ~same, True]))  # run length of each distinct edge
    first = np.flatnonzero(np.r_[True, ~same])
    return np.concatenate([key[shared[bent]], key[first[counts == 1]]])


def deformed_body_png(path, model, sol, *, title=None, stress_unit=None, view=(24, -55)) -> str:
    """PNG of a solved 3D body (:func:`deformed_surface`) with a von Mises colour bar labelled
    in ``stress_unit`` (default: the units of the material constants, in which the model's
    stresses come). ``view`` = (elevation, azimuth) in degrees. Returns the path."""
    fig = plt.figure(figsize=(7.0, 5.6))
    ax = fig.add_subplot(projection="3d", computed_zorder=False)   # the reference wireframe on top
    polys = deformed_surface(ax, model, sol, colorbar=False)
    ax.view_init(*view)
    unit = stress_unit or "units of the material constants"
    fig.colorbar(polys, ax=ax, shrink=0.7, pad=0.1, label=f"von Mises (Cauchy) stress ({unit})")
    if title:
        ax.set_title(title, fontsize=10)
    save(fig, path)
    return str(path)

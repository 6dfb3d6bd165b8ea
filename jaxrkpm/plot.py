"""Figures in the manner of the thesis: deformed particles coloured by displacement magnitude."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

# the thesis' objects are dimensionless: lengths in units of the square's side (the cube's
# edge), forces per unit thickness in units of the material constants times a length
UNITS = "model units"


def deformed_particles(ax, X, u, title=None, vmax=None, cmap="viridis", size=30, show_reference=True):
    """Scatter the deformed particles x = X + u (2D, or the x-z projection in 3D),
    coloured by |u|. Returns the scatter artist (for a colour bar)."""
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
    return sc


def save(fig, path):
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)

"""The thesis' data and reference values, each defined once, with where it comes from (NumPy
only: the command line reads them without loading JAX).

Paths: :data:`PATHS` (Tables 5.3-5.5 and the set point), :data:`TABLE_5_1`; the needle
phantom's paddle positions and inclusions (:data:`TABLE_6_2`, :data:`INCLUSIONS`); the
numbers the thesis reports, which the studies and ``jaxrkpm reproduce`` compare with.
"""
from __future__ import annotations

import numpy as np


# ================================================================== chapter 5: planar square
# section 5.2 / 5.3.2: the unit square, left edge immobile, the paddle on the right edge
# around (1, 0.5), the control point at the centre (the 9x9 grid: spacing 0.125)
CP_2D = np.array([[0.5, 0.5]])

PADDLE_HALF_WIDTH = 0.125   # |y - 0.5| <= 0.125: the three particles nearest (1, 0.5) at 9x9

# ================================================================== chapter 5: the 3D cube
# section 5.3.1: x in [-2.5, -1.5], y in [-0.5, 0.5], z in [1.5, 2.5]; face x = -1.5
# immobile, the paddle on face x = -2.5, the control point at the top centre (-2, 0, 2.5)
CP_3D = np.array([[-2.0, 0.0, 2.5]])

CUBE_ORIGIN = (-2.5, -0.5, 1.5)

CUBES = {"reduced": (3, 0.5), "refined": (5, 0.25)}   # particles per side, spacing

# ================================================================== chapter 5: paths
PATHS = {
    # control point displacements (chapter 5); the set point goes (0,0) -> (0.05,0.05) (Fig 5.19)
    "setpoint": [[0.0, 0.0], [0.05, 0.05]],
    "box": [[0.00, 0.00], [0.00, 0.01], [0.00, 0.02], [0.00, 0.03], [0.00, 0.04], [0.01, 0.04],
            [0.02, 0.04], [0.03, 0.04], [0.04, 0.04], [0.04, 0.03], [0.04, 0.02], [0.04, 0.01],
            [0.04, 0.00], [0.03, 0.00], [0.02, 0.00], [0.01, 0.00], [0.00, 0.00]],     # Table 5.3
    "figure8": [[0.00, 0.00], [0.01, 0.01], [0.01, 0.02], [0.00, 0.03], [-0.01, 0.02], [-0.01, 0.01],
                [0.00, 0.00], [0.01, -0.01], [0.01, -0.02], [0.00, -0.03], [-0.01, -0.02],
                [-0.01, -0.01]],                                                         # Table 5.4
    "line": [[0.01 * i, 0.0] for i in range(16)],                                        # Table 5.5
}

# Table 5.1: control point positions of the 3D cube (object coordinates)
TABLE_5_1 = [[-2.0, 0.0, 2.5], [-2.0, 0.0, 2.7], [-2.2, 0.0, 2.7], [-2.3, 0.0, 2.9],
             [-2.5, 0.0, 2.9], [-2.6, 0.0, 3.0]]

# ================================================================== chapter 5: reference values
# section 5.3.1 (Figs 5.2 and 5.6): maximum absolute control point error along Table 5.1
CUBE_MAX_ERROR = {"reduced": 0.049859, "refined": 0.090322}

# section 5.3.2: tracking run times in minutes, Gaussian quadrature and collocated models
# (set point: Figs 5.19/5.20; box: Figs 5.21/5.27; figure 8: Figs 5.23/5.29)
TRACKING_MINUTES = {"gauss": {"setpoint": 75, "box": 625, "figure8": 412},
                    "collocated": {"setpoint": 6, "box": 38, "figure8": 25}}

# section 5.2: compression (fraction of the side) at which the model breaks down:
# Gauss straight 43% (Figs 5.10-5.12), shear 50% (Figs 5.13-5.16; Fig 5.16 shows 58%, 59%),
# collocated straight 15% (Fig 5.17) and shear 14% (Fig 5.18)
COMPRESSION_BREAKDOWN = {("straight", "gauss"): 0.43, ("shear", "gauss"): 0.50,
                         ("straight", "collocated"): 0.15, ("shear", "collocated"): 0.14}

# section 5.3.2: the rig's controller model, Fung alpha = 1 with beta tuned by hand to 0.02,
# and the physical control point settling within 1 mm of the target (Figs 5.33, 5.35)
RIG_MODEL_BETA = 0.02

RIG_SETTLE_MM = 1.0

# ================================================================== chapter 6: needle phantom
# Figure 6.1: the phantom's outline, the unit square with the corner x + y < 0.5 cut away
PHANTOM_OUTLINE = ((0.5, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.5))

# Table 6.2: paddle position index -> the two boundary particles it covers (Fig 6.1 phantom)
TABLE_6_2 = (((0.4, 0.1), (0.3, 0.2)),
             ((0.3, 0.2), (0.2, 0.3)),
             ((0.2, 0.3), (0.1, 0.4)),
             ((0.1, 0.4), (0.0, 0.5)),
             ((0.0, 0.5), (0.0, 0.6)))

# section 6.3.1: inclusions given by the four nodes at their corners, (x range, y range);
# the stiffness (x100) is carried by those nodes, i.e. by their cells (half a spacing around)
INCLUSIONS = {"none": None, "right": ((0.6, 0.7), (0.3, 0.4)), "left": ((0.3, 0.4), (0.4, 0.5))}

# ================================================================== beyond the thesis: 3D phantom
# Chapter 6 lifted to 3D (:class:`jaxrkpm.thesis.phantom3d.Phantom3D`; our choices, not the thesis'):
# a half-ellipsoid "breast" on the chest wall z = 0 (held fixed: "base"), a horizontal needle
# entering through the skin from x < 0 along +x on the line y = 0, z = 0.3 (in the plane of
# symmetry, so with no paddle the target leaves the line only vertically: the fixed base plays
# the 2D phantom's immobile edge), a probe of radius 0.1 (resolved by the mesh: the no-paddle
# deviation converges with it), the target at 40% of the needle's chord through the phantom
# (as the thesis' target at 40% of the height). Paddle patches: centres on an angle grid of the upper skin,
# theta (polar angle from the top) x phi (azimuth from +x), over the target's side of the
# dome top (theta <= 0.45: clear of the needle entry and the base); a patch is a compression paddle's
# contact, ~0.5 in radius (smaller patches barely move the target: 4 particles at spacing
# 0.25 cut the deviation at most 2x).
PHANTOM_3D = {
    "semi_axes": (1.0, 0.8, 0.6),
    "needle_point": (0.0, 0.0, 0.3),  # a point of the needle line: in the symmetry plane y = 0
    "needle_axis": (1.0, 0.0, 0.0),   # its direction
    "target_depth": 0.4,              # fraction of the chord from the entry
    "needle_length": 0.3,             # the needle particles: near the first 0.3 of the track
    "needle_radius": 0.1,             # the needle's physical radius (a probe: resolved by the mesh)
    "track_spacing": 0.1,             # mesh size along the needle's lines
    "insertion": 0.12,                # needle advance (absolute; 6.5% of the chord)
    # patch centres over the target's half of the dome top (the target lies under the skin
    # point theta ~0.17, phi = pi), clear of the needle entry (theta ~1.05, phi = pi): the
    # tissue above the target is what a paddle must restrain (experiments/phantom3d_patch_grid.py
    # compares the best patch's reduction of the deviation on this grid and others)
    "theta": (0.1, 0.45, 4),          # polar angles (lo, hi, count)
    "phi": (0.4 * np.pi, 1.6 * np.pi, 5),   # azimuths (lo, hi, count; pi included): 4 x 5 = 20 patches
    "patch_radius": 0.5,              # a paddle patch: the skin within ~0.5 of its centre
}

# inclusions (x100 stiffness): balls (centre offset from the target, radius) beside the target,
# off the needle line, as the squares of section 6.3.1 beside the 2D target
INCLUSIONS_3D = {"none": None, "side": ((0.0, 0.25, 0.0), 0.15), "above": ((0.0, 0.0, 0.22), 0.15)}

NEEDLE = {
    # section 6.3 (Figs 6.2-6.3): target deviation with no paddle at 15% insertion
    "no_paddle_deviation": 0.0307454,
    # Figs 6.3-6.5 (section 6.3.1): best static paddle (Table 6.2 index) per inclusion
    "best_static": {"none": 4, "right": 2, "left": 1},
    # Table 6.3: controllability delta x_min per paddle 1-5 (no inclusion, inclusion right)
    "controllability": {"none": (4.7822, 4.1544, 3.2715, 3.3748, 3.3999),
                        "right": (6.3556, 5.3583, 4.8749, 5.4552, 5.9523)},
    # Table 6.3, Fig 6.6: the most controllable paddle (no inclusion), used by the dynamic run
    "most_controllable": 3,
}

"""The 3D needle-insertion phantom: thesis chapter 6 lifted to a half-ellipsoid.

A half-ellipsoid "breast" (semi-axes a, b, c; :data:`jaxrkpm.thesis.data.PHANTOM_3D`) sits on the
chest wall z = 0, which holds its flat face fixed ("base"). A straight needle enters through
the skin (by default from x < 0 along +x in the symmetry plane y = 0, 0.3 above the chest
wall; ``needle_point``, ``needle_axis``) and is modelled, as in 2D, by the particles of the
first ``needle_length`` of its track, translated along the needle by the insertion depth.
The needle has a physical radius (``needle_radius``): the mesh conforms to its axis and to
four lines on its surface (gmsh embedding, ``tracks``), so the loaded region is the same
cylinder at every mesh spacing and the no-paddle deviation converges with the mesh (it did
not while the needle was "the particles within a multiple of the spacing of the track").
With the needle in y = 0 the mesh is mirror-symmetric, so the no-paddle deviation is purely
vertical (the fixed base plays the 2D phantom's immobile edge), not polluted by mesh
asymmetry. The target lies on the needle line at ``target_depth`` of the chord (a particle
sits on it); its lateral deviation (its displacement across the needle) is what a paddle
must prevent.

Paddle positions: contact patches = the ``patch_size`` skin particles nearest to centres on
an angle grid (theta, phi) of the accessible skin over the target (the dome's top on the
needle's side, clear of the needle entry): the same size for all, so the patch models stack
into one batch and the static sweep of ``jaxrkpm.thesis.needle`` runs every patch x every increment
in one compiled call. The continuous paddle of the optimiser is one discrete patch's contact
points (``paddle_footprint``, ``with_footprint``) as stiff zero-length springs, carried
rigidly over the skin by the same two angles (``paddle_points``), movable through
``Model.springs_at``: at that patch's centre it is the held patch again, so
``jaxrkpm.thesis.needle.optimize_paddle`` (Adam through the solve) compares like with like.

Everything the generic needle functions need comes from :class:`jaxrkpm.thesis.needle.NeedleTrack`
(needle direction, lateral basis y-z); ``insert``, ``static_sweep``, ``dynamic_paddle``,
``spring_insertion`` and ``optimize_paddle`` run on this phantom unchanged.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import jax.numpy as jnp
import numpy as np

from ..mechanics.loads import Springs
from ..discretise.body import Body
from ..mechanics.materials import NeoHookean
from ..model.model import Model
from .needle import TISSUE_LAWS, TISSUE_POISSON, NeedleTrack, tissue_material
from .data import INCLUSIONS_3D, PHANTOM_3D

__all__ = ["Phantom3D", "ellipsoid_point", "ball_field", "MATERIALS_3D"]

# the material laws the phantom offers (Phantom3D.material_law); see Phantom3D for the choice
# "neo-hookean" (default): nearly incompressible tissue, nu = 0.45; "neohookean": the
# compressible neo-Hookean solid (lam = 4, mu = 1: nu = 0.4) the phantom had before
MATERIALS_3D = ("neo-hookean", "neohookean", "fung", "fung-barrier")
assert set(TISSUE_LAWS) <= set(MATERIALS_3D)


def _is_number(v) -> bool:
    """A finite real number (not a bool, not a string)."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) \
        and bool(np.isfinite(v))


def ellipsoid_point(semi_axes, theta, phi, scale=1.0):
    """The point at polar angle theta (from +z) and azimuth phi (from +x) on the ellipsoid
    (x/a)^2 + (y/b)^2 + (z/c)^2 = scale^2: (..., 3), JAX (differentiable in the angles)."""
    a, b, c = semi_axes
    s = jnp.sin(theta)
    return scale * jnp.stack([a * s * jnp.cos(phi), b * s * jnp.sin(phi), c * jnp.cos(theta) * jnp.ones_like(phi)], -1)


# the material constants a model of the phantom may take in place of the phantom's own
# (``Phantom3D.material``; a 3D sweep's optional columns)
MATERIAL_VALUES = ("stiffness_ratio", "mu", "nu", "lam", "alpha", "beta")


def _ones(X):
    """X (Q, 3) -> (Q,) ones: the factor of a material without an inclusion, as a field."""
    return np.ones(len(np.asarray(X)))


def ball_field(centre, radius: float, ratio: float):
    """X (Q, 3) -> (Q,): ``ratio`` inside the ball, 1 outside (an inclusion as data)."""
    centre = np.asarray(centre, float)

    def factor(X):
        return np.where(np.linalg.norm(np.asarray(X) - centre, axis=1) <= radius, ratio, 1.0)
    return factor


@dataclass(frozen=True)
class Phantom3D(NeedleTrack):
    """The half-ellipsoid phantom (defaults: :data:`jaxrkpm.thesis.data.PHANTOM_3D`).

    spacing        mesh size of the tetrahedral mesh (particles at its vertices)
    needle_radius  the needle's physical radius: its particles are those within
                   needle_radius of the first ``needle_length`` of the track; the mesh
                   conforms to the axis and four lines on the needle's surface (``tracks``)
    track_spacing  mesh size along those lines (default ``spacing``); a particle sits on
                   the target
    patch_radius   a paddle patch: the skin near its centre (see ``patch_size``)
    paddle_footprint  the patch (1-based) whose contact points form the continuous paddle
                   (``paddle_points``): start the optimiser there (``with_footprint``)
    material_law   "neo-hookean" (default: nearly incompressible neo-Hookean tissue, shear
                   modulus ``mu``, Poisson's ratio ``nu`` = 0.45), "neohookean" (compressible,
                   ``lam`` and ``mu``: ν = 0.4), "fung" (chapter 6's law
                   with the 3D Table 5.2 pattern) or "fung-barrier" (the same with the
                   volumetric barrier); see ``material``
    mu, lam, nu    neo-Hookean constants; alpha, beta the Fung ones
    integration    "gauss" (Gauss points on the tetrahedra, ``order`` per direction: 1 = one
                   point per tetrahedron, half the cost of order 2 with the same
                   convergence at every increment) or "scni"/"mscni"
    """

    semi_axes: tuple = PHANTOM_3D["semi_axes"]
    spacing: float = 0.2
    needle_point: tuple = PHANTOM_3D["needle_point"]
    needle_axis: tuple = PHANTOM_3D["needle_axis"]
    target_depth: float = PHANTOM_3D["target_depth"]
    needle_length: float = PHANTOM_3D["needle_length"]
    needle_radius: float = PHANTOM_3D["needle_radius"]
    track_spacing: float | None = PHANTOM_3D["track_spacing"]
    insertion: float = PHANTOM_3D["insertion"]
    theta: tuple = PHANTOM_3D["theta"]
    phi: tuple = PHANTOM_3D["phi"]
    patch_radius: float = PHANTOM_3D["patch_radius"]
    paddle_footprint: int = 1
    stiffness_ratio: float = 100.0
    material_law: str = "neo-hookean"
    mu: float = 1.0
    lam: float = 4.0
    nu: float = TISSUE_POISSON
    alpha: float = 1.0
    beta: float = 1.0
    support: float = 2.0
    integration: str = "gauss"
    order: int = 1
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self):
        self._check_line()
        self._check_lengths()
        if self.material_law not in MATERIALS_3D:
            raise ValueError(f"unknown material_law {self.material_law!r}: choose {list(MATERIALS_3D)}")
        self._check_needle_radius()
        self._check_patches()

    def _check_line(self):
        """The phantom's semi-axes, and a needle line that crosses it above the base."""
        a = np.asarray(self.semi_axes, float)
        if a.shape != (3,) or not np.all(np.isfinite(a) & (a > 0)):
            raise ValueError(f"semi_axes must be three positive lengths, got {self.semi_axes}")
        axis = np.asarray(self.needle_axis, float)
        if axis.shape != (3,) or not np.isfinite(axis).all() or np.linalg.norm(axis) == 0:
            raise ValueError(f"needle_axis must be a non-zero 3-vector, got {self.needle_axis}")
        if self._crossing() is None:
            raise ValueError(f"the needle line through {self.needle_point} along {self.needle_axis} "
                             "must cross the phantom above the base (z > 0)")

    def _check_lengths(self):
        """Positive needle length, stiffness ratio and insertion, a target depth inside the
        chord, and a needle that stops short of the target."""
        if not (_is_number(self.needle_length) and self.needle_length > 0):
            raise ValueError(f"needle_length must be a positive length (the needle's part inside the "
                             f"phantom, whose particles it moves), got {self.needle_length!r}")
        if not (_is_number(self.stiffness_ratio) and self.stiffness_ratio > 0):
            raise ValueError(f"stiffness_ratio must be a positive factor (the inclusion's stiffness over "
                             f"the phantom's), got {self.stiffness_ratio!r}")
        if not 0 < self.target_depth < 1:
            raise ValueError(f"target_depth must be a fraction of the chord in (0, 1), got {self.target_depth}")
        if not (np.isfinite(self.insertion) and self.insertion > 0):
            raise ValueError(f"insertion must be a positive depth, got {self.insertion}")
        if self.needle_length + self.insertion >= self.target_depth * self.chord:
            raise ValueError(f"the needle (length {self.needle_length} + insertion {self.insertion}) "
                             f"would reach the target at {self.target_depth * self.chord:.3f} along the track")

    def _check_needle_radius(self):
        """A positive needle radius whose surface lines all cross the phantom."""
        if not (_is_number(self.needle_radius) and self.needle_radius > 0):
            raise ValueError(f"needle_radius must be a positive length, got {self.needle_radius!r}")
        for e in self.lateral:
            for sign in (1, -1):
                if self._line_crossing(self.entry + sign * self.needle_radius * e) is None:
                    raise ValueError(f"needle_radius {self.needle_radius:g} is too large for the phantom: the "
                                     f"needle's surface {(sign * e).round(3).tolist()} off its axis misses the "
                                     f"body (semi-axes {tuple(self.semi_axes)}, entry height "
                                     f"{self.entry[2]:.3g} above the base)")

    def _check_patches(self):
        """A positive patch radius and a paddle footprint among the patches."""
        if not (np.isfinite(self.patch_radius) and self.patch_radius > 0):
            raise ValueError(f"patch_radius must be a positive length, got {self.patch_radius}")
        n = len(self.patch_coordinates)
        if isinstance(self.paddle_footprint, bool) or not isinstance(self.paddle_footprint, (int, np.integer)) \
                or not 1 <= self.paddle_footprint <= n:
            raise ValueError(f"paddle_footprint must be a 1-based patch index in 1..{n} (the patch whose "
                             f"particles form the continuous paddle), got {self.paddle_footprint!r}")

    # ----------------------------------------------------------- the needle and target
    def _crossing(self):
        """(t_in, t_out) of the needle line p + t axis inside the half-ellipsoid (the
        ellipsoid cut by the base z = 0), or None if it misses."""
        return self._line_crossing(self.needle_point)

    @property
    def needle_direction(self) -> np.ndarray:
        axis = np.asarray(self.needle_axis, float)
        return axis / np.linalg.norm(axis)

    @property
    def lateral(self) -> np.ndarray:
        """(2, 3) orthonormal rows across the needle: the deviation's components."""
        d = self.needle_direction
        ref = np.eye(3)[np.argmin(np.abs(d))]            # the axis least aligned with the needle
        e1 = np.cross(d, ref)
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(d, e1)])

    @property
    def entry(self) -> np.ndarray:
        """Where the needle line enters the phantom through the skin."""
        return np.asarray(self.needle_point, float) + self._crossing()[0] * self.needle_direction

    @property
    def chord(self) -> float:
        """Length of the needle line inside the phantom."""
        t0, t1 = self._crossing()
        return float(t1 - t0)

    @property
    def target(self) -> tuple:
        return tuple(self.entry + self.target_depth * self.chord * self.needle_direction)

    def _line_crossing(self, point):
        """(t_in, t_out) of the line point + t needle_direction inside the half-ellipsoid,
        or None if it misses."""
        semi = np.asarray(self.semi_axes, float)
        p, d = np.asarray(point, float) / semi, self.needle_direction / semi
        A, B, C = d @ d, 2 * p @ d, p @ p - 1
        disc = B * B - 4 * A * C
        if disc <= 0:
            return None
        t0, t1 = sorted(((-B - np.sqrt(disc)) / (2 * A), (-B + np.sqrt(disc)) / (2 * A)))
        z0, dz = point[2], self.needle_direction[2]
        if abs(dz) > 1e-12:                      # clip to z >= 0
            tb = -z0 / dz
            t0, t1 = (max(t0, tb), t1) if dz > 0 else (t0, min(t1, tb))
        elif z0 <= 0:
            return None
        return (t0, t1) if t1 > t0 else None

    @property
    def tracks(self) -> np.ndarray:
        """(K, 2, 3) the lines the mesh conforms to: the needle's axis, from the skin entry to
        the target, and four lines on its surface (needle_radius off the axis along +-each
        lateral direction) from the skin to the target's cross-section, so the needle is a
        resolved cylinder of its physical radius at every mesh spacing. Each starts half a
        track spacing inside the skin (gmsh cannot mesh a mirror face whose embedded line
        touches its rim). For a mirror-symmetric mesh only the lines on the meshed side
        y >= 0 (the mirror makes the others)."""
        d = self.needle_direction
        end = (np.asarray(self.target) - self.entry) @ d
        inset = 0.5 * (self.track_spacing or self.spacing)
        out = []
        for offset in [np.zeros(3), *(s * self.needle_radius * e for e in self.lateral for s in (1, -1))]:
            if self.mirror_symmetric and offset[1] < -1e-12:
                continue
            point = self.entry + offset
            t_in, _ = self._line_crossing(point)
            out.append([point + (t_in + inset) * d, point + end * d])
        return np.asarray(out)

    @property
    def mirror_symmetric(self) -> bool:
        """Whether the needle line lies in the phantom's symmetry plane y = 0: then the mesh is
        made mirror-symmetric about it, so the no-paddle deviation has no sideways part from
        mesh asymmetry (only the vertical one the fixed base causes)."""
        return abs(self.needle_point[1]) < 1e-12 and abs(self.needle_direction[1]) < 1e-12

    # ------------------------------------------------------------------ geometry
    def mesh(self):
        """The tetrahedral half-ellipsoid (gmsh, at ``spacing``) conforming to the needle's
        lines (``tracks``), mirror-symmetric when the needle lies in y = 0: a meshio.Mesh."""
        from ..discretise import surface
        return surface.half_ellipsoid(self.semi_axes, self.spacing, embed_segments=self.tracks,
                                      segment_spacing=self.track_spacing,
                                      symmetric="y" if self.mirror_symmetric else None)

    @property
    def body(self) -> Body:
        """The phantom's mesh (``mesh``) as a particle body."""
        if "body" not in self._cache:
            self._cache["body"] = Body.from_mesh(self.mesh())
        return self._cache["body"]

    def level(self, X) -> np.ndarray:
        """(P,) the ellipsoid's level sqrt((x/a)^2 + (y/b)^2 + (z/c)^2): 1 on the skin."""
        return np.linalg.norm(np.asarray(X, float) / np.asarray(self.semi_axes, float), axis=-1)

    @property
    def base(self) -> np.ndarray:
        """Particles on the flat face z = 0 (the mesh's "base" group: held by the chest wall)."""
        return self.body.tagged("base")

    @property
    def needle(self) -> np.ndarray:
        """Particles within needle_radius of the first needle_length of the axis: those on the
        needle's axis and its four surface lines (``tracks``), and any between."""
        tip = self.entry + self.needle_length * self.needle_direction
        idx = np.setdiff1d(self.body.near_segment(self.entry, tip, self.needle_radius * (1 + 1e-9)), self.base)
        if len(idx) < 2:
            raise ValueError(f"only {len(idx)} particle(s) on the needle's first {self.needle_length}: "
                             f"refine the track (track_spacing {self.track_spacing}, spacing {self.spacing})")
        return idx

    @property
    def skin(self) -> np.ndarray:
        """Particles on the curved surface (the mesh's "skin" group), off the base and the needle."""
        return np.setdiff1d(self.body.tagged("skin"), np.concatenate([self.base, self.needle]))

    @property
    def patch_coordinates(self) -> np.ndarray:
        """(P, 2) the (theta, phi) of the patch centres: the angle grid of ``theta`` x ``phi``."""
        t = np.linspace(*self.theta[:2], int(self.theta[2]))
        p = np.linspace(*self.phi[:2], int(self.phi[2]))
        return np.stack(np.meshgrid(t, p, indexing="ij"), -1).reshape(-1, 2)

    @property
    def paddles(self) -> np.ndarray:
        """(P, 3) the patch centres on the skin."""
        q = self.patch_coordinates
        return np.asarray(ellipsoid_point(self.semi_axes, q[:, 0], q[:, 1]))

    @property
    def patch_size(self) -> int:
        """Particles per patch: the fewest skin particles within ``patch_radius`` of any
        centre (the same for every patch, so the patch models stack into one batch; each
        patch is then the patch_size skin particles nearest its centre)."""
        if "patch_size" not in self._cache:
            X = self.body.X[self.skin]
            counts = [int(np.sum(np.linalg.norm(X - c, axis=1) <= self.patch_radius)) for c in self.paddles]
            if min(counts) < 3:
                raise ValueError(f"a paddle patch of radius {self.patch_radius} holds only {min(counts)} skin "
                                 f"particle(s) (spacing {self.spacing}): widen patch_radius or refine the mesh")
            self._cache["patch_size"] = min(counts)
        return self._cache["patch_size"]

    def patch(self, paddle: int) -> np.ndarray:
        """Particle indices of paddle patch ``paddle`` (1-based): the patch_size skin
        particles nearest its centre."""
        if isinstance(paddle, (bool, np.bool_)) or not isinstance(paddle, (int, np.integer)):
            raise TypeError(f"paddle must be a 1-based int index into the {len(self.paddles)} patches, "
                            f"got {paddle!r} ({type(paddle).__name__})")
        if not 1 <= paddle <= len(self.paddles):
            raise ValueError(f"paddle index {paddle} out of range 1..{len(self.paddles)}")
        skin = self.skin
        dist = np.linalg.norm(self.body.X[skin] - self.paddles[paddle - 1], axis=1)
        return np.sort(skin[np.argsort(dist, kind="stable")[:self.patch_size]])

    def sets(self, paddle: int | None) -> dict:
        """Essential sets: "base", "needle" and, for a patch index (1-based), "paddle"."""
        out = {"base": self.base, "needle": self.needle}
        if paddle is not None:
            out["paddle"] = self.patch(paddle)
        return out

    # ------------------------------------------------------------------ material, models
    def material(self, inclusion: str = "none", *, as_field: bool = False, **values):
        """The phantom's material, x ``stiffness_ratio`` inside the inclusion ball.

        Nearly incompressible neo-Hookean tissue by default (mu = 1, Poisson's ratio ``nu`` =
        0.45, W = mu/2 (I1bar - 3) + kappa/2 (ln J)^2); ``material_law="neohookean"`` the
        compressible neo-Hookean solid (lam = 4, mu = 1: nu = 0.4);
        ``"fung"`` chapter 6's law with the Table 5.2 pattern extended to 3D (its tensors are
        the 2D thesis' numbers), ``"fung-barrier"`` the same with the volumetric barrier
        (:func:`jaxrkpm.thesis.needle.tissue_material`).

        ``values``: constants in place of the phantom's (any of :data:`MATERIAL_VALUES`, e.g.
        a sweep's row); ``as_field``: the stiffnesses as fields of X also without an inclusion
        (a factor of one), so that the models of every inclusion batch together
        (:class:`jaxrkpm.thesis.sweeps.NeedleSweep3D`)."""
        if inclusion not in INCLUSIONS_3D:
            raise ValueError(f"unknown inclusion {inclusion!r}: choose {list(INCLUSIONS_3D)}")
        unknown = set(values) - set(MATERIAL_VALUES)
        if unknown:
            raise TypeError(f"unknown material value(s) {sorted(unknown)}: choose from {list(MATERIAL_VALUES)}")
        v = {name: values.get(name, getattr(self, name)) for name in MATERIAL_VALUES}
        spec = INCLUSIONS_3D[inclusion]
        factor = None
        if spec is not None:
            offset, radius = spec
            factor = ball_field(np.asarray(self.target) + np.asarray(offset), radius, v["stiffness_ratio"])
        elif as_field:
            factor = _ones
        if self.material_law in TISSUE_LAWS:
            return tissue_material(self.material_law, v["alpha"], v["beta"], factor, nu=v["nu"],
                                   mu=v["mu"] if self.material_law == "neo-hookean" else None)
        if factor is None:
            return NeoHookean(lam=v["lam"], mu=v["mu"])
        return NeoHookean(lam=lambda X: v["lam"] * factor(X), mu=lambda X: v["mu"] * factor(X))

    def model(self, inclusion: str = "none", paddle: int | None = None, *, as_field: bool = False,
              **values) -> Model:
        """The phantom's model with the inclusion and the paddle patch (1-based; None: no
        paddle); ``as_field``, ``values``: its material's (see ``material``), a model built
        anew (the phantom keeps its own models only)."""
        def build():
            return Model(self.body, self.material(inclusion, as_field=as_field, **values), self.integration,
                         essential=self.sets(paddle), support=self.support, order=self.order)
        if as_field or values:
            return build()
        key = ("model", inclusion, paddle)
        if key not in self._cache:
            self._cache[key] = build()
        return self._cache[key]

    # ------------------------------------------------- continuous paddle (the optimiser's)
    def with_footprint(self, patch: int) -> "Phantom3D":
        """This phantom with the continuous paddle made of patch ``patch``'s contact points
        (``paddle_footprint``), sharing the mesh and the models built so far."""
        return replace(self, paddle_footprint=patch, _cache=self._cache)

    @property
    def paddle_bounds(self):
        """(lower (2,), upper (2,)) of the continuous paddle coordinates (theta, phi): the
        azimuths of the patch grid, and polar angles up to the grid's largest on either side
        of the pole (``ellipsoid_point(-t, phi) = ellipsoid_point(t, phi + pi)``, so the
        paddle slides smoothly over the dome's top, where the best patches lie, instead of
        stopping at the grid's first ring)."""
        return np.array([-self.theta[1], self.phi[0]]), np.array([self.theta[1], self.phi[1]])

    def paddle_frame(self, q):
        """(centre (3,), frame (3, 3)) of the paddle at q = (theta, phi): its centre on the
        skin and the rows t_theta, t_phi (unit tangents) and n (the unit outward normal)
        there. JAX: differentiable in q."""
        q = jnp.asarray(q, jnp.float64)
        semi = jnp.asarray(self.semi_axes, jnp.float64)
        theta, phi = q[0], q[1]
        c = ellipsoid_point(self.semi_axes, theta, phi)
        t1 = semi * jnp.stack([jnp.cos(theta) * jnp.cos(phi), jnp.cos(theta) * jnp.sin(phi), -jnp.sin(theta)])
        t1 = t1 / jnp.linalg.norm(t1)
        n = c / semi**2
        n = n / jnp.linalg.norm(n)
        t2 = jnp.cross(n, t1)
        return c, jnp.stack([t1, t2 / jnp.linalg.norm(t2), n])

    def contact_face(self, paddle: int):
        """(centre (3,), outward unit normal (3,), tangents (2, 3), face half extents (2,)) of
        a contact paddle at patch ``paddle`` (``jaxrkpm.thesis.contact_paddle``): a flat square
        face tangent to the skin at the patch centre, inscribed in the patch's circle."""
        self.patch(paddle)            # a clear error for a bad index
        c, frame = (np.asarray(v) for v in self.paddle_frame(self.patch_coordinates[paddle - 1]))
        return c, frame[2], frame[:2], np.full(2, self.patch_radius / np.sqrt(2.0))

    @property
    def footprint(self) -> np.ndarray:
        """(k, 3) the continuous paddle's contact points in its own frame (``paddle_frame``):
        the particles of discrete patch ``paddle_footprint`` relative to that patch's centre."""
        key = ("footprint", self.paddle_footprint)
        if key not in self._cache:
            p = self.paddle_footprint
            c, frame = self.paddle_frame(self.patch_coordinates[p - 1])
            self._cache[key] = (self.body.X[self.patch(p)] - np.asarray(c)) @ np.asarray(frame).T
        return self._cache[key]

    def paddle_points(self, q):
        """(k, 3) the spring points of the continuous paddle at q = (theta, phi): the contact
        points of discrete patch ``paddle_footprint`` carried rigidly with the paddle's frame
        (``paddle_frame``) over the skin. At that patch's centre they are its particles, so
        the spring paddle there is the held patch (to the penalty error O(1/stiffness)): the
        optimiser moves the same contact patch as the discrete sweep holds. JAX:
        differentiable in q."""
        c, frame = self.paddle_frame(q)
        return c + jnp.asarray(self.footprint) @ frame

    def spring_model(self, inclusion: str = "none", stiffness: float = 1e6) -> Model:
        """Base and needle as essential sets; the paddle as stiff zero-length springs at
        ``paddle_points`` (movable through ``model.springs_at``), their region the particles
        whose windows cover the paddle anywhere within ``paddle_bounds``."""
        key = ("spring_model", inclusion, float(stiffness), self.paddle_footprint)
        if key not in self._cache:
            lo, hi = self.paddle_bounds
            grid = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 9), np.linspace(lo[1], hi[1], 17),
                                        indexing="ij"), -1).reshape(-1, 2)
            pts = np.concatenate([np.asarray(self.paddle_points(q)) for q in grid])
            a = self.support * self.spacing
            nb = self.body.neighbours(pts, a)
            region = np.unique(nb.idx[nb.mask])
            # placed first on the footprint patch's own particles (in the body; elsewhere the
            # rigid footprint may stand just off the faceted skin, where the RK fit still holds)
            q0 = self.patch_coordinates[self.paddle_footprint - 1]
            springs = Springs(np.asarray(self.paddle_points(q0)), stiffness, region)
            self._cache[key] = Model(self.body, self.material(inclusion), self.integration,
                                     essential=self.sets(None), support=self.support, order=self.order,
                                     springs=springs)
        return self._cache[key]

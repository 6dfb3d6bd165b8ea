"""Simulated rig closing the thesis' physical loop (section 5.3.2, chapter 4), no hardware.

The "physical" object is a finer RKPM model than the controller's with different material
parameters and an unmodelled stiff inclusion. Its markers (three L-markers on the rigid
clamp, one on the control point) are rendered into synthetic stereo images with pixel
noise by a Bumblebee-like parallel rig at ~0.45 m; the vision pipeline of
:mod:`jaxrkpm.rig.stereo` finds and triangulates the blobs, :mod:`jaxrkpm.rig.frames` maps
them into the object frame (eqs 4.4-4.9), the 9x9 controller model's Jacobian turns the
measured error into a paddle increment (the tracking law of :mod:`jaxrkpm.control.tracking`), and
the increment goes through the robot link (JSON lines over loopback TCP to
:class:`SimulatedRobotServer`, model-side safety limits) to the simulated robot, whose
paddle position then drives the physical object.

Units: the models live on the unit square; ``scale_m`` metres per model unit maps them to
the object frame (metres, origin at the L corner marker, x/y along the L legs, z out of
the object plane). The robot's ``target_m`` is the paddle displacement in that frame
(robot frame = object frame: the registration would come from
:func:`jaxrkpm.rig.frames.arun_registration`). Forces: model force units x ``force_scale_n``.

Per iteration three errors are kept apart (all in the object plane, mm):
physical error = true physical control point - desired; camera error = measured - true;
model mismatch = controller-model prediction at the commanded paddle - true physical.

Corrections (see :mod:`jaxrkpm.thesis.rigsim.calibrate`): :meth:`ClosedLoop.probe` records camera and
force data for calibrating the controller model; ``RigSettings(broyden=True)`` corrects its
Jacobian online from the camera (J = J_model + D, D updated by Broyden on large enough steps).

It imports the solver core (Model, the solve, the control law) and the hardware package
:mod:`jaxrkpm.rig`; neither of those imports it.
"""
from __future__ import annotations

import dataclasses
import itertools
from typing import Callable

import jax.numpy as jnp
import numpy as np

from ... import Fung, Model
from ...base.progress import progress_bar
from ...model.model import SolveError
from ...control.tracking import control_increment
from ...base.outcome import Outcome
from ..data import CP_2D, PADDLE_HALF_WIDTH, RIG_MODEL_BETA
from ..scenarios import planar_square
from .calibrate import Recording, broyden_update
from ...rig.frames import RigidTransform, label_l_markers, object_frame_from_l_markers
from ...rig.link import RobotClient, SafetyError, SafetyLimits, SimulatedRobotServer, LinkError
from ...rig.stereo import ParallelStereo, StereoTracker, render_markers

__all__ = [
    "CONTROL_POINT", "Inclusion", "planar_object", "PhysicalObject", "RigGeometry", "Vision",
    "InProcessRobot", "RigSettings", "RigStatus", "RigRun", "ClosedLoop",
]

CONTROL_POINT = CP_2D[0].copy()   # model coordinates of the control point marker


# ----------------------------------------------------------------------------- objects
@dataclasses.dataclass(frozen=True)
class Inclusion:
    """A disc (model coordinates) whose alpha and beta are ``factor`` times the matrix'."""

    center: tuple = (0.3, 0.7)
    radius: float = 0.15
    factor: float = 10.0

    def field(self, base: float) -> Callable[[np.ndarray], np.ndarray]:
        c, r, f = np.asarray(self.center, float), float(self.radius), float(self.factor)
        return lambda X: np.where(np.linalg.norm(np.asarray(X)[:, :2] - c, axis=1) < r, f * base, base)


def planar_object(n: int = 9, alpha: float = 1.0, beta: float = RIG_MODEL_BETA,
                  paddle_halfwidth: float = PADDLE_HALF_WIDTH, integration: str = "gauss") -> Model:
    """The chapter-5 planar object of the rig (:func:`jaxrkpm.thesis.scenarios.planar_square`): Fung(alpha,
    beta), "wall" = left edge, "paddle" = the right-edge particles with |y - 0.5| <=
    paddle_halfwidth (the same physical contact patch at every resolution: 3 particles at
    9x9, 5 at 17x17)."""
    return planar_square(n, integration, Fung(alpha=alpha, beta=beta), paddle=paddle_halfwidth)


class _Tracked:
    """A model with its paddle driven rigidly, its current equilibrium and cached control
    point shape functions (the Jacobian is the model's implicit one, ``Model.jacobian``)."""

    def __init__(self, model: Model, params: dict | None = None, points=CONTROL_POINT[None]):
        self.model = model
        self.params = dict(params or {})
        self.points = np.atleast_2d(np.asarray(points, float))
        sf = model.shape_functions(self.points, gradients=False)
        self._idx, self._psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
        self.sol = model.initial()
        self.paddle = np.zeros(model.dim)

    def settle(self, paddle) -> None:
        """Equilibrium with the paddle displaced by ``paddle`` (model units) from rest,
        warm-started from the current state (raises SolveError on failure)."""
        p = np.asarray(paddle, float)
        if np.array_equal(p, self.paddle):
            return   # nothing moved (a solve at rest has no force scale to converge against)
        self.sol = self.model.solve({"paddle": jnp.asarray(p)}, params=self.params or None,
                                    initial=self.sol, steps=2)
        self.paddle = p.copy()

    def cp(self) -> np.ndarray:
        """Control point displacement (model units), flattened."""
        return np.asarray(self.model.constraint.point_values(self._idx, self._psi, self.sol.u, self.sol.g)).ravel()

    def jacobian(self) -> np.ndarray:
        """d(control point displacement)/d(paddle translation) at the current equilibrium, (P*d, d)."""
        return np.asarray(self.model.jacobian(self.sol, "paddle", self.points, params=self.params or None))

    def force(self) -> np.ndarray:
        """Force of the object on the paddle (model units): minus the constraint reaction."""
        return -np.asarray(self.model.reaction(self.sol, "paddle", params=self.params or None))


class PhysicalObject(_Tracked):
    """The simulated physical object: a finer grid, its own alpha/beta and an optional stiff
    inclusion (all unknown to the controller)."""

    def __init__(self, n: int = 17, alpha: float = 1.0, beta: float = 0.04,
                 inclusion: Inclusion | None = Inclusion(), paddle_halfwidth: float = PADDLE_HALF_WIDTH):
        model = planar_object(n, alpha, beta, paddle_halfwidth)
        params = {}
        if inclusion is not None:
            Q = model.volume.points
            params = {"alpha": inclusion.field(alpha)(Q), "beta": inclusion.field(beta)(Q)}
        super().__init__(model, params)
        self.n, self.alpha, self.beta, self.inclusion = n, alpha, beta, inclusion

    def describe(self) -> dict:
        inc = None if self.inclusion is None else dataclasses.asdict(self.inclusion)
        return {"grid": f"{self.n}x{self.n}", "alpha": self.alpha, "beta": self.beta, "inclusion": inc,
                "paddle_particles": int(len(self.model.set_indices("paddle")))}


# ----------------------------------------------------------------------------- vision
@dataclasses.dataclass(frozen=True)
class RigGeometry:
    """Where things are. ``l_markers``: model coordinates of the L-markers on the rigid clamp
    (corner V0, x-leg end V1, y-leg end V2: |V2-V0| = 2 |V1-V0| as in the thesis); the object
    frame has its origin at V0. The object plane faces the camera at ``standoff_m``, rolled
    about the optical axis (so no two markers share an image row: Algorithm 2 matches by
    row) and tilted about the image x axis."""

    scale_m: float = 0.2
    standoff_m: float = 0.45
    roll_deg: float = 15.0
    tilt_deg: float = 20.0
    l_markers: tuple = ((-0.5, 0.0), (-0.25, 0.0), (-0.5, 0.5))

    def object_xy(self, model_xy) -> np.ndarray:
        """Model coordinates (n, 2) -> object frame (n, 3) metres (z = 0)."""
        P = (np.atleast_2d(model_xy) - np.asarray(self.l_markers[0])) * self.scale_m
        return np.c_[P, np.zeros(len(P))]

    def model_xy(self, object_m) -> np.ndarray:
        """Object frame (n, 3) metres -> model coordinates (n, 2) (the plane's z dropped)."""
        return np.atleast_2d(object_m)[:, :2] / self.scale_m + np.asarray(self.l_markers[0])

    def camera_from_object(self) -> RigidTransform:
        """Object -> left-camera frame: the object's centre (model (0.25, 0.5), the middle of
        clamp + object) on the optical axis at ``standoff_m``."""
        r, t = np.radians(self.roll_deg), np.radians(self.tilt_deg)
        Rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
        Rx = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
        R = Rx @ Rz
        centre = self.object_xy([[0.25, 0.5]])[0]
        return RigidTransform(R, np.array([0.0, 0.0, self.standoff_m]) - R @ centre)


class Vision:
    """Synthetic stereo camera + the rig's vision pipeline: marker positions (model
    coordinates) -> two noisy 8-bit images -> blobs -> Algorithm-2 row matching ->
    triangulation -> L-marker object frame -> control point in model coordinates.

    Each frame is identified by geometry, not by image order: the three markers whose
    pairwise distances best fit the designed L are the L (labelled by
    :func:`label_l_markers`), the fourth is the control point."""

    def __init__(self, geometry: RigGeometry = RigGeometry(), camera: ParallelStereo | None = None,
                 noise_std: float = 2.0, radius_px: float = 3.0, seed: int = 0, max_retries: int = 3):
        self.geometry = geometry
        self.camera = camera or ParallelStereo.bumblebee_like()
        self.noise_std, self.radius_px = float(noise_std), float(radius_px)
        self.rng = np.random.default_rng(seed)
        self.tracker = StereoTracker(self.camera, 4)
        self.max_retries = int(max_retries)
        self.n_flagged = 0
        L = geometry.object_xy(np.asarray(geometry.l_markers))
        self._l_sides = np.sort([np.linalg.norm(L[i] - L[j]) for i, j in ((0, 1), (0, 2), (1, 2))])
        self._T_cam = geometry.camera_from_object()
        self.last_images = None

    def marker_positions(self, cp_model_xy) -> np.ndarray:
        """(4, 3) camera-frame marker centres: the L (fixed) and the control point marker."""
        g = self.geometry
        pts = np.vstack([g.object_xy(np.asarray(g.l_markers)), g.object_xy(cp_model_xy)])
        return self._T_cam.apply(pts)

    def images(self, cp_model_xy):
        return render_markers(self.marker_positions(cp_model_xy), self.camera, radius_px=self.radius_px,
                              noise_std=self.noise_std, rng=self.rng)

    def split(self, points_m: np.ndarray):
        """Unordered (4, 3) camera points -> (L markers labelled V0, V1, V2; control point)."""
        best, best_cost = None, np.inf
        for trio in itertools.combinations(range(4), 3):
            P = points_m[list(trio)]
            sides = np.sort([np.linalg.norm(P[i] - P[j]) for i, j in ((0, 1), (0, 2), (1, 2))])
            cost = float(np.abs(sides - self._l_sides).max())
            if cost < best_cost:
                best, best_cost = trio, cost
        if best_cost > 0.1 * self._l_sides[0]:
            raise ValueError(f"no three markers form the designed L (closest side mismatch {best_cost:.4g} m)")
        rest = [i for i in range(4) if i not in best][0]
        return label_l_markers(points_m[list(best)]), points_m[rest]

    def measure(self, cp_model_xy) -> np.ndarray:
        """Render the scene with the control point marker at ``cp_model_xy`` (model
        coordinates, the truth) and return what the vision pipeline measures there (2,).
        A flagged frame (missing / extra / ambiguous blobs) is re-grabbed up to
        ``max_retries`` times, then its error is raised."""
        for attempt in range(self.max_retries + 1):
            left, right = self.images(cp_model_xy)
            frame = self.tracker.track(left, right)
            if frame.ok:
                self.last_images = (left, right)
                L, cp = self.split(frame.points_m)
                T = object_frame_from_l_markers(L, leg_ratio=2.0)
                return self.geometry.model_xy(T.apply(cp[None]))[0]
            self.n_flagged += 1
        frame.raise_if_bad()


# ----------------------------------------------------------------------------- robot
class InProcessRobot:
    """The simulated robot without sockets: the same ``move_paddle`` / ``read_pose`` /
    ``read_force`` calls and the same model-side safety checks as :class:`RobotClient`,
    answered by :meth:`SimulatedRobotServer.handle` directly (the protocol, minus TCP)."""

    def __init__(self, server: SimulatedRobotServer, safety: SafetyLimits | None = None):
        self.server, self.safety = server, safety
        self.last_commanded_m = None
        self._id = 0

    def _request(self, op, **fields):
        self._id += 1
        r = self.server.handle({"v": 1, "id": self._id, "op": op, **fields})
        if not r["ok"]:
            raise LinkError(f"{r['code']}: {r['error']}")
        return r

    def move_paddle(self, target_m) -> np.ndarray:
        t = np.asarray(target_m, float)
        if self.safety is not None:
            last = self.last_commanded_m if self.last_commanded_m is not None else self.read_pose()
            self.safety.check(t, last)
        r = self._request("move_paddle", target_m=t.tolist())
        self.last_commanded_m = t.copy()
        return np.asarray(r["position_m"])

    def read_pose(self) -> np.ndarray:
        return np.asarray(self._request("read_pose")["position_m"])

    def read_force(self) -> np.ndarray:
        return np.asarray(self._request("read_force")["force_n"])

    def close(self):
        pass


class _TcpRobot:
    """:class:`RobotClient` with the same small interface as :class:`InProcessRobot`."""

    def __init__(self, client: RobotClient):
        self.client = client

    def move_paddle(self, target_m):
        return self.client.move_paddle(target_m)

    def read_pose(self):
        return self.client.read_pose().position_m

    def read_force(self):
        return self.client.read_force()

    def close(self):
        self.client.close()


# ----------------------------------------------------------------------------- loop
class RigStatus(Outcome):
    """How a :meth:`ClosedLoop.run` ended (an :class:`~jaxrkpm.base.outcome.Outcome`: an int that
    prints as its name, with a message). Summaries write ``status.name``."""

    DONE = 0, "every waypoint reached within tolerance (measured by the camera)"
    ITERATION_CAP = 1, "a waypoint used its max_iter iterations (expected in budget mode)"
    SAFETY_STOP = 2, "the robot link refused a command (workspace or step limit)"
    SOLVE_FAILED = 3, "the controller or the physical model did not converge"
    VISION_FAILED = 4, "no good stereo frame after the retries"


@dataclasses.dataclass(frozen=True)
class RigSettings:
    """Loop settings. ``gain``/``clamp`` as in Algorithm 3 (clamp per paddle component, model
    units); ``tol_m``: measured error at which a waypoint counts as reached; ``max_iter``
    iterations per waypoint (``advance_on_cap``: go on to the next waypoint when spent, the
    fixed-budget mode that exposes Jacobian quality). Broyden: the Jacobian correction
    D (J = J_model + D) is updated only on paddle steps of at least ``broyden_min_step_m``,
    since on smaller ones the camera noise dominates the measured change (Fig 5.34)."""

    gain: float = 0.7
    clamp: float = 0.05
    tol_m: float = 0.3e-3
    max_iter: int = 30
    advance_on_cap: bool = False
    broyden: bool = False
    broyden_min_step_m: float = 2e-3
    workspace_m: float = 0.05
    max_step_m: float = 0.02

    def __post_init__(self):
        for k in ("gain", "clamp", "tol_m", "broyden_min_step_m", "workspace_m", "max_step_m"):
            v = getattr(self, k)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"RigSettings.{k} must be positive, got {v}")
        if self.max_iter < 1:
            raise ValueError(f"RigSettings.max_iter must be >= 1, got {self.max_iter}")


@dataclasses.dataclass
class RigRun:
    """History (model units unless named _mm). Per iteration k (0 = before any move):
    paddle (n, 2), true (n, 2) physical control point displacement, measured (n, 2) by the
    camera, predicted (n, 2) by the controller model, force_n (n, 3) robot force reading,
    waypoint (n,). Per waypoint: reached (W,) iteration (-1 if not within tol), final (W,)
    last iteration spent on it, desired (W, 2)."""

    scale_m: float
    desired: np.ndarray
    paddle: list = dataclasses.field(default_factory=list)
    true: list = dataclasses.field(default_factory=list)
    measured: list = dataclasses.field(default_factory=list)
    predicted: list = dataclasses.field(default_factory=list)
    force_n: list = dataclasses.field(default_factory=list)
    waypoint: list = dataclasses.field(default_factory=list)
    reached: np.ndarray | None = None
    final: np.ndarray | None = None
    status: RigStatus = RigStatus.DONE
    message: str = ""
    broyden_updates: int = 0

    def arrays(self) -> dict:
        return {k: np.asarray(getattr(self, k)) for k in
                ("paddle", "true", "measured", "predicted", "force_n", "waypoint")}

    def _mm(self, a):
        return np.linalg.norm(a, axis=-1) * self.scale_m * 1e3

    @property
    def physical_error_mm(self) -> np.ndarray:
        """(W,) |true - desired| at the last iteration of each waypoint (NaN if never tried)."""
        T = np.asarray(self.true)
        return np.array([self._mm(T[k] - d) if k >= 0 else np.nan for k, d in zip(self.final, self.desired)])

    @property
    def camera_error_mm(self) -> np.ndarray:
        """(W,) |measured - true| there."""
        T, M = np.asarray(self.true), np.asarray(self.measured)
        return np.array([self._mm(M[k] - T[k]) if k >= 0 else np.nan for k in self.final])

    @property
    def mismatch_mm(self) -> np.ndarray:
        """(W,) |controller model prediction - true| there."""
        T, P = np.asarray(self.true), np.asarray(self.predicted)
        return np.array([self._mm(P[k] - T[k]) if k >= 0 else np.nan for k in self.final])

    @property
    def iterations(self) -> int:
        return len(self.paddle) - 1


class ClosedLoop:
    """Vision -> object frame -> controller (model Jacobian, optional Broyden correction) ->
    robot link -> simulated robot -> physical object, one iteration at a time.

    ``transport``: "tcp" (a :class:`SimulatedRobotServer` thread on loopback and a
    :class:`RobotClient` with safety limits) or "inprocess" (the same protocol handler,
    no sockets). The server's force reading is the physical object's paddle force."""

    def __init__(self, controller: Model, physical: PhysicalObject, vision: Vision,
                 settings: RigSettings = RigSettings(), *, controller_params: dict | None = None,
                 transport: str = "tcp", force_scale_n: float = 1.0):
        if transport not in ("tcp", "inprocess"):
            raise ValueError(f"unknown transport {transport!r}: choose 'tcp' or 'inprocess'")
        self.ctrl = _Tracked(controller, controller_params)
        self.phys, self.vision, self.settings = physical, vision, settings
        self.scale = vision.geometry.scale_m
        self.force_scale_n = float(force_scale_n)
        s = settings
        self.safety = SafetyLimits(np.full(3, -s.workspace_m), np.full(3, s.workspace_m), s.max_step_m)
        self.server = SimulatedRobotServer(force_fn=self._force_at)
        self.transport = transport
        if transport == "tcp":
            self.server.start()
            self.robot = _TcpRobot(RobotClient(port=self.server.port, safety=self.safety, timeout_s=30.0))
        else:
            self.robot = InProcessRobot(self.server, self.safety)
        self.D = np.zeros((2, 2))   # Broyden correction of the model Jacobian

    def close(self):
        self.robot.close()
        if self.transport == "tcp":
            self.server.stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _force_at(self, position_m):
        """Robot force sensor: the physical object's force on the paddle at the robot's
        current position (the physical object has settled there already)."""
        f = self.phys.force() * self.force_scale_n
        return [f[0], f[1], 0.0]

    def _record(self, run: RigRun, wp: int):
        true = self.phys.cp()
        run.paddle.append(self.phys.paddle.copy())
        run.true.append(true)
        run.measured.append(self.vision.measure(CONTROL_POINT + true) - CONTROL_POINT)
        run.predicted.append(self.ctrl.cp())
        run.force_n.append(self.robot.read_force())
        run.waypoint.append(wp)

    def set_controller_params(self, params: dict | None) -> None:
        """Use (calibrated) material parameters in the controller model from now on."""
        self.ctrl = _Tracked(self.ctrl.model, params)

    def reset(self) -> None:
        """Paddle back to rest (through the robot), both models and the Broyden correction
        back to their initial state (the objects are elastic: rest is rest)."""
        self._go(np.zeros(2))
        self.phys.sol, self.phys.paddle = self.phys.model.initial(), np.zeros(2)
        self.ctrl.sol, self.ctrl.paddle = self.ctrl.model.initial(), np.zeros(2)
        self.D = np.zeros((2, 2))

    def _go(self, target):
        """Move the paddle to ``target`` (model units) in steps the safety limit allows,
        letting the physical object settle at each."""
        start = self.phys.paddle.copy()
        n = max(1, int(np.ceil(np.linalg.norm(target - start) * self.scale / (0.9 * self.settings.max_step_m))))
        for a in np.linspace(0, 1, n + 1)[1:]:
            pos = self.robot.move_paddle(np.r_[(start + a * (target - start)) * self.scale, 0.0])
            self.phys.settle(np.asarray(pos)[:2] / self.scale)

    def probe(self, targets) -> "Recording":
        """Identification run: move the paddle to each target (model units), record the
        camera's control point and the robot's force reading, then return to rest. The
        controller model is left untouched."""
        targets = np.atleast_2d(np.asarray(targets, float))
        cps, forces = [], []
        for t in targets:
            self._go(t)
            cps.append(self.vision.measure(CONTROL_POINT + self.phys.cp()) - CONTROL_POINT)
            forces.append(self.robot.read_force()[:2])
        self._go(np.zeros(2))
        return Recording(targets, np.array(cps), np.array(forces), CONTROL_POINT[None], self.force_scale_n)

    def run(self, path, progress: bool = True) -> RigRun:
        """Track ``path`` (W, 2) of control point displacements (model units) from rest.
        ``progress``: a bar of the waypoints on a terminal."""
        path = np.atleast_2d(np.asarray(path, float))
        if path.ndim != 2 or path.shape[1] != 2:
            raise ValueError(f"path must be (W, 2) control point displacements, got {np.shape(path)}")
        s = self.settings
        run = RigRun(self.scale, path)
        W = len(path)
        run.reached, run.final = -np.ones(W, int), -np.ones(W, int)
        self._record(run, 0)
        wp, it_wp, k = 0, 0, 0
        bar = progress_bar(W, desc="rig run", unit="waypoint", progress=progress)
        while wp < W:
            e = path[wp] - run.measured[-1]
            if np.linalg.norm(e) * self.scale < s.tol_m:
                run.reached[wp] = run.final[wp] = k
                wp, it_wp = wp + 1, 0
                bar.update()
                continue
            if it_wp >= s.max_iter:
                run.final[wp] = k
                if not s.advance_on_cap:
                    run.status = RigStatus.ITERATION_CAP
                    break
                wp, it_wp = wp + 1, 0
                bar.update()
                continue
            J = self.ctrl.jacobian()
            step = np.asarray(control_increment(jnp.asarray(J + self.D), jnp.asarray(e), s.gain, s.clamp))
            target = self.phys.paddle + step
            try:
                pos = self.robot.move_paddle(np.r_[target * self.scale, 0.0])
            except SafetyError as err:
                run.final[wp] = k
                run.status, run.message = RigStatus.SAFETY_STOP, str(err)
                break
            before = run.measured[-1]
            try:
                # the robot is where it says; the object follows the paddle there
                self.phys.settle(np.asarray(pos)[:2] / self.scale)
                self.ctrl.settle(target)
            except SolveError as err:   # keep the history up to here
                run.final[wp] = k
                run.status, run.message = RigStatus.SOLVE_FAILED, str(err)
                break
            try:
                self._record(run, wp)
            except ValueError as err:   # MarkerCountError / no L in the frame
                run.final[wp] = k
                run.status, run.message = RigStatus.VISION_FAILED, str(err)
                break
            k += 1
            it_wp += 1
            if s.broyden and np.linalg.norm(step) * self.scale >= s.broyden_min_step_m:
                # secant on the Jacobian used for this step; D keeps what the model lacks
                self.D = broyden_update(J + self.D, step, run.measured[-1] - before) - J
                run.broyden_updates += 1
        bar.close()
        if run.status == RigStatus.DONE and not np.all(run.reached >= 0):
            run.status = RigStatus.ITERATION_CAP
        if not run.message:
            n = int(np.sum(run.reached >= 0))
            run.message = f"{run.status.name}: {n}/{W} waypoints within {s.tol_m * 1e3:.2f} mm (camera), " \
                          f"{run.iterations} iterations"
        return run

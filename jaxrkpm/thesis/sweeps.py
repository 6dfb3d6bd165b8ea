"""The needle study's sweeps to disk: many static paddle configurations of the 2D phantom
(paddle position, inclusion, its stiffness ratio, the phantom's Fung parameters;
:class:`NeedleSweep`) or of the 3D half-ellipsoid phantom (paddle patch, inclusion, stiffness
ratio, the tissue's constants; :class:`NeedleSweep3D`), evaluated a chunk at a time by the
batched insertion (``needle.insert``: every configuration x every increment in one compiled
call) and written by :func:`jaxrkpm.sweep` (Parquet, resumable, in process or on
a Dask cluster); and tracking sweeps over the object's material and the control gains
(:class:`TrackSweep`).
"""
from __future__ import annotations

import copy
import json
from typing import Sequence

import numpy as np

from ..control.tracking import TrackStatus, track
from ..model.model import Model
from ..mechanics.materials import Fung
from ..solvers.results import Status
from ..sweeps.runner import sweep
from .data import CP_2D, INCLUSIONS, INCLUSIONS_3D, PATHS
from .needle import Phantom, controllability, inclusion_field, insert
from .phantom3d import MATERIAL_VALUES, Phantom3D
from .scenarios import planar_square

PHANTOM_OPTIONS = ("spacing", "immobile", "needle_x", "needle_particles", "insertion", "support", "integration")
PHANTOM_3D_OPTIONS = ("spacing", "material_law", "integration", "order", "insertion", "support", "patch_radius",
                      "needle_radius", "track_spacing")
# the material columns a 3D row may give, by the phantom's material law (``Phantom3D.material``)
LAW_VALUES_3D = {"neo-hookean": ("mu", "nu"), "neohookean": ("lam", "mu"), "fung": ("alpha", "beta"),
                 "fung-barrier": ("alpha", "beta")}
INVALID = "INVALID"


class _InsertionSweep:
    """What the 2D and 3D needle evaluators share: a chunk's valid configurations inserted in
    batched calls (``needle.insert``) padded to ``batch`` members (one compiled program for
    every chunk), the result columns, and the rows that cannot be run (``INVALID``). A
    subclass names its phantom, its options, inclusions and optional material columns, and
    builds a configuration's model (``model``) and the models that set the batch's shapes
    (``like``)."""

    requires = {"paddle": "int", "inclusion": "str", "stiffness_ratio": "float"}
    PHANTOM: type = Phantom
    OPTIONS: tuple = PHANTOM_OPTIONS
    INCLUSIONS: dict = INCLUSIONS

    def __init__(self, increments: int = 15, *, jacobian: bool = True, keep_jacobians: bool = False,
                 batch: int | None = None, batching: str | None = None, n_devices: int | None = None,
                 chunk_size: int | str | None = None, **phantom):
        unknown = set(phantom) - set(self.OPTIONS)
        if unknown:
            raise TypeError(f"unknown phantom option(s) {sorted(unknown)}: choose from {list(self.OPTIONS)}")
        if batch is not None and not (isinstance(batch, int) and batch >= 1):
            raise ValueError(f"batch must be a positive number of members (or None), got {batch!r}")
        self.increments, self.jacobian, self.keep_jacobians = increments, jacobian, keep_jacobians
        self.batch, self.batching, self.n_devices, self.chunk_size = batch, batching, n_devices, chunk_size
        self.phantom_options = dict(sorted(phantom.items()))
        self._phantom = self._like = None
        self.PHANTOM(**self.phantom_options).depths(increments)   # checks the options and the increments now

    @property
    def sweep_key(self) -> str:
        """What the results depend on besides the configurations (the sweep's manifest)."""
        kind = type(self)
        return f"{kind.__module__}.{kind.__qualname__}:" + json.dumps(
            {"increments": self.increments, "jacobian": self.jacobian, "keep_jacobians": self.keep_jacobians,
             "phantom": self.phantom_options}, sort_keys=True)

    def for_chunk_size(self, size: int):
        """This evaluator with every batch padded to ``size`` members, unless it was given a
        ``batch`` of its own (what :func:`jaxrkpm.sweep` asks once it knows the
        chunk size)."""
        if self.batch is not None:
            return self
        new = copy.copy(self)
        new.batch = int(size)
        return new

    def __getstate__(self):
        return {**self.__dict__, "_phantom": None, "_like": None}    # the phantom's cache (models, arrays) stays home

    @property
    def phantom(self):
        if self._phantom is None:
            self._phantom = self.PHANTOM(**self.phantom_options)
        return self._phantom

    @property
    def values(self) -> tuple:
        """The optional material columns of a row (the phantom's value where absent)."""
        raise NotImplementedError

    def model(self, paddle: int, inclusion: str, values: dict) -> Model:
        """The model of one configuration (``values``: stiffness_ratio and the material columns)."""
        raise NotImplementedError

    @property
    def like(self) -> list:
        """Models that set the padded shapes and the batched leaves of every chunk's batch
        (``stack_models(like=)``: their materials differ in every constant a row may set), so
        that all chunks share one compiled program."""
        raise NotImplementedError

    def _invalid(self, paddle, inclusion, values: dict, unused: Sequence[str]) -> str:
        P = len(self.phantom.paddles)
        if not 1 <= paddle <= P:
            return f"paddle {paddle} out of range 1..{P}"
        if inclusion not in self.INCLUSIONS:
            return f"unknown inclusion {inclusion!r}: choose {list(self.INCLUSIONS)}"
        if unused:
            return (f"column(s) {list(unused)} are not constants of this phantom's material "
                    f"(it takes {list(self.values)})")
        for name, v in values.items():
            if not (np.isfinite(v) and v > 0):
                return f"{name} must be positive and finite, got {v}"
        if "nu" in values and not values["nu"] < 0.5:
            return f"nu must be a Poisson's ratio below 0.5, got {values['nu']}"
        return ""

    def _unused(self, chunk: dict) -> list:
        """Material columns of the table this evaluator's phantom does not take."""
        return []

    def __call__(self, chunk: dict) -> dict:
        ph = self.phantom
        B, n, dim = len(chunk["paddle"]), self.increments, len(ph.needle_direction)
        paddle = np.asarray(chunk["paddle"], int)
        inclusion = [str(s) for s in chunk["inclusion"]]
        rows = self._rows(chunk, B)
        unused = self._unused(chunk)
        reasons = [self._invalid(paddle[i], inclusion[i], rows[i], unused) for i in range(B)]
        valid = [i for i, r in enumerate(reasons) if not r]
        out = self._empty(B, n, dim)
        status = np.array([INVALID if r else "" for r in reasons], object)
        reason = np.array(reasons, object)
        depths = ph.depths(n)
        size = self.batch or max(len(valid), 1)
        for start in range(0, len(valid), size):
            part = valid[start:start + size]
            models = [self.model(int(paddle[i]), inclusion[i], rows[i]) for i in part]
            models += [models[-1]] * (size - len(models))       # one program for every chunk
            run = insert(models, depths, ph.target, jacobian_set="paddle" if self.jacobian else None,
                         direction=ph.needle_direction, batching=self.batching, n_devices=self.n_devices,
                         like=self.like)
            self._record(out, status, reason, part, run, depths)
        out["status"], out["reason"] = status, reason
        return out

    def _rows(self, chunk: dict, B: int) -> list:
        """Per configuration its stiffness ratio and material constants (the phantom's where
        the chunk has no such column)."""
        ph = self.phantom
        columns = {"stiffness_ratio": np.asarray(chunk["stiffness_ratio"], float)}
        for name in self.values:
            columns[name] = np.asarray(chunk.get(name, np.full(B, getattr(ph, name))), float)
        return [{k: float(v[i]) for k, v in columns.items()} for i in range(B)]

    def _empty(self, B: int, n: int, dim: int) -> dict:
        """The result columns of B configurations, n increments, before any is run."""
        out = {"deviation": np.full((B, n), np.nan), "final_deviation": np.full(B, np.nan),
               "target_u": np.full((B, dim), np.nan), "increment_status": np.full((B, n), -1, np.int8),
               "iterations": np.full(B, -1, np.int64)}
        if self.jacobian:
            out["controllability"] = np.full(B, np.nan)
        if self.keep_jacobians:
            out["jacobian"] = np.full((B, n, dim, dim), np.nan)
        return out

    def _record(self, out: dict, status, reason, part: list, run, depths) -> None:
        """The batched insertion ``run`` of the configurations ``part`` into the columns."""
        ph = self.phantom
        k = len(part)
        tu = np.asarray(run.target_u)[:k]                   # (k, n, d)
        st = np.asarray(run.status)[:k]
        dev = np.asarray(ph.deviation_of(tu))
        out["deviation"][part] = dev
        out["target_u"][part] = tu[:, -1]
        out["increment_status"][part] = st
        out["iterations"][part] = np.asarray(run.iterations)[:k].sum(axis=1)
        ok = np.all(st == Status.CONVERGED, axis=1)
        out["final_deviation"][part] = np.where(ok, dev[:, -1], np.nan)
        J = np.asarray(run.jacobian)[:k]
        for j, i in enumerate(part):
            status[i], reason[i] = _outcome(st[j], depths)
            if self.jacobian and st[j, 0] == Status.CONVERGED:
                try:
                    out["controllability"][i] = float(controllability(J[j, 0], ph.lateral))
                except np.linalg.LinAlgError:
                    pass
        if self.keep_jacobians:
            out["jacobian"][part] = J


def _outcome(st: np.ndarray, depths) -> tuple[str, str]:
    """(status, reason) of one configuration from its increments' solve status: the first
    failed increment's, else CONVERGED with no reason."""
    bad = np.flatnonzero(st != Status.CONVERGED)
    if not len(bad):
        return Status.CONVERGED.name, ""
    s = Status.of(st[bad[0]])
    return s.name, f"increment {bad[0] + 1} of {len(st)} (depth {depths[bad[0]]:.4g}): {s.message}"


class NeedleSweep(_InsertionSweep):
    """The evaluator of a 2D needle sweep: ``evaluate(chunk) -> columns`` for
    :func:`jaxrkpm.sweep`. A configuration is a row with ``paddle`` (1-based
    Table 6.2 position), ``inclusion`` (a name of ``INCLUSIONS``), ``stiffness_ratio`` and,
    optionally, ``alpha`` and ``beta`` (Fung; the phantom's where absent). A chunk's valid
    configurations are inserted in one batched call (``needle.insert``), padded to ``batch``
    members where given (one compiled program for every chunk, the last one too); a row with
    an out-of-range value is an ``INVALID`` row, not an error of the chunk.

    Result columns: ``deviation`` (n increments, the target's lateral deviation),
    ``final_deviation`` (NaN unless every increment converged), ``target_u`` (2,) at the last
    increment, ``increment_status`` (n solve status codes), ``iterations`` (Newton, all
    increments), ``controllability`` (delta x_min after the first increment, with
    ``jacobian``), ``jacobian`` (n, 2, 2; with ``keep_jacobians``), ``status`` (the first
    failed increment's solve status, else CONVERGED) and ``reason``.

    ``phantom``: options of :class:`jaxrkpm.thesis.needle.Phantom` (spacing, immobile, ...).
    The evaluator holds numbers only (it is sent to cluster workers); each process builds
    its phantom once."""

    values = ("alpha", "beta")

    def material(self, inclusion: str, ratio: float, alpha: float, beta: float):
        """Fung with alpha and beta x ratio inside the inclusion: fields for every
        configuration (also without an inclusion), so that any of them batch together."""
        ph = self.phantom
        box = INCLUSIONS[inclusion]
        if box is None:
            factor = inclusion_field(((np.inf, -np.inf), (np.inf, -np.inf)), 1.0)
        else:
            h = 0.5 * ph.spacing
            (x0, x1), (y0, y1) = box
            factor = inclusion_field(((x0 - h, x1 + h), (y0 - h, y1 + h)), ratio)
        return Fung(alpha=lambda X: alpha * factor(X), beta=lambda X: beta * factor(X))

    def model(self, paddle: int, inclusion: str, values: dict) -> Model:
        ph = self.phantom
        return Model(ph.body, self.material(inclusion, values["stiffness_ratio"], values["alpha"], values["beta"]),
                     ph.integration, essential=ph.sets(paddle), support=ph.support)

    @property
    def like(self) -> list:
        if self._like is None:
            self._like = [self.model(p, "right", {"stiffness_ratio": 2.0 + p, "alpha": 1.0 + 0.1 * p,
                                                  "beta": 1.0 + 0.2 * p})
                          for p in range(1, len(self.phantom.paddles) + 1)]
        return self._like


class NeedleSweep3D(_InsertionSweep):
    """The evaluator of a 3D needle sweep on the half-ellipsoid phantom
    (:class:`jaxrkpm.thesis.phantom3d.Phantom3D`): a row is ``paddle`` (1-based patch on the
    skin), ``inclusion`` (``none``, ``side``, ``above``), ``stiffness_ratio`` and, optionally,
    the constants of the phantom's material law (``LAW_VALUES_3D``: ``mu`` and ``nu`` for the
    default nearly incompressible tissue; the phantom's where absent; a column of another
    law's constant makes the row ``INVALID``). The result columns are those of
    :class:`NeedleSweep` in 3D: ``target_u`` (3,), ``jacobian`` (n, 3, 3), the deviation the
    length of the target's displacement across the needle.

    ``phantom``: options of ``Phantom3D`` (``PHANTOM_3D_OPTIONS``: spacing, material_law, ...)."""

    PHANTOM = Phantom3D
    OPTIONS = PHANTOM_3D_OPTIONS
    INCLUSIONS = INCLUSIONS_3D

    @property
    def values(self) -> tuple:
        return LAW_VALUES_3D[self.phantom_options.get("material_law", Phantom3D.material_law)]

    def _unused(self, chunk: dict) -> list:
        return [c for c in MATERIAL_VALUES if c in chunk and c != "stiffness_ratio" and c not in self.values]

    def model(self, paddle: int, inclusion: str, values: dict) -> Model:
        return self.phantom.model(inclusion, paddle, as_field=True, **values)

    @property
    def like(self) -> list:
        if self._like is None:
            base = {name: getattr(self.phantom, name) for name in self.values}
            self._like = [self.model(p, "side", {"stiffness_ratio": 2.0 + p,
                                                 **{k: (v * (1.0 - 0.02 * p) if k == "nu" else v * (1.0 + 0.1 * p))
                                                    for k, v in base.items()}})
                          for p in range(1, len(self.phantom.paddles) + 1)]
        return self._like


class TrackSweep:
    """The evaluator of a tracking sweep over the object's material (chapter 5, Algorithm 3 on
    the 9x9 Fung square): how well the controller's model, the thesis' ``model_alpha``,
    ``model_beta`` (1, 1), drives an object whose material differs. A row is the object's
    (the plant's) Fung ``alpha`` and ``beta`` and, optionally, the control ``gain`` and
    ``clamp`` (the thesis' 0.05 and 0.01 where absent); each row tracks ``path`` (a name of
    the thesis' paths) with the controller's Jacobian moving the plant's paddle
    (``jaxrkpm.track(..., plant=)``), one row after another (a tracking run is one compiled
    loop; the rows share it).

    Result columns: ``waypoints_reached`` and ``waypoints`` (of the path), ``max_waypoint_error``
    (NaN where none was reached), ``final_error`` (|e| at the last iteration), ``iterations``,
    ``final_cp`` (d,) the control point's displacement at the end, ``status`` (the
    ``TrackStatus`` name, ``DONE`` where every waypoint was reached) and ``reason``; a row
    with a non-positive or non-finite value is ``INVALID``."""

    requires = {"alpha": "float", "beta": "float"}

    def __init__(self, path: str = "box", *, n: int = 9, integration: str = "gauss", model_alpha: float = 1.0,
                 model_beta: float = 1.0, tol: float = 1e-4, max_iter: int = 2000, max_steps: int = 20000):
        if path not in PATHS:
            raise ValueError(f"unknown path {path!r}: choose {list(PATHS)}")
        for name, v in (("model_alpha", model_alpha), ("model_beta", model_beta), ("tol", tol)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        self.path, self.n, self.integration = path, n, integration
        self.model_alpha, self.model_beta, self.tol = float(model_alpha), float(model_beta), float(tol)
        self.max_iter, self.max_steps = max_iter, max_steps
        self._controller = None
        planar_square(n, integration)          # checks n and the integration now

    @property
    def sweep_key(self) -> str:
        return "jaxrkpm.thesis.sweeps.TrackSweep:" + json.dumps(
            {k: v for k, v in self.__dict__.items() if not k.startswith("_")}, sort_keys=True)

    def __getstate__(self):
        return {**self.__dict__, "_controller": None}

    def plant(self, alpha: float, beta: float) -> Model:
        return planar_square(self.n, self.integration, Fung(alpha=alpha, beta=beta), paddle="three")

    @property
    def controller(self) -> Model:
        if self._controller is None:
            self._controller = self.plant(self.model_alpha, self.model_beta)
        return self._controller

    def __call__(self, chunk: dict) -> dict:
        B = len(chunk["alpha"])
        alpha, beta = np.asarray(chunk["alpha"], float), np.asarray(chunk["beta"], float)
        gain = np.asarray(chunk.get("gain", np.full(B, 0.05)), float)
        clamp = np.asarray(chunk.get("clamp", np.full(B, 0.01)), float)
        path = np.asarray(PATHS[self.path], float)
        out = {"waypoints_reached": np.full(B, -1, np.int64), "waypoints": np.full(B, len(path), np.int64),
               "max_waypoint_error": np.full(B, np.nan), "final_error": np.full(B, np.nan),
               "iterations": np.full(B, -1, np.int64), "final_cp": np.full((B, 2), np.nan),
               "status": np.full(B, "", object), "reason": np.full(B, "", object)}
        for i in range(B):
            bad = [f"{name} must be positive and finite, got {v[i]}"
                   for name, v in (("alpha", alpha), ("beta", beta), ("gain", gain), ("clamp", clamp))
                   if not (np.isfinite(v[i]) and v[i] > 0)]
            if bad:
                out["status"][i], out["reason"][i] = INVALID, bad[0]
                continue
            # Python floats: the settings of a direct ``track`` call, so the rows share its program
            res = track(self.controller, path, "paddle", CP_2D, plant=self.plant(float(alpha[i]), float(beta[i])),
                        gain=float(gain[i]), clamp=float(clamp[i]), tol=self.tol, max_iter=self.max_iter,
                        max_steps=self.max_steps)
            out["waypoints_reached"][i] = int(np.sum(res.reached >= 0))
            out["max_waypoint_error"][i] = res.max_waypoint_error
            out["final_error"][i] = float(res.error[-1])
            out["iterations"][i] = len(res.error) - 1
            out["final_cp"][i] = res.cp[-1]
            out["status"][i], out["reason"][i] = res.status.name, "" if res.status == TrackStatus.DONE else res.message
        return out


def paddle_configurations(paddles: Sequence[int] | None = None, ratios: Sequence[float] = (100.0,),
                          inclusions: Sequence[str] = ("right",), alphas: Sequence[float] = (1.0,),
                          betas: Sequence[float] = (1.0,)) -> dict:
    """Every combination of paddle position (default all of Table 6.2), inclusion,
    stiffness ratio and Fung alpha, beta as a table (a dict of columns), paddles varying
    fastest."""
    from .data import TABLE_6_2
    paddles = list(range(1, len(TABLE_6_2) + 1)) if paddles is None else list(paddles)
    grid = [(i, r, a, b, p) for i in inclusions for r in ratios for a in alphas for b in betas for p in paddles]
    if not grid:
        raise ValueError("no configurations: paddles, ratios, inclusions, alphas and betas must each give at least one")
    i, r, a, b, p = zip(*grid)
    return {"paddle": np.asarray(p, np.int64), "inclusion": list(i), "stiffness_ratio": np.asarray(r, float),
            "alpha": np.asarray(a, float), "beta": np.asarray(b, float)}


def needle_sweep(out, configurations=None, *, increments: int = 15, chunk_size: int | str = 20,
                 executor=None, progress: bool = True, **options):
    """The 2D needle sweep of ``configurations`` (default :func:`paddle_configurations`)
    into the folder ``out``: :class:`NeedleSweep` (``options``: its own and the phantom's)
    padded to ``chunk_size`` members (``"auto"``: measured, see
    :func:`jaxrkpm.choose_chunk_size`), through
    :func:`jaxrkpm.sweep`; a rerun resumes. Returns its ``SweepSummary``;
    ``read_sweep(out)`` gives the table."""
    evaluate = NeedleSweep(increments, **options)
    return sweep(paddle_configurations() if configurations is None else configurations, evaluate, out,
                 chunk_size=chunk_size, executor=executor, progress=progress)

"""The needle study's sweeps to disk: many static paddle configurations of the 2D phantom
(paddle position, inclusion, its stiffness ratio, the phantom's Fung parameters), evaluated a
chunk at a time by the batched insertion (``needle.insert``: every configuration x every
increment in one compiled call) and written by :func:`jaxrkpm.control.sweep.sweep` (Parquet,
resumable, in process or on a Dask cluster).
"""
from __future__ import annotations

import copy
import json
from typing import Sequence

import numpy as np

from ..control.sweep import sweep
from ..model.model import Model
from ..mechanics.materials import Fung
from ..solvers.results import Status
from .data import INCLUSIONS
from .needle import Phantom, controllability, inclusion_field, insert

PHANTOM_OPTIONS = ("spacing", "immobile", "needle_x", "needle_particles", "insertion", "support", "integration")
INVALID = "INVALID"


class NeedleSweep:
    """The evaluator of a 2D needle sweep: ``evaluate(chunk) -> columns`` for
    :func:`jaxrkpm.control.sweep.sweep`. A configuration is a row with ``paddle`` (1-based
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

    requires = {"paddle": "int", "inclusion": "str", "stiffness_ratio": "float"}

    def __init__(self, increments: int = 15, *, jacobian: bool = True, keep_jacobians: bool = False,
                 batch: int | None = None, batching: str | None = None, n_devices: int | None = None,
                 chunk_size: int | None = None, **phantom):
        unknown = set(phantom) - set(PHANTOM_OPTIONS)
        if unknown:
            raise TypeError(f"unknown phantom option(s) {sorted(unknown)}: choose from {list(PHANTOM_OPTIONS)}")
        if batch is not None and not (isinstance(batch, int) and batch >= 1):
            raise ValueError(f"batch must be a positive number of members (or None), got {batch!r}")
        self.increments, self.jacobian, self.keep_jacobians = increments, jacobian, keep_jacobians
        self.batch, self.batching, self.n_devices, self.chunk_size = batch, batching, n_devices, chunk_size
        self.phantom_options = dict(sorted(phantom.items()))
        self._phantom = self._like = None
        Phantom(**self.phantom_options).depths(increments)   # checks the options and the increments now

    @property
    def sweep_key(self) -> str:
        """What the results depend on besides the configurations (the sweep's manifest)."""
        return "jaxrkpm.thesis.sweeps.NeedleSweep:" + json.dumps(
            {"increments": self.increments, "jacobian": self.jacobian, "keep_jacobians": self.keep_jacobians,
             "phantom": self.phantom_options}, sort_keys=True)

    def for_chunk_size(self, size: int) -> "NeedleSweep":
        """This evaluator with every batch padded to ``size`` members, unless it was given a
        ``batch`` of its own (what :func:`jaxrkpm.control.sweep.sweep` asks once it knows the
        chunk size)."""
        if self.batch is not None:
            return self
        new = copy.copy(self)
        new.batch = int(size)
        return new

    def __getstate__(self):
        return {**self.__dict__, "_phantom": None, "_like": None}    # the phantom's cache (models, arrays) stays home

    @property
    def phantom(self) -> Phantom:
        if self._phantom is None:
            self._phantom = Phantom(**self.phantom_options)
        return self._phantom

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

    @property
    def like(self) -> list:
        """One model per paddle position, with differing materials: every chunk's batch is
        padded and batched like them (``stack_models(like=)``), so all chunks share one
        compiled program."""
        if self._like is None:
            ph = self.phantom
            self._like = [Model(ph.body, self.material("right", 2.0 + p, 1.0 + 0.1 * p, 1.0 + 0.2 * p), ph.integration,
                                essential=ph.sets(p), support=ph.support) for p in range(1, len(ph.paddles) + 1)]
        return self._like

    def _invalid(self, paddle, inclusion, ratio, alpha, beta) -> str:
        P = len(self.phantom.paddles)
        if not 1 <= paddle <= P:
            return f"paddle {paddle} out of range 1..{P}"
        if inclusion not in INCLUSIONS:
            return f"unknown inclusion {inclusion!r}: choose {list(INCLUSIONS)}"
        for name, v in (("stiffness_ratio", ratio), ("alpha", alpha), ("beta", beta)):
            if not (np.isfinite(v) and v > 0):
                return f"{name} must be positive and finite, got {v}"
        return ""

    def __call__(self, chunk: dict) -> dict:
        ph = self.phantom
        B, n = len(chunk["paddle"]), self.increments
        paddle = np.asarray(chunk["paddle"], int)
        inclusion = [str(s) for s in chunk["inclusion"]]
        ratio = np.asarray(chunk["stiffness_ratio"], float)
        alpha = np.asarray(chunk.get("alpha", np.full(B, ph.alpha)), float)
        beta = np.asarray(chunk.get("beta", np.full(B, ph.beta)), float)
        reasons = [self._invalid(*row) for row in zip(paddle, inclusion, ratio, alpha, beta)]
        valid = [i for i, r in enumerate(reasons) if not r]
        out = {"deviation": np.full((B, n), np.nan), "final_deviation": np.full(B, np.nan),
               "target_u": np.full((B, 2), np.nan), "increment_status": np.full((B, n), -1, np.int8),
               "iterations": np.full(B, -1, np.int64)}
        if self.jacobian:
            out["controllability"] = np.full(B, np.nan)
        if self.keep_jacobians:
            out["jacobian"] = np.full((B, n, 2, 2), np.nan)
        status = np.array([INVALID if r else "" for r in reasons], object)
        reason = np.array(reasons, object)
        depths = ph.depths(n)
        size = self.batch or max(len(valid), 1)
        for start in range(0, len(valid), size):
            rows = valid[start:start + size]
            models = [Model(ph.body, self.material(inclusion[i], ratio[i], alpha[i], beta[i]), ph.integration,
                            essential=ph.sets(int(paddle[i])), support=ph.support) for i in rows]
            models += [models[-1]] * (size - len(models))       # one program for every chunk
            run = insert(models, depths, ph.target, jacobian_set="paddle" if self.jacobian else None,
                         direction=ph.needle_direction, batching=self.batching, n_devices=self.n_devices,
                         like=self.like)
            k = len(rows)
            tu = np.asarray(run.target_u)[:k]                   # (k, n, 2)
            st = np.asarray(run.status)[:k]
            dev = np.asarray(ph.deviation_of(tu))
            out["deviation"][rows] = dev
            out["target_u"][rows] = tu[:, -1]
            out["increment_status"][rows] = st
            out["iterations"][rows] = np.asarray(run.iterations)[:k].sum(axis=1)
            ok = np.all(st == Status.CONVERGED, axis=1)
            out["final_deviation"][rows] = np.where(ok, dev[:, -1], np.nan)
            J = np.asarray(run.jacobian)[:k]
            for j, i in enumerate(rows):
                bad = np.flatnonzero(st[j] != Status.CONVERGED)
                if len(bad):
                    s = Status.of(st[j, bad[0]])
                    status[i] = s.name
                    reason[i] = f"increment {bad[0] + 1} of {n} (depth {depths[bad[0]]:.4g}): {s.message}"
                else:
                    status[i] = Status.CONVERGED.name
                if self.jacobian and st[j, 0] == Status.CONVERGED:
                    try:
                        out["controllability"][i] = float(controllability(J[j, 0], ph.lateral))
                    except np.linalg.LinAlgError:
                        pass
            if self.keep_jacobians:
                out["jacobian"][rows] = J
        out["status"], out["reason"] = status, reason
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
    :func:`jaxrkpm.control.sweep.choose_chunk_size`), through
    :func:`jaxrkpm.control.sweep.sweep`; a rerun resumes. Returns its ``SweepSummary``;
    ``read_sweep(out)`` gives the table."""
    evaluate = NeedleSweep(increments, **options)
    return sweep(paddle_configurations() if configurations is None else configurations, evaluate, out,
                 chunk_size=chunk_size, executor=executor, progress=progress)

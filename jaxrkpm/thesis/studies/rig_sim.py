"""Simulated rig: the thesis' physical validation (section 5.3.2, Figs 5.33-5.39) closed
in software. ``jaxrkpm rig-sim --path setpoint|box [--calibrate] [--broyden] --out DIR``.

The 9x9 Fung controller model (alpha 1, beta 0.02: the thesis' hand-tuned value) tracks
the path on a "physical" object it does not know: a finer grid (``--physical-n``, 17 by
default; 33 is closer to a real object but much slower per solve), beta twice the model's and a stiff
inclusion (x10 in a disc of radius 0.15 at (0.3, 0.7)). The control point is seen through
synthetic noisy stereo images (Bumblebee-like rig at 0.45 m, object 0.2 m wide) and the
paddle moves through the JSON-lines robot link over loopback TCP.

Runs (each from rest): ``uncorrected``; with ``--calibrate`` the controller's beta and a
3x3 stiffness map are first fitted (L-BFGS through the differentiable solve) to an
identification probe of the physical object (paddle at 10 positions, camera + force);
with ``--broyden`` the Jacobian is corrected online from camera feedback; with both, also
the two combined. Each variant runs twice: ``tracking`` (to a 0.3 mm camera tolerance per
waypoint: iterations needed) and ``budget`` (``--budget`` iterations per waypoint at gain
1, then on: the physical error left shows the Jacobian's quality; its ITERATION_CAP status is
expected, the budget is the cap).

Writes summary.json (per waypoint: physical error, camera error, model mismatch in mm;
status) and figures to ``--out`` (default results/rig_sim/<path>).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from jaxrkpm.thesis.data import PATHS, RIG_MODEL_BETA, RIG_SETTLE_MM
from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import Command, lazy
from jaxrkpm.thesis.studies.experiments import DIFFERS, IN_KIND, Entry

plot = lazy("jaxrkpm.io.plot")
sim = lazy("jaxrkpm.thesis.rigsim.sim")
calibration = lazy("jaxrkpm.thesis.rigsim.calibrate")

RIG_PATHS = ("setpoint", "box")
MODEL_ALPHA, MODEL_BETA = 1.0, RIG_MODEL_BETA   # section 5.3.2: beta tuned by hand
PROBE = np.array([[a, b] for a in (0.0, 0.06, 0.12) for b in (0.0, 0.06, 0.12) if a or b]
                 + [[-0.03, 0.06], [0.06, -0.03]])   # paddle positions (model units)


def build(physical_n=17, noise=2.0, seed=0, gain=0.7, tol_mm=0.3, max_iter=30, transport="tcp"):
    ctrl = sim.planar_object(9, MODEL_ALPHA, MODEL_BETA)
    phys = sim.PhysicalObject(physical_n, alpha=MODEL_ALPHA, beta=2 * MODEL_BETA, inclusion=sim.Inclusion())
    vision = sim.Vision(noise_std=noise, seed=seed)
    settings = sim.RigSettings(gain=gain, tol_m=tol_mm * 1e-3, max_iter=max_iter)
    return sim.ClosedLoop(ctrl, phys, vision, settings, transport=transport)


def _stats(x):
    x = np.asarray(x, float)
    return {"mean": float(np.nanmean(x)), "max": float(np.nanmax(x))}


def describe(run: sim.RigRun, wall_s: float) -> dict:
    phys, cam, mis = run.physical_error_mm, run.camera_error_mm, run.mismatch_mm
    return {"status": run.status.name, "message": run.message, "iterations": run.iterations,
            "wall_s": round(wall_s, 2), "broyden_updates": run.broyden_updates,
            "physical_error_mm": _stats(phys[1:]), "camera_error_mm": _stats(cam[1:]),
            "model_mismatch_mm": _stats(mis[1:]),
            "waypoints": [{"index": w, "desired_mm": (run.desired[w] * run.scale_m * 1e3).round(3).tolist(),
                           "reached_at": int(run.reached[w]), "physical_error_mm": round(float(phys[w]), 4),
                           "camera_error_mm": round(float(cam[w]), 4), "model_mismatch_mm": round(float(mis[w]), 4)}
                          for w in range(len(run.desired))]}


def execute(loop: sim.ClosedLoop, path, variants, budget: int):
    """Run every variant in tracking and budget mode; returns {variant: {mode: RigRun}} and
    the summaries. ``variants``: name -> (controller params or None, broyden flag)."""
    base = loop.settings
    runs, out = {}, {}
    bar = interface.progress(total=2 * len(variants), desc="rig-sim runs", unit="run")
    for name, (params, broyden) in variants.items():
        loop.set_controller_params(params)
        runs[name], out[name] = {}, {}
        for mode, st in (("tracking", sim.RigSettings(**{**base.__dict__, "broyden": broyden})),
                         ("budget", sim.RigSettings(**{**base.__dict__, "broyden": broyden, "gain": 1.0,
                                                   "max_iter": budget, "advance_on_cap": True}))):
            bar.set_postfix_str(f"{name} {mode}")
            loop.settings = st
            loop.reset()
            t = time.perf_counter()
            r = loop.run(path)
            runs[name][mode] = r
            out[name][mode] = describe(r, time.perf_counter() - t)
            if mode == "budget" and r.status.name == "ITERATION_CAP":
                out[name][mode]["note"] = (f"expected: budget mode gives each waypoint {budget} iteration(s) at "
                                           "gain 1 by design; the physical error left measures the Jacobian")
            bar.update()
    bar.close()
    loop.settings = base
    return runs, out


# --------------------------------------------------------------------------- figures
def _mm(a, scale):
    return np.asarray(a) * scale * 1e3


def fig_paths(run: sim.RigRun, name: str, out: Path):
    """Figs 5.36-5.39: desired vs recorded (camera) vs true physical vs simulated model."""
    plt = plot.plt
    a = run.arrays()
    s = run.scale_m
    D, M, T, P, Pad = (_mm(x, s) for x in (run.desired, a["measured"], a["true"], a["predicted"], a["paddle"]))
    fig, ax = plt.subplots(1, 4, figsize=(21, 5.2))
    for axis, (other, lab, col) in zip(ax, ((M, "recorded (camera)", "tab:blue"),
                                            (P, "simulated (9x9 model)", "tab:green"),
                                            (None, None, None))):
        axis.plot(*D.T, "k--o", ms=4, lw=1, label="desired")
        if other is not None:
            axis.plot(*other.T, "-", color=col, lw=1.2, marker=".", ms=4, label=lab)
        else:
            axis.plot(*P.T, "-", color="tab:green", lw=1.2, marker=".", ms=4, label="simulated (9x9 model)")
            axis.plot(*M.T, "-", color="tab:blue", lw=1.2, marker=".", ms=4, label="recorded (camera)")
        axis.plot(*T.T, ":", color="tab:red", lw=1.2, label="true physical")
        axis.set_xlabel("control point x displacement (mm)")
        axis.set_ylabel("control point y displacement (mm)")
        axis.set_aspect("equal", adjustable="datalim")
        axis.grid(alpha=0.3)
        axis.legend(fontsize=8)
    ax[0].set_title("desired vs recorded (Fig 5.37)")
    ax[1].set_title("desired vs simulated model (Fig 5.38)")
    ax[2].set_title("simulated vs recorded (Fig 5.39)")
    ax[3].plot(*Pad.T, "-o", ms=3, color="tab:purple", label="paddle (robot)")
    ax[3].plot([0], [0], "k+", ms=10, label="rest")
    ax[3].set_xlabel("paddle x displacement (mm)")
    ax[3].set_ylabel("paddle y displacement (mm)")
    ax[3].set_aspect("equal", adjustable="datalim")
    ax[3].grid(alpha=0.3)
    ax[3].legend(fontsize=8)
    ax[3].set_title("manipulation point moved by the robot (Fig 5.36)")
    fig.suptitle(f"{name}: {run.message}")
    fig.tight_layout()
    plot.save(fig, out / "cp_paths.png")


def fig_errors(run: sim.RigRun, name: str, tol_mm: float, out: Path):
    """Figs 5.33/5.34: error per iteration, and the per-waypoint error split."""
    plt = plot.plt
    a = run.arrays()
    s = run.scale_m
    k = np.arange(len(a["true"]))
    desired = run.desired[a["waypoint"]]
    # an exact zero (at rest, iteration 0) has no logarithm
    e_phys = np.linalg.norm(_mm(a["true"] - desired, s), axis=1)
    e_phys = np.where(e_phys > 0, e_phys, np.nan)
    e_meas = np.linalg.norm(_mm(a["measured"] - desired, s), axis=1)
    fig, (l, r) = plt.subplots(1, 2, figsize=(14, 4.8))
    l.semilogy(k, e_phys, "-o", ms=3, color="tab:red", label="physical |true - desired|")
    l.semilogy(k, e_meas, "-", lw=1, color="tab:blue", label="camera |measured - desired|")
    l.axhline(tol_mm, color="k", ls="--", lw=1, label=f"tolerance {tol_mm} mm (camera)")
    l.axhline(RIG_SETTLE_MM, color="0.5", ls=":", lw=1, label=f"{RIG_SETTLE_MM:g} mm (thesis)")
    l.set_xlabel("iteration")
    l.set_ylabel("control point error to the current waypoint (mm)")
    l.grid(alpha=0.3, which="both")
    l.legend(fontsize=8)
    l.set_title("error per iteration (Figs 5.33/5.34)")
    w = np.arange(len(run.desired))
    bw = 0.27
    r.bar(w - bw, run.physical_error_mm, bw, label="physical error", color="tab:red")
    r.bar(w, run.camera_error_mm, bw, label="camera error", color="tab:blue")
    r.bar(w + bw, run.mismatch_mm, bw, label="model mismatch", color="tab:green")
    r.set_xlabel("waypoint")
    r.set_ylabel("mm")
    r.set_xticks(w)
    r.grid(alpha=0.3, axis="y")
    r.legend(fontsize=8)
    r.set_title("at each waypoint: physical error, camera error, model mismatch")
    fig.suptitle(f"{name}: {run.message}")
    fig.tight_layout()
    plot.save(fig, out / "errors.png")


def fig_compare(runs: dict, out: Path):
    plt = plot.plt
    fig, (l, r) = plt.subplots(1, 2, figsize=(14, 4.8))
    names = list(runs)
    for name in names:
        rb = runs[name]["budget"]
        l.plot(np.arange(len(rb.desired)), rb.physical_error_mm, "-o", ms=4, label=name)
    l.set_xlabel("waypoint")
    l.set_ylabel("physical error after the budget (mm)")
    l.grid(alpha=0.3)
    l.legend(fontsize=8)
    l.set_title("fixed budget per waypoint (gain 1): what the Jacobian leaves")
    its = [runs[n]["tracking"].iterations for n in names]
    r.bar(names, its, color="tab:purple")
    for i, v in enumerate(its):
        r.annotate(str(v), (i, v), ha="center", va="bottom")
    r.set_ylabel("iterations to track the path (0.3 mm camera tolerance)")
    r.grid(alpha=0.3, axis="y")
    r.set_title("tracking to tolerance")
    fig.tight_layout()
    plot.save(fig, out / "compare.png")


def fig_forces(run: sim.RigRun, name: str, out: Path):
    """Figs 5.40/5.41: the robot's force reading per iteration and in space."""
    plt = plot.plt
    F = run.arrays()["force_n"]
    fig, (l, r) = plt.subplots(1, 2, figsize=(12, 4.5))
    l.plot(F[:, 0], "-o", ms=3, label="Fx")
    l.plot(F[:, 1], "-o", ms=3, label="Fy")
    l.set_xlabel("iteration")
    l.set_ylabel("force on the paddle (model force units)")
    l.grid(alpha=0.3)
    l.legend(fontsize=8)
    r.plot(F[:, 0], F[:, 1], "-o", ms=3, color="tab:orange")
    r.set_xlabel("Fx (model force units)")
    r.set_ylabel("Fy (model force units)")
    r.grid(alpha=0.3)
    r.set_title("force in the plane (Fig 5.40)")
    fig.suptitle(f"{name}: force sensor of the simulated robot")
    fig.tight_layout()
    plot.save(fig, out / "forces.png")


def fig_calibration(cal, rec, out: Path):
    plt = plot.plt
    fig, (l, r) = plt.subplots(1, 2, figsize=(11, 4.5))
    l.semilogy(cal.loss, "-o", ms=3)
    l.set_xlabel("L-BFGS iteration")
    l.set_ylabel("loss (noise-normalised misfit)")
    l.grid(alpha=0.3, which="both")
    l.set_title(f"calibration: cp RMS {cal.cp_rms[0]:.2e} -> {cal.cp_rms[1]:.2e} (model units)")
    im = r.imshow(cal.stiffness_map.T, origin="lower", extent=(0, 1, 0, 1), cmap="viridis")
    r.add_patch(plot.plt.Circle((0.3, 0.7), 0.15, fill=False, color="w", ls="--", label="true inclusion"))
    r.set_title("fitted stiffness multiplier (3x3 map; one marker:\nfits the kinematics, does not locate the inclusion)", fontsize=10)
    r.legend(fontsize=8, loc="lower right")
    r.set_xlabel(f"x ({plot.UNITS})")
    r.set_ylabel(f"y ({plot.UNITS})")
    fig.colorbar(im, ax=r, label="stiffness multiplier (x the model's, -)")
    fig.tight_layout()
    plot.save(fig, out / "calibration.png")


# --------------------------------------------------------------------------- entry
def run(out: Path, path: str = "box", calibrate_model: bool = False, broyden: bool = False,
        physical_n: int = 17, noise: float = 2.0, seed: int = 0, gain: float = 0.7,
        tol_mm: float = 0.3, max_iter: int = 30, budget: int = 1, transport: str = "tcp",
        waypoints: int | None = None, make_figures: bool = True) -> dict:
    if path not in RIG_PATHS:
        raise ValueError(f"unknown rig path {path!r}: choose {list(RIG_PATHS)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    desired = np.asarray(PATHS[path], float)[:waypoints]
    t0 = time.perf_counter()
    summary = {"path": path, "controller": {"grid": "9x9", "alpha": MODEL_ALPHA, "beta": MODEL_BETA},
               "settings": {"gain": gain, "tol_mm": tol_mm, "max_iter": max_iter, "budget": budget,
                            "noise_std": noise, "seed": seed, "transport": transport}}
    with build(physical_n, noise, seed, gain, tol_mm, max_iter, transport) as loop:
        summary["physical"] = loop.phys.describe()
        summary["rig"] = {"scale_m_per_model_unit": loop.scale, "standoff_m": loop.vision.geometry.standoff_m,
                          "focal_px": loop.vision.camera.focal_px, "baseline_m": loop.vision.camera.baseline_m}
        variants = {"uncorrected": (None, False)}
        cal = rec = None
        if calibrate_model:
            fit = interface.progress(total=2, desc="rig-sim calibration", unit="stage")
            fit.set_postfix_str(f"probe, {len(PROBE)} paddle positions")
            rec = loop.probe(PROBE)
            fit.update()
            fit.set_postfix_str("L-BFGS fit")
            t = time.perf_counter()
            cal = calibration.calibrate(loop.ctrl.model, rec, {"alpha": MODEL_ALPHA, "beta": MODEL_BETA},
                            fit=("beta",), regions=(3, 3), steps=60)
            summary["calibration"] = {
                "probe_paddle": rec.paddle.tolist(), "fit": ["beta", "3x3 stiffness map"],
                "beta_median": float(np.median(cal.params["beta"])),
                "stiffness_map": cal.stiffness_map.T[::-1].round(3).tolist(),
                "cp_rms_model_units": list(cal.cp_rms), "force_rel_rms": list(cal.force_rel_rms),
                "iterations": len(cal.loss) - 1, "wall_s": round(time.perf_counter() - t, 1),
                "solves_converged": cal.converged_solves}
            fit.update()
            fit.close()
            variants["calibrated"] = (cal.params, False)
        if broyden:
            variants["broyden"] = (None, True)
        if calibrate_model and broyden:
            variants["calibrated+broyden"] = (cal.params, True)
        runs, summary["runs"] = execute(loop, desired, variants, budget)
        summary["camera_frames_flagged"] = loop.vision.n_flagged
    base = summary["runs"]["uncorrected"]
    summary["vs_uncorrected"] = {
        name: {"budget_mean_physical_error_ratio": r["budget"]["physical_error_mm"]["mean"]
               / base["budget"]["physical_error_mm"]["mean"],
               "tracking_iterations_ratio": r["tracking"]["iterations"] / max(base["tracking"]["iterations"], 1)}
        for name, r in summary["runs"].items() if name != "uncorrected"}
    primary = list(runs)[-1]
    summary["primary"] = primary
    summary["wall_s"] = round(time.perf_counter() - t0, 1)
    if make_figures:
        main_run = runs[primary]["tracking"]
        fig_paths(main_run, f"{path} - {primary}", out)
        fig_errors(main_run, f"{path} - {primary}", tol_mm, out)
        fig_forces(main_run, f"{path} - {primary}", out)
        names = ["cp_paths.png", "errors.png", "forces.png"]
        if len(runs) > 1:   # a comparison needs two variants (--calibrate and/or --broyden)
            fig_compare(runs, out)
            names.append("compare.png")
        if cal is not None:
            fig_calibration(cal, rec, out)
            names.append("calibration.png")
        summary["figures"] = names
    np.savez_compressed(out / "history.npz", **{f"{n}_{m}_{k}": v for n, modes in runs.items()
                                               for m, r in modes.items() for k, v in r.arrays().items()})
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def result(s: dict) -> tuple[bool, str]:
    """(goal reached, the result in words) of a rig summary. The goal, the thesis' finding:
    every tracking run reaches every waypoint and settles within RIG_SETTLE_MM of it
    physically. The budget run's error (a fixed number of iterations per waypoint, by design
    short of settling) measures the Jacobian and is said apart from it."""
    tol = s["settings"]["tol_mm"]
    parts = []
    for name, r in s["runs"].items():
        t, b = r["tracking"], r["budget"]
        reached = sum(w["reached_at"] >= 0 for w in t["waypoints"])
        parts.append(f"{name}: {reached}/{len(t['waypoints'])} waypoints within {tol:g} mm (camera) in "
                     f"{t['iterations']} iterations, physical error max {t['physical_error_mm']['max']:.2f} mm "
                     f"(thesis: settles within {RIG_SETTLE_MM:g} mm)"
                     + ("" if t["status"] == "DONE" else f" ({t['status']}: {t['message']})")
                     + f"; budget run, {s['settings']['budget']} iteration(s) per waypoint (a measure of the "
                       f"Jacobian, not a settling): mean physical error {b['physical_error_mm']['mean']:.2f} mm")
    ok = all(r["tracking"]["status"] == "DONE" and r["tracking"]["physical_error_mm"]["max"] <= RIG_SETTLE_MM
             for r in s["runs"].values())
    return ok, f"rig-sim {s['path']}: " + " | ".join(parts)


SEED_MAX = 2 ** 32 - 1          # NumPy's seeds are unsigned 32-bit words


def _waypoints(a, given):
    n_path = len(PATHS[a.path])
    if a.waypoints is not None and a.waypoints > n_path:
        return f"argument --waypoints: the {a.path} path has {n_path} waypoints, got {a.waypoints}"
    return None


def parser() -> interface.Parser:
    number = interface.number
    p = interface.parser("rig-sim", __doc__, "results/rig_sim/<path>")
    p.add_argument("--path", choices=RIG_PATHS, default="box")
    p.add_argument("--calibrate", action="store_true", help="fit beta + a 3x3 stiffness map to a probe first")
    p.add_argument("--broyden", action="store_true", help="online Broyden Jacobian correction")
    p.add_argument("--physical-n", type=number(int, 5), default=17,
                   help="particles per side of the physical object (bounded by the memory available)")
    p.add_argument("--noise", type=number(float, 0, 255), default=2.0, help="pixel noise std (grey levels, 0..255)")
    p.add_argument("--seed", type=number(int, 0, SEED_MAX), default=0, help="noise seed, 0..2^32-1")
    p.add_argument("--gain", type=number(float, 0, 1, low_open=True), default=0.7,
                   help="the fraction of the camera error each iteration corrects, in (0, 1] (above 1 every "
                        "step overshoots its waypoint and the loop oscillates)")
    p.add_argument("--tol-mm", type=interface.POSITIVE, default=0.3, help="camera tolerance per waypoint (mm)")
    p.add_argument("--max-iter", type=number(int, 1, 10_000), default=30,
                   help="iterations per waypoint (tracking), 1..10000")
    p.add_argument("--budget", type=number(int, 1, 10_000), default=1,
                   help="iterations per waypoint (budget mode), 1..10000")
    p.add_argument("--transport", choices=("tcp", "inprocess"), default="tcp")
    p.add_argument("--waypoints", type=interface.COUNT, default=None,
                   help="only the first N waypoints (default: all; at most the path's)")
    p.add_argument("--no-figures", action="store_true")
    p.check(_waypoints)
    p.check(interface.memory_check("--physical-n", lambda k: k * k))
    return p


def main(argv=None):
    a = parser().parse_args(argv)
    results = interface.results("rig-sim", a, a.out or f"results/rig_sim/{a.path}")
    with results as out:
        s = run(out, a.path, a.calibrate, a.broyden, a.physical_n, a.noise, a.seed, a.gain, a.tol_mm,
                a.max_iter, a.budget, a.transport, a.waypoints, not a.no_figures)
        results.finish(s, *result(s), a.json)
    return s


# ------------------------------------------------------------------ the experiment of reproduce
def _run(out: Path, quick: bool) -> tuple[str, list]:
    return "rig-sim", ["--path", "setpoint", "--out", str(out)]


def _ours(s):
    r = s["runs"]["uncorrected"]["tracking"]
    return (f"uncorrected: physical error at the waypoints max {r['physical_error_mm']['max']:.2f} mm "
            f"(mean {r['physical_error_mm']['mean']:.2f} mm), {r['iterations']} iterations, {r['status']}")


def _judge(s):
    r = s["runs"]["uncorrected"]["tracking"]
    return (IN_KIND, "simulated") if r["physical_error_mm"]["max"] <= RIG_SETTLE_MM else (DIFFERS, "error")


def entries() -> list:
    return [Entry("rig_sim_setpoint", "Figs 5.33, 5.35", '"the physical control point is shown to settle within '
                  f'a error margin of {RIG_SETTLE_MM:g} millimeter of the target"', _run, _ours,
                  note="simulated rig (stereo vision, TCP robot link, a physical object the model does not know)",
                  judge=_judge)]


COMMAND = Command("rig-sim", "the simulated rig of section 5.3.2: vision, robot link, an object the model does "
                             "not know", parser, main, result, order=30, reproduce=entries)

"""Render the performance page, ``docs/performance.md``, from the benches' records.

    python -m experiments.performance                 # from experiments/records/, into docs/
    python -m experiments.performance --smoke --out /tmp/performance.md   # smoke runs too
    python -m experiments.performance --check         # exit 1 if the page is not up to date

Each bench (``experiments/bench_*.py``) gets a section: what it measures (its docstring's
first line), and for the latest record of each of its variants the command that made it,
the commit, the date, the machine and the load average beside the tables of its figures
and same-run ratios. A bench with no record yet is listed with the command to run. The page
holds no figure that a bench run did not write.
"""
from __future__ import annotations

import argparse
import ast
import shlex
import sys
from pathlib import Path

from experiments import records

ROOT = records.ROOT
OUT = ROOT / "docs" / "performance.md"
BENCHES = sorted(p.stem for p in Path(__file__).resolve().parent.glob("bench_*.py"))

# the commands that fill the page on a quiet machine (the figures the docs used to quote)
COMMANDS = {
    "bench_solve": ["python -m experiments.bench_solve"],
    "bench_scni": ["python -m experiments.bench_scni"],
    "bench_tracking": ["python -m experiments.bench_tracking"],
    "bench_sweep": ["python -m experiments.bench_sweep"],
    "bench_contact": ["python -m experiments.bench_contact"],
    "bench_cube3d": ["python -m experiments.bench_cube3d --n 6 10 --loop-steps 20 --crossover",
                     "python -m experiments.bench_cube3d --only-crossover"],
    "bench_cube3d_large": ["python -m experiments.bench_cube3d_large --n 14 20 --solver sparse krylov",
                           "python -m experiments.bench_cube3d_large --n 30 --solver sparse --repeats 0 "
                           "--max-rss-gb 14 --label '30^3 cold'"],
    "bench_contention": ["python -m experiments.bench_contention",
                         "python -m experiments.bench_contention --workloads cube20 --repeats 3 --label cube20"],
    "bench_needle3d": ["python -m experiments.bench_needle3d --resolutions 500 2000",
                       "python -m experiments.bench_needle3d --resolutions 8000 --increments 1 --repeats 1 "
                       "--no-sweep --label 8000"],
    "bench_needle3d_memory": ["python -m experiments.bench_needle3d_memory 0.055 --solve --limit-gb 13"],
}


# ------------------------------------------------------------------ formatting
def num(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if isinstance(x, float):
        return f"{x:.{digits}g}"
    return str(x)


def spread(s) -> str:
    """A records.stats dict as 'median (min–max, n)'; a plain number as itself."""
    if isinstance(s, dict) and "median" in s:
        if s["repeats"] in (0, None):
            return "–"
        if s["repeats"] == 1:
            return f"{num(s['median'])} (n=1)"
        return f"{num(s['median'])} ({num(s['min'])}–{num(s['max'])}, n={s['repeats']})"
    return num(s)


def table(headers, rows) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(str(c).replace("|", "\\|") for c in row) + " |" for row in rows]
    return "\n".join(out)


def get(d, *keys, default=None):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


# ------------------------------------------------------------------ the benches' tables
def t_solve(f):
    rows = [[k, num(get(r, "dof")), f"{get(r, 'solver')} {get(r, 'factorisation') or ''}".strip(),
             num(get(r, "build_s")), num(get(r, "compile_s")), num(get(r, "first_solve_s")),
             spread(get(r, "warm_solve_s")), num(get(r, "newton_iterations")), num(get(r, "peak_rss_gb")),
             get(r, "status") or get(r, "error")] for k, r in f.items()]
    return [("Neo-Hookean blocks, 30% compression in 10 load steps (seconds; memory in GB)",
             ["case", "DOF", "solver", "build", "compile", "first solve", "warm solve", "Newton its", "peak RSS",
              "status"], rows)]


def t_contact(f):
    rows = []
    for k, r in f.items():
        if not (isinstance(r, dict) and "contact" in r):
            continue
        for m in ("contact", "glued"):
            x = r[m]
            rows.append([k, num(r.get("particles")), m, num(x.get("build_s")), num(x.get("first_solve_s")),
                         spread(x.get("warm_solve_s")), num(x.get("load_steps")), num(x.get("newton_iterations")),
                         num(x.get("force"))])
    return [("A block pressed by a rigid paddle (contact) or by its glued particles (seconds)",
             ["case", "particles", "paddle", "build", "first solve", "warm solve", "load steps", "Newton its",
              "force"], rows)]


def t_scni(f):
    rows = [[f"{r['n']}x{r['n']}", r["integration"], r["solver"], num(r["integration_points"]), num(r["free_dof"]),
             num(r["newton_iterations"]), spread(r.get("warm_solve_s", r.get("warm_solve_s_median"))),
             num(r["time_per_iteration_s"]), spread(r.get("assembly_s", r.get("assembly_s_median")))]
            for r in f.get("results", [])]
    return [("Fung block, paddle pushed 5% (seconds)",
             ["size", "integration", "solver", "points", "free DOF", "Newton its", "warm solve", "per iteration",
              "assembly"], rows)]


def t_tracking(f):
    out = []
    if f.get("tracking"):
        rows = [[k, r.get("status", r.get("error")), num(r.get("iterations")), spread(r.get("wall_s")),
                 num(r.get("compile_s")), num(r.get("thesis_min_gauss")), num(r.get("thesis_min_collocated"))]
                for k, r in f["tracking"].items()]
        out.append(("Chapter-5 tracking on the 9x9 Fung square (seconds; the thesis' run times in minutes)",
                    ["path", "status", "iterations", "warm run", "compile", "thesis Gauss (min)",
                     "thesis collocated (min)"], rows))
    if f.get("jacobian"):
        rows = [[k, num(r.get("free_dof")), spread(r.get("implicit_ms")), spread(r.get("central_fd_ms")),
                 num(r.get("tracking_loop_jacobian_ms")), num(r.get("in_loop_marginal_ms")),
                 num(r.get("relative_difference"))] for k, r in f["jacobian"].items() if "error" not in r]
        out.append(("Control-point Jacobian per call (milliseconds)",
                    ["grid", "free DOF", "implicit", "central FD", "as the loop takes it", "marginal in the loop",
                     "FD vs implicit (rel.)"], rows))
    return out


def t_sweep(f):
    rows = [[num(r["configurations"]), num(r["solves"]), num(r["converged_fraction"]), num(r["newton_iterations"]),
             spread(r.get("batched_warm_s", r.get("batched_warm_median_s"))),
             spread(r.get("loop_warm_s", r.get("loop_warm_median_s"))), num(r.get("batched_cold_s")),
             num(r.get("loop_cold_s")), num(r.get("max_abs_difference"))] for r in f.get("rows", [])]
    out = [(f"Needle sweep, batched ({f.get('batching')}, {f.get('devices')} device(s)) against a Python loop "
            "(seconds)", ["configurations", "solves", "converged", "Newton its", "batched warm", "loop warm",
                          "batched cold", "loop cold", "max difference"], rows)]
    if "floor" in f:
        fl = f["floor"]
        out.append(("The arithmetic floor of the same solves (seconds)", ["configurations", "floor", "loop",
                    "batched"], [[num(fl["configurations"]), num(fl["floor_s"]), num(fl["loop_warm_s"]),
                                  num(fl["batched_warm_s"])]]))
        if "operations" in fl:    # the counted floor: each executed operation at its kernel's cost
            ops = list(fl["operations"]) + ["jacobian_rhs"]
            count = lambda op: fl["jacobians"] if op == "jacobian_rhs" else fl["operations"][op]
            out.append(("The floor's operations: how many the sweep executed, each at its kernel's cost per "
                        "member", ["operation", "executed", "per member (ms)", "total (s)"],
                        [[op, num(count(op)), num(fl["per_member"][f"{op}_s"] * 1e3), num(fl["terms_s"][op])]
                         for op in ops]))
    prof = [r for r in f.get("rows", []) if "lockstep" in r]
    if prof:
        piece = lambda ls, k: num(ls["pieces_s"][k] * 1e3)
        out.append(("One lock-step iteration against its pieces, each over the whole batch (milliseconds)",
                     ["configurations", "lock-step its", "member its", "per iteration", "assembly", "factorisation",
                      "triangular solves", "energy + gradient", "force scale", "other"],
                     [[num(r["configurations"]), num(ls["lockstep_iterations"]), num(ls["member_iterations"]),
                       num(ls["seconds_per_lockstep_iteration"] * 1e3)
                       + ("" if "batched_warm_median_s" in r else " (cold: compile included)"), piece(ls, "assembly_s"),
                       piece(ls, "factorisation_s"), piece(ls, "triangular_solves_s"),
                       piece(ls, "energy_and_gradient_s"), piece(ls, "force_scale_s"), num(ls["other_s"] * 1e3)]
                      for r in prof for ls in [r["lockstep"]]]))
    prof = [r for r in f.get("rows", []) if "lock_step_profile" in r]
    if prof:
        ms = lambda v: num(v * 1e3) if isinstance(v, (int, float)) else "–"
        keys = ["assembly_s", "factorisation_s", "triangular_solves_s", "energy_residual_s", "force_scale_s"]
        out.append(("The lock step against its pieces, each over the whole batch (pieces: milliseconds a call; "
                    "whole run: seconds)",
                    ["configurations", "lock-step its", "stragglers' its", "members that left",
                     "assembly", "factorisation", "triangular solves", "energy + residual", "force scale",
                     "modelled", "warm", "other"],
                    [[num(r["configurations"]), num(ls["lock_step_iterations"]),
                      num(ls["straggler_iterations"]) if "straggler_iterations" in ls else
                      f'{num(ls["straggler_iterations_estimate"])} (counted as one group)',   # earlier records
                      num(ls["members_that_left"]),
                      *(ms(ls["pieces_s"].get(k)) for k in keys), num(ls["modelled_s"]),
                      num(r.get("batched_warm_median_s", "–")), num(ls.get("other_s", "–"))]
                     for r in prof for ls in [r["lock_step_profile"]]]))
    return out


def t_cube3d(f):
    out = []
    cases = {k: v for k, v in f.items() if k.startswith("cube_")}
    if cases:
        rows = []
        for k, r in cases.items():
            if "error" in r:
                rows.append([k] + ["–"] * 9 + [r["error"]])
                continue
            sp = r.get("spread_s", {})
            rows.append([k, num(r["dof"]), r["path"], spread(sp.get("default_solve", r["default_warm_solve_s"])),
                         spread(sp.get("full_newton_solve", r["full_newton_warm_solve_s"])),
                         spread(sp.get("jacobian", r["jacobian_s"])), spread(sp.get("control_step", r["control_step_s"])),
                         num(r["loop_factorise_every_step"]["s_per_iteration"]),
                         num(r["loop_kept_factorisation"]["s_per_iteration"]), num(r["peak_rss_gb"]), r["status"]])
        out.append(("Neo-Hookean n³ cube, 30% in 10 steps (seconds)",
                    ["case", "DOF", "path", "default solve", "full Newton", "Jacobian", "control step",
                     "loop step, factorise every step", "loop step, kept", "peak RSS (GB)", "status"], rows))
    cross = get(f, "crossover", "sizes")
    if cross:
        rows = [[num(r["n"]), num(r.get("dof")), num(get(r, "dense", "iteration_s")),
                 num(get(r, "dense_mixed", "iteration_s")), num(get(r, "sparse", "iteration_s")),
                 num(r.get("dense_over_sparse"))] for r in cross]
        out.append(("One Newton iteration's linear work, dense against sparse (seconds)",
                    ["n", "DOF", "dense double", "dense mixed", "sparse", "dense (auto) / sparse"], rows))
    return out


def t_cube3d_large(f):
    rows = []
    for k, r in f.items():
        if not k.startswith("cube_"):
            continue
        if "error" in r:
            rows.append([k] + ["–"] * 8 + [r["error"]])
            continue
        p = r.get("profile", {})
        rows.append([k, num(r["dof"]), num(r["build_s"]), num(r["cold_solve_s"]), spread(r["warm_solves"])
                     if r["warm_solves"] else num(r["warm_solve_s"]), num(r["newton_iterations"]),
                     num(p.get("assembly_s")), num(p.get("other_s")), num(r.get("peak_rss_gb")), r["status"]])
    return [("Large neo-Hookean cubes, 30% in 10 steps (seconds; memory in GB)",
             ["case", "DOF", "build", "cold solve", "warm solve", "Newton its", "assembly", "other", "peak RSS",
              "status"], rows)]


def t_contention(f):
    rows = [[k, spread(r.get("quiet_s", r["quiet_median_s"])), spread(r.get("busy_s", r["busy_median_s"])),
             num(r["busy_over_quiet"])] for k, r in f.get("workloads", {}).items()]
    return [(f"Each workload quiet and beside one busy process, interleaved (seconds; BLAS threads "
             f"{f.get('blas_threads')}, sparse threads {f.get('sparse_threads')})",
             ["workload", "quiet", "beside a busy process", "busy / quiet"], rows)]


def t_needle3d(f):
    out = []
    rows = [[k.split(":")[1], num(r.get("particles")), num(r.get("free_dof")), r.get("solver"), num(r.get("build_s")),
             num(r.get("first_insertion_s")), spread(r.get("warm_insertion_s", r.get("warm_insertion_s_median"))),
             num(r.get("peak_rss_gb")), r.get("status") or r.get("error")]
            for k, r in f.items() if k.startswith("resolution:")]
    if rows:
        out.append((f"3D phantom, the needle inserted in {f.get('increments')} increments (seconds; memory in GB)",
                    ["resolution", "particles", "free DOF", "solver", "build", "first insertion", "warm insertion",
                     "peak RSS", "status"], rows))
    rows = [[k.split(":")[1], num(r.get("particles")), num(r.get("patches")), spread(r.get("batched_warm_s")),
             spread(r.get("loop_warm_s")), num(r.get("batched_cold_s")), num(r.get("loop_cold_s")),
             num(r.get("max_abs_difference"))] for k, r in f.items() if k.startswith("sweep:") and "error" not in r]
    if rows:
        out.append(("3D patch sweep, batched against a Python loop (seconds)",
                    ["resolution", "particles", "patches", "batched warm", "loop warm", "batched cold", "loop cold",
                     "max difference"], rows))
    return out


def t_memory(f):
    rows = [[k, num(v)] for k, v in f.items() if not isinstance(v, (dict, list))]
    rows += [[f"peak at stage {stage}", f"{num(p['peak_gb'])} GB"] for stage, p in f.get("peak_by_stage", {}).items()]
    return [("Where the 3D phantom's memory goes", ["quantity", "value"], rows)]


def t_generic(f):
    """Scalars in one table; a dict of like records (e.g. one per scheme) as a table of its own,
    a row per record and a column per scalar field."""
    rows, tables = [[k, num(v)] for k, v in f.items() if not isinstance(v, (dict, list))], []
    for k, v in f.items():
        if not isinstance(v, dict):
            continue
        if v and all(isinstance(r, dict) and "median" not in r for r in v.values()):
            cols = [c for c in dict.fromkeys(c for r in v.values() for c in r)
                    if all(not isinstance(r.get(c), (dict, list)) for r in v.values())]
            tables.append((k, [k, *cols], [[name, *(num(r.get(c, "")) for c in cols)] for name, r in v.items()]))
        else:
            rows += [[f"{k}: {k2}", num(v2) if not isinstance(v2, dict) else spread(v2)] for k2, v2 in v.items()
                     if not isinstance(v2, list)]
    return [("Figures", ["quantity", "value"], rows), *tables]


TABLES = {"bench_contact": t_contact, "bench_solve": t_solve, "bench_scni": t_scni, "bench_tracking": t_tracking, "bench_sweep": t_sweep,
          "bench_cube3d": t_cube3d, "bench_cube3d_large": t_cube3d_large, "bench_contention": t_contention,
          "bench_needle3d": t_needle3d, "bench_needle3d_memory": t_memory}


# ------------------------------------------------------------------ the page
def purpose(bench: str) -> str:
    """The first sentence of the bench's docstring (read statically: nothing is imported)."""
    doc = ast.get_docstring(ast.parse((ROOT / "experiments" / f"{bench}.py").read_text())) or ""
    first = " ".join(doc.split("\n\n")[0].split()).split(". ")[0]
    first = first.removeprefix("Benchmark: ").removeprefix("Benchmark of ")
    first = first[:1].upper() + first[1:]
    return first if first.endswith((".", "?", "!")) else first + "."


def machine_line(r: dict) -> str:
    m, c = r["machine"], r["commit"]
    gpus = ", ".join(m.get("gpus") or []) or "no GPU"
    v = m.get("versions", {})
    before, after = r["load_average"]["before"], r["load_average"].get("after", [None])
    sha = f"`{(c.get('sha') or 'unknown')[:8]}`" + (" (with uncommitted changes)" if c.get("dirty") else "")
    smoke = " **Smoke run: the figures check the pipeline, they measure nothing.**" if r.get("smoke") else ""
    mem = f", {m['memory_gb']:.0f} GB" if m.get("memory_gb") else ""
    return (f"Run {r['date']} at commit {sha} on {m.get('cpu')} ({m.get('cores')} cores, "
            f"{m.get('usable_cores')} usable{mem}; {gpus}); jax {v.get('jax')}, jaxlib {v.get('jaxlib')}; "
            f"load average (1 min) {before[0]:.1f} before, {after[0]:.1f} after; the run took "
            f"{num(r.get('wall_s'))} s.{smoke}")


def command_of(r: dict) -> str:
    return "python -m experiments." + r["bench"] + "".join(" " + shlex.quote(a) for a in r.get("argv", []))


def section(bench: str, recs: list[dict]) -> str:
    out = [f"## {bench}", "", purpose(bench), ""]
    if not recs:
        out += ["No record yet. On a quiet machine, from the repository root:", "", "```bash"]
        out += COMMANDS.get(bench, [f"python -m experiments.{bench}"]) + ["```", ""]
        return "\n".join(out)
    for r in recs:
        if r.get("variant"):
            out += [f"### {r['variant']}", ""]
        out += [f"`{command_of(r)}`", "", machine_line(r), ""]
        for caption, headers, rows in TABLES.get(bench, t_generic)(r["figures"]):
            if rows:
                out += [f"*{caption}*", "", table(headers, rows), ""]
        if r.get("ratios"):
            out += ["*Same-run ratios*", "", table(["ratio", "value"], [[k, num(v)] for k, v in r["ratios"].items()]), ""]
    return "\n".join(out)


def render(smoke: bool = False, folder: Path = records.RECORDS) -> str:
    head = ["# Performance", "",
            "<!-- generated by experiments/performance.py from experiments/records/: edit those, not this page -->",
            "",
            "Every figure on this page was written by a bench run (`experiments/bench_*.py`) into a record",
            "under `experiments/records/`, with the commit, the machine and the load average it ran at;",
            "`python -m experiments.performance` renders the latest record of each bench. Compare figures",
            "within one table: the same machine's speed differs from day to day and with its load. The",
            "rest of the documentation gives the reasons behind the choices these benches measure",
            "([design](design.md)).", ""]
    return "\n".join(head + [section(b, records.latest(b, smoke, folder)) for b in BENCHES]).rstrip() + "\n"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--records", type=Path, default=records.RECORDS, help="the records folder")
    p.add_argument("--smoke", action="store_true", help="include smoke runs (never for the committed page)")
    p.add_argument("--check", action="store_true", help="exit 1 if --out differs from what the records give")
    a = p.parse_args(argv)
    page = render(a.smoke, a.records)
    if a.check:
        current = a.out.read_text() if a.out.exists() else ""
        if current != page:
            print(f"{a.out} is not up to date: run python -m experiments.performance", file=sys.stderr)
            return 1
        return 0
    a.out.write_text(page)
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Reproduce the thesis: run every thesis experiment the project implements and write
``DIR/report.md`` (per experiment: the thesis' figure/table, the thesis' value quoted, ours,
a verdict, agrees / agrees in kind / differs, with its reason in a word, and the figures we
made; each note once, below the table) and ``DIR/report.json``.

``jaxrkpm reproduce --out DIR [--quick] [--only ID ...]``. Each experiment runs through its
script's ``main(argv)`` (the same options as its own command) into ``DIR/<id>/``; its printed
output goes to ``DIR/<id>/log.txt``. ``--quick`` runs a small subset at reduced sizes (5x5
instead of 9x9, a few compression steps): a smoke test of the pipeline, not the thesis'
numbers. A progress bar tracks the experiments (on a terminal); the full run takes minutes
(``jaxrkpm reproduce`` prints its wall time). An experiment that fails is reported as failed;
the others still run (exit code 1).
"""
from __future__ import annotations

import contextlib
import io
import json
import time
import traceback
from pathlib import Path

from jaxrkpm.base.programs import release_compiled_programs
from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import Command, command
from jaxrkpm.thesis.studies.experiments import AGREES, DIFFERS, IN_KIND, Entry, entries


def run_entry(e: Entry, root: Path, quick: bool, reuse: bool = False) -> dict:
    """Run one experiment into root/<id>/ (``reuse``: read an existing summary.json instead,
    e.g. to resume an interrupted run or to rebuild the report) and return its report row."""
    out = root / e.id
    log = io.StringIO()
    t0 = time.perf_counter()
    row = {"id": e.id, "thesis_ref": e.thesis_ref, "thesis_value": e.thesis_value, "note": e.note}
    try:
        if reuse and (out / "summary.json").exists():
            s = json.loads((out / "summary.json").read_text())
            row["reused"] = True
        else:
            study, argv = e.run(out, quick)
            # reproduce's own folder was claimed for this run: its experiments replace theirs
            with contextlib.redirect_stdout(log):
                s = command(study).main(argv + ["--overwrite"])
        if s is None:   # scripts that only write their summary
            s = json.loads((out / "summary.json").read_text())
        row.update(status="ok", ours=e.ours(s))
        row["verdict"], row["reason"] = e.judge(s) if e.judge else ("-", "not in the thesis")
    except Exception as exc:  # one failing experiment must not sink the report
        log.write(traceback.format_exc())
        row.update(status="failed", ours=f"failed: {type(exc).__name__}: {exc}", verdict="-", reason="failed")
    except SystemExit as exc:  # argparse errors inside a script
        row.update(status="failed", ours=f"failed: bad options (exit {exc.code})", verdict="-", reason="failed")
    row["wall_s"] = round(time.perf_counter() - t0, 1)
    if not row.get("reused"):
        out.mkdir(parents=True, exist_ok=True)
        (out / "log.txt").write_text(log.getvalue())
        interface.also_written(out, "log.txt")
    row["figures"] = sorted(str(p.relative_to(root)) for p in out.rglob("*.png"))
    return row


MAIN_FIGURES = ("cp_path", "cp_paths", "deformed", "convergence")   # preferred, in this order


def main_figure(figures) -> str:
    """The figure that shows the experiment best (the path, the deformed shapes), else the first."""
    for stem in MAIN_FIGURES:
        for f in figures:
            if Path(f).stem.startswith(stem):
                return f
    return figures[0]


def report_md(rows, quick: bool, total_s: float) -> str:
    lines = ["# Reproduction of the thesis", "",
             ("**Quick run** (reduced sizes): a smoke test of the pipeline, not the thesis' numbers."
              if quick else "Full run at the thesis' sizes."),
             f"Experiments' wall time (sum) {sum(r['wall_s'] for r in rows) / 60:.1f} min; "
             f"this invocation {total_s / 60:.1f} min"
             + (f" ({sum(bool(r.get('reused')) for r in rows)} experiments read from an earlier run, --reuse)."
                if any(r.get("reused") for r in rows) else "."), "",
             "Verdict: **agrees** (the thesis' number, within its tolerance), **agrees in kind** (the "
             "same finding where the setup cannot match exactly: another integration scheme, a "
             "simulated rig, a phantom with unstated details) or **differs**, with the reason in a "
             "word; [n]: a note below.", "",
             "| experiment | thesis | thesis' value | ours | verdict | run (s) | figures |",
             "|---|---|---|---|---|---|---|"]
    notes = list(dict.fromkeys(r["note"] for r in rows if r["note"]))   # each note once, in order
    for r in rows:
        figs = " ".join(f"[{Path(f).stem}]({f})" for f in r["figures"]) or "-"
        verdict = f"{r.get('verdict', '-')} ({r.get('reason', '?')})"
        if r["note"]:
            verdict += f" [{notes.index(r['note']) + 1}]"
        lines.append(f"| `{r['id']}` | {r['thesis_ref']} | {r['thesis_value']} | {r['ours']} | {verdict} "
                     f"| {r['wall_s']:.0f} | {figs} |")
    counts = {v: sum(r.get("verdict") == v for r in rows) for v in (AGREES, IN_KIND, DIFFERS)}
    lines += ["", "Verdicts: " + ", ".join(f"{v} {n}" for v, n in counts.items()) + "."]
    if notes:
        lines += ["", "Notes:", ""] + [f"{i}. {n}" for i, n in enumerate(notes, 1)]
    lines += ["", "Figures (the main one of each experiment):", ""]
    for r in rows:
        if r["figures"]:
            lines += [f"### {r['id']}", "", f"![{r['id']}]({main_figure(r['figures'])})", ""]
    return "\n".join(lines) + "\n"


def result(rep: dict) -> tuple[bool, str]:
    """(every experiment ran, the result in words) of a report."""
    rows = rep["experiments"]
    failed = [r["id"] for r in rows if r["status"] != "ok"]
    counts = {v: sum(r.get("verdict") == v for r in rows) for v in (AGREES, IN_KIND, DIFFERS)}
    words = (f"{len(rows) - len(failed)}/{len(rows)} experiments ran in {rep['total_wall_s'] / 60:.1f} min"
             + (f" (failed: {', '.join(failed)})" if failed else "") + "; "
             + "verdicts: " + ", ".join(f"{v} {n}" for v, n in counts.items()) + " (report.md)")
    return not failed, words


def parser() -> interface.Parser:
    known = [e.id for e in entries()]
    p = interface.parser("reproduce", __doc__, "results/reproduce")
    p.add_argument("--quick", action="store_true", help="small subset at reduced sizes (smoke test)")
    p.add_argument("--only", nargs="+", default=None, metavar="ID",
                   help=f"run only these (default: all): {', '.join(known)}")
    p.add_argument("--reuse", action="store_true",
                   help="read DIR/<id>/summary.json where it exists instead of re-running (resume / rebuild)")

    @p.check
    def known_ids(a, given):
        bad = [i for i in a.only or () if i not in known]
        return f"unknown experiment id(s) {bad}; choose from {sorted(known)}" if bad else None
    return p


def main(argv=None):
    a = parser().parse_args(argv)
    chosen = [e for e in entries() if (e.id in a.only if a.only else (e.quick or not a.quick))]
    results = interface.results("reproduce", a, staged=False, ignore=("only", "reuse"))
    earlier = {}
    if a.reuse and (Path(a.out) / "report.json").exists():   # keep the timings of the runs reused
        earlier = earlier_rows(Path(a.out) / "report.json")
    with results as root:
        rep = run_all(a, chosen, root, earlier)
        results.finish(rep, *result(rep), a.json)
    return rep


def earlier_rows(path: Path) -> dict:
    """id -> row of an earlier report.json; an OutputError (exit 3) naming it if it cannot
    be read as one."""
    try:
        rows = json.loads(path.read_text())["experiments"]
        return {r["id"]: r for r in rows}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise interface.OutputError(f"cannot --reuse {path}: not a readable report "
                                    f"({type(e).__name__}: {' '.join(str(e).split())})") from None


def run_all(a, entries, root: Path, earlier: dict) -> dict:
    """Run (or reuse) every experiment into root/<id>/; write report.json and report.md."""
    t0 = time.perf_counter()
    rows = []
    bar = interface.progress(entries, desc="reproduce", unit="exp", leave=True)
    for e in bar:
        bar.set_postfix_str(e.id)
        row = run_entry(e, root, a.quick, a.reuse)
        # the experiments share no compiled program worth keeping, and all of them together could
        # hold more memory mappings than Linux allows a process (jaxrkpm/programs.py)
        release_compiled_programs()
        if row.get("reused") and e.id in earlier:
            row["wall_s"] = earlier[e.id].get("wall_s", row["wall_s"])
        rows.append(row)
    total = time.perf_counter() - t0
    rep = {"quick": a.quick, "total_wall_s": round(total, 1),
           "experiments_wall_s": round(sum(r["wall_s"] for r in rows), 1), "experiments": rows}
    (root / "report.json").write_text(json.dumps(rep, indent=2))
    (root / "report.md").write_text(report_md(rows, a.quick, total))
    return rep


COMMAND = Command("reproduce", "every experiment above; report.md with a verdict per row", parser, main, result,
                  order=90, interrupted="the experiments finished so far are kept in DIR/<id>/; the same command "
                                        "with --reuse reads them instead of running them again")

"""Volumetric locking on Cook's membrane (plane strain) and a cantilever block (3D): the
displacement of a corner against FElupe's mixed (u-p-J) reference, for Gauss, SCNI and MSCNI
integration at several resolutions and Poisson's ratios, with the model's default
(anti-locking on from nu = 0.45) and, at nu = 0.499, with it off.

    python -m experiments.cook_membrane                 # every case (minutes), writes the JSON
    python -m experiments.cook_membrane --table         # the ratio tables from the JSON
    python -m experiments.cook_membrane --cook-spacings --block-spacings 0.1666666666666667
                                                        # one resolution, merged into the JSON
    python -m experiments.cook_membrane --schemes scni mscni   # some integrations, merged

The problems are ``tests/problems.py``'s ``cook_membrane`` and ``cantilever_block``; the
references are ``experiments/cook_reference.json`` (made by ``experiments/cook_reference.py``).
A ratio is u / reference at the same nu."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "cook_membrane.json"
REFERENCE = HERE / "cook_reference.json"
sys.path.insert(0, str(HERE.parent))

NUS = (0.3, 0.45, 0.49, 0.499)
SCHEMES = ("gauss", "scni", "mscni")


def references() -> dict:
    """problem -> {nu: reference value} from cook_reference.json."""
    data = json.loads(REFERENCE.read_text())
    return {"cook_2d": {float(nu): v["uy_48_60"] for nu, v in data["cook"]["results"].items()},
            "block_3d": {float(nu): v["points"]["(4,0.5,1)"]["uz"] for nu, v in data["block"]["results"].items()}}


def run(problem: str, spacings, nus=NUS, schemes=SCHEMES) -> list:
    from tests.problems import cantilever_block, cook_membrane
    solve = cook_membrane if problem == "cook_2d" else cantilever_block
    rows = []
    for spacing in spacings:
        for scheme in schemes:
            for nu, anti in [(nu, None) for nu in nus] + [(0.499, False)]:
                t0 = time.perf_counter()
                value, particles = solve(spacing, nu, scheme, anti_locking=anti, count=True)
                rows.append({"problem": problem, "spacing": spacing, "particles": particles, "integration": scheme,
                             "nu": nu, "anti_locking": "default" if anti is None else anti, "value": value,
                             "seconds": time.perf_counter() - t0})
                print(json.dumps(rows[-1]), flush=True)
    return rows


def table(rows: list) -> str:
    """Markdown: per problem, resolution and integration, the ratio at each nu (default) and at
    nu = 0.499 with anti-locking off."""
    refs = references()
    lines = []
    for problem in ("cook_2d", "block_3d"):
        mine = [r for r in rows if r["problem"] == problem]
        if not mine:
            continue
        lines += [f"\n{problem}: u / reference", "",
                  "| spacing (particles) | integration | " + " | ".join(f"nu = {nu}" for nu in NUS)
                  + " | 0.499, anti-locking off |", "|---" * (3 + len(NUS)) + "|"]
        for spacing in sorted({r["spacing"] for r in mine}, reverse=True):
            for scheme in SCHEMES:
                case = [r for r in mine if r["spacing"] == spacing and r["integration"] == scheme]
                if not case:
                    continue
                ratio = lambda nu, anti: next((f"{r['value'] / refs[problem][nu]:.4f}" for r in case
                                               if r["nu"] == nu and r["anti_locking"] == anti
                                               and nu in refs[problem]), "–")
                lines.append(f"| {spacing:g} ({case[0]['particles']}) | {scheme} | "
                             + " | ".join(ratio(nu, "default") for nu in NUS) + f" | {ratio(0.499, False)} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--table", action="store_true", help="print the tables of the stored results")
    p.add_argument("--cook-spacings", type=float, nargs="*", default=[4.0, 2.0, 1.0])
    p.add_argument("--block-spacings", type=float, nargs="*", default=[0.5, 0.25])
    p.add_argument("--schemes", nargs="*", default=list(SCHEMES), choices=SCHEMES)
    a = p.parse_args(argv)
    if not a.table:
        rows = (run("cook_2d", a.cook_spacings, schemes=a.schemes)
                + run("block_3d", a.block_spacings, schemes=a.schemes))
        # the rows of the resolutions and integrations not run this time are kept
        new = {(n["problem"], n["particles"], n["integration"]) for n in rows}
        kept = [r for r in (json.loads(OUT.read_text())["rows"] if OUT.exists() else [])
                if (r["problem"], r["particles"], r["integration"]) not in new]
        OUT.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "rows": kept + rows}, indent=1))
    print(table(json.loads(OUT.read_text())["rows"]))


if __name__ == "__main__":
    main()

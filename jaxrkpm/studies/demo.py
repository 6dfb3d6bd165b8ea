"""Demo: the thesis' box trajectory (Table 5.3) tracked by the Jacobian control law
(Algorithm 3) on the 9x9 Fung square (Table 5.2 tensors, alpha = beta = 1), Gauss
integration, gain 0.05, increment clamp 0.01, tolerance 1e-4.

Writes summary.json (waypoint errors, status, warm and compile time, ...), figures
(control point path, error per iteration, manipulation point path, deformed snapshots) and
ParaView files: final.vtu (the final state) and series.pvd (a frame per waypoint).
The same run as ``jaxrkpm track --path box``."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from jaxrkpm.studies import track


def run(out: Path, path: str = "box", integration: str = "gauss", **kw) -> dict:
    """Track ``path`` (default the box) on the 9x9 planar model; see jaxrkpm.studies.track.run."""
    return track.run(Path(out), path, dim=2, integration=integration, **kw)


def main(argv=None):
    p = argparse.ArgumentParser(prog="jaxrkpm demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="results/demo")
    a = p.parse_args(argv)
    s = run(Path(a.out))
    keys = ("experiment", "status", "message", "max_waypoint_error", "iterations", "wall_s",
            "compile_s", "speedup_vs_thesis_gauss", "material", "integration", "particles",
            "gain", "clamp", "tol", "figures", "vtu", "series")
    print(json.dumps({k: s[k] for k in keys if k in s}, indent=2))
    print(f"wrote {a.out}/summary.json")
    return s


if __name__ == "__main__":
    main()

"""Demo: the thesis' box trajectory (Table 5.3) tracked by the Jacobian control law
(Algorithm 3) on the 9x9 Fung square (Table 5.2 tensors, alpha = beta = 1), Gauss
integration, gain 0.05, increment clamp 0.01, tolerance 1e-4.

Writes summary.json (waypoint errors, status, warm and compile time, ...), history.npz and
figures (control point path, error per iteration, manipulation point path, deformed
snapshots), ParaView files (final.vtu: the final state; series.pvd: a frame per
waypoint) and prints one line: what it wrote, waypoints reached, the largest waypoint
error, iterations and times. The same run as ``jaxrkpm track --path box``."""
from __future__ import annotations

from pathlib import Path

from jaxrkpm.thesis.studies import interface, track
from jaxrkpm.thesis.studies.command import Command


def run(out: Path, path: str = "box", integration: str = "gauss", **kw) -> dict:
    """Track ``path`` (default the box) on the 9x9 planar model; see jaxrkpm.thesis.studies.track.run."""
    return track.run(Path(out), path, dim=2, integration=integration, **kw)


result = track.result   # (every waypoint reached, the result in words)


def parser() -> interface.Parser:
    return interface.parser("demo", __doc__, "results/demo")


def main(argv=None):
    a = parser().parse_args(argv)
    results = interface.results("demo", a)
    with results as out:
        s = run(out)
        results.finish(s, *result(s), a.json)
    return s


COMMAND = Command("demo", "the thesis' box path tracked on the 9x9 Fung square (Table 5.3)", parser, main, result,
                  order=0)

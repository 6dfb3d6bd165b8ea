"""2D needle sweeps to disk: every combination of paddle position (Table 6.2), inclusion,
inclusion stiffness ratio and Fung alpha, beta, each inserted through the increments with the
paddle Jacobian at each, a chunk of configurations per batched call.

The results go to DIR/table/ as Parquet, one file per finished chunk (read them with
jaxrkpm.read_sweep("DIR/table"), pandas.read_parquet or any Parquet reader); DIR/summary.json
counts the statuses. Interrupted (Ctrl-C, a killed worker), the same command again skips the
finished chunks. --workers N runs the chunks on a local Dask cluster of N processes,
--executor tcp://host:8786 on a running Dask cluster (both need Dask: pip install
'dask[distributed]'). Where the chunks run is not part of the sweep: a sweep started with
--workers 2 resumes in process, and the other way round. --overwrite over another sweep's
results starts it afresh (its table/ goes); the same options resume.
"""
from __future__ import annotations

import json
import math
import shutil
import sys

import numpy as np

from jaxrkpm.thesis.studies import interface


# what ``jaxrkpm sweep`` keeps when interrupted (the CLI's last line)
ON_INTERRUPT = ("the chunks finished so far are kept in DIR/table/; the same command again skips them "
                "and runs the rest")


def _cluster(args):
    """(executor, close) for --executor / --workers."""
    if args.executor:
        return args.executor, lambda: None
    if args.workers:
        from distributed import Client, LocalCluster
        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)
        client = Client(cluster)

        def close():
            client.close()
            cluster.close()
        return client, close
    return None, lambda: None


def main(argv=None) -> dict:
    args = interface.parse("sweep", argv)
    from jaxrkpm.thesis.data import TABLE_6_2
    paddles = args.paddles or list(range(1, len(TABLE_6_2) + 1))
    count = math.prod(len(x) for x in (paddles, args.ratios, args.inclusions, args.alphas, args.betas))
    if count > interface.SWEEP_MAX:
        interface.PARSERS["sweep"]().error(f"the options make {count:,} configurations, more than "
                                           f"{interface.SWEEP_MAX:,}: split the sweep")
    # where the chunks run is checked before the folder is claimed: a wrong address writes nothing
    if args.workers or args.executor:
        import importlib.util
        if importlib.util.find_spec("distributed") is None:
            interface.PARSERS["sweep"]().error(
                f"--{'workers' if args.workers else 'executor'} runs the chunks on Dask, which is not installed: "
                "pip install 'dask[distributed]' (or leave the option out to run in this process)")
    if args.executor and (why := interface.unreachable(args.executor)):
        interface.PARSERS["sweep"]().error(f"--executor: {why}")
    # where the chunks run does not change the results: not part of the run's identity
    results = interface.results("sweep", args, staged=False, ignore=("executor", "workers"))
    from jaxrkpm.sweeps.storage import SweepFolderError, SweepInUseError, read_sweep
    from jaxrkpm.thesis import sweeps
    with results as out:
        if results.replaces:              # --overwrite over another sweep: start afresh
            shutil.rmtree(out / "table", ignore_errors=True)
            (out / "summary.json").unlink(missing_ok=True)
        cfg = sweeps.paddle_configurations(paddles, args.ratios, args.inclusions, args.alphas, args.betas)
        executor, close = _cluster(args)

        def run():
            return sweeps.needle_sweep(out / "table", cfg, increments=args.increments, chunk_size=args.chunk_size,
                                       executor=executor, progress=sys.stderr.isatty(), insertion=args.insertion,
                                       keep_jacobians=args.jacobians)
        try:
            try:
                done = run()
            except SweepFolderError as e:
                # table/ holds another sweep (e.g. one an earlier version computed) or a damaged chunk
                if not args.overwrite or isinstance(e, SweepInUseError):
                    raise interface.OutputError(f"{e} (--overwrite starts the sweep afresh)") from None
                shutil.rmtree(out / "table", ignore_errors=True)
                done = run()
        finally:
            close()
        table = read_sweep(out / "table", ["id", "paddle", "inclusion", "stiffness_ratio", "final_deviation", "status"])
        dev = np.abs(np.asarray(table.column("final_deviation").to_numpy(zero_copy_only=False), float))
        summary = {"configurations": done.configurations, "chunks": done.chunks, "skipped_chunks": done.skipped,
                   "evaluated_chunks": done.evaluated, "statuses": done.statuses, "table": "table/"}
        if np.isfinite(dev).any():
            i = int(np.nanargmin(dev))
            summary["best"] = {k: table.column(k)[i].as_py() for k in ("id", "paddle", "inclusion", "stiffness_ratio")
                               if k in table.column_names}
            summary["best"]["final_deviation"] = float(table.column("final_deviation")[i].as_py())
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
        reached, words = result(summary)
        results.finish(summary, reached, words, args.json)
    return summary


GOOD = ("CONVERGED", "OK", "DONE")      # the statuses of rows that reached their result


def result(summary: dict) -> tuple[bool, str]:
    """Goal: a row for every configuration and each of them good (a solve that converged):
    the line counts the rows that failed and their statuses, and a sweep with any misses
    its goal (exit code 1), as a study whose solve failed does."""
    statuses = summary.get("statuses", {})
    rows = sum(statuses.values())
    bad = {s: n for s, n in statuses.items() if s not in GOOD}
    words = (f"{rows}/{summary['configurations']} configurations in table/ ({summary['skipped_chunks']} of "
             f"{summary['chunks']} chunks already there): "
             + ", ".join(f"{n} {s}" for s, n in sorted(statuses.items())))
    if bad:
        words += (f"; {sum(bad.values())} of {rows} rows failed ("
                  + ", ".join(f"{n} {s}" for s, n in sorted(bad.items(), key=lambda kv: -kv[1]))
                  + "; their reasons are in table/'s reason column)")
    if "best" in summary:
        b = summary["best"]
        words += (f"; smallest |final deviation| {abs(b['final_deviation']):.2e} at paddle {b['paddle']}, "
                  f"{b['inclusion']} x {b['stiffness_ratio']:g}")
    return rows == summary["configurations"] and not bad, words

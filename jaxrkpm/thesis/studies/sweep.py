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
from jaxrkpm.thesis.studies.command import Command


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
        parser().error(f"the options make {count:,} configurations, more than {interface.SWEEP_MAX:,}: "
                       "split the sweep")
    # where the chunks run is checked before the folder is claimed: a wrong address writes nothing
    if args.workers or args.executor:
        import importlib.util
        if importlib.util.find_spec("distributed") is None:
            parser().error(
                f"--{'workers' if args.workers else 'executor'} runs the chunks on Dask, which is not installed: "
                "pip install 'dask[distributed]' (or leave the option out to run in this process)")
    if args.executor and (why := unreachable(args.executor)):
        parser().error(f"--executor: {why}")
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


# ------------------------------------------------------------------ the command line
def parser() -> interface.Parser:
    import argparse
    from jaxrkpm.thesis.data import INCLUSIONS, TABLE_6_2
    number, positive = interface.number, interface.POSITIVE
    p = interface.parser("sweep", __doc__, "results/sweep")
    p.add_argument("--paddles", type=number(int, 1, len(TABLE_6_2)), nargs="+", default=None,
                   help=f"paddle positions of Table 6.2, 1..{len(TABLE_6_2)} (default: all)")
    p.add_argument("--ratios", type=positive, nargs="+", default=[100.0], help="inclusion stiffness ratios")
    p.add_argument("--inclusions", choices=tuple(INCLUSIONS), nargs="+", default=["right"])
    p.add_argument("--alphas", type=positive, nargs="+", default=[1.0], help="Fung alpha values")
    p.add_argument("--betas", type=positive, nargs="+", default=[1.0], help="Fung beta values")
    p.add_argument("--increments", type=number(int, 1, interface.INCREMENTS_MAX), default=15,
                   help=f"insertion increments, 1..{interface.INCREMENTS_MAX}")
    p.add_argument("--insertion", type=number(float, 0, 0.5, low_open=True), default=0.15,
                   help="needle depth at full insertion (fraction of the phantom's height)")
    count = number(int, 1, interface.SWEEP_CHUNK_MAX)

    def chunk_size(text: str):
        if text == "auto":
            return text
        try:
            return count(text)
        except argparse.ArgumentTypeError as e:
            raise argparse.ArgumentTypeError(str(e).replace(", got", " or auto, got")) from None
    p.add_argument("--chunk-size", type=chunk_size, default=20,
                   help=f"configurations per batched call (one file each), 1..{interface.SWEEP_CHUNK_MAX}, or "
                        "auto: measured on the first configurations (throughput per chunk size; a rerun keeps the "
                        "size the sweep started with)")
    p.add_argument("--jacobians", action="store_true", help="keep every increment's paddle Jacobian")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--executor", type=scheduler_address, default=None, metavar="ADDRESS",
                       help="a Dask scheduler's address (tcp://host:8786): run the chunks on that cluster "
                            "(default: in this process)")
    where.add_argument("--workers", type=number(int, 1, 256), default=None,
                       help="run the chunks on a local Dask cluster of this many worker processes, 1..256 "
                            "(default: in this process)")
    return p


SCHEDULER_SCHEMES = ("tcp", "tls", "ucx", "ws", "wss")     # Dask's network protocols with a host and port


def scheduler_address(text: str) -> str:
    """A Dask scheduler's address, checked for its form (``tcp://host:8786``); whether one
    answers there is checked before any work (:func:`unreachable`)."""
    import argparse
    from urllib.parse import urlsplit
    try:
        parts = urlsplit(text)
        port = parts.port
    except ValueError:
        port, parts = None, None
    if parts is None or parts.scheme not in SCHEDULER_SCHEMES or not parts.hostname or port is None:
        raise argparse.ArgumentTypeError(f"a Dask scheduler's address is SCHEME://HOST:PORT with SCHEME one of "
                                         f"{', '.join(SCHEDULER_SCHEMES)} (e.g. tcp://localhost:8786), got {text!r}")
    return text


def unreachable(address: str, timeout: float = 5.0) -> str | None:
    """Why nothing answers at the scheduler ``address`` (None where something does): checked
    before a sweep claims its folder, so that a wrong address ends at once, having written
    nothing."""
    import socket
    from urllib.parse import urlsplit
    parts = urlsplit(address)
    try:
        with socket.create_connection((parts.hostname, parts.port), timeout=timeout):
            return None
    except OSError as e:
        return f"no Dask scheduler answers at {address} ({e.strerror or e}): start one (dask scheduler) or fix the address"


COMMAND = Command("sweep", "2D needle sweeps to disk: paddle x inclusion x stiffness, resumable Parquet, in process "
                           "or on a Dask cluster", parser, main, result, order=70, interrupted=ON_INTERRUPT)

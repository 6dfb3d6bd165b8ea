"""Benchmark: one assembly of the strain energy's tangent blocks (``StrainEnergy.blocks``, the
B^T D B contraction of the material tangent dP/dF with tabulated shape-function gradients, summed
into the particle pairs of the pattern), counted and timed against what this machine does.

Per n^3 cube (neo-Hookean, Gauss integration by default, ``--integration``) it counts the work
of one assembly:

* ``gemm_flops``: the batched matrix products that contract each integration-point group's
  weighted gradients with the material tangent (a group: the points of one background cell,
  which share one neighbour list), per pair of neighbour-list parts that is formed (one
  triangle of each group's blocks where the list is split, ``StrainEnergy.half_part``);
* ``tangent_flops``: Y = w grad Psi . dP/dF per point (the small contraction before the GEMM);
* ``scatter_bytes``: the (d, d) blocks summed into the pair sums (read block, read and write
  the sum, read the index), and the pair sums' final transpose gather where a triangle is formed;

and times, in the same process: the whole assembly (median of ``--repeats`` warm calls),
its material-tangent part alone, and two references of this machine taken beside it: a
float64 matrix product (1024^3: XLA's own DGEMM rate with its threads on this machine), and a segment sum of the same size as the assembly's scatter. The
record gives each assembly's achieved GEMM rate as a fraction of the measured DGEMM rate, and
the time the flop and byte counts would take at the measured rates (``floor_s``) against the
time measured. ``--half-part`` / ``--block-budget`` time other settings of the two knobs.
Run from the repository root: ``python -m experiments.bench_assembly [--n 6 10 14]``; writes a
record (experiments/records.py). Figures only from a quiet machine."""
from __future__ import annotations

import argparse
import json
import statistics
from dataclasses import replace

from experiments import records


def counts(term, pairs) -> dict:
    """Flops and bytes of one ``term.blocks`` (the count follows its loop structure)."""
    import numpy as np
    Q, K, dim = term.dpsi.shape
    G, S = term.groups.shape
    n_parts = max(1, K // term.half_part)
    cut = np.linspace(0, K, n_parts + 1).astype(int)
    sizes = np.diff(cut)
    formed = [(a, b) for a in range(n_parts) for b in range(a, n_parts)]
    gemm = sum(2.0 * G * S * dim * sizes[a] * sizes[b] * dim * dim for a, b in formed)
    tangent = 2.0 * G * S * dim * K * dim ** 3          # "cskj,csajbl->cslkab" per group
    blocks = sum(sizes[a] * sizes[b] for a, b in formed) * G
    scatter = blocks * (dim * dim * 8 * 3 + 4)          # block read, sum read+write, index
    if n_parts >= 2:
        scatter += pairs.count * dim * dim * 8 * 3      # U + U[t]^T
    return {"Q": int(Q), "K": int(K), "groups": int(G), "points_per_group": int(S), "pairs": int(pairs.count),
            "parts": int(n_parts), "gemm_flops": gemm, "tangent_flops": tangent, "scattered_blocks": int(blocks),
            "scatter_bytes": float(scatter)}


def machine_rates(repeats) -> dict:
    """XLA:CPU's float64 GEMM rate (a 1024^3 product, with XLA's threads) and its segment-sum
    throughput on (3, 3) blocks, measured here."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    rng = np.random.default_rng(0)
    a, b = (jnp.asarray(rng.standard_normal((1024, 1024))) for _ in range(2))
    mm = jax.jit(lambda a, b: a @ b)
    t, _ = records.warm(lambda: mm(a, b), repeats)
    nb, segs = 2_000_000, 200_000
    blocks = jnp.asarray(rng.standard_normal((nb, 3, 3)))
    ids = jnp.asarray(rng.integers(0, segs, nb).astype(np.int32))
    seg = jax.jit(lambda x, i: jax.ops.segment_sum(x, i, num_segments=segs))
    ts, _ = records.warm(lambda: seg(blocks, ids), repeats)
    return {"dgemm_flops_per_s": 2 * 1024 ** 3 / t["median"], "dgemm_s": t,
            "scatter_bytes_per_s": nb * (9 * 8 * 3 + 4) / ts["median"], "scatter_s": ts}


def case(n, integration, repeats, rates, half_part=None, block_budget=None) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxrkpm as jr
    from jaxrkpm.internal import StrainEnergy
    from jaxrkpm.mechanics.strain import deformation_gradients, material_tangent

    body = jr.Body.grid((n,) * 3, 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.5, mu=1.0), integration=integration, essential=sets, solver="sparse")
    prob = model.problem()
    term = next(t for t in prob.terms if isinstance(t, StrainEnergy))
    if half_part is not None:
        term = replace(term, half_part=half_part)
    if block_budget is not None:
        term = replace(term, block_budget=block_budget)
    d = jnp.asarray(np.random.default_rng(0).standard_normal((body.n, 3)) * 0.01 * body.spacing)
    blocks = jax.jit(lambda t, d: t.blocks(d, 1.0, prob.pairs))
    t_all, _ = records.warm(lambda: blocks(term, d), repeats)

    def tangent(t, d):
        p = {**t.point, **t.tensors}
        axes = {**{k: 0 for k in t.point}, **{k: None for k in t.tensors}}
        return material_tangent(t.W, deformation_gradients(t.idx, t.dpsi, d), p, axes)

    t_tan, _ = records.warm(lambda: jax.jit(tangent)(term, d), repeats)
    c = counts(term, prob.pairs)
    floor = c["gemm_flops"] / rates["dgemm_flops_per_s"] + c["scatter_bytes"] / rates["scatter_bytes_per_s"]
    gemm_rate = c["gemm_flops"] / max(t_all["median"] - t_tan["median"], 1e-12)
    return {"n": n, "integration": integration, "half_part": term.half_part, "block_budget": term.block_budget,
            **c, "assembly_s": t_all, "material_tangent_s": t_tan,
            "floor_s": floor, "assembly_over_floor": t_all["median"] / floor,
            "gemm_flops_per_s_achieved": gemm_rate,
            "gemm_fraction_of_dgemm": gemm_rate / rates["dgemm_flops_per_s"]}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--n", type=int, nargs="*", default=[6, 10, 14], help="particles per edge")
    p.add_argument("--integration", nargs="*", default=["gauss"], choices=["gauss", "scni", "mscni"])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--half-part", type=int, nargs="*", default=[None],
                   help="StrainEnergy.half_part values to time (default: the term's own)")
    p.add_argument("--block-budget", type=int, nargs="*", default=[None],
                   help="StrainEnergy.block_budget values to time (default: the term's own)")
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.smoke:
        a.n, a.repeats = [4], 2
    run = records.start("bench_assembly", a)
    rates = machine_rates(a.repeats)
    rows = []
    for n in a.n:
        for integration in a.integration:
            for hp in a.half_part:
                for bb in a.block_budget:
                    row = case(n, integration, a.repeats, rates, hp, bb)
                    print(json.dumps({k: row[k] for k in ("n", "integration", "half_part", "block_budget",
                                                          "assembly_over_floor", "gemm_fraction_of_dgemm")}))
                    rows.append(row)
    figures = {"machine_rates": rates, "cases": rows}
    ratios = {f"{r['integration']}_{r['n']}_hp{r['half_part']}_bb{r['block_budget']}_over_floor":
              r["assembly_over_floor"] for r in rows}
    ratios["median_gemm_fraction_of_dgemm"] = statistics.median(r["gemm_fraction_of_dgemm"] for r in rows)
    records.finish(run, figures, ratios)


if __name__ == "__main__":
    main()

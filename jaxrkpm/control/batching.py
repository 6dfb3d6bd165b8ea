"""Many problems in one compiled call: models that share a body and integration table
stacked into one batch (``stack_models``), mapped (``lax.map``) or vmapped over it, and
sharded over devices (``run_batched``).
"""
from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ..model.model import Model
from ..mechanics.problem import Problem


# ----------------------------------------------------------------------- batching
def stack_models(models: Sequence[Model], like: Sequence[Model] = ()) -> tuple[Problem, tuple]:
    """The problems of models that share a body and integration table as one batch:
    (problem, batched). ``batched`` (a tuple of bools, one per leaf of the problem's pytree,
    static) says which leaves carry a leading batch axis: those that differ between the
    models (the essential partition, the material fields), stacked and zero-padded where
    ragged (padded neighbours carry zero shape function values and padded coupling columns
    are zero, so they contribute nothing). The leaves every model shares (integration
    table, pair structure, tensors) are kept once: vmapped, they stay unbatched operands
    (``batch_axes``), so gathers and scatters over the table are not repeated per member
    on a stacked copy (``experiments/bench_sweep.py`` compares the two).

    ``like``: models that count as members for the padded shapes and for which leaves are
    batched, but are not stacked: the chunks of a sweep (``jaxrkpm.sweep``) given
    the same ``like`` stack to one shape and one set of batched leaves, so one compiled
    program serves them all instead of one per chunk."""
    ref = models[0]
    like = list(like)
    for m in list(models[1:]) + like:
        if m.body is not ref.body or m.volume.idx.shape != ref.volume.idx.shape:
            raise ValueError("batched models must share one body and integration table")
        if m.sets.free.shape != ref.sets.free.shape:
            raise ValueError("batched models must have essential sets of equal sizes "
                             f"({m.sets.bnd.shape[0]} vs {ref.sets.bnd.shape[0]} essential particles)")
        if m.material.W != ref.material.W or m.linear != ref.linear:
            raise ValueError("batched models must share one material law and linear solver")

    def same(xs):
        # the one object every model shares (the integration table) needs no comparison
        if all(x is xs[0] for x in xs[1:]):
            return True
        a = np.asarray(xs[0])
        return all(x is xs[0] or (np.shape(x) == a.shape and np.array_equal(np.asarray(x), a)) for x in xs[1:])

    B = len(models)

    def stack(xs):
        if not np.ndim(xs[0]):
            return jnp.stack(xs[:B])
        shape = tuple(np.max([np.shape(x) for x in xs], axis=0))
        out = np.zeros((B,) + shape, np.result_type(*[np.asarray(x).dtype for x in xs[:B]]))
        for i, x in enumerate(xs[:B]):          # zero-padded where ragged
            x = np.asarray(x)
            out[(i,) + tuple(slice(0, n) for n in x.shape)] = x
        return jnp.asarray(out)

    flat = [jax.tree.flatten(m.problem()) for m in list(models) + like]
    treedef = flat[0][1]
    if any(t != treedef for _, t in flat[1:]):
        raise ValueError("batched models must have the same terms (kinds, names and settings)")
    columns = list(zip(*[leaves for leaves, _ in flat]))
    batched = tuple(not same(xs) for xs in columns)
    leaves = [stack(xs) if b else jnp.asarray(xs[0]) for xs, b in zip(columns, batched)]
    return treedef.unflatten(leaves), batched


def batch_axes(tree, batched: tuple):
    """vmap's ``in_axes`` for a (problem, batched) pair of ``stack_models``: 0 for the
    batched leaves, None for the shared ones."""
    leaves, treedef = jax.tree.flatten(tree)
    if len(leaves) != len(batched):
        raise ValueError(f"batched has {len(batched)} flags for a tree of {len(leaves)} leaves")
    return treedef.unflatten([0 if b else None for b in batched])


def map_batch(fn, tree, batched: tuple, *xs):
    """``lax.map`` of fn(member, *x) over the members of a (tree, batched) pair (see
    ``stack_models``) and the leading axis of ``xs``: the shared leaves pass into every
    member as they are (loop invariants), only the batched ones are sliced."""
    leaves, treedef = jax.tree.flatten(tree)

    def member(args):
        own, x = args
        it = iter(own)
        return fn(treedef.unflatten([next(it) if b else leaf for leaf, b in zip(leaves, batched)]), *x)

    return jax.lax.map(member, ([leaf for leaf, b in zip(leaves, batched) if b], xs))


def _device_mesh(n_devices: int | None):
    devices = jax.local_devices()
    if n_devices is not None and not (isinstance(n_devices, int) and 1 <= n_devices <= len(devices)):
        raise ValueError(f"n_devices must be None (every local device) or 1..{len(devices)} (the local "
                         f"devices JAX sees), got {n_devices!r}")
    return Mesh(np.array(devices[:n_devices]), ("batch",))


def run_batched(fn, batched_args, n_devices: int | None = None, axes=0):
    """fn maps arguments with a leading batch axis to outputs with one. ``axes``: a pytree
    prefix of ``batched_args`` (as vmap's ``in_axes``: 0 batched, None shared by every
    member). ``n_devices``: None (default) every local device of this process (a 1-D mesh
    over ``jax.local_devices()``), else the first that many. With several devices the batch
    is padded to a multiple of their number (repeating the last member), each device runs
    its shard independently (shard_map: no cross-device step) and the shared arguments are
    replicated."""
    mesh = _device_mesh(n_devices)
    n_dev = mesh.devices.size
    if n_dev == 1:
        return fn(*batched_args)
    flags = jax.tree.leaves(jax.tree.map(lambda a, x: jax.tree.map(lambda _: a == 0, x), axes, batched_args,
                                         is_leaf=lambda a: a is None),)
    leaves, treedef = jax.tree.flatten(batched_args)
    B = next(x for x, b in zip(leaves, flags) if b).shape[0]
    pad = -B % n_dev

    def padded(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x

    args = treedef.unflatten([padded(x) if b else x for x, b in zip(leaves, flags)])
    specs = treedef.unflatten([PartitionSpec("batch") if b else PartitionSpec() for b in flags])
    out = jax.shard_map(fn, mesh=mesh, in_specs=tuple(specs), out_specs=PartitionSpec("batch"),
                        check_vma=False)(*args)
    return jax.tree.map(lambda x: x[:B], out)


BATCHING = ("map", "vmap")


def default_batching() -> str:
    """``insert``'s batching where none is given: "map" on CPU, "vmap" on an accelerator
    (measured: see ``_insert_batch``)."""
    return "map" if jax.default_backend() == "cpu" else "vmap"

"""The particle-pair pattern of the tangent and the groups of integration points that share a
neighbour list (built once, NumPy).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def pair_keys(lists, N):
    """Sorted unique keys i * N + j of the particle pairs (i, j) that share a row of
    ``lists`` (R, K): the pattern of S^T S for the row-particle incidence S (a sparse
    product: sorting all R K^2 pairs would dominate the set-up of large 3D models). Float
    ones: the counts must never wrap to 0, which the sparse product would drop."""
    R, K = lists.shape
    S = sp.csr_matrix((np.ones(R * K), (np.repeat(np.arange(R), K), lists.ravel())),
                      shape=(R, N))
    P = (S.T @ S).tocoo()
    return np.unique(P.row.astype(np.int64) * N + P.col)


def pair_ids(uniq, lists, N, chunk: int = 2**22):
    """Positions in ``uniq`` of the keys lists[r, k] * N + lists[r, m]: (R, K, K) int32.

    Looked up a few rows at a time straight into the int32 table: the int64 keys of all
    rows at once are R K^2 x 8 bytes, which would set the peak memory of a 3D model build
    (``experiments/bench_needle3d_memory.py`` reports it per stage). ``chunk``: the keys
    looked up at once (one int64 temporary of this many)."""
    R, K = lists.shape
    out = np.empty((R, K, K), np.int32)
    rows = max(1, chunk // max(K * K, 1))
    for a in range(0, R, rows):
        blk = lists[a:a + rows].astype(np.int64)
        out[a:a + rows] = np.searchsorted(uniq, blk[:, :, None] * N + blk[:, None, :])
    return out


def split_groups(grp_of, counts, size):
    """Group ids (Q,) and counts with every group cut into consecutive pieces of at most
    ``size`` points."""
    srt = np.argsort(grp_of, kind="stable")
    rank = np.empty(len(grp_of), np.int64)
    rank[srt] = np.arange(len(grp_of)) - np.repeat(np.r_[0, np.cumsum(counts)[:-1]], counts)
    _, grp_of, counts = np.unique(np.stack([grp_of, rank // size], 1), axis=0,
                                  return_inverse=True, return_counts=True)
    return grp_of.ravel(), counts


def padded_groups(grp_of: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Points (Q,) by group id ``grp_of`` (``counts`` points a group) as groups (G, S) of point
    indices, in point order within a group, padded with Q."""
    Q = len(grp_of)
    srt = np.argsort(grp_of, kind="stable")
    groups = np.full((len(counts), counts.max()), Q, np.int64)
    start = np.r_[0, np.cumsum(counts)[:-1]]
    groups[grp_of[srt], np.arange(Q) - np.repeat(start, counts)] = srt
    return groups


def point_groups(idx: np.ndarray) -> np.ndarray:
    """The integration points (Q,) with identical neighbour lists (the Gauss points of one
    cell) as groups (G, S) of point indices, padded with Q: their tangent contributions are
    summed before the scatter (``jaxrkpm.mechanics.strain.StrainEnergy.blocks``). Where padding
    would cost more than a quarter of the points, one point a group."""
    Q = idx.shape[0]
    _, grp_of, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    grp_of = grp_of.ravel()
    if counts.max() > np.median(counts):
        # lists shared beyond one cell (neighbouring mesh cells with the same union list):
        # split such groups into pieces of the typical size, so groups need little padding
        grp_of, counts = split_groups(grp_of, counts, int(np.median(counts)))
    if len(counts) * counts.max() > 1.25 * Q:
        return np.arange(Q)[:, None]
    return padded_groups(grp_of, counts)


def pair_pattern(lists, N: int):
    """The tangent's pattern: the particle pairs that share a row of any of ``lists`` (a
    sequence of (R, K) particle lists: one per integration group, ``point_groups``, since per
    point it would be Q K^2 keys, GBs in 3D; the spring points; a loaded facet). Returns
    (pair_i, pair_j, pair_t (P,): the index of each pair's transpose (the pattern is
    symmetric), [the pair ids (R, K, K) of each list's rows])."""
    keys = [pair_keys(rows, N) for rows in lists if len(rows)]
    uniq = keys[0] if len(keys) == 1 else np.unique(np.concatenate(keys))
    pair_i, pair_j = uniq // N, uniq % N
    pair_t = np.searchsorted(uniq, pair_j * N + pair_i)
    return pair_i, pair_j, pair_t, [pair_ids(uniq, rows, N) for rows in lists]

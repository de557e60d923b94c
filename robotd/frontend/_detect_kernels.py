"""numba kernel of the detectors' grid bucketing; numpy twin: tests/support/reference_frontend.py.

The caller sorts (two stable numpy sorts, ≈ 0.08 ms on 4000 ORB candidates); the per-cell quota
and the refill are one pass here instead of the numpy version's further sorts and gathers
(≈ 0.45 ms per image in all, holding the GIL the other image's detection thread also needs).
numba's own stable argsort was slower than numpy's and data-dependent. Compiled by
:func:`robotd.core.jit.jit` (disk cache, GIL released).
"""

from __future__ import annotations

import numpy as np

from robotd.core.jit import jit


@jit
def bucket_kernel(g: np.ndarray, cell: np.ndarray, response: np.ndarray, max_features: int, n_cells: int) -> np.ndarray:
    """Indices of at most ``max_features`` features (``detectors.bucket_select``'s contract).

    ``g``: (N,) all indices ordered by (−response, cell, index); ``cell``: (N,) int64 grid cell of
    each feature in [0, n_cells); ``response``: (N,). Each cell keeps its ceil(max_features /
    n_cells) strongest (earliest index on ties); unused quota goes to the strongest remaining
    features. Order of the result: decreasing response; on ties the per-cell picks before the
    refill, then by cell, then by index.
    """
    n = cell.shape[0]
    quota = -(-max_features // n_cells)
    taken = np.zeros(n_cells, np.int64)
    first = np.empty(n, np.int64)
    rest = np.empty(n, np.int64)
    nf = 0
    nr = 0
    for q in range(n):
        k = g[q]
        c = cell[k]
        if taken[c] < quota:
            taken[c] += 1
            first[nf] = k
            nf += 1
        else:
            rest[nr] = k
            nr += 1
    if nf >= max_features:
        return first[:max_features].copy()
    nr = min(nr, max_features - nf)
    out = np.empty(nf + nr, np.int64)
    a = 0
    b = 0
    for q in range(nf + nr):
        # merge by decreasing response, a per-cell pick first on ties
        if b >= nr or (a < nf and response[first[a]] >= response[rest[b]]):
            out[q] = first[a]
            a += 1
        else:
            out[q] = rest[b]
            b += 1
    return out

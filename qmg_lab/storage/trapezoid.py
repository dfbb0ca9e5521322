"""The rate output's running trapezoid integral, one compiled pass over a block (the study storage level's
/edges, qmg_lab/storage/summary.py).

    I_k = I_(k-1) + (0.5 (t_k - t_(k-1))) (r_k + r_(k-1))

operation for operation and in the order of the numpy form it replaces, `np.cumsum` (sequential) of
`0.5 * np.diff(t) * (r[1:] + r[:-1])`: the same rounding, so the integral does not depend on how the stream was cut
into blocks. numpy needs six passes and a temporary per term for it, and its cumsum alone costs ~5 ns a sample.

Compiled with cache=True (once in a fresh environment, then loaded from __pycache__). Imported only by the study
writer when it starts, never by `qmg-lab analyze`, which reads the summaries and need not load numba.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def running_trapezoid(
    t: np.ndarray, r: np.ndarray, t_prev: float, r_prev: float, i_prev: float, first: bool
) -> np.ndarray:
    """I at every sample of a block (t, r 1-D float64, n >= 1). first: the block starts the stream, I_0 = 0 at its
    first sample; else the block continues after the sample (t_prev, r_prev) where the integral was i_prev."""
    n = t.shape[0]
    out = np.empty(n)
    acc = 0.0 if first else i_prev + (0.5 * (t[0] - t_prev)) * (r[0] + r_prev)
    out[0] = acc
    for k in range(1, n):
        acc = acc + (0.5 * (t[k] - t[k - 1])) * (r[k] + r[k - 1])
        out[k] = acc
    return out

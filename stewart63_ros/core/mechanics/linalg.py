"""Small dense linear solves, compiled: a leaf module (imports nothing of the
package but ``_jit``), so that ``fk`` and ``dynamics`` share it without one
importing the other."""
from __future__ import annotations

import numpy as np

from stewart63_ros.core.plumbing._jit import njit


@njit
def solve_linear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x = a^-1 b by Gaussian elimination with partial pivoting; NaN when singular.

    Compiled; ``a`` and ``b`` are left untouched. Cheaper than a LAPACK call at 6x6.

    Args:
        a: (n, n) float array; b: (n,) float array.

    Returns:
        x (n,); all NaN when ``a`` is singular.
    """
    a = a.copy()
    x = b.copy()
    n = b.shape[0]
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if a[p, k] == 0.0:
            x[:] = np.nan
            return x
        if p != k:
            for j in range(n):
                tmp = a[k, j]
                a[k, j] = a[p, j]
                a[p, j] = tmp
            tmp = x[k]
            x[k] = x[p]
            x[p] = tmp
        for i in range(k + 1, n):
            f = a[i, k] / a[k, k]
            for j in range(k + 1, n):
                a[i, j] -= f * a[k, j]
            x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        v = x[i]
        for j in range(i + 1, n):
            v -= a[i, j] * x[j]
        x[i] = v / a[i, i]
    return x

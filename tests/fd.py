"""Central differences for the derivative checks of the tests (one helper for every energy)."""
import numpy as np


def central_difference(f, x, eps=1e-6):
    """df/dx at x (n,) by central differences with step eps: (..., n) for f(x) of shape (...);
    column d is (f(x + eps e_d) - f(x - eps e_d)) / (2 eps)."""
    cols = []
    for d in range(x.size):
        xp, xm = x.copy(), x.copy()
        xp[d] += eps
        xm[d] -= eps
        cols.append((np.asarray(f(xp), float) - np.asarray(f(xm), float)) / (2 * eps))
    return np.stack(cols, axis=-1)

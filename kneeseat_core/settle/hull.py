"""The minimum-norm point of a convex hull: the steepest move that gains at every contact.

The climb (D1) asks for the shortest vector in the convex hull of the contact patches'
depth gradients: its direction is the steepest move that gains depth at every patch at
once, and a zero vector means the patches balance. Wolfe's algorithm finds it exactly in
finitely many steps (the active set holds at most d + 1 points). It stays hand-written:
scipy offers no exact solver for it (SLSQP, which takes the constraints, iterates to a
tolerance), and every table's bits depend on this arithmetic.
"""
from __future__ import annotations

import numpy as np

from kneeseat_core.geometry import TOL
from kneeseat_core.typed import Floats

__all__ = ['min_norm_point']


def min_norm_point(points: Floats) -> Floats:
    """Minimum-norm point of the convex hull of `points` (k, d): Wolfe's algorithm (exact
    in finitely many steps; the active set is at most d + 1 points)."""
    sq = np.einsum('ij,ij->i', points, points)
    if len(points) == 1:
        first: Floats = points[0].copy()
        return first
    scale = float(sq.max())
    active = [int(np.argmin(sq))]
    weights = np.array([1.0])
    x = points[active[0]].copy()
    for _ in range(8 * len(points) + 16):
        j = int(np.argmin(points @ x))
        if float(x @ x) - float(points[j] @ x) <= TOL.hull_weight * scale or j in active:
            break
        active.append(j)
        weights = np.append(weights, 0.0)
        while True:                        # minor cycle: the affine min-norm point
            basis = points[active]
            n = len(active)
            kkt = np.zeros((n + 1, n + 1))
            kkt[:n, :n] = basis @ basis.T
            kkt[:n, n] = kkt[n, :n] = 1.0
            rhs = np.zeros(n + 1)
            rhs[n] = 1.0
            try:
                alpha = np.linalg.solve(kkt, rhs)[:n]
            except np.linalg.LinAlgError:  # affinely dependent points
                alpha = np.linalg.lstsq(kkt, rhs, rcond=None)[0][:n]
            if np.all(alpha > TOL.hull_weight):
                weights = alpha
                break
            low = alpha <= TOL.hull_weight
            step = float(np.min(weights[low] / (weights[low] - alpha[low])))
            weights = weights + step * (alpha - weights)
            keep = weights > TOL.hull_weight
            active = [a for a, k in zip(active, keep) if k]
            weights = weights[keep]
        x = weights @ points[active]
    out: Floats = x
    return out

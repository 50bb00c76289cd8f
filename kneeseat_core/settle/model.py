"""The travel to first order about a pose at contact, from the features the exact travel
returns (`kneeseat_core.meshes.sweep`).

Each feature k closes at a gap g_k along Δ from the pose; a lateral move x = (slide e1,
slide e2, arc) moves the moving body's point at the feature by dp = x0 e1 + x1 e2 + x2 (Δ x
(p - c)) / arm and changes that gap by -n . dp / n . Δ (n its normal), so the travel after
the move is, to first order,

    s(x) = min_k (g_k + a_k . x).

Each feature's slopes are computed from its normal and point by the planner
(`kneeseat_core.settle.planner`, `Planner.model`, compiled with the moves it plans). For
pure slides each term is exact while its feature stays one (the vertex over the same
triangle, the crossing on the same edges); the climb uses the model to order its moves, to
propose the move that climbs where several contacts hold the body at once (`best_move`: the
objective press s(x) + drive . x is then best raised along a combination of slide and spin
that keeps every contact, a linear program in (x, s)) and to name the pairs of triangles
likely to stop a move (its witnesses, `SweepPair.measure`), never to decide a gain
(`kneeseat_core.settle.climb`). The linear program is solved by a small simplex written by
hand (`_simplex.cpp`, compiled with the package): the climb asks it at every fine step, and
a general solver's setup alone costs more than that (scipy's linprog about 3 ms), and the
program is built there too (numpy's calls on its few small arrays cost more than solving it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneeseat_core.typed import Floats, Ints
from . import _simplex

__all__ = ['Model', 'STEEPEST', 'best_move']

# A feature whose gap changes faster than this with a move (m of gap per m of move, in any
# coordinate) is left out of the model: a crossing of two edges nearly parallel seen along
# Δ, a triangle seen edge on - their slope holds for a sliver of a move. A lateral move of
# length l goes at most this deep into what the model keeps.
STEEPEST = 3.0


@dataclass(frozen=True, slots=True, eq=False)
class Model:
    """The travel about a pose to first order: gaps (k,) and slopes (k, 3) over (slide e1,
    slide e2, arc), with the two triangles (moving, fixed) of each feature (k, 2)."""

    gaps: Floats
    slopes: Floats
    faces: Ints

    def travel(self, moves: Floats) -> Floats:
        """(m,) the modelled travel after each of `moves` (m, 3)."""
        out: Floats = np.min(self.gaps[None, :] + moves @ self.slopes.T, axis=1)
        return out


def best_move(model: Model, press: float, drive: Floats, radius: Floats) -> tuple[Floats, float]:
    """The move x (3,) with |x_i| <= radius_i that maximises press s(x) + drive . x under
    the model (at least one feature), and the gain that promises over no move (measured on
    the model itself). Slopes below a nanometre per metre count as none (rounding: a pivot
    on one would blow the tableau up), and each unit of a move's length costs a millionth
    of the objective's rates, so a direction the model holds level (a slide along a groove)
    stays at no move instead of running to the box's corner (`_simplex.cpp`)."""
    x, promised = _simplex.best_move(
        np.ascontiguousarray(model.gaps, dtype=np.float64),
        np.ascontiguousarray(model.slopes, dtype=np.float64), float(press),
        np.ascontiguousarray(drive, dtype=np.float64),
        np.ascontiguousarray(radius, dtype=np.float64))
    return np.frombuffer(x, dtype=np.float64), promised

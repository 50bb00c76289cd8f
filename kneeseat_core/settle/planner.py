"""The climb's arithmetic around the exact travel, compiled (`_moves.cpp`): the moves it
tries, what a pose is worth, the objective's first-order terms, the travel's model.

At every step the climb (`kneeseat_core.settle.climb`) considers up to 27 lateral moves:
it orders them by what the near-active features promise (`kneeseat_core.settle.model`),
turns the most promising into poses (a slide across the push Δ and a spin about the axis
through the body's centroid parallel to it) and asks how far along Δ each must then reach
to gain: one Newton step of the lift, from the objective's terms
(`Objective`: the load's line and the ligaments, weighed at every pose). On arrays that
small numpy's calls cost several times the arithmetic, so the whole plan is one compiled
call. The rest of the objective's arithmetic is there too: what a pose at contact is worth
(`value`), its first-order terms (`first_order`) and the travel's first-order model about
a pose (`model`).
"""
from __future__ import annotations

import numpy as np

from kneeseat_core.ligaments import Tissue
from kneeseat_core.meshes.sweep import Touch
from kneeseat_core.typed import Floats, Ints, Pose
from . import _moves
from .model import Model, STEEPEST
from .objective import Objective
from .search import Search

__all__ = ['Planner']


def _floats(a: Floats) -> Floats:
    return np.ascontiguousarray(a, dtype=np.float64)


def _fibres(tissue: Tissue | None) -> tuple[Floats, ...] | None:
    """The tissue's segments and fibres as the compiled planner reads them."""
    if tissue is None:
        return None
    return (_floats(tissue.seg_local), _floats(tissue.seg_sign), _floats(tissue.seg_fixed),
            np.ascontiguousarray(tissue.seg_fibre, dtype=np.int64), _floats(tissue.slack_m),
            _floats(tissue.stiffness_n), _floats(tissue.transition))


class Planner:
    """One climb's planner: the push frame, the arm of a spin, the standoff and the
    objective's terms, fixed for the climb."""

    def __init__(self, search: Search, objective: Objective, arm: float,
                 standoff: float) -> None:
        toward = None if objective.toward is None else _floats(objective.toward)
        self._native = _moves.Planner(
            _floats(search.push), _floats(search.e1), _floats(search.e2), _floats(search.free),
            _floats(search.pair.moving.centroid), float(arm), float(standoff), STEEPEST,
            objective.work, float(objective.load_n), toward, _fibres(objective.tissue))

    def laterals(self, base: Pose, moves: Floats) -> Floats:
        """`base` (4, 4) slid by move[0] e1 + move[1] e2 and spun by move[2] / arm (rad)
        about the axis through its centroid parallel to Δ, for each of `moves` (m, 3): (m,
        4, 4). A spin about any other centre is this plus a slide; a locked slide is not
        made."""
        raw = self._native.laterals(_floats(base), _floats(moves))
        return np.frombuffer(raw, dtype=np.float64).reshape(-1, 4, 4)

    def model(self, touch: Touch, centre: Floats, within: float, room: float) -> Model:
        """The travel's first-order model about a pose from its features `touch` (gaps
        from the pose; `centre` the body's centroid there, the spins' axis through it):
        those closing within `within` that hold for a slide of at least `room` (all of those
        within, where none does; a feature that stops being one sooner - a crossing of two
        edges nearly parallel seen along Δ runs off its edge within micrometres - stands
        for a slope the surfaces have only that far), none steeper than `STEEPEST`
        (`kneeseat_core.settle.model`: a slope that steep holds for a sliver of a move)."""
        gaps, slopes, faces = self._native.model(touch.features, float(touch.rise),
                                                 _floats(centre), float(within), float(room))
        return Model(np.frombuffer(gaps, dtype=np.float64),
                     np.frombuffer(slopes, dtype=np.float64).reshape(-1, 3),
                     np.frombuffer(faces, dtype=np.int64).reshape(-1, 2))

    def plan(self, base: Pose, moves: Floats, near: Model, press: float, drive: Floats,
             tries: int | None, gain: float, want: float) -> tuple[Ints, Floats, Floats]:
        """The moves `moves` (m, 3) from `base` most promising first under the model
        `near` (press (s(x) - its least gap) + drive . x; ties in the order given), only the
        `tries` first when given: their indices (t,), their poses (t, 4, 4) and the travel
        along Δ each must reach to gain `gain` (one Newton step of the lift bringing the
        objective to `want`, its value at `base` plus `gain`; inf where the body is not
        pressed on), the standoff included."""
        order, targets, needed = self._native.plan(
            _floats(base), _floats(moves), _floats(near.gaps), _floats(near.slopes),
            float(press), _floats(drive), -1 if tries is None else int(tries), float(gain),
            float(want))
        return (np.frombuffer(order, dtype=np.int64),
                np.frombuffer(targets, dtype=np.float64).reshape(-1, 4, 4),
                np.frombuffer(needed, dtype=np.float64))

    def value(self, pose: Pose) -> float:
        """What `pose` (at contact) is worth: the objective per unit load (m), the load's
        work less the ligaments' energy, or the depth along Δ for the travel alone."""
        return float(self._native.value(_floats(pose)))

    def terms(self, pose: Pose) -> tuple[float, Floats, float, float]:
        """`first_order` and `pulls` at `pose` from one call: (press, drive, pull, line)."""
        press, drive, pull, line = self._native.first_order(_floats(pose))
        return press, np.frombuffer(drive, dtype=np.float64), pull, line

    def first_order(self, pose: Pose) -> tuple[float, Floats]:
        """(press, drive (3,)) at `pose`: a move x over (slide e1, slide e2, arc) that
        changes the travel by dt changes the objective by press dt + drive . x, to first
        order (`kneeseat_core.settle.objective`); the travel alone: (1, 0)."""
        press, drive, _, _ = self.terms(pose)
        return press, drive

    def pulls(self, pose: Pose) -> tuple[float, float]:
        """At `pose`, per unit load: the ligaments' pull along -Δ (dE/ds / F) and the load's
        along Δ (l . Δ); the body is pressed on while the second exceeds the first."""
        _, _, pull, line = self.terms(pose)
        return pull, line

    def pushes(self, poses: Floats) -> tuple[Floats, Floats]:
        """The ligaments' energies (m,) and dE/dt (m, 3) at each of `poses` (m, 4, 4) as the
        planner weighs them (`Tissue.energy` and its rate under a translation, to rounding;
        zero without ligaments)."""
        energies, forces = self._native.pushes(_floats(poses))
        return (np.frombuffer(energies, dtype=np.float64),
                np.frombuffer(forces, dtype=np.float64).reshape(-1, 3))

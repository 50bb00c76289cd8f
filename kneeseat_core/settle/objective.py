"""What the default method climbs: the travel, or the load's work less the soft tissue's energy.

Without soft tissue (`Travel`) rest is a local maximum of the travel s along the push Δ over
the lateral state (slides across Δ, spin about it): the patent's own measure, unchanged bit
for bit. With ligaments acting on the body (`Work`, a load F on the push and a `Tissue`),
rest is a local maximum of the load's work less the elastic energy E of the ligaments at
the contact pose, per unit load:

    W / F = l . c(pose) - E(pose) / F        (m; c the body's centroid)

for a load along a fixed line l, with the body in contact along Δ as before; for a load
along the push (l = Δ, a tibia) that is the travel less E / F. A load that pulls toward a
point o (a patella's quadriceps toward the femur, its tendon in E holding it against the
pull) does the work -|o - c|, and l is the unit vector from c to o. A lateral move x over
(slide e1, slide e2, arc about the centroid) that changes the travel by dt changes it by

    (l . Δ - dE/ds / F) dt + (l_lateral - dE/dx / F) . x

to first order (`first_order`: press and drive), where dE/ds is the energy's rate along the
push and dE/dx its rate over the lateral state. The press is how hard the body is pressed
into contact per unit load: where it is not positive the ligaments pull the body off the
fixed body against its load, and the settle says so (`Status.PULLED`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from kneeseat_core.ligaments import Tissue
from kneeseat_core.typed import Floats, Pose
from .search import Search

__all__ = ['ObjectiveTerms', 'Objective', 'Travel', 'Work', 'objective_for']

# Poses whose tissue evaluation a Work objective keeps.
_SEEN = 4


@dataclass(frozen=True, slots=True, eq=False)
class ObjectiveTerms:
    """What the planner computes the objective from (`Objective.terms`)."""

    work: bool                   # the load's work less the tissue's energy (else the travel)
    load_n: float                # N, the load the work and energy are taken per unit of
    toward: Floats | None        # (3,) the point the load pulls toward, or None: the push
    tissue: Tissue | None        # the ligaments acting on the body, if any


class Objective:
    """The climb's measure of a pose at contact (its value is computed by the planner from
    `terms`), and its first-order model."""

    gain = ''        # what a gain is measured in, for the settle's reasons
    # the share of the resolution the objective is climbed to: a smooth energy's maximum
    # lies in a valley the travel's resolution would leave a millimetre wide
    precision = 1.0

    def first_order(self, pose: Pose) -> tuple[float, Floats]:
        """(press, drive (3,)) at `pose`: a move x over (slide e1, slide e2, arc) that
        changes the travel by dt changes the objective by press dt + drive . x, to first
        order."""
        raise NotImplementedError

    def terms(self) -> ObjectiveTerms:
        """What the planner (`kneeseat_core.settle.planner`, compiled) computes the
        objective from: its value at a pose at contact, and how far along Δ each move it
        considers must be lifted for the objective there to gain (one Newton step from no
        lift, inf where the body is not pressed on). The objective is concave along Δ (the
        load's work is; the energy is convex in each length, each length convex along Δ),
        so the step lifts no higher than needed: a contact short of it proves that the
        move cannot gain."""
        raise NotImplementedError

    def pressing(self, pose: Pose) -> float:
        """How hard the body at `pose` is pressed into contact per unit load (1 for the
        travel); not positive: the tissue pulls it off against its load."""
        raise NotImplementedError

    def pulled_off(self, pose: Pose) -> str:
        """Why the body at `pose` leaves contact (the end's reason)."""
        raise NotImplementedError


@dataclass(frozen=True, slots=True, eq=False)
class Travel(Objective):
    """Geometry alone: the travel along the push (the patent's measure)."""

    search: Search
    gain = 'along the push'

    def first_order(self, pose: Pose) -> tuple[float, Floats]:
        """The travel itself: (1, 0)."""
        return 1.0, np.zeros(3)

    def terms(self) -> ObjectiveTerms:
        """The travel alone: a pose is worth its depth along Δ, and a lateral move leaves
        the depth as it was, so a move must reach the gain itself."""
        return ObjectiveTerms(False, 1.0, None, None)

    def pressing(self, pose: Pose) -> float:
        """Always pressed: the push is all there is."""
        return 1.0

    def pulled_off(self, pose: Pose) -> str:
        """Never happens without tissue."""
        return ''


@dataclass(slots=True, eq=False)
class Work(Objective):
    """The load's work less the tissue's energy, per unit load (module docstring)."""

    search: Search
    tissue: Tissue | None
    load_n: float
    toward: Floats | None        # (3,) the point the load pulls toward, or None: the push
    arm: float                   # m of arc per radian of spin (the climb's)
    # the tissue's energy and rates at the last few poses asked about: a climb asks for the
    # value, the pressing and the first-order terms at a pose in turn, and about its
    # current pose between the others
    _seen: dict[bytes, tuple[float, float, Floats]] = field(default_factory=dict)
    gain = "in the load's work less the ligaments' energy (per unit load)"
    precision = 0.1

    def terms(self) -> ObjectiveTerms:
        """The load (its size and the point it pulls toward, if any) and the tissue."""
        return ObjectiveTerms(True, self.load_n, self.toward, self.tissue)

    def _along(self, force: Floats) -> float:
        """dE/ds / F: the tissue's rate along Δ per unit load, from its dE/dt `force`."""
        return float(force @ self.search.push) / self.load_n

    def _press(self, pose: Pose, along: float) -> float:
        """l . Δ - dE/ds / F at `pose`, given dE/ds / F (`along`)."""
        return float(self.line(pose) @ self.search.push) - along

    def line(self, pose: Pose) -> Floats:
        """(3,) unit direction of the load on the body at `pose`."""
        if self.toward is None:
            return self.search.push
        d = self.toward - self.search.centre(pose)
        out: Floats = d / math.sqrt(float(d @ d))
        return out

    def _tissue(self, pose: Pose) -> tuple[float, float, Floats]:
        """E / F, dE/ds / F along Δ and dE/dx / F over (slide e1, slide e2, arc) at `pose`
        (one evaluation of the tissue, kept for the next question about the same pose)."""
        if self.tissue is None:
            return 0.0, 0.0, np.zeros(3)
        key = pose.tobytes()
        seen = self._seen.get(key)
        if seen is not None:
            return seen
        s = self.search
        energy, force, torque = self.tissue.rates(pose)
        # the spin turns the body about the axis through its centre along the push, at one
        # radian per arm of arc: its rate is the moment about the centre along the push
        (cx, cy, cz), (fx, fy, fz), (ux, uy, uz) = s.centre(pose), force, s.push
        about_centre = ux * (cy * fz - cz * fy) + uy * (cz * fx - cx * fz) \
            + uz * (cx * fy - cy * fx)                      # (c x force) . push
        moment = (float(torque @ s.push) - about_centre) / self.arm
        along = self._along(force)
        lateral = np.array([float(force @ s.e1), float(force @ s.e2),
                            moment]) / self.load_n
        if len(self._seen) >= _SEEN:
            del self._seen[next(iter(self._seen))]          # the oldest
        self._seen[key] = (energy / self.load_n, along, lateral)
        return energy / self.load_n, along, lateral

    def _rates(self, pose: Pose) -> tuple[float, Floats]:
        """dE/ds / F along Δ, and dE/dx / F over (slide e1, slide e2, arc), at `pose`."""
        _, along, lateral = self._tissue(pose)
        return along, lateral

    def first_order(self, pose: Pose) -> tuple[float, Floats]:
        """(l . Δ - dE/ds / F, l_lateral - dE/dx / F) (module docstring)."""
        s = self.search
        along, lateral = self._rates(pose)
        line = self.line(pose)
        press = float(line @ s.push) - along
        drive: Floats = np.array([float(line @ s.e1), float(line @ s.e2), 0.0]) - lateral
        return press, drive

    def pressing(self, pose: Pose) -> float:
        """l . Δ - dE/ds / F."""
        return self._press(pose, self._rates(pose)[0])

    def pulled_off(self, pose: Pose) -> str:
        """The ligaments' pull along -Δ against the load's along Δ, in newtons."""
        s = self.search
        pull = self._rates(pose)[0] * self.load_n
        load = float(self.line(pose) @ s.push) * self.load_n
        return (f'pulled off: its ligaments pull it away from the fixed body with '
                f'{pull:.0f} N along the push, more than the load presses it on '
                f'({load:.0f} N along the push); no rest in contact at this attitude')


def objective_for(search: Search, tissue: Tissue | None, arm: float) -> Objective:
    """The travel when no tissue acts and the load (if any) is along the push, else the
    load's work less the tissue's energy."""
    p = search.params
    if tissue is None and p.load_toward is None:
        return Travel(search)
    toward = None if p.load_toward is None else np.asarray(p.load_toward, dtype=np.float64)
    return Work(search, tissue, float(p.load_n if p.load_n is not None else 1.0), toward, arm)

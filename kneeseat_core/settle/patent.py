"""`--method patent`: the letter of US 6,708,142 FIGS. 2-16 (see kneeseat_core/settle.py).

1. translate along Δ by the step until collision, then dichotomy to within T2;
2. contacts at the last colliding pose of the dichotomy; back-facing normals
   (normal · motion >= 0, FIG. 5) dropped;
3. torque test (barycentre, then each point, then the candidates' barycentre, re-checked):
   if a centre exists, rotate about the axis through it parallel to Δ by the angle that
   moves the farthest vertex an arc of one step (or `rotation_step_rad`), and find exact
   contact by dichotomy on the rotation (only while the remaining angle is above the
   rotation resolution, as written);
4. otherwise slide by the step times the component-wise average of the unit projected
   normals (+X, -X, +Z, -Z averaged separately, then summed, FIGS. 8, 9, 14); stop when
   that slide is shorter than T2 (our reading of "resultant below the resolution");
5. after any motion without collision, translate along Δ again.
Readings of ambiguous text: a zero torque is ignored (not a change of sign), and
python-fcl contacts are mapped to the reference by object identity. A repeated pose (the
slide/rotate cycle), leaving the envelope or the iteration cap ends "not converged".
"""
from __future__ import annotations

from dataclasses import dataclass, field
import math

import numpy as np

from kneeseat_core.geometry import rotation_about, TOL
from kneeseat_core.status import Status
from kneeseat_core.typed import Floats, Pose
from .search import Bracket, Contacts, LOST_CONTACT, rotated, Search, SettleResult, translated

__all__ = ['run_patent']


def _torque_centre(search: Search, contacts: Contacts) -> tuple[Floats, float] | None:
    """The patent's O(n^2) torque test: a centre and the torque sign, or None."""
    pts, nrm = contacts.points, contacts.normals

    def sign_at(centre: Floats) -> float:
        torque = np.cross(pts - centre, nrm) @ search.push
        nonzero = torque[np.abs(torque) > TOL.torque]
        if len(nonzero) == 0:
            return 0.0
        if np.all(nonzero > 0):
            return 1.0
        if np.all(nonzero < 0):
            return -1.0
        return 0.0

    centre = pts.mean(axis=0)
    sign = sign_at(centre)
    if sign:
        return centre, sign
    valid = [p for p in pts if sign_at(p)]
    if not valid:
        return None
    centre = np.mean(valid, axis=0)
    sign = sign_at(centre)
    return (centre, sign) if sign else None


def _component_resultant(search: Search, contacts: Contacts) -> Floats:
    """FIGS. 8, 9, 14: unit projected normals averaged per signed in-plane axis."""
    proj = np.stack([contacts.normals @ search.e1, contacts.normals @ search.e2], axis=1)
    lengths = np.linalg.norm(proj, axis=1)
    proj = proj[lengths > TOL.zero_length] / lengths[lengths > TOL.zero_length, None]
    total = np.zeros(2)
    for axis in (0, 1):
        comp = proj[:, axis]
        for part in (comp[comp > 0], comp[comp < 0]):
            if len(part):
                total[axis] += part.mean()
    out: Floats = total[0] * search.e1 + total[1] * search.e2
    return out


def run_patent(search: Search, bracket: Bracket) -> SettleResult:
    """The literal loop of FIGS. 2-16 from the first exact contact `bracket`."""
    p = search.params
    state = _Patent(search, bracket.free, search.contacts(bracket.touching), search.push,
                    p.rotation_resolution_rad if p.rotation_resolution_rad is not None
                    else math.radians(1.0))
    while search.iterations < p.max_iterations:
        search.iterations += 1
        if state.cycled():
            return search.result(state.pose, Status.WEDGED, 'wedged: the slide and the '
                                 'rotation are both blocked and the method cycles between '
                                 'the same poses', state.contacts)
        facing = search.facing(state.contacts, state.motion)
        if len(facing.points) == 0:
            facing = search.facing(state.contacts, search.push)
        if len(facing.points) == 0:
            return search.result(state.pose, Status.FAILED, 'no usable contact: every normal '
                                 'is back-facing', state.contacts)
        found = _torque_centre(search, facing)
        if found is not None:
            if state.rotate(*found):
                continue
        else:
            slide = state.slide_for(facing)
            if np.linalg.norm(slide) < p.resolution_m:
                return search.result(state.pose, Status.REST, 'stable: the resultant of the '
                                     'projected normals is below the resolution', facing)
            if state.slide(slide):
                continue
        ended = state.fall()
        if ended is not None:
            return ended
    return search.result(state.pose, Status.CAP, f'iteration cap ({p.max_iterations}) reached',
                         state.contacts)


@dataclass(slots=True, eq=False)
class _Patent:
    """The state of the literal loop: pose, contacts there, the last motion's direction."""

    search: Search
    pose: Pose
    contacts: Contacts
    motion: Floats
    rot_res: float                       # rotation resolution (rad)
    seen: dict[bytes, int] = field(default_factory=dict)   # pose key -> iteration

    def cycled(self) -> bool:
        """The pose repeats one seen before the last iteration (the slide/rotate cycle)."""
        s, p = self.search, self.search.params
        key = np.round(self.pose[:3, :] / (p.resolution_m * 0.5)).astype(np.int64).tobytes()
        if key in self.seen and s.iterations - self.seen[key] > 1:
            return True
        self.seen[key] = s.iterations
        return False

    def rotate(self, centre: Floats, sign: float) -> bool:
        """Step 3: turn about the axis through `centre` parallel to the push by the arc of
        one step at the farthest vertex; True when it collided (then stopped at contact,
        or dropped below the rotation resolution: FIG. 7 never runs below it)."""
        s, p = self.search, self.search.params
        radius = max(s.radius_about(self.pose, centre), p.step_m)
        angle = p.rotation_step_rad if p.rotation_step_rad is not None else p.step_m / radius
        base = self.pose

        def turn(f: float) -> Pose:
            return rotated(base, rotation_about(s.push, sign * angle * f), centre)

        if not s.collides(turn(1.0)):
            self.pose = turn(1.0)
            return False
        if angle > self.rot_res:
            lo, hi = s.bisect(turn, self.rot_res / angle)
            self.pose, self.contacts = turn(lo), s.contacts(turn(hi))
        motion = np.cross(s.push, self.contacts.points.mean(axis=0) - centre) \
            if len(self.contacts.points) else s.push
        self.motion = motion * sign if np.linalg.norm(motion) > 0 else s.push
        return True

    def slide_for(self, facing: Contacts) -> Floats:
        """Step 4's slide (3,): the step times the component-wise resultant of `facing`,
        without its locked part; the body is at rest when it is shorter than T2."""
        s, p = self.search, self.search.params
        slide = _component_resultant(s, facing) * p.step_m
        if p.locked_slide is not None:
            slide -= (slide @ s.e1) * s.e1
        return slide

    def slide(self, slide: Floats) -> bool:
        """Step 4: make the slide; True when it collided (then stopped at exact contact)."""
        s, p = self.search, self.search.params
        base = self.pose

        def shift(f: float) -> Pose:
            return translated(base, f * slide)

        if not s.collides(shift(1.0)):
            self.pose = shift(1.0)
            return False
        length = float(np.linalg.norm(slide))
        lo, hi = s.bisect(shift, p.resolution_m / length)
        self.pose, self.contacts = shift(lo), s.contacts(shift(hi))
        self.motion = slide / length
        return True

    def fall(self) -> SettleResult | None:
        """Step 5: after a motion without collision, translate along the push again; the end
        when contact is lost or the pose left the envelope."""
        s, p = self.search, self.search.params
        dropped = s.drop(self.pose, p.resolution_m)
        if dropped is None:
            return s.result(self.pose, Status.LOST, LOST_CONTACT, self.contacts)
        self.pose, self.contacts = dropped.free, s.contacts(dropped.touching)
        self.motion = s.push
        too_far = s.beyond_envelope(self.pose)
        if too_far:
            return s.result(self.pose, Status.ENVELOPE, too_far, self.contacts)
        return None

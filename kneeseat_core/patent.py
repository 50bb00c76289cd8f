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

import math

import numpy as np

from .geometry import rotation_about, TOL
from .search import Bracket, Contacts, LOST_CONTACT, rotated, Search, SettleResult, translated
from .status import Status
from .typed import Floats, Pose

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
    return total[0] * search.e1 + total[1] * search.e2


def run_patent(search: Search, bracket: Bracket) -> SettleResult:
    """The literal loop of FIGS. 2-16 from the first exact contact `bracket`."""
    p = search.params
    pose, contacts = bracket.free, search.contacts(bracket.touching)
    motion = search.push
    rot_res = p.rotation_resolution_rad if p.rotation_resolution_rad is not None \
        else math.radians(1.0)
    seen: dict[bytes, int] = {}
    while search.iterations < p.max_iterations:
        search.iterations += 1
        key = np.round(pose[:3, :] / (p.resolution_m * 0.5)).astype(np.int64).tobytes()
        if key in seen and search.iterations - seen[key] > 1:
            return search.result(pose, Status.WEDGED, 'wedged: the slide and the rotation are '
                                 'both blocked and the method cycles between the same poses',
                                 contacts)
        seen[key] = search.iterations
        facing = search.facing(contacts, motion)
        if len(facing.points) == 0:
            facing = search.facing(contacts, search.push)
        if len(facing.points) == 0:
            return search.result(pose, Status.FAILED, 'no usable contact: every normal is '
                                 'back-facing', contacts)
        found = _torque_centre(search, facing)
        if found is not None:
            centre, sign = found
            radius = max(search.radius_about(pose, centre), p.step_m)
            angle = p.rotation_step_rad if p.rotation_step_rad is not None \
                else p.step_m / radius
            base = pose

            def turn(s: float, base: Pose = base, centre: Floats = centre, sign: float = sign,
                     angle: float = angle) -> Pose:
                return rotated(base, rotation_about(search.push, sign * angle * s), centre)

            if search.collides(turn(1.0)):
                if angle > rot_res:
                    lo, hi = search.bisect(turn, rot_res / angle)
                    pose, contacts = turn(lo), search.contacts(turn(hi))
                # else: the rotation is dropped (FIG. 7 never runs below resolution)
                motion = np.cross(search.push, contacts.points.mean(axis=0) - centre) \
                    if len(contacts.points) else search.push
                motion = motion * sign if np.linalg.norm(motion) > 0 else search.push
                continue
            pose = turn(1.0)
        else:
            slide = _component_resultant(search, facing) * p.step_m
            if p.locked_slide is not None:
                slide -= (slide @ search.e1) * search.e1
            if np.linalg.norm(slide) < p.resolution_m:
                return search.result(pose, Status.REST, 'stable: the resultant of the projected '
                                     'normals is below the resolution', facing)
            base = pose

            def shift(s: float, base: Pose = base, slide: Floats = slide) -> Pose:
                return translated(base, s * slide)

            if search.collides(shift(1.0)):
                length = float(np.linalg.norm(slide))
                lo, hi = search.bisect(shift, p.resolution_m / length)
                pose, contacts = shift(lo), search.contacts(shift(hi))
                motion = slide / length
                continue
            pose = shift(1.0)
        # a motion without collision: translate along Δ again
        dropped = search.drop(pose, p.resolution_m)
        if dropped is None:
            return search.result(pose, Status.LOST, LOST_CONTACT, contacts)
        pose, contacts = dropped.free, search.contacts(dropped.touching)
        motion = search.push
        too_far = search.beyond_envelope(pose)
        if too_far:
            return search.result(pose, Status.ENVELOPE, too_far, contacts)
    return search.result(pose, Status.CAP, f'iteration cap ({p.max_iterations}) reached',
                         contacts)

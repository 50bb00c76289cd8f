"""Settle one moving rigid body against a fixed one along a push direction (US 6,708,142).

The moving body may translate in any direction and rotate only about axes parallel to the
push direction `Δ` (`push`). Two methods share the same primitives (exact contact by
dichotomy, contacts = colliding reference triangles with the reference's outward normals):

`patent` - the letter of FIGS. 2-16:
  1. translate along Δ by the step until collision, then dichotomy to within T2;
  2. contacts at the last colliding pose of the dichotomy; back-facing normals
     (normal · motion >= 0, FIG. 5) dropped;
  3. torque test (barycentre, then each point, then the candidates' barycentre,
     re-checked): if a centre exists, rotate about the axis through it parallel to Δ by the
     angle that moves the farthest vertex an arc of one step (or `rotation_step_rad`), and
     find exact contact by dichotomy on the rotation (only while the remaining angle is
     above the rotation resolution, as written);
  4. otherwise slide by the step times the component-wise average of the unit projected
     normals (+X, -X, +Z, -Z averaged separately, then summed, FIGS. 8, 9, 14); stop when
     that slide is shorter than T2 (our reading of "resultant below the resolution");
  5. after any motion without collision, translate along Δ again.
  Two readings of ambiguous text are fixed as DESIGN.md says: a zero torque is ignored
  (not a change of sign), and python-fcl contacts are mapped to the reference by object
  identity. A repeated pose (slide/rotate cycle) or the iteration cap ends "not converged".

`default` - the same loop carried to a true rest pose. Departures, each named:
  D1 combined moves: the next motion is the steepest admissible one for the contact set
     as a whole - slide and rotation about Δ together - found as the minimum-norm point
     of the convex hull of the contacts' depth gradients (first-order quasi-static
     equilibrium; an unbalanced torque and an unbalanced slide are no longer exclusive).
  D2 blocked moves teach: a motion that collides is cut by dichotomy and the blocking
     contacts join the contact set at that depth, so the next direction respects them
     (this is what frees a wedged body, instead of cycling slide/rotate).
  D3 step control: the step halves whenever a move fails to gain T2 along Δ; moves that
     lose depth are undone. Exact contact along Δ is found to T2 = resolution / 2 so that
     depth comparisons are meaningful at the resolution.
  D4 rotation resolution is an arc at the farthest vertex (resolution / radius) unless
     given explicitly, so a rotation can always be refined below one step.
  D5 rest is verified, not assumed: when the step is below the resolution, probe moves
     (slides, rotations about Δ and their combinations, at several scales) must all fail
     to gain more than the resolution along Δ; a probe that gains restarts the loop.
  D6 honest ends: "converged" only after D5; otherwise the iteration cap is reported.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import itertools
import logging
import math
import time
from typing import Literal

import numpy as np

from .collision import CollisionPair, RigidBody
from .errors import NoContactError, SettleError
from .geometry import rotation_about, TOL, unit
from .typed import Floats, Pose

__all__ = ['Method', 'SettleParams', 'Contacts', 'SettleResult', 'settle']

log = logging.getLogger(__name__)

Method = Literal['default', 'patent']


@dataclass(frozen=True, slots=True)
class SettleParams:
    """Knobs of one settle, SI units; defaults are the patent's numbers for a knee."""

    push: tuple[float, float, float] = (0.0, -1.0, 0.0)   # Δ, fixed frame (normalised)
    step_m: float = 1e-3                    # translation modeling step
    resolution_m: float = 1e-4              # T2, exact-contact tolerance
    rotation_step_rad: float | None = None  # None: arc of one step at the farthest vertex
    rotation_resolution_rad: float | None = None  # None: method's own rule (see module)
    max_iterations: int = 500
    method: Method = 'default'
    # A slide direction (fixed frame) the body may not translate along, e.g. a patella
    # held at its height along the groove by its tendon; None: the whole plane is free.
    locked_slide: tuple[float, float, float] | None = None
    # A body that slides farther than this across the push has no rest near its start
    # (e.g. an insert escaping over a condyle at extreme varus): "not converged".
    max_slide_m: float = 0.02

    def check(self) -> None:
        """Raise SettleError naming the first invalid parameter."""
        unit(np.asarray(self.push, dtype=float), 'push direction')
        for name in ('step_m', 'resolution_m', 'max_slide_m'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SettleError(f'{name}={value} must be a positive number')
        if self.resolution_m > self.step_m:
            raise SettleError(f'resolution {self.resolution_m} m is coarser than the step '
                              f'{self.step_m} m; give a resolution below the step')
        for name in ('rotation_step_rad', 'rotation_resolution_rad'):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0 < value < math.pi):
                raise SettleError(f'{name}={value} must be between 0 and pi rad')
        if self.max_iterations < 1:
            raise SettleError(f'max_iterations={self.max_iterations} must be at least 1')
        if self.locked_slide is not None:
            lock = unit(np.asarray(self.locked_slide, dtype=float), 'locked slide')
            push = unit(np.asarray(self.push, dtype=float), 'push direction')
            if float(np.linalg.norm(lock - (lock @ push) * push)) < 0.1:
                raise SettleError('the locked slide direction is (nearly) parallel to the push; '
                                  'give a direction across the push')
        if self.method not in ('default', 'patent'):
            raise SettleError(f"method '{self.method}' is unknown; use default or patent")


@dataclass(frozen=True, slots=True, eq=False)
class Contacts:
    """Contact application points and reaction normals, fixed frame."""

    points: Floats    # (k, 3) m: centres of the colliding reference triangles
    normals: Floats   # (k, 3) unit outward normals of the reference there

    @classmethod
    def empty(cls) -> Contacts:
        """No contact."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)))


@dataclass(frozen=True, slots=True, eq=False)
class SettleResult:
    """Outcome of one settle; `converged` False always comes with a reason."""

    pose: Pose                  # (4, 4) fixed_from_moving at the end (apart, within T2)
    converged: bool
    reason: str
    iterations: int
    collision_checks: int
    contacts: Contacts          # final contacts
    elapsed_s: float
    fcl_s: float                # part of elapsed_s spent inside python-fcl (s)
    backed_out_m: float = 0.0   # distance the start was backed out along -Δ


def settle(fixed: RigidBody, moving: RigidBody, start: Pose,
           params: SettleParams) -> SettleResult:
    """Push `moving` along `params.push` until it rests on `fixed`.

    Args:
        fixed: the reference body, at identity.
        moving: the moving body.
        start: (4, 4) fixed_from_moving start pose (m). A start in collision is backed
            out along -Δ first (reported in `backed_out_m`).
    Returns:
        The settle result; `converged` says whether the method's stop rule was met.
    Raises:
        NoContactError: no contact along Δ within the travel limit.
        SettleError: invalid parameters, or a start buried too deep to back out.
    """
    params.check()
    return _Settler(CollisionPair(fixed, moving), start, params).run()


def _translated(pose: Pose, v: Floats) -> Pose:
    out = pose.copy()
    out[:3, 3] += v
    return out


def _rotated(pose: Pose, rot: Floats, centre: Floats) -> Pose:
    """Rotate the whole body by `rot` (3, 3) about `centre` (3,) (fixed frame)."""
    out = np.empty((4, 4))
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = rot @ (pose[:3, 3] - centre) + centre
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


@dataclass(slots=True, eq=False)
class _Settler:
    """State of one settle: the pair, the push frame and the counters."""

    pair: CollisionPair
    start: Pose
    params: SettleParams
    push: Floats = field(init=False)
    e1: Floats = field(init=False)
    e2: Floats = field(init=False)
    free: Floats = field(init=False)    # (3,) 1 for each free move coordinate (e1, e2, arc)
    iterations: int = 0

    def __post_init__(self) -> None:
        self.push = unit(np.asarray(self.params.push, dtype=float), 'push direction')
        if self.params.locked_slide is not None:   # e1 is the locked direction
            axis = np.asarray(self.params.locked_slide, dtype=float)
        else:
            axis = np.eye(3)[int(np.argmin(np.abs(self.push)))]
        self.e1 = unit(axis - (axis @ self.push) * self.push, 'in-plane axis')
        self.free = np.array([0.0 if self.params.locked_slide is not None else 1.0, 1.0, 1.0])
        self.e2 = np.cross(self.push, self.e1)

    # ---- geometry helpers -------------------------------------------------------------
    def _radius_about(self, pose: Pose, centre: Floats) -> float:
        """Distance of the farthest moving vertex from the axis through `centre` ∥ Δ."""
        world = self.pair.moving.vertices @ pose[:3, :3].T + pose[:3, 3]
        rel = world - centre
        rel -= np.outer(rel @ self.push, self.push)
        return float(np.sqrt(np.max(np.einsum('ij,ij->i', rel, rel))))

    def _travel_limit(self, pose: Pose) -> float:
        """Farthest travel along Δ after which no contact can happen any more."""
        fixed, moving = self.pair.fixed, self.pair.moving
        moving_c = pose[:3, :3] @ moving.bound_centre + pose[:3, 3]
        return float(np.linalg.norm(moving_c - fixed.bound_centre) + fixed.bound_radius
                     + moving.bound_radius)

    def _contacts(self, pose: Pose) -> Contacts:
        ids = self.pair.contacts(pose)
        return Contacts(self.pair.fixed.centres[ids], self.pair.fixed.normals[ids])

    def _facing(self, contacts: Contacts, motion: Floats) -> Contacts:
        """Drop back-facing normals: normal · motion >= 0 (patent FIG. 5)."""
        keep = contacts.normals @ motion < 0.0
        return Contacts(contacts.points[keep], contacts.normals[keep])

    # ---- exact contact ----------------------------------------------------------------
    def _bisect(self, move, tol_fraction: float) -> tuple[float, float]:
        """Dichotomy on a motion `move(s)`, s in [0, 1]: free at 0, colliding at 1.

        Returns (free_s, colliding_s) with colliding_s - free_s <= tol_fraction.
        """
        lo, hi = 0.0, 1.0
        while hi - lo > tol_fraction:
            mid = 0.5 * (lo + hi)
            if self.pair.collides(move(mid)):
                hi = mid
            else:
                lo = mid
        return lo, hi

    def _back_out(self, pose: Pose) -> tuple[Pose, float]:
        """Move a start in collision back along -Δ until free."""
        if not self.pair.collides(pose):
            return pose, 0.0
        limit = self._travel_limit(pose)
        dist = self.params.step_m
        while dist <= 2.0 * limit:
            cand = _translated(pose, -dist * self.push)
            if not self.pair.collides(cand):
                lo, hi = self._bisect(lambda s: _translated(pose, -dist * (1.0 - s) * self.push),
                                      self.params.resolution_m / dist)
                backed = dist * (1.0 - lo)
                log.info('start pose was in collision: backed out %.3f mm along -push',
                         backed * 1e3)
                return _translated(pose, -backed * self.push), backed
            dist *= 2.0
        raise SettleError('the start pose is buried in the fixed body and cannot be backed out '
                          'along the push direction; start the moving body outside it')

    def _drop(self, pose: Pose, tol_m: float, limit_m: float | None = None,
              step_m: float | None = None) -> tuple[Pose, Pose] | None:
        """Translate along Δ by steps until collision, then dichotomy (FIGS. 2-4).

        Returns (free pose, colliding pose) less than `tol_m` apart, or None when no
        contact happens within `limit_m`. `step_m` defaults to the translation step.
        """
        step = self.params.step_m if step_m is None else step_m
        limit = self._travel_limit(pose) if limit_m is None else limit_m
        travelled = 0.0
        while travelled <= limit:
            nxt = _translated(pose, step * self.push)
            if self.pair.collides(nxt):
                base = pose
                lo, hi = self._bisect(lambda s: _translated(base, s * step * self.push),
                                      tol_m / step)
                return (_translated(base, lo * step * self.push),
                        _translated(base, hi * step * self.push))
            pose = nxt
            travelled += step
        return None

    def _depth(self, pose: Pose) -> float:
        return float(pose[:3, 3] @ self.push)

    def _slid_too_far(self, origin: Pose, pose: Pose) -> str | None:
        """The not-converged reason when `pose` slid beyond `max_slide_m` from `origin`."""
        d = pose[:3, 3] - origin[:3, 3]
        slide = float(np.linalg.norm(d - (d @ self.push) * self.push))
        if slide <= self.params.max_slide_m:
            return None
        return (f'slid {slide * 1e3:.1f} mm across the push without finding rest (limit '
                f'{self.params.max_slide_m * 1e3:.0f} mm): no resting place near the start')

    def _result(self, pose: Pose, converged: bool, reason: str, contacts: Contacts,
                started: float, backed: float) -> SettleResult:
        return SettleResult(pose, converged, reason, self.iterations, self.pair.checks,
                            contacts, time.perf_counter() - started, self.pair.fcl_s, backed)

    def run(self) -> SettleResult:
        started = time.perf_counter()
        pose, backed = self._back_out(np.asarray(self.start, dtype=np.float64))
        limit = self._travel_limit(pose)
        tol = self.params.resolution_m if self.params.method == 'patent' \
            else self.params.resolution_m / 2.0
        bracket = self._drop(pose, tol, limit)
        if bracket is None:
            raise NoContactError(limit)
        if self.params.method == 'patent':
            return self._run_patent(bracket, started, backed)
        return self._run_default(bracket, started, backed)

    # ---- the patent, literally ---------------------------------------------------------
    def _torque_centre(self, contacts: Contacts) -> tuple[Floats, float] | None:
        """The patent's O(n^2) torque test: a centre and the torque sign, or None."""
        pts, nrm = contacts.points, contacts.normals

        def sign_at(centre: Floats) -> float:
            torque = np.cross(pts - centre, nrm) @ self.push
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

    def _component_resultant(self, contacts: Contacts) -> Floats:
        """FIGS. 8, 9, 14: unit projected normals averaged per signed in-plane axis."""
        proj = np.stack([contacts.normals @ self.e1, contacts.normals @ self.e2], axis=1)
        lengths = np.linalg.norm(proj, axis=1)
        proj = proj[lengths > TOL.zero_length] / lengths[lengths > TOL.zero_length, None]
        total = np.zeros(2)
        for axis in (0, 1):
            comp = proj[:, axis]
            for part in (comp[comp > 0], comp[comp < 0]):
                if len(part):
                    total[axis] += part.mean()
        return total[0] * self.e1 + total[1] * self.e2

    def _run_patent(self, bracket: tuple[Pose, Pose], started: float,
                    backed: float) -> SettleResult:
        p = self.params
        pose, colliding = bracket
        origin = pose
        contacts = self._contacts(colliding)
        motion = self.push
        rot_res = p.rotation_resolution_rad if p.rotation_resolution_rad is not None \
            else math.radians(1.0)
        seen: dict[bytes, int] = {}
        while self.iterations < p.max_iterations:
            self.iterations += 1
            key = np.round(pose[:3, :] / (p.resolution_m * 0.5)).astype(np.int64).tobytes()
            if key in seen and self.iterations - seen[key] > 1:
                return self._result(pose, False, 'wedged: the slide and the rotation are both '
                                    'blocked and the method cycles between the same poses',
                                    contacts, started, backed)
            seen[key] = self.iterations
            facing = self._facing(contacts, motion)
            if len(facing.points) == 0:
                facing = self._facing(contacts, self.push)
            if len(facing.points) == 0:
                return self._result(pose, False, 'no usable contact: every normal is '
                                    'back-facing', contacts, started, backed)
            found = self._torque_centre(facing)
            if found is not None:
                centre, sign = found
                radius = max(self._radius_about(pose, centre), p.step_m)
                angle = p.rotation_step_rad if p.rotation_step_rad is not None \
                    else p.step_m / radius
                base = pose
                turn = lambda s, base=base, centre=centre, sign=sign, angle=angle: _rotated(  # noqa
                    base, rotation_about(self.push, sign * angle * s), centre)
                if self.pair.collides(turn(1.0)):
                    if angle > rot_res:
                        lo, hi = self._bisect(turn, rot_res / angle)
                        pose, contacts = turn(lo), self._contacts(turn(hi))
                    # else: the rotation is dropped (FIG. 7 never runs below resolution)
                    motion = np.cross(self.push, contacts.points.mean(axis=0) - centre) \
                        if len(contacts.points) else self.push
                    motion = motion * sign if np.linalg.norm(motion) > 0 else self.push
                    continue
                pose = turn(1.0)
            else:
                slide = self._component_resultant(facing) * p.step_m
                if p.locked_slide is not None:
                    slide -= (slide @ self.e1) * self.e1
                if np.linalg.norm(slide) < p.resolution_m:
                    return self._result(pose, True, 'stable: the resultant of the projected '
                                        'normals is below the resolution', facing, started,
                                        backed)
                base = pose
                shift = lambda s, base=base, slide=slide: _translated(base, s * slide)  # noqa
                if self.pair.collides(shift(1.0)):
                    length = float(np.linalg.norm(slide))
                    lo, hi = self._bisect(shift, p.resolution_m / length)
                    pose, contacts = shift(lo), self._contacts(shift(hi))
                    motion = slide / length
                    continue
                pose = shift(1.0)
            # a motion without collision: translate along Δ again
            bracket = self._drop(pose, p.resolution_m)
            if bracket is None:
                return self._result(pose, False, _LOST_CONTACT, contacts, started, backed)
            pose, colliding = bracket
            contacts = self._contacts(colliding)
            motion = self.push
            too_far = self._slid_too_far(origin, pose)
            if too_far:
                return self._result(pose, False, too_far, contacts, started, backed)
        return self._result(pose, False, f'iteration cap ({p.max_iterations}) reached',
                            contacts, started, backed)

    # ---- default: carried to a true rest pose ----------------------------------------
    def _run_default(self, bracket: tuple[Pose, Pose], started: float,
                     backed: float) -> SettleResult:
        return _DefaultSearch(self, bracket).run(started, backed)


def _min_norm_point(points: Floats, iterations: int = 64) -> Floats:
    """Minimum-norm point of the convex hull of `points` (k, d), by Frank-Wolfe.

    Stops when the duality gap x.x - min_j p_j.x falls below 1e-4 x.x (the direction is
    then exact to well under a degree).
    """
    x = points[int(np.argmin(np.einsum('ij,ij->i', points, points)))].copy()
    for _ in range(iterations):
        dots = points @ x
        j = int(np.argmin(dots))
        xx = float(x @ x)
        if xx - float(dots[j]) <= 1e-4 * xx + 1e-18:
            break
        d = points[j] - x
        dd = float(d @ d)
        if dd < 1e-30:
            break
        t = -float(x @ d) / dd
        if t <= 1e-12:
            break
        x += min(t, 1.0) * d
    return x


@dataclass(slots=True, eq=False)
class _DefaultSearch:
    """The default method's loop (departures D1-D6 of the module docstring)."""

    s: _Settler
    bracket: tuple[Pose, Pose]

    def run(self, started: float, backed: float) -> SettleResult:
        s, p = self.s, self.s.params
        tol = p.resolution_m / 2.0
        pose, colliding = self.bracket
        floor = s._contacts(colliding)
        radius = max(s.pair.moving.reach, p.step_m)      # bounds the farthest vertex
        rot_step = p.rotation_step_rad if p.rotation_step_rad is not None else p.step_m / radius
        rot_res = p.rotation_resolution_rad if p.rotation_resolution_rad is not None \
            else p.resolution_m / radius
        arm = p.step_m / rot_step              # metres of arc per radian of the 3rd coordinate
        finest = min(p.resolution_m, rot_res * arm)
        step = p.step_m
        blocked = Contacts.empty()
        last_blocked: Floats | None = None
        refine_dir: Floats | None = None     # last direction of a D1' (mean-normal) move

        def moved(base: Pose, x: Floats) -> Pose:
            """Slide by x[0] e1 + x[1] e2 and turn by x[2] / arm about the centre axis."""
            c = base[:3, :3] @ s.pair.moving.centroid + base[:3, 3]
            x = x * s.free
            out = _rotated(base, rotation_about(s.push, x[2] / arm), c)
            out[:3, 3] += x[0] * s.e1 + x[1] * s.e2
            return out

        def gradients(contacts: Contacts, base: Pose) -> Floats:
            """Depth gradient (k, 3) of each contact w.r.t. (slide e1, slide e2, arc)."""
            facing = s._facing(contacts, s.push)
            if len(facing.points) == 0:
                return np.zeros((0, 3))
            n, pts = facing.normals, facing.points
            c = base[:3, :3] @ s.pair.moving.centroid + base[:3, 3]
            lever = np.cross(s.push, pts - c) / arm           # d(point)/d(arc)
            down = -(n @ s.push)                               # > 0
            return np.stack([n @ s.e1, n @ s.e2, np.einsum('ij,ij->i', n, lever)], 1) \
                * s.free / down[:, None]

        def drop_from(base: Pose, expected_m: float) -> tuple[Pose, Contacts] | None:
            # the first-order model says how far the floor is: step by about that much
            b = s._drop(base, tol, step_m=min(p.step_m, max(1.5 * expected_m, 4.0 * tol)))
            if b is None:
                return None
            return b[0], s._contacts(b[1])

        while s.iterations < p.max_iterations:
            s.iterations += 1
            contacts = Contacts(np.concatenate([floor.points, blocked.points]),
                                np.concatenate([floor.normals, blocked.normals]))
            grads = gradients(contacts, pose)
            direction = None
            refining = False
            if len(grads) and step >= finest:
                g = _min_norm_point(grads)
                norm = float(np.linalg.norm(g))
                if norm > _FLAT_SLOPE and float(np.min(grads @ g)) > 0.0:
                    direction = g / norm
                else:
                    # D1': one smooth patch straddling the optimum balances the hull but
                    # not the patch's mean normal; follow the mean to centre the patch
                    g = grads.mean(axis=0)
                    norm = float(np.linalg.norm(g))
                    if norm > _FLAT_SLOPE and not len(blocked.points):
                        direction = g / norm
                        refining = True
                        if refine_dir is not None:
                            # bracket the patch's centre: shrink when it was passed,
                            # grow (slower than the shrink) while it is still ahead
                            step *= 0.5 if float(direction @ refine_dir) < 0.0 else 1.5
                            step = min(step, p.step_m)
                        refine_dir = direction
            if direction is None:
                if step >= finest and len(blocked.points):
                    # the blocking contacts balance the floor at this step: refine
                    step *= 0.5
                    blocked = Contacts.empty()
                    continue
                probe = self._probe(pose, moved, finest, tol, grads)
                if probe is None:
                    return s._result(pose, True, 'rest: no slide, rotation about the push '
                                     'axis or combination gains more than the resolution '
                                     'along the push', contacts, started, backed)
                pose, floor = probe
                blocked = Contacts.empty()
                step = max(step, 2.0 * finest)
                continue
            log.debug('iteration %d: step %.4f mm, %s move %s, %d contacts', s.iterations,
                      step * 1e3, 'centring' if refining else 'hull', np.round(direction, 3),
                      len(grads))
            target = moved(pose, step * direction)
            base = pose
            if s.pair.collides(target):
                lo, hi = s._bisect(lambda t: moved(base, t * step * direction), tol / step)
                new_block = s._contacts(moved(base, hi * step * direction))
                if lo * step < tol:
                    # D2: blocked at once; learn the blocking contacts, or refine when
                    # they teach nothing new (the same direction comes back)
                    if last_blocked is not None and float(direction @ last_blocked) > 0.999:
                        step *= 0.5
                        blocked, last_blocked = Contacts.empty(), None
                        continue
                    blocked = Contacts(np.concatenate([blocked.points, new_block.points]),
                                       np.concatenate([blocked.normals, new_block.normals]))
                    last_blocked = direction
                    continue
                target = moved(base, lo * step * direction)
                blocked = new_block
            else:
                blocked = Contacts.empty()
            last_blocked = None
            expected = max(step * float(np.min(grads @ direction)), 0.0)
            dropped = drop_from(target, expected)
            if dropped is None:
                return s._result(target, False, _LOST_CONTACT, floor, started, backed)
            new_pose, new_floor = dropped
            gain = s._depth(new_pose) - s._depth(pose)
            if gain < -tol:            # lost depth: undo, refine
                step *= 0.5
                blocked = Contacts.empty()
                continue
            pose, floor = new_pose, new_floor
            too_far = s._slid_too_far(self.bracket[0], pose)
            if too_far:
                return s._result(pose, False, too_far, floor, started, backed)
            if not refining:
                refine_dir = None
                if gain < tol:
                    step *= 0.5
        return s._result(pose, False, f'iteration cap ({p.max_iterations}) reached before '
                         'rest was verified', floor, started, backed)

    def _probe(self, pose: Pose, moved, finest: float, tol: float, grads: Floats
               ) -> tuple[Pose, Contacts] | None:
        """D5: try slides, turns and combinations; return the first that gains depth.

        A probe is only sent to python-fcl when the contacts' first-order model leaves it
        a chance: every contact in the set lies within T2 of touching, so a move the
        model says gains less than T2 / 2 cannot gain the resolution (2 T2) at these
        scales; contacts missing from the set can only block, never help.
        """
        s = self.s
        lift = 2.0 * tol      # a probe must gain more than the resolution
        for scale in (finest, 3.0 * finest):
            for d in _PROBE_DIRECTIONS:
                if np.any(d * (1.0 - s.free)):
                    continue
                if len(grads) and float(np.min(grads @ (scale * d))) < 0.5 * tol:
                    continue
                cand = moved(pose, scale * d)
                if not s.pair.collides(_translated(cand, lift * s.push)):
                    b = s._drop(_translated(cand, lift * s.push), tol)
                    if b is None:     # free all the way down: an edge; not a gain
                        continue
                    return b[0], s._contacts(b[1])
        return None


_LOST_CONTACT = ('lost contact: the body slid off the edge of the fixed body without finding '
                 'rest along this push')

# Depth gained per metre of lateral motion below which the contact set counts as balanced.
_FLAT_SLOPE = 1e-3

_PROBE_DIRECTIONS = [np.array(d, dtype=float)
                     for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)]

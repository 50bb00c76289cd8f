"""What both settle methods share: parameters, results, the push frame and exact contact.

`Search` holds one settle's collision pair, its push direction `Δ` with an in-plane basis
(e1, e2), the lateral moves (slides across Δ and spins about an axis parallel to Δ), the
envelope, python-fcl's queries (exact contact along Δ by dichotomy and the contacts at a
pose, the patent's; backing a pose in collision out along -Δ, both methods') and, for the
default method, the exact travel (`sweep`). The methods (`kneeseat_core.settle.patent`,
`kneeseat_core.settle.climb`) decide which moves to make.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import logging
import math
import time
from typing import Callable

import numpy as np

from kneeseat_core.errors import SettleError
from kneeseat_core.geometry import unit
from kneeseat_core.meshes import CollisionPair, SweepPair
from kneeseat_core.params import SettleParams
from kneeseat_core.status import AT_REST, Status
from kneeseat_core.typed import Floats, Ints, Pose

__all__ = ['Contacts', 'SettleResult', 'Search', 'Bracket', 'LOST_CONTACT', 'translated',
           'rotated']

log = logging.getLogger('kneeseat_core.settle')

# the relative margin by which a move must stay inside the envelope's bounds for its room
# not to be computed (`Search.limits_to_envelope`)
_MARGIN = 1e-9
_SQRT2 = math.sqrt(2.0)

LOST_CONTACT = ('lost contact: the body slid off the edge of the fixed body without finding '
                'rest along this push')


@dataclass(frozen=True, slots=True, eq=False)
class Contacts:
    """Contact application points and reaction normals, fixed frame."""

    points: Floats    # (k, 3) m
    normals: Floats   # (k, 3) unit outward normals of the reference there

    @classmethod
    def empty(cls) -> Contacts:
        """No contact."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)))

    def __len__(self) -> int:
        return len(self.points)


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
    status: int = Status.REST   # `Status` code
    proof_checks: int = 0       # probes asked in proving rest (refuted or measured)
    proof_s: float = 0.0        # wall time of those proofs (s)
    travels: int = 0            # exact travels measured (default method)
    fcl_checks: int = 0         # python-fcl queries (of `collision_checks`)
    judged_back_m: float = 0.0  # how far python-fcl backed the final pose out
    # (k, 2) the pairs of triangles (moving face, fixed face) in contact at the end (the
    # default method's): a neighbouring settle's search starts from them (`settle`'s seeds)
    touching: Ints = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))

    @property
    def constrained(self) -> bool:
        """A rest held by the envelope (`envelope_holds`), not by the geometry alone."""
        return self.status == Status.CONSTRAINED


def translated(pose: Pose, v: Floats) -> Pose:
    """`pose` moved by the vector `v` (fixed frame)."""
    out = pose.copy()
    out[:3, 3] += v
    return out


def rotated(pose: Pose, rot: Floats, centre: Floats) -> Pose:
    """Rotate the whole body by `rot` (3, 3) about `centre` (3,) (fixed frame)."""
    out = np.empty((4, 4))
    out[:3, :3] = rot @ pose[:3, :3]
    out[:3, 3] = rot @ (pose[:3, 3] - centre) + centre
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


@dataclass(frozen=True, slots=True, eq=False)
class Bracket:
    """Exact contact along Δ: `free` and `touching` poses at most the tolerance apart."""

    free: Pose
    touching: Pose


@dataclass(slots=True, eq=False)
class Search:
    """One settle's pair, push frame, counters and shared primitives."""

    pair: CollisionPair
    start: Pose
    params: SettleParams
    anchor: Pose                        # the envelope is measured from here
    # the exact travel along Δ (the default method); None: python-fcl answers everything
    sweep: SweepPair | None = None
    push: Floats = field(init=False)
    e1: Floats = field(init=False)
    e2: Floats = field(init=False)
    free: Floats = field(init=False)    # (3,) 1 for each free move coordinate (e1, e2, spin)
    _anchor_centre: Floats = field(init=False, repr=False)   # the anchor's centroid
    _anchor_turn: Floats = field(init=False, repr=False)     # (3, 3) its rotation, inverse
    iterations: int = 0
    started: float = field(default_factory=time.perf_counter)
    backed_out_m: float = 0.0

    def __post_init__(self) -> None:
        self.push = unit(np.asarray(self.params.push, dtype=float), 'push direction')
        if self.params.locked_slide is not None:   # e1 is the locked direction
            axis = np.asarray(self.params.locked_slide, dtype=float)
        else:
            axis = np.eye(3)[int(np.argmin(np.abs(self.push)))]
        self.e1 = unit(axis - (axis @ self.push) * self.push, 'in-plane axis')
        self.free = np.array([0.0 if self.params.locked_slide is not None else 1.0, 1.0, 1.0])
        # Δ x e1, written out: numpy's cross costs half of this set-up, which every settle
        # makes (the same products and differences, the same bits)
        (p0, p1, p2), (a0, a1, a2) = self.push, self.e1
        self.e2 = np.array([p1 * a2 - p2 * a1, p2 * a0 - p0 * a2, p0 * a1 - p1 * a0])
        self._anchor_centre = self.centre(self.anchor)
        self._anchor_turn = self.anchor[:3, :3].T

    # ---- geometry ---------------------------------------------------------------------
    def depth(self, pose: Pose) -> float:
        """Position of `pose` along Δ (m)."""
        return float(pose[:3, 3] @ self.push)

    def centre(self, pose: Pose) -> Floats:
        """The moving body's centroid at `pose` (the spin axis passes through it)."""
        return pose[:3, :3] @ self.pair.moving.centroid + pose[:3, 3]

    def radius_about(self, pose: Pose, centre: Floats) -> float:
        """Distance of the farthest moving vertex from the axis through `centre` ∥ Δ."""
        world = self.pair.moving.vertices @ pose[:3, :3].T + pose[:3, 3]
        rel = world - centre
        rel -= np.outer(rel @ self.push, self.push)
        return float(np.sqrt(np.max(np.einsum('ij,ij->i', rel, rel))))

    def travel_limit(self, pose: Pose) -> float:
        """Farthest travel along Δ after which no contact can happen any more."""
        fixed, moving = self.pair.fixed, self.pair.moving
        moving_c = pose[:3, :3] @ moving.bound_centre + pose[:3, 3]
        return float(np.linalg.norm(moving_c - fixed.bound_centre) + fixed.bound_radius
                     + moving.bound_radius)

    def offset(self, pose: Pose) -> tuple[Floats, float]:
        """Slide across Δ (e1, e2) of the centroid and spin about Δ (rad) from the anchor."""
        d = self.centre(pose) - self._anchor_centre
        rel = pose[:3, :3] @ self._anchor_turn
        sin = 0.5 * np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                              rel[1, 0] - rel[0, 1]]) @ self.push
        trace = float(rel[0, 0]) + float(rel[1, 1]) + float(rel[2, 2])
        spin = math.atan2(float(sin), 0.5 * (trace - 1.0))
        return np.array([d @ self.e1, d @ self.e2]), spin

    def beyond_envelope(self, pose: Pose) -> str | None:
        """Why `pose` lies outside the search envelope, or None."""
        slide, spin = self.offset(pose)
        p = self.params
        if float(np.linalg.norm(slide)) > p.max_slide_m:
            return (f'slid {np.linalg.norm(slide) * 1e3:.1f} mm across the push without '
                    f'finding rest (envelope {p.max_slide_m * 1e3:.0f} mm): no resting place '
                    'near the start')
        if abs(spin) > p.max_spin_rad:
            return (f'turned {math.degrees(abs(spin)):.1f} deg about the push without finding '
                    f'rest (envelope {math.degrees(p.max_spin_rad):.0f} deg): no resting place '
                    'near the start')
        return None

    def limits_to_envelope(self, pose: Pose, arm: float, directions: Floats, length: float,
                           offset: tuple[Floats, float] | None = None) -> list[float] | None:
        """The longest move from `pose` along each of `directions` (m, 3), each of max-norm
        at most 1 (so a move slides at most sqrt(2) of its length across Δ and turns at most
        an arc of it), up to `length`, that stays inside an envelope that holds; None where
        every one keeps `length` (an envelope that does not hold, or one no move reaches);
        `offset`: the pose's `offset`, where the caller has it already."""
        p = self.params
        if not p.envelope_holds:
            return None
        slide, spin = self.offset(pose) if offset is None else offset
        # far enough inside that no move reaches a bound (with a margin no rounding of the
        # bounds below can cross): every move keeps its whole length
        if (math.hypot(float(slide[0]), float(slide[1])) + _SQRT2 * length
                < (1.0 - _MARGIN) * p.max_slide_m
                and abs(spin) + length / arm < (1.0 - _MARGIN) * p.max_spin_rad):
            return None
        bb = float(slide @ slide)
        out = []
        for direction in directions:
            a, most = direction[:2], length
            aa = float(a @ a)
            if aa > 0.0:                       # |b + t a| <= max_slide
                ab = float(a @ slide)
                disc = ab * ab - aa * (bb - p.max_slide_m ** 2)
                if disc >= 0.0:
                    most = min(most, max((-ab + math.sqrt(disc)) / aa, 0.0))
            if direction[2] != 0.0:
                room = p.max_spin_rad - math.copysign(1.0, direction[2]) * spin
                most = min(most, max(room * arm / abs(direction[2]), 0.0))
            out.append(most)
        return out

    def on_boundary(self, pose: Pose, margin: float, arm: float) -> str | None:
        """Which envelope bound `pose` rests on (within `margin` m), if any."""
        p = self.params
        slide, spin = self.offset(pose)
        if float(np.linalg.norm(slide)) >= p.max_slide_m - margin:
            return f'slide {p.max_slide_m * 1e3:g} mm'
        if abs(spin) >= p.max_spin_rad - margin / arm:
            return f'spin {math.degrees(p.max_spin_rad):g} deg'
        return None

    # ---- collision ----------------------------------------------------------------------
    def collides(self, pose: Pose) -> bool:
        """Boolean collision query (python-fcl)."""
        return self.pair.collides(pose)

    def contacts(self, pose: Pose) -> Contacts:
        """The colliding reference triangles at `pose`: centres and normals."""
        ids = self.pair.contacts(pose)
        return Contacts(self.pair.fixed.centres[ids], self.pair.fixed.normals[ids])

    def facing(self, contacts: Contacts, motion: Floats) -> Contacts:
        """Drop back-facing normals: normal · motion >= 0 (patent FIG. 5)."""
        keep = contacts.normals @ motion < 0.0
        return Contacts(contacts.points[keep], contacts.normals[keep])

    def bisect(self, move: Callable[[float], Pose], tol_fraction: float,
               collides: Callable[[Pose], bool] | None = None) -> tuple[float, float]:
        """Dichotomy on a motion `move(s)`, s in [0, 1]: free at 0, colliding at 1, by
        `collides` (default: `self.collides`).

        Returns (free_s, colliding_s) with colliding_s - free_s <= tol_fraction.
        """
        query = self.collides if collides is None else collides
        lo, hi = 0.0, 1.0
        while hi - lo > tol_fraction:
            mid = 0.5 * (lo + hi)
            if query(move(mid)):
                hi = mid
            else:
                lo = mid
        return lo, hi

    def back_out(self, pose: Pose) -> Pose:
        """Move a start in collision back along -Δ until free (recorded in backed_out_m);
        python-fcl decides."""
        if not self.pair.collides(pose):
            return pose
        self.backed_out_m = self._retreat(
            pose, self.params.step_m, self.params.resolution_m,
            'the start pose is buried in the fixed body and cannot be backed out along the '
            'push direction; start the moving body outside it')
        log.info('start pose was in collision: backed out %.3f mm along -push',
                 self.backed_out_m * 1e3)
        return translated(pose, -self.backed_out_m * self.push)

    def _retreat(self, pose: Pose, first_m: float, tol_m: float, buried: str) -> float:
        """How far `pose`, in collision, must move back along -Δ to be free for python-fcl
        (to `tol_m`): steps doubling from `first_m`, then a dichotomy. Raises SettleError
        (`buried`) when no free pose lies within twice the travel limit."""
        limit = self.travel_limit(pose)
        dist = first_m
        while dist <= 2.0 * limit:
            if not self.pair.collides(translated(pose, -dist * self.push)):
                lo, _ = self.bisect(lambda s: translated(pose, -dist * (1.0 - s) * self.push),
                                    tol_m / dist, self.pair.collides)
                return dist * (1.0 - lo)
            dist *= 2.0
        raise SettleError(buried)

    def drop(self, pose: Pose, tol_m: float, limit_m: float | None = None,
             step_m: float | None = None) -> Bracket | None:
        """Translate along Δ by steps until collision, then dichotomy (FIGS. 2-4).

        Returns the bracket (less than `tol_m` wide), or None when no contact happens
        within `limit_m`. `step_m` defaults to the translation step.
        """
        step = self.params.step_m if step_m is None else step_m
        limit = self.travel_limit(pose) if limit_m is None else limit_m
        travelled = 0.0
        while travelled <= limit:
            nxt = translated(pose, step * self.push)
            if self.collides(nxt):
                base = pose
                lo, hi = self.bisect(lambda s: translated(base, s * step * self.push),
                                     tol_m / step)
                return Bracket(translated(base, lo * step * self.push),
                               translated(base, hi * step * self.push))
            pose = nxt
            travelled += step
        return None

    def judge(self, pose: Pose, tol_m: float) -> tuple[Pose, float]:
        """python-fcl judges the end pose of a climb on the exact travel: a pose it finds in
        collision is backed out along -Δ until free, to `tol_m`. Returns the pose and how
        far it was backed out (m)."""
        if not self.pair.collides(pose):
            return pose, 0.0
        back = self._retreat(pose, tol_m, tol_m, 'python-fcl finds the end pose buried; no '
                             'free pose behind it along the push')
        log.debug('end pose in collision for python-fcl: backed out %.4f mm', back * 1e3)
        return translated(pose, -back * self.push), back

    def result(self, pose: Pose, status: int, reason: str, contacts: Contacts,
               proof_checks: int = 0, proof_s: float = 0.0, judged_back_m: float = 0.0,
               touching: Ints | None = None) -> SettleResult:
        """Package the end of a settle (`status`: a `Status` code)."""
        travels = self.sweep.queries if self.sweep is not None else 0
        return SettleResult(pose, status in AT_REST, reason,
                            self.iterations, self.pair.checks + travels, contacts,
                            time.perf_counter() - self.started, self.pair.fcl_s,
                            self.backed_out_m, status, proof_checks, proof_s,
                            travels, self.pair.checks, judged_back_m,
                            np.zeros((0, 2), dtype=np.int64) if touching is None else touching)

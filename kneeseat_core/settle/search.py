"""What both settle methods share: parameters, results, the push frame and exact contact.

`Search` holds one settle's collision pair, its push direction `Δ` with an in-plane basis
(e1, e2), the lateral moves (slides across Δ and spins about an axis parallel to Δ), exact
contact along Δ by bracketing and dichotomy, and the contacts at a pose. The methods
(`kneeseat_core.settle.patent`, `kneeseat_core.settle.climb`) decide which moves to make.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import logging
import math
import time
from typing import Callable

import numpy as np

from kneeseat_core.errors import SettleError
from kneeseat_core.geometry import rotation_about, unit
from kneeseat_core.meshes import CollisionPair, RayPair
from kneeseat_core.params import SettleParams
from kneeseat_core.status import AT_REST, Status
from kneeseat_core.typed import Floats, Ints, Pose
from .patches import contact_patches

__all__ = ['Contacts', 'SettleResult', 'Search', 'Bracket', 'LOST_CONTACT', 'translated',
           'rotated']

log = logging.getLogger('kneeseat_core.settle')

LOST_CONTACT = ('lost contact: the body slid off the edge of the fixed body without finding '
                'rest along this push')


@dataclass(frozen=True, slots=True, eq=False)
class Contacts:
    """Contact application points and reaction normals, fixed frame."""

    points: Floats    # (k, 3) m
    normals: Floats   # (k, 3) unit outward normals of the reference there
    # the triangles that cross (repeats allowed): the moving body's, the reference's
    triangles: tuple[Ints, Ints] = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))

    @classmethod
    def empty(cls) -> Contacts:
        """No contact."""
        return cls(np.zeros((0, 3)), np.zeros((0, 3)))

    def __add__(self, other: Contacts) -> Contacts:
        return Contacts(np.concatenate([self.points, other.points]),
                        np.concatenate([self.normals, other.normals]),
                        (np.concatenate([self.triangles[0], other.triangles[0]]),
                         np.concatenate([self.triangles[1], other.triangles[1]])))

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
    proof_checks: int = 0       # queries (fcl and ray casts) spent proving rest (default)
    proof_s: float = 0.0        # wall time of those proofs (s)
    ray_casts: int = 0          # casts of rays (the travel's, the proof's probes')
    rays: int = 0               # rays in those casts
    judged_back_m: float = 0.0  # how far python-fcl backed the final pose out (rays missed)

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
    # rays: the default method's proof asks them first, and with `travel: rays` they
    # measure the travel too (None: python-fcl answers everything)
    rays: RayPair | None = None
    push: Floats = field(init=False)
    e1: Floats = field(init=False)
    e2: Floats = field(init=False)
    free: Floats = field(init=False)    # (3,) 1 for each free move coordinate (e1, e2, spin)
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
        self.e2 = np.cross(self.push, self.e1)

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

    def lateral(self, base: Pose, move: Floats, arm: float) -> Pose:
        """`base` slid by move[0] e1 + move[1] e2 and spun by move[2] / arm (rad) about the
        axis through its centroid parallel to Δ (a spin about any other centre is this
        plus a slide)."""
        out: Pose = self.laterals(base, np.asarray(move, dtype=np.float64)[None], arm)[0]
        return out

    def laterals(self, base: Pose, moves: Floats, arm: float) -> Floats:
        """`lateral` for each of `moves` (m, 3) at once: (m, 4, 4), each pose bit for bit
        the one it gives alone (the same products, stacked)."""
        x = np.asarray(moves, dtype=np.float64) * self.free
        rots = rotation_about(self.push, x[:, 2] / arm)
        centre = self.centre(base)
        out = np.empty((len(x), 4, 4))
        out[:, :3, :3] = rots @ base[:3, :3]
        out[:, :3, 3] = (rots @ (base[:3, 3] - centre)[:, None])[:, :, 0] + centre
        out[:, 3] = (0.0, 0.0, 0.0, 1.0)
        out[:, :3, 3] += x[:, 0:1] * self.e1 + x[:, 1:2] * self.e2
        return out

    def offset(self, pose: Pose) -> tuple[Floats, float]:
        """Slide across Δ (e1, e2) of the centroid and spin about Δ (rad) from the anchor."""
        d = self.centre(pose) - self.centre(self.anchor)
        rel = pose[:3, :3] @ self.anchor[:3, :3].T
        sin = 0.5 * np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                              rel[1, 0] - rel[0, 1]]) @ self.push
        spin = math.atan2(float(sin), 0.5 * (float(np.trace(rel)) - 1.0))
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

    def envelope_mask(self, pose: Pose, margin: float, arm: float,
                      direction: Floats) -> Floats:
        """Where the envelope holds: `direction` (slide e1, e2, arc) without the parts that
        leave it from `pose` (within `margin` m of a bound; `arm`: m of arc per radian)."""
        p = self.params
        if not p.envelope_holds:
            return direction
        slide, spin = self.offset(pose)
        out = direction.copy()
        norm = float(np.linalg.norm(slide))
        if norm >= p.max_slide_m - margin and norm > 0.0:
            radial = slide / norm
            outward = float(out[:2] @ radial)
            if outward > 0.0:
                out[:2] -= outward * radial
        if abs(spin) >= p.max_spin_rad - margin / arm and out[2] * spin > 0.0:
            out[2] = 0.0
        return out

    def limit_to_envelope(self, pose: Pose, arm: float, direction: Floats,
                          length: float) -> float:
        """The longest move from `pose` along `direction` (up to `length`) that stays inside
        an envelope that holds (`length` itself otherwise)."""
        return self.limits_to_envelope(pose, arm, direction[None], length)[0]

    def limits_to_envelope(self, pose: Pose, arm: float, directions: Floats,
                           length: float) -> list[float]:
        """`limit_to_envelope` along each of `directions` (m, 3) from one `pose`."""
        p = self.params
        if not p.envelope_holds:
            return [length] * len(directions)
        slide, spin = self.offset(pose)
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
    @property
    def rays_travel(self) -> RayPair | None:
        """The rays, when they measure the travel along Δ (`travel: rays`)."""
        return self.rays if self.params.travel == 'rays' else None

    def collides(self, pose: Pose) -> bool:
        """Boolean collision query (python-fcl; the rays measure travels, not booleans)."""
        return self.pair.collides(pose)

    def ray_travel(self, pose: Pose, limit_m: float | None = None,
                   known_free: bool = False) -> float | None:
        """The travel along Δ from `pose` to exact contact by rays (one cast from the near
        set instead of a dichotomy), negative when python-fcl finds `pose` itself in
        collision (then found from behind it; `known_free`: the caller knows it is not).
        None: no contact within `limit_m` (default: the travel limit), or a pose buried
        deeper than that."""
        rays = self.rays_travel
        assert rays is not None
        limit = self.travel_limit(pose) if limit_m is None else limit_m
        back = 0.0
        while True:
            base = pose if back == 0.0 else translated(pose, -back * self.push)
            travel = rays.travel_from(base, limit + back, known_free and back == 0.0)
            if travel is not None:
                return travel - back if math.isfinite(travel) else None
            back = max(2.0 * back, self.params.resolution_m)
            if back > limit:
                return None

    def contacts(self, pose: Pose) -> Contacts:
        """The colliding reference triangles at `pose`: centres and normals."""
        ids = self.pair.contacts(pose)
        return Contacts(self.pair.fixed.centres[ids], self.pair.fixed.normals[ids])

    def patches(self, pose: Pose) -> Contacts:
        """The contact patches at `pose`, one (point, normal) each (D7,
        `kneeseat_core.settle.patches.contact_patches`)."""
        ids, moving_ids, points = self.pair.crossings(pose)
        return Contacts(*contact_patches(self.pair.fixed, ids, points), (moving_ids, ids))

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

    def bisect_along(self, pose: Pose, lo: float, hi: float, tol_m: float) -> tuple[float, float]:
        """Dichotomy on the travel along Δ from `pose`: free at `lo`, touching at `hi` (m);
        returns (free, touching) at most `tol_m` apart (by rays: one cast, unless the rays
        see no contact where python-fcl did)."""
        if self.rays_travel is not None and hi - lo > tol_m:
            travel = self.ray_travel(translated(pose, lo * self.push), hi - lo + tol_m,
                                     known_free=True)
            if travel is not None and 0.0 <= travel <= hi - lo:
                at = lo + travel
                return max(lo, at - 0.5 * tol_m), min(hi, at + 0.5 * tol_m)
        while hi - lo > tol_m:
            mid = 0.5 * (lo + hi)
            if self.collides(translated(pose, mid * self.push)):
                hi = mid
            else:
                lo = mid
        return lo, hi

    def back_out(self, pose: Pose) -> Pose:
        """Move a start in collision back along -Δ until free (recorded in backed_out_m);
        python-fcl decides (a start may be buried where no vertex ray sees it)."""
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
        if self.rays_travel is not None:
            return self._ray_bracket(pose, tol_m, limit, known_free=True)
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

    def touch(self, pose: Pose, guess_m: float, tol_m: float,
              free_at_start: bool = False) -> Bracket | None:
        """Exact contact along Δ from a lateral pose whose contact is expected `guess_m`
        further along Δ (negative: it overlaps; `free_at_start`: `pose` is known free).
        Probes just past the guess, then just short of it, widening by doubling until the
        contact is bracketed, then bisects to `tol_m`. None: no contact within the travel
        limit (or a body buried beyond it)."""
        if self.rays_travel is not None:
            return self._ray_bracket(pose, tol_m, known_free=free_at_start)
        lo: float | None = 0.0 if free_at_start else None     # free here
        hi: float | None = None                               # touching here
        limit = self.travel_limit(pose)
        width = 2.0 * tol_m
        first = guess_m + tol_m if guess_m > tol_m else 0.0
        if free_at_start and first <= 0.0:
            first = tol_m
        t = first
        while lo is None or hi is None:
            if abs(t) > 2.0 * limit:
                return None
            if self.collides(translated(pose, t * self.push)):
                hi = t
            else:
                lo = t
            if hi is None:        # advance (steps no longer than the translation step)
                t = lo + min(width, self.params.step_m)   # type: ignore[operator]
            elif lo is None:      # retreat
                t = hi - width
            width *= 2.0
        lo, hi = self.bisect_along(pose, lo, hi, tol_m)
        return Bracket(translated(pose, lo * self.push), translated(pose, hi * self.push))

    def queries(self) -> int:
        """Queries answered so far: python-fcl's and the casts of rays."""
        return self.pair.checks + (self.rays.casts if self.rays is not None else 0)

    def judge(self, pose: Pose, tol_m: float) -> tuple[Pose, float]:
        """python-fcl judges the end pose of a climb by rays: a pose it finds in collision
        (an edge crossing an edge where no vertex ray sees it) is backed out along -Δ until
        free, to `tol_m`. Returns the pose and how far it was backed out (m)."""
        if self.rays_travel is None or not self.pair.collides(pose):
            return pose, 0.0
        back = self._retreat(pose, tol_m, tol_m, 'python-fcl finds the end pose buried; no '
                             'free pose behind it along the push')
        log.debug('end pose in collision for python-fcl: backed out %.4f mm', back * 1e3)
        return translated(pose, -back * self.push), back

    def _ray_bracket(self, pose: Pose, tol_m: float, limit_m: float | None = None,
                     known_free: bool = False) -> Bracket | None:
        """Exact contact along Δ from `pose` by rays: a bracket `tol_m` wide about it."""
        travel = self.ray_travel(pose, limit_m, known_free)
        if travel is None:
            return None
        return Bracket(translated(pose, (travel - 0.5 * tol_m) * self.push),
                       translated(pose, (travel + 0.5 * tol_m) * self.push))

    def result(self, pose: Pose, status: int, reason: str, contacts: Contacts,
               proof_checks: int = 0, proof_s: float = 0.0,
               judged_back_m: float = 0.0) -> SettleResult:
        """Package the end of a settle (`status`: a `Status` code)."""
        rays = self.rays
        return SettleResult(pose, status in AT_REST, reason,
                            self.iterations, self.pair.checks, contacts,
                            time.perf_counter() - self.started, self.pair.fcl_s,
                            self.backed_out_m, status, proof_checks, proof_s,
                            rays.casts if rays else 0, rays.rays if rays else 0,
                            judged_back_m)

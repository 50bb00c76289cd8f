"""`--method default`: the patent's loop carried to a true rest pose (see kneeseat_core.settle).

Rest is a local maximum of the objective over the lateral state (slides across the push Δ
and a spin about an axis parallel to it): the travel s along Δ before the body touches, or,
with ligaments, the load's work less their energy at the contact pose
(`kneeseat_core.settle.objective`). The travel comes exactly from the swept triangles
(`kneeseat_core.meshes.sweep`): one query from a pose gives how far the body goes along Δ
and the contact features that close within a window beyond. The climb is a pattern search
on the exact objective, over a small state object (`_Climb`):

- `step`: the moves of the current scale (the 26 probe directions: slides, spins and their
  combinations; at the finest scales also the way up, the move the contacts say climbs
  most with every contact kept, and below one finest move the way up alone) are tried,
  most promising first, until one gains: the proof's lift for a long move, anything
  measurable for a short one (`move_gain_res`: a spin the contacts determine weakly is
  followed to its top). The scale grows after a gain and shrinks after none, down to one
  finest move, so a shallow slope is climbed in long moves and a crease in short ones.
- `_try`: most moves run into a contact, and the features say which: the near-active ones
  (the travel after a small move to first order, `kneeseat_core.settle.model`) order the
  moves; the pairs of triangles the features say close first after a move, and the
  vertices of their moving triangles, refute a move exactly where one meets the fixed body
  short of the travel the move needs; only the rest are measured.
- `prove` (D5): when no move of the finest scale gains, the way up at a quarter and a
  half of a finest move (along a ridge between the probe directions), then
  probes in the 26 directions at 1, 4 and 16 finest moves (and a quarter of one first
  where ligaments press the body on hard), each needing the proof's lift, are tried the
  same way, the directions at every scale not yet tried in every direction at the pose;
  one that gains is taken and the climb resumes. None gains: at rest.
- the envelope: the climb may not leave a search envelope (D6); an envelope that holds (a
  config's soft-tissue stand-in) bounds the moves instead, and a rest on its boundary is
  reported as constrained.
Every number that steers the climb is in `kneeseat_core.settle.tuning`; why each step is
what it is: docs/design.md, "The default method".
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
import itertools
import math
import time

import numpy as np

from kneeseat_core.errors import NoContactError
from kneeseat_core.ligaments import Tissue
from kneeseat_core.meshes.sweep import SHORT, SweepPair, Touch
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Ints, Pose
from .model import best_move, Model, STEEPEST
from .objective import Objective, objective_for
from .planner import Planner
from .search import Contacts, LOST_CONTACT, Search, SettleResult, translated
from .tuning import SettleTuning, TUNING

__all__ = ['run_climb']

# The probe directions: every combination of -1, 0, +1 on (slide e1, slide e2, arc), unit.
_DIRECTIONS = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)])
_DIRECTIONS = _DIRECTIONS / np.linalg.norm(_DIRECTIONS, axis=1, keepdims=True)

End = tuple[int, str]    # (Status code, reason)


@cache
def _directions(free: bytes) -> Floats:
    """The probe directions that move only the free coordinates (`Search.free`, as bytes:
    every settle of a sweep asks the same), read only."""
    mask = np.frombuffer(free, dtype=np.float64) == 0
    out: Floats = _DIRECTIONS[~np.any((_DIRECTIONS != 0) & mask, axis=1)]
    out.flags.writeable = False
    return out


@dataclass(slots=True, eq=False)
class _Place:
    """A pose at contact (free, a standoff short of touching along Δ): what it is worth,
    its lateral state (slide e1, slide e2, arc from the anchor) and the features closing
    within the window beyond it (gaps from the pose itself); `wide`: within the pool's."""

    pose: Pose
    value: float
    state: Floats
    touch: Touch
    wide: bool
    # the models of the travel about it, by (within, room) (`_Climb.model`)
    models: dict[tuple[float, float], Model] = field(default_factory=dict)
    # the objective's first-order terms and the pulls there (`Planner.terms`), once asked
    terms: tuple[float, Floats, float, float] | None = None
    # the body's centroid there (`Search.centre`: the spins' axis), once asked
    centre: Floats | None = None
    # its slide and spin from the envelope's anchor (`Search.offset`), once asked
    offset: tuple[Floats, float] | None = None


class _Short:
    """A target measured short of the travel its gain needs (`_Climb.arrive`): it cannot
    gain, and its search stopped as soon as that was known."""


_SHORT = _Short()
# no pool: a single pose is measured without witnesses, where it stands
_NO_POOL = (np.zeros(0), np.zeros((0, 3)), np.zeros((0, 2), dtype=np.int64))
_NO_MOVE = np.zeros((1, 3))


@dataclass(frozen=True, slots=True, eq=False)
class _Witnesses:
    """Every feature within a wide window of a place (the pool the witnesses of a move are
    drawn from, and the farther contacts of the proof's way up), one row each, the lateral
    state it was taken at and how far along Δ that place stands."""

    model: Model
    state: Floats
    height: float           # the place's origin along Δ (a slide or a spin about Δ keeps it)


class _Climb:
    """The state of one climb and its steps."""

    def __init__(self, search: Search, sweep: SweepPair, tuning: SettleTuning,
                 tissue: Tissue | None, near_rest: bool = False) -> None:
        p = search.params
        self.search, self.sweep, self.tuning = search, sweep, tuning
        self.arm = max(search.pair.moving.reach, p.step_m)
        rot_res = p.rotation_resolution_rad if p.rotation_resolution_rad is not None \
            else p.resolution_m / self.arm          # D4: an arc of one resolution
        self.objective: Objective = objective_for(p, tissue)
        self.finest = min(p.resolution_m, rot_res * self.arm)
        self.standoff = tuning.standoff_res * p.resolution_m
        self.contact_tol = tuning.contact_tol_res * p.resolution_m
        self.windows = (tuning.window_res * p.resolution_m,        # a place's, and the
                        tuning.pool_window_res * p.resolution_m)   # pool's
        self.lift = self.objective.precision * tuning.probe_lift_res * p.resolution_m
        self.gain = self.objective.precision * tuning.move_gain_res * p.resolution_m
        self.scale = (tuning.near_first_moves if near_rest else tuning.first_moves) \
            * self.finest
        self.directions = _directions(search.free.tobytes())
        self.planner = Planner(search, self.objective, self.arm, self.standoff)
        self.here: _Place | None = None
        self.pool: _Witnesses | None = None
        # how far from where the witnesses' pool was taken it still names the pairs that
        # close first (`_beyond_pool`)
        self.pool_reach = tuning.pool_reach_moves * self.finest
        self.failed: set[float] = set()     # scales tried whole that found nothing here
        self.proof_checks = 0
        self.proof_s = 0.0

    # ---- measuring -------------------------------------------------------------------
    def arrive(self, target: Pose, expected: float = 0.0, window_res: float | None = None,
               short_of: float = -math.inf, seeds: Ints | None = None) -> _Place | _Short | None:
        """The lateral pose `target` moved along Δ to contact (`SweepPair.measure`: the
        travel measured exactly from it lowered by enough that the lowered pose is free,
        `expected` the travel expected there, negative where `target` may be in collision),
        with the features within `window_res` resolutions (default: the tuning's window);
        None: no contact along Δ (the body slid off the fixed body); `_SHORT`: the travel is
        less than `short_of` (the search stops as soon as a gap says so). `seeds`: pairs of
        triangles likely to close first there (they change how fast the answer comes,
        never the answer)."""
        t = self.tuning
        window = t.window_res if window_res is None else window_res
        length = window * self.search.params.resolution_m
        _, kind, touch, _ = self.sweep.measure(
            target[None], np.array([short_of]), np.array([expected]), (length, length), _NO_POOL,
            _NO_MOVE, _NO_MOVE[0], math.inf, 0, self.standoff, 0.0, 0, seeds, cap=t.pool_cap,
            keep=self.windows[0])
        if kind == SHORT:
            return _SHORT
        if touch is None:
            return None
        return self._place(target, touch, window >= t.pool_window_res, self.state_of(target))

    def _place(self, target: Pose, touch: Touch, wide: bool, state: Floats) -> _Place:
        """The place `target` reaches along Δ, its travel and features measured (`touch`):
        the standoff short of touching, its features' gaps from there (`state`: its lateral
        state, the target's; `wide`: its features gathered within the pool's window)."""
        s = self.search
        rise = touch.travel - self.standoff
        pose = translated(target, rise * s.push)
        return _Place(pose, self.planner.value(pose), state, touch.lifted(rise, s.push), wide)

    def state_of(self, pose: Pose) -> Floats:
        """(3,) the lateral state of `pose`: slides along e1, e2 and the arc of its spin,
        from the anchor."""
        slide, spin = self.search.offset(pose)
        return np.array([slide[0], slide[1], spin * self.arm])

    def model(self, place: _Place, within: float = math.inf, room: float = 0.0) -> Model:
        """The model of the travel about `place` from its features closing within `within`
        that hold for a slide of at least `room` (`Planner.model`), kept with the place."""
        found = place.models.get((within, room))
        if found is None:
            if place.centre is None:
                place.centre = self.search.centre(place.pose)
            found = place.models[(within, room)] = self.planner.model(
                place.touch, place.centre, within, room)
        return found

    def terms(self, place: _Place) -> tuple[float, Floats, float, float]:
        """(press, drive, pull, line) at `place` (`Planner.terms`), kept with the place:
        every step and proof there asks for them."""
        if place.terms is None:
            place.terms = self.planner.terms(place.pose)
        return place.terms

    def first_order(self, place: _Place) -> tuple[float, Floats]:
        """(press, drive) at `place` (`Planner.first_order`)."""
        press, drive, _, _ = self.terms(place)
        return press, drive

    def settle_in(self, place: _Place) -> None:
        """Start at `place` (the first contact): its features within the wide window are
        the witnesses' pool."""
        self.here = place
        self._pool(place)

    def _pool(self, place: _Place) -> None:
        self.pool = _Witnesses(self.model(place), place.state,
                               float(place.pose[:3, 3] @ self.search.push))

    def _beyond_pool(self, offsets: Floats) -> Bools:
        """Whether the pool is too far from each lateral state `offsets` (..., 3) away from
        where it was taken to name the pairs that close first there: a place there becomes
        the pool when the climb moves to it, so it is measured with the pool's window (the
        engine applies the same rule to the moves `_try` measures, `SweepPair.measure`)."""
        out: Bools = np.abs(offsets).max(axis=-1) > self.pool_reach
        return out

    # ---- the steps -------------------------------------------------------------------
    def step(self) -> End | None | bool:
        """One pattern move at the current scale: True when one was made (the scale then
        grows) or the scale shrank, False when it has shrunk below the finest move (the
        proof's turn), an end when the climb must stop."""
        assert self.here is not None
        t = self.tuning
        if len(self.here.touch) == 0:
            return (Status.LOST, LOST_CONTACT)
        scale = self.scale
        # a long move must gain what the proof could see; a short one anything (so that a
        # spin the contacts determine weakly is followed to its top), and the contacts' way
        # up joins the directions there (slide and spin combined as no fixed direction
        # combines them); shorter than a finest move it is the only move: their first-order
        # model holds that close, and to first order its move beats every direction of that
        # length
        fine = scale <= t.fine_moves * self.finest
        every_way = scale >= t.directions_from_moves * self.finest
        if not every_way:
            moves = self._uphill(scale)
        elif fine:
            moves = np.concatenate([scale * self.directions, self._uphill(scale)])
        else:
            moves = scale * self.directions
        tries = None if scale <= t.every_direction_moves * self.finest else t.far_tries
        found = self._try(self._inside(moves, scale), self.gain if fine else self.lift, tries)
        if isinstance(found, _Place):
            self.scale = min(t.grow * scale, t.far_moves * self.finest)
            return self.take(found)
        if found is not None:
            return found
        if tries is None and every_way:
            # every direction failed at this scale: the proof need not probe it again (a
            # long step tries only its most promising moves, and a short one only the way
            # up, which spares the proof nothing)
            self.failed.add(scale)
        self.scale = scale * t.shrink
        if self.scale < t.least_moves * self.finest:
            self.scale = self.finest
            return False
        return True

    def _uphill(self, scale: float, contacts: Model | None = None) -> Floats:
        """(0 or 1, 3) the move of `scale` the contacts say climbs most (every contact kept:
        slide and spin combined as no fixed direction combines them), the way up; the
        contacts: the near-active features, or `contacts` where given (`_with_pool`)."""
        assert self.here is not None
        if contacts is None:
            contacts = self.model(self.here, self.contact_tol)
        if len(contacts.gaps) == 0:
            return np.zeros((0, 3))
        press, drive = self.first_order(self.here)
        x, promised = best_move(contacts, press, drive, scale * self.search.free)
        return x[None] if promised > 0.0 and x.any() else np.zeros((0, 3))

    def _with_pool(self, near: Model) -> Model:
        """The near-active features `near` of the pose with the pool's farther ones carried
        there to first order (one beyond the contact tolerance can close before the travel a
        way up promises: the proof's); none where `near` has none."""
        assert self.here is not None and self.pool is not None
        pool = self.pool
        if len(near.gaps) == 0:
            return near
        # the pool's features seen from here: their gaps after the lateral move from where
        # the pool was taken, less how much farther along Δ this place stands; the nearer
        # ones are this place's own
        rise = float(self.here.pose[:3, 3] @ self.search.push) - pool.height
        gaps = pool.model.gaps + pool.model.slopes @ (self.here.state - pool.state) - rise
        far = gaps > self.contact_tol
        return Model(np.concatenate([near.gaps, gaps[far]]),
                     np.concatenate([near.slopes, pool.model.slopes[far]]),
                     np.concatenate([near.faces, pool.model.faces[far]]))

    def _inside(self, moves: Floats, length: float) -> Floats:
        """The moves of `moves` (m, 3), each of max-norm `length`, shortened to stay inside
        an envelope that holds (a move with no room left is dropped)."""
        assert self.here is not None
        if not self.search.params.envelope_holds:
            return moves
        if self.here.offset is None:
            self.here.offset = self.search.offset(self.here.pose)
        limits = self.search.limits_to_envelope(self.here.pose, self.arm, moves / length, length,
                                                self.here.offset)
        if limits is None:          # no move reaches the envelope's bounds
            return moves
        rooms = np.asarray(limits)
        # a move the envelope leaves whole is made (the shortest ones included); one it
        # shortens only while it leaves more than a share of the finest move
        keep = (rooms >= length) | (rooms > self.tuning.room_share * self.finest)
        out: Floats = moves[keep] * (rooms[keep] / length)[:, None]
        return out

    def take(self, place: _Place) -> End | None | bool:
        """Move to `place`; outside the search envelope, or pulled off the fixed body by its
        ligaments, the climb ends."""
        s = self.search
        self.here = place
        self.failed = set()
        assert self.pool is not None
        if self._beyond_pool(place.state - self.pool.state):
            wide = place if place.wide else self.arrive(place.pose, 0.0,
                                                        self.tuning.pool_window_res)
            self._pool(wide if isinstance(wide, _Place) else place)
        outside = None if s.params.envelope_holds else s.beyond_envelope(place.pose)
        if outside:
            return (Status.ENVELOPE, outside)
        return self.pulled() or True

    def pulled(self) -> End | None:
        """The end when the body's ligaments pull it off the fixed body against its load."""
        assert self.here is not None
        _, _, pull, load = self.terms(self.here)
        if load - pull > 0.0:
            return None
        return (Status.PULLED, self.objective.pulled_off(pull, load))

    def prove(self) -> End | None | bool:
        """D5: probe about the pose, the way up at the shortest lengths first, then in every
        direction at every scale not yet tried there in every direction; True when a probe
        gained (the climb resumes there), an end when the climb must stop, None at rest."""
        assert self.here is not None
        s, t = self.search, self.tuning
        started = time.perf_counter()
        try:
            press, drive = self.first_order(self.here)
            pressed = max(1.0, press)
            scales = list(zip(t.probe_scales_moves, t.hopeless_res))
            if pressed >= t.pressed_from:
                scales.insert(0, (t.pressed_probe_moves, t.hopeless_res[0]))
            near = self.model(self.here, self.contact_tol,
                              t.room_share * self.finest)
            floor = float(np.min(near.gaps)) if len(near.gaps) else 0.0
            # the way up first, a quarter and a half of a finest move long: it follows a
            # ridge narrower than the probe directions' spacing, along which every one of
            # them loses (docs/design.md, "How rest is proved")
            contacts = self._with_pool(self.model(self.here, self.contact_tol))
            for scale in t.uphill_probe_moves:
                length = scale * self.finest
                moves = self._inside(self._uphill(length, contacts), length)
                self.proof_checks += len(moves)
                found = self._probe(moves, length)
                if found is not None:
                    return found
            for scale, hopeless_res in scales:
                length = scale * self.finest
                moves = self._inside(length * self.directions, length)
                self.proof_checks += len(moves)
                if length in self.failed:      # tried there already, needing less
                    continue
                # what the near-active features say each probe gains (to first order, at
                # most what it can: the others can only close sooner); short of the lift
                # by more than their curvature can hide (a length along Δ, worth `pressed`
                # times as much objective where ligaments press), a probe cannot gain
                if len(near.gaps) and len(moves):
                    modelled = press * (near.travel(moves) - floor) + moves @ drive
                    margin = hopeless_res * s.params.resolution_m * pressed
                    moves = moves[modelled >= self.lift - margin]
                found = self._probe(moves, length)
                if found is not None:
                    return found
        finally:
            self.proof_s += time.perf_counter() - started
        return None

    def _probe(self, moves: Floats, length: float) -> End | bool | None:
        """The proof's probes `moves` (m, 3) of `length`, each needing the lift: True when
        one gained (the climb moved there and resumes at that scale), an end when the climb
        must stop, None when none gained."""
        found = self._try(moves, self.lift)
        if isinstance(found, _Place):
            self.scale = length
            return self.take(found)
        return found

    def _try(self, moves: Floats, gain: float, tries: int | None = None
             ) -> _Place | End | None:
        """The first of the moves `moves` (m, 3), most promising first, that gains `gain`,
        or None; only the `tries` most promising when given. A move after which the body
        no longer meets the fixed body along Δ ends the climb (lost contact).

        The near-active features order them (to first order they bound the travel after a
        move from above). A move is refuted without a search where a contact closes short
        of the travel it needs: a pair of triangles from the witnesses' pool that the pool
        says close first after it, or a vertex of their moving triangles onto whatever face
        of the fixed body it meets there. The first that none refutes is measured, its
        search stopping as soon as a contact short of the travel the move needs is found,
        and so on, in one compiled call up to the first that reaches its travel
        (`SweepPair.measure`); that one gains or the next call goes on from it."""
        assert self.here is not None and self.pool is not None
        t, sweep = self.tuning, self.sweep
        if len(moves) == 0:
            return None
        here = self.here
        longest = float(np.abs(moves).max())
        near = self.model(here, self.contact_tol, t.room_share * longest)
        press, drive = self.first_order(here)
        # ordered by what the near-active features promise (to first order they bound the
        # travel after a move from above), each with the travel it must reach: one Newton
        # step of the lift that gains (no more than the lift needed: the objective is
        # concave along Δ) plus the standoff (a place stands that short of its travel), so
        # a contact short of it refutes the move
        order, targets, needed = self.planner.plan(here.pose, moves, near, press, drive,
                                                   tries, gain, here.value + gain)
        moves = moves[order]
        pool = self.pool.model
        # penetration from a lateral move of length l is at most its steepest slope times l:
        # a vertex that far above a face is through it
        deepest = STEEPEST * longest + self.standoff
        # a move's offset from where the pool was taken is the move and this; one beyond the
        # pool's reach is measured with the pool's window (`_beyond_pool`'s rule, applied by
        # the engine)
        shift = here.state - self.pool.state
        i = 0
        while True:
            # the next move that its witnesses (the pairs the pool says close first there)
            # do not refute, measured from them (none short of the travel needed, they bound
            # it from above), its search stopping once a contact short of it is found; a
            # move found short is passed over
            i, kind, touch, wide = sweep.measure(targets, needed, needed, self.windows,
                                                 (pool.gaps, pool.slopes, pool.faces), moves,
                                                 shift, self.pool_reach, t.witnesses,
                                                 self.standoff, deepest, i, cap=t.pool_cap,
                                                 keep=self.windows[0])
            if i >= len(moves):
                return None
            if touch is None:
                return (Status.LOST, LOST_CONTACT)
            # a lateral move adds itself to the state (a lift along Δ changes none of it)
            place = self._place(targets[i], touch, wide, here.state + moves[i])
            if place.value - here.value >= gain:
                return place
            i += 1


def run_climb(search: Search, start: Pose, tissue: Tissue | None = None,
              tuning: SettleTuning = TUNING, seeds: Ints | None = None,
              near_rest: bool = False) -> SettleResult:
    """Climb from `start` (its contact along Δ found first, its search starting from the
    pairs of triangles `seeds` where given; `near_rest`: a neighbouring cell's rest
    carried over, whose first moves are short) to a rest pose (module docstring), of the
    travel, or of the load's work less the energy of the `tissue` acting on the body
    (`kneeseat_core.settle.objective`). A start that the exact travel finds in collision,
    or within the standoff of touching, is judged by python-fcl (`Search.back_out`) and
    backed out along -Δ where it collides; one farther from touching is free."""
    p = search.params
    assert search.sweep is not None
    climb = _Climb(search, search.sweep, tuning, tissue, near_rest)
    first = climb.arrive(start, 0.0, tuning.pool_window_res, seeds=seeds)
    if not isinstance(first, _Place) or first.touch.travel < climb.standoff:
        # python-fcl decides where the start touches, or nearly (D7); where it backs the
        # start out, the contact is found again from there
        start = search.back_out(start)
        if search.backed_out_m > 0.0:
            first = climb.arrive(start, 0.0, tuning.pool_window_res, seeds=seeds)
    if not isinstance(first, _Place):
        raise NoContactError(search.travel_limit(start))
    climb.settle_in(first)
    end: End | None = climb.pulled()
    while end is None and search.iterations < p.max_iterations:
        search.iterations += 1
        outcome = climb.step()
        if outcome is False:
            outcome = climb.prove()
            if outcome is None:
                end = _at_rest(search, climb)
                break
        if outcome is not True:
            end = outcome      # type: ignore[assignment]
    status, reason = end or (
        Status.CAP, f'iteration cap ({p.max_iterations}) reached before rest was verified')
    assert climb.here is not None
    pose, back = search.judge(climb.here.pose, tuning.finest_tol_res * p.resolution_m)
    touch = climb.here.touch
    gaps = touch.gaps
    near = gaps <= climb.standoff + tuning.contact_tol_res * p.resolution_m
    contacts = Contacts(touch.points[near] + (gaps[near] - back)[:, None] * search.push,
                        -touch.normals[near])
    return search.result(pose, status, reason, contacts, proof_checks=climb.proof_checks,
                         proof_s=climb.proof_s, judged_back_m=back,
                         touching=np.ascontiguousarray(touch.faces[near], dtype=np.int64))


def _at_rest(search: Search, climb: _Climb) -> End:
    """The end of a climb whose proof found nothing that gains: a plain rest, or a rest on
    the boundary of an envelope that holds."""
    assert climb.here is not None
    bound = (search.on_boundary(climb.here.pose, climb.finest, climb.arm)
             if search.params.envelope_holds else None)
    gain = climb.objective.gain
    if bound:
        return (Status.CONSTRAINED, f'rest on the envelope boundary ({bound}): nothing inside '
                f'the envelope gains more than the resolution {gain}')
    return (Status.REST, 'rest: no slide, spin about the push or combination, short or '
            f'long, gains more than the resolution {gain}')

"""`--method default`: the patent's loop carried to a true rest pose (see kneeseat_core.settle).

Rest is a local maximum of the travel s: how far the body goes along the push Δ before it
touches, as a function of the lateral state (slides across Δ and a spin about an axis
parallel to Δ). The climb is a steepest ascent of s over that state, in five named steps
over a small state object (`_Climb`):

- `choose`: the contacts at the current pose are grouped into patches (one mean point
  and normal each); each patch's depth gradient says how much depth a unit move gains
  there, and the steepest move that gains at every patch is the minimum-norm point of
  their convex hull (D1). A slope that could not gain one resolution across the whole
  envelope counts as flat: the contacts balance.
- `move`: a line search along that direction. The move is accepted while it does not
  lose depth beyond the contact tolerance; its length grows (doubles) while the slope
  measured at the new pose stays above half the slope at the old one and is cut to the
  secant estimate of the crest when the slope changes sign (D3), so a shallow slope is
  followed whatever the length of the climb and however little each step gains.
  A move that loses depth teaches the contacts that blocked it (D2).
- `leap`: where ligaments act and the patches' model has no move left, the gap field of one
  cast of rays (every near ray's gap along Δ and the normal it meets) models the travel
  over a small lateral move; the model's best move within a trust radius is measured like
  any move, and repeated from there while the field promises a gain the
  proof could see (D8).
- `prove`: when the contacts balance (or no move of the finest size is left), probes in
  26 directions (slides, spins and their combinations) at three scales, from the finest
  move to 16 times it (and a quarter of it first where ligaments press the body on hard),
  each lifted by a quarter resolution, must all collide; a probe that gains is followed
  outward while it gains (a pattern move) and the climb resumes (D5).
  A probe that the near-active patches prove hopeless by a wide margin is not queried;
  the rest are asked of rays first (one cast per scale from the vertices of the triangles
  in contact: a ray entering the other body short of a probe's lift blocks it exactly;
  then one along the same triangles' edges: an edge crossing a face of the other body at
  the lifted probe is a contact, exactly), and python-fcl decides every probe the rays
  leave open.
- the envelope: the climb may not leave it (D6); where the envelope holds (a config's
  soft-tissue stand-in), the move is kept inside and a rest on its boundary is
  reported as constrained.
Each step returns what happened (`_Outcome`: the next step's length, and the end when the
climb must stop); `run_climb` is the only place that applies it. Every number that steers
the climb is in `kneeseat_core.settle.tuning`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
import itertools
import math
import time

import numpy as np

from kneeseat_core.ligaments import Tissue
from kneeseat_core.status import Status
from kneeseat_core.typed import Bools, Floats, Pose
from .hull import min_norm_point
from .objective import Objective, objective_for
from .search import Bracket, Contacts, LOST_CONTACT, Search, SettleResult, translated
from .tuning import SettleTuning, TUNING

__all__ = ['run_climb']

# The probe directions: every combination of -1, 0, +1 on (slide e1, slide e2, arc), unit.
_DIRECTIONS = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)])
_DIRECTIONS = _DIRECTIONS / np.linalg.norm(_DIRECTIONS, axis=1, keepdims=True)

End = tuple[int, str]    # (Status code, reason)


@dataclass(frozen=True, slots=True)
class _Outcome:
    """What one step of the climb did: the length of the next move, and the end when the
    climb must stop there (lost contact, left the search envelope)."""

    step: float
    end: End | None = None


@dataclass(frozen=True, slots=True, eq=False)
class _FloorNear:
    """What the proof's rays are cast from: the vertices (k, 3) and the edges (e, 2, 3) of
    the triangles that cross at the floor's contact, each in its body's frame."""

    moving: Floats
    fixed: Floats
    moving_edges: Floats
    fixed_edges: Floats


@dataclass(slots=True, eq=False)
class _Climb:
    """The state of one climb and its five steps."""

    search: Search
    tuning: SettleTuning
    objective: Objective       # what the climb maximises (the travel, or work less energy)
    arm: float                 # m of arc per radian of spin (the farthest vertex)
    tol: float                 # exact-contact tolerance along Δ (m)
    flat: float                # slope at or below which the contacts count as balanced
    finest: float              # the finest move (m of slide or arc)
    pose: Pose                 # at contact: free, within `tol` of touching
    touching: Pose             # `pose` moved along Δ until it touches
    floor: Contacts            # contact patches at `touching`
    step: float                # length of the next move (m)
    learned: Contacts = field(default_factory=Contacts.empty)   # taught by a rejected move
    proof_checks: int = 0
    proof_s: float = 0.0
    stalled_at: Pose | None = None   # where the climb last ran out of moves
    trusted: bool = False      # the last measured move kept its promise (see `move`)

    @classmethod
    def start(cls, search: Search, bracket: Bracket, tuning: SettleTuning,
              tissue: Tissue | None) -> _Climb:
        """The climb from the first exact contact `bracket`, its scales derived from the
        settle's parameters (D4: the rotation resolution is an arc at the farthest vertex
        unless given), its objective from the tissue acting on the body."""
        p = search.params
        arm = max(search.pair.moving.reach, p.step_m)
        rot_res = p.rotation_resolution_rad if p.rotation_resolution_rad is not None \
            else p.resolution_m / arm
        objective = objective_for(search, tissue, arm)
        return cls(search=search, tuning=tuning, objective=objective, arm=arm,
                   tol=tuning.contact_tol_res * p.resolution_m,
                   # a slope that cannot gain one resolution across the whole envelope
                   flat=objective.precision * p.resolution_m
                   / max(p.max_slide_m, p.max_spin_rad * arm),
                   finest=min(p.resolution_m, rot_res * arm),
                   pose=bracket.free, touching=bracket.touching,
                   floor=search.patches(bracket.touching), step=p.step_m)

    @property
    def proof_lift(self) -> float:
        """The gain (m) a probe of the proof of rest must show."""
        return self.objective.precision * self.tuning.probe_lift_res \
            * self.search.params.resolution_m

    @property
    def has_step(self) -> bool:
        """A move of at least the shortest length the climb makes is left."""
        return self.step >= self.tuning.min_move * self.finest

    def _moved_since_stall(self) -> bool:
        """True unless the pose is within one finest move of where the climb last stalled."""
        if self.stalled_at is None:
            return True
        s = self.search
        d = s.centre(self.pose) - s.centre(self.stalled_at)
        slide = float(np.linalg.norm(d - (d @ s.push) * s.push))
        rel = self.pose[:3, :3] @ self.stalled_at[:3, :3].T
        spin = math.acos(max(-1.0, min(1.0, 0.5 * (float(np.trace(rel)) - 1.0))))
        return slide + spin * self.arm > self.finest

    def resume(self) -> tuple[Floats, float] | None:
        """When the contacts balance or the step ran out: narrow the contact set, or restart
        a fresh slope with the finest step - at most once per place, so a kink (a wedge
        whose walls take turns in a narrow contact set) ends in the proof instead of a cycle.
        """
        if not self._moved_since_stall():
            return None
        self.stalled_at = self.pose
        if self.has_step and not self.sharpen():
            return None
        chosen = self.choose()
        if chosen is not None:
            self.step = max(self.step, self.finest)
        return chosen

    # ---- first-order model ---------------------------------------------------------
    def gradients(self, contacts: Contacts, pose: Pose | None = None) -> Floats:
        """The objective's gradient (k, 3) at each facing patch w.r.t. (slide e1, slide e2,
        arc), for the body at `pose` (default: the current pose): from the patch's depth
        gradient, the travel's."""
        s = self.search
        pose = self.pose if pose is None else pose
        facing = s.facing(contacts, s.push)
        if len(facing) == 0:
            return np.zeros((0, 3))
        n, pts = facing.normals, facing.points
        lever = np.cross(s.push, pts - s.centre(pose)) / self.arm
        down = -(n @ s.push)
        depth = np.stack([n @ s.e1, n @ s.e2, np.einsum('ij,ij->i', n, lever)], 1) \
            * s.free / down[:, None]
        return self.objective.gradients(depth, pose)

    def _mask(self, direction: Floats) -> Floats:
        """Where the envelope holds: `direction` without the parts that leave it."""
        return self.search.envelope_mask(self.pose, self.finest, self.arm, direction)

    def _room(self, direction: Floats, length: float) -> float:
        """The longest move along `direction` (up to `length`) that stays inside."""
        return self.search.limit_to_envelope(self.pose, self.arm, direction, length)

    # ---- the steps ---------------------------------------------------------------------
    def choose(self) -> tuple[Floats, float] | None:
        """The steepest admissible move (unit direction, slope), or None when balanced.

        Contacts learned from a rejected move (D2) that balance the floor are dropped
        again: they were the same slope seen past its crest, not a new wall, and the
        shortened step along the floor's own direction finds the crest instead.
        """
        for contacts in ((self.floor + self.learned, self.floor) if len(self.learned)
                         else (self.floor,)):
            grads = self.gradients(contacts)
            if len(grads) == 0:
                return None
            d = self._mask(min_norm_point(grads))
            norm = float(np.linalg.norm(d))
            if norm > self.flat:
                direction = d / norm
                slope = float(np.min(grads @ direction))
                if slope > 0.0:
                    return direction, slope
        self.learned = Contacts.empty()
        return self.pivot()

    def pivot(self) -> tuple[Floats, float] | None:
        """D1b: the hull balances only because one patch sits at its own crest (its normal
        along Δ, so its gradient vanishes): a smooth crest does not hold the body there to
        first order. Pin that patch's point and spin about it, the way that gains at every
        other patch; None when that gains nowhere (or two crests pin the body)."""
        s = self.search
        facing = s.facing(self.floor, s.push)
        grads = self.gradients(facing)
        if len(grads) < 2 or not s.free[0]:
            return None
        flat = np.linalg.norm(grads, axis=1) <= self.tuning.crest_flat * self.flat
        if int(flat.sum()) != 1:
            return None
        lever = np.cross(s.push, facing.points[flat][0] - s.centre(self.pose))
        spin = np.array([-(lever @ s.e1) / self.arm, -(lever @ s.e2) / self.arm, 1.0])
        spin = self._mask(spin / np.linalg.norm(spin))
        norm = float(np.linalg.norm(spin))
        if norm == 0.0:
            return None
        spin /= norm
        for direction in (spin, -spin):
            slope = float(np.min(grads[~flat] @ direction))
            if slope > self.flat:
                return direction, slope
        return None

    def sharpen(self) -> bool:
        """Narrow the contact bracket to `sharpen` of the tolerance and take the patches
        there; True when the contact set changed (a patch that was only near contact drops
        out and no longer balances)."""
        fine = self.tol * self.tuning.sharpen
        if self._gap() <= fine:
            return False
        self._narrow(fine, rebase=True)
        before = len(self.floor)
        self.floor = self.search.patches(self.touching)
        return len(self.floor) != before

    def move(self, direction: Floats, slope: float) -> _Outcome:
        """One line-search step along `direction`.

        A move is kept only if it delivers `promise` of the gain its slope promised,
        measured: one query asks whether the moved body, lifted by that much (plus what
        the current pose's own bracket leaves open), is still free (python-fcl's contact
        set there, which costs what a boolean does on a free pose and is what a blocked
        move learns from). The current bracket is
        narrowed first to `measure` of the promise, so a promise of a few micrometres is
        held to a fraction of one and a promise of a millimetre to the contact tolerance.
        A promise too small to measure is taken on trust (it only has to not lose depth),
        and only while the last measured promise was kept: normals that promised a slope
        the surfaces do not have are not followed through the flats they stand on.
        """
        s, t = self.search, self.tuning
        length = self._room(direction, self.step)
        if length < t.min_move * self.finest:
            return _Outcome(0.0)                       # the step has run out
        promised = length * slope
        if self.objective.smooth and promised < self.proof_lift:
            return _Outcome(0.0)                       # the proof's to find (Objective.smooth)
        floor_tol = t.finest_tol_res * s.params.resolution_m
        tau = self._measuring(promised)
        width = self._narrow(tau)
        target = s.lateral(self.pose, length * direction, self.arm)
        measured = promised >= t.measurable * floor_tol
        if not (measured or self.trusted):
            return _Outcome(t.untrusted_cut * length)
        base_gap, gain = (width, t.promise * promised) if measured else (-width, 0.0)
        kept = self.objective.lift_to(target, self.pose, base_gap, gain)
        if abs(kept) <= self.objective.lift_limit:
            lifted = translated(target, kept * s.push)
            # the contact set there at once: empty where the lifted body is free (python-fcl
            # walks the same pairs as for a boolean), what `_blocked` learns from otherwise
            crossing = s.patches(lifted)
            if len(crossing):
                return self._blocked(direction, slope, length, measured, crossing, target)
            bracket = s.touch(lifted, self.objective.travel_guess(promised, kept), tau,
                              free_at_start=True)
        else:
            # the load barely presses along the push: a lift that deep proves nothing (an
            # open sheet has no inside), so the contact itself is found and weighed
            bracket = s.touch(target, self.objective.travel_guess(promised, 0.0), tau)
            if bracket is not None and self.objective.value(bracket.free) < \
                    self.objective.target(self.pose, base_gap, gain):
                return self._blocked(direction, slope, length, measured,
                                     s.patches(bracket.touching), target)
        if bracket is None:
            return _Outcome(self.step, (Status.LOST, LOST_CONTACT))
        floor = self._floor_at(bracket.free)
        grads = self.gradients(floor, bracket.free)
        new_slope = float(np.min(grads @ direction)) if len(grads) else slope
        if measured:
            self.trusted = True           # the surfaces kept a measured promise
        end = self._arrive(bracket, floor)
        if new_slope >= t.steep * slope:
            return _Outcome(min(t.grow * length, t.max_move_steps * s.params.step_m), end)
        return _Outcome(length * self._crest(slope, new_slope), end)

    def _blocked(self, direction: Floats, slope: float, length: float, measured: bool,
                 floor: Contacts, target: Pose) -> _Outcome:
        """The move kept less than its promise: past the crest, a contact the patches did
        not know (D2: learn it from the contact patches `floor` of the body held back
        there, so that the next direction respects it), or a slope the normals promise but
        the surfaces do not have; the next step is shorter."""
        s, t = self.search, self.tuning
        grads = self.gradients(floor, target)
        new_slope = float(np.min(grads @ direction)) if len(grads) else 0.0
        blocking = grads @ direction < 0.0 if len(grads) else np.zeros(0, dtype=bool)
        facing = s.facing(floor, s.push)
        self.learned = self.learned + Contacts(facing.points[blocking],
                                               facing.normals[blocking])
        if measured and new_slope >= t.steep * slope:
            # nothing blocks and the normals there still promise the slope (this is
            # no overshoot of a crest): the surfaces do not have that slope
            self.trusted = False
        return _Outcome(length * min(self._crest(slope, new_slope), t.blocked_cap))

    def _floor_at(self, free: Pose) -> Contacts:
        """The contact patches within the contact tolerance of the free pose `free` (the
        near-active set, whatever precision the pose itself was measured to)."""
        s = self.search
        return s.patches(translated(free, self.tol * s.push))

    def _pressed(self) -> float:
        """How much objective one unit of travel along Δ is worth at the current pose (at
        least 1): the pose's contact bracket, a length along Δ, is narrowed by this much
        more than a tolerance on the objective, so that where stretched ligaments press the
        body on with many times its load, the bracket's uncertainty does not swamp the
        gain a move must show (1 for the travel: its bits unchanged)."""
        return max(1.0, self.objective.pressing(self.pose))

    def _measuring(self, promised: float) -> float:
        """The contact tolerance (m) that measures a move promising `promised`: `measure` of
        it in travel along Δ, between the finest tolerance and the contact tolerance."""
        t = self.tuning
        return min(self.tol, max(t.measure * promised / self._pressed(),
                                 t.finest_tol_res * self.search.params.resolution_m))

    def _gap(self) -> float:
        """How far the current pose is from touching along Δ (m): its bracket's width."""
        return self.search.depth(self.touching) - self.search.depth(self.pose)

    def _narrow(self, tau: float, rebase: bool = False) -> float:
        """Narrow the current pose's contact bracket to at most `tau` (the patches stay);
        return its width (m). With `rebase` the touching pose is placed from the narrowed
        pose rather than from the old one: another rounding, which `sharpen` keeps because
        the tables' bits depend on it (measured: the total knee's table differs in 1,074
        cells, 12 of them by more than the resolution, when both use one rounding)."""
        s = self.search
        gap = self._gap()
        if gap <= tau:
            return gap
        lo, hi = s.bisect_along(self.pose, 0.0, gap, tau)
        if rebase:
            self.pose = translated(self.pose, lo * s.push)
            self.touching = translated(self.pose, (hi - lo) * s.push)
        else:
            self.touching = translated(self.pose, hi * s.push)
            self.pose = translated(self.pose, lo * s.push)
        return hi - lo

    def _arrive(self, bracket: Bracket, floor: Contacts) -> End | None:
        """Take the pose of `bracket`; outside the search envelope, or pulled off the fixed
        body by its ligaments, the climb ends."""
        s = self.search
        self.pose, self.touching, self.floor = bracket.free, bracket.touching, floor
        self.learned = Contacts.empty()
        outside = None if s.params.envelope_holds else s.beyond_envelope(self.pose)
        return (Status.ENVELOPE, outside) if outside else self.pulled()

    def pulled(self) -> End | None:
        """The end when the body's ligaments pull it off the fixed body against its load."""
        if self.objective.pressing(self.pose) > 0.0:
            return None
        return (Status.PULLED, self.objective.pulled_off(self.pose))

    def _crest(self, slope: float, new_slope: float) -> float:
        """Share of the last move at which the slope would reach zero (secant), at least
        `crest_floor`."""
        if new_slope >= slope:
            return 1.0
        return min(max(slope / (slope - new_slope), self.tuning.crest_floor), 1.0)

    def leap(self) -> End | None:
        """D8: where the patches' model has no move left, climb on the gap field before the
        proof. One cast (`RayPair.gaps`) gives every near ray's gap g_k and the normal of
        the face it enters, so the travel after a lateral move x is min_k (g_k + a_k . x)
        to first order, and the objective's change press dt + drive . x
        (`Objective.first_order`): the best move within a trust radius is searched on that
        model (`_best_move`). python-fcl measures each move as `move` does (contact from the
        model's travel, to `measure` of its promise); a move that keeps `promise` of it is
        taken and the field cast again there, the radius growing or shrinking with how well
        the promise was kept. The leap ends when the field promises less than the proof's
        lift, at the first move that keeps less than `promise`, or after `leap_casts`
        casts. Only smooth objectives leap: their rests lie in creases narrower than the
        finest move, where the patches' mean normals promise slopes the surfaces do not
        have and the climb would creep by one proof's lift at a time (docs/design.md).
        The end when the climb must stop there, else None: the proof follows."""
        s, t, objective = self.search, self.tuning, self.objective
        if s.rays is None or not objective.smooth:      # never the travel
            return None
        lift, res = self.proof_lift, s.params.resolution_m
        radius, longest = t.leap_moves * self.finest, t.max_move_steps * s.params.step_m
        moved = False
        for _ in range(t.leap_casts):
            gaps, slopes = self._gap_field(t.leap_window_res * res)
            if len(gaps) == 0:
                break
            press, drive = objective.first_order(self.pose)
            x, travel, promised = _best_move(gaps, slopes, press, drive, radius, s.free)
            if promised < lift:
                break                                  # nothing the proof could see
            length = float(np.linalg.norm(x))
            x = x * (self._room(x / length, length) / length)
            bracket = s.touch(s.lateral(self.pose, x, self.arm), travel,
                              self._measuring(promised))
            if bracket is None:
                break
            kept = objective.value(bracket.free) - objective.value(self.pose)
            if kept < t.promise * promised:
                break                                  # the field misled: the proof decides
            self.pose, self.touching, moved = bracket.free, bracket.touching, True
            radius = min(2.0 * radius, longest) if kept >= t.leap_grow_share * promised \
                else max(0.5 * radius, t.leap_min_moves * self.finest)
        if not moved:
            return None
        return self._arrive(Bracket(self.pose, self.touching), self._floor_at(self.pose))

    def _gap_field(self, within: float) -> tuple[Floats, Floats]:
        """The gaps (k,) of the rays entering the other body within `within` at the current
        pose, and each gap's gradient (k, 3) over (slide e1, slide e2, arc): a point of the
        moving body moved by dp changes a gap to the face of normal n by -n . dp / n . Δ."""
        s = self.search
        assert s.rays is not None
        gaps, normals, points = s.rays.gaps(self.pose, within)
        lever = np.cross(s.push, points - s.centre(self.pose)) / self.arm
        slopes = -np.stack([normals @ s.e1, normals @ s.e2,
                            np.einsum('ij,ij->i', normals, lever)], 1) \
            / (normals @ s.push)[:, None]
        return gaps, slopes * s.free

    def prove(self) -> _Outcome | None:
        """D5: probe around the pose; the outcome when a probe gained (it was followed, or
        the climb ended), None at rest."""
        s, t = self.search, self.tuning
        lift = self.proof_lift
        checks_before, started = s.queries(), time.perf_counter()
        # the pose's own bracket is narrowed first, so a probe free at the lift has gained
        # at least the lift less a sliver: every probe that succeeds is real progress
        pressed = self._pressed()
        self._narrow(t.probe_bracket_res * s.params.resolution_m / pressed)
        grads = self.gradients(self.floor)
        directions = _DIRECTIONS[~np.any((_DIRECTIONS != 0) & (s.free == 0), axis=1)]
        model = np.min(grads @ directions.T, axis=0) if len(grads) \
            else np.zeros(len(directions))
        order = np.argsort(-model)                       # most promising first
        near = self._floor_near()
        try:
            scales = list(zip(t.probe_scales_moves, t.hopeless_res))
            if pressed >= t.pressed_from:      # never the travel (pressed 1)
                scales.insert(0, (t.pressed_probe_moves, t.hopeless_res[0]))
            for scale, hopeless_res in scales:
                length = scale * self.finest
                # the near-active patches bound the travel after the probe by
                # tol + length * model (plus curvature); where that is short of the lift by
                # a wide margin, the probe cannot gain: no query needed. The curvature the
                # model leaves out is a length along Δ, worth `pressed` times as much
                # objective where ligaments press the body on
                margin = hopeless_res * s.params.resolution_m * pressed
                hopeless = length * model < lift - self.tol - margin
                asked = directions[order[~hopeless[order]]]
                moves = [d for d, room in zip(asked, s.limits_to_envelope(
                    self.pose, self.arm, asked, length)) if room >= length]
                if not moves:
                    continue
                cands = s.laterals(self.pose, length * np.array(moves), self.arm)
                firsts = self.objective.first_lifts(cands, self.pose, 0.0, lift)
                refuted = self._refuted(cands, firsts, near)
                for d, cand, first, no in zip(moves, cands, firsts, refuted):
                    if no or not self._gains(cand, lift, float(first)):
                        continue
                    return self._follow(d, length, lift)
        finally:
            self.proof_checks += s.queries() - checks_before
            self.proof_s += time.perf_counter() - started
        return None

    def _floor_near(self) -> _FloorNear:
        """The vertices and the edges (body frames) of the triangles that cross at the
        floor's contact, each body's."""
        pair = self.search.pair
        moving_tris, fixed_tris = self.floor.triangles
        return _FloorNear(pair.moving.vertices[np.unique(pair.moving.faces[moving_tris])],
                          pair.fixed.vertices[np.unique(pair.fixed.faces[fixed_tris])],
                          pair.moving.edge_ends(moving_tris),
                          pair.fixed.edge_ends(fixed_tris))

    def _refuted(self, cands: Floats, firsts: Floats, near: _FloorNear) -> Bools:
        """(m,) True for each probe of `cands` (m, 4, 4) that the rays find in collision
        lifted by its `firsts` (the Newton step `_gains` asks python-fcl about first), from
        the floor's triangles (`_floor_near`): one cast of vertex rays at every probe (a
        ray that enters the other body short of the lift: the travel there is shorter than
        the lift), then one of the edges at the lifted probes the vertices left open (an
        edge that crosses a face of the other body there: the edge-by-edge contacts vertex
        rays miss). Either refutes the probe exactly; False leaves it to `_gains`."""
        s = self.search
        asked = np.isfinite(firsts) & (np.abs(firsts) <= self.objective.lift_limit)
        if s.rays is None or not asked.any() or not (len(near.moving) or len(near.fixed)):
            return np.zeros(len(cands), dtype=bool)
        lifts = np.where(asked, firsts, 0.0)
        bases = cands.copy()              # lifted back first where the lift is negative
        bases[:, :3, 3] += np.minimum(lifts, 0.0)[:, None] * s.push
        refuted = s.rays.blocked(near.moving, near.fixed, bases, np.maximum(lifts, 0.0)) \
            & asked
        open_ = np.flatnonzero(asked & ~refuted)
        if len(open_):
            lifted = cands[open_]
            lifted[:, :3, 3] += lifts[open_, None] * s.push
            refuted[open_] = s.rays.crossed(near.moving_edges, near.fixed_edges, lifted)
        return refuted

    def _gains(self, cand: Pose, lift: float, first: float) -> bool:
        """Whether the lateral pose `cand` is at least `lift` above the current pose in the
        objective: one query at the lift that proves it, or, where that lift is too deep
        to prove anything, the contact itself found and weighed (`first`: the Newton
        step of the lift from `cand`, `Objective.first_lifts`)."""
        s, objective = self.search, self.objective
        # the objective is concave along Δ (the load's work is, the energy convex), so one
        # Newton step from the lateral pose lifts no higher than needed: touching there, the
        # probe cannot gain; free, the lift is found exactly and asked again
        if abs(first) <= objective.lift_limit and s.collides(translated(cand, first * s.push)):
            return False
        h = objective.lift_to(cand, self.pose, 0.0, lift)
        if abs(h) <= objective.lift_limit:
            return h == first or not s.collides(translated(cand, h * s.push))
        bracket = s.touch(cand, 0.0, self.tol)
        return bracket is not None and \
            objective.value(bracket.free) >= objective.target(self.pose, 0.0, lift)

    def _follow(self, direction: Floats, length: float, lift: float) -> _Outcome:
        """A probe gained: follow its direction outward while it keeps gaining (a pattern
        move), and continue from the best pose found."""
        s, t, objective = self.search, self.tuning, self.objective
        best: Bracket | None = None
        while True:
            target = s.lateral(self.pose, length * direction, self.arm)
            h = objective.lift_to(target, self.pose, 0.0, lift)
            bracket = s.touch(translated(target, h * s.push) if abs(h) <= objective.lift_limit
                              else target, 0.0, self.tol)
            if bracket is None:
                if best is None:
                    return _Outcome(self.step, (Status.LOST, LOST_CONTACT))
                break
            if best is not None and \
                    objective.value(bracket.free) <= objective.value(best.free) + self.tol:
                break
            best = bracket
            grown = self._room(direction, t.follow_grow * length)
            if grown <= length or grown > t.max_move_steps * s.params.step_m:
                break
            length = grown
        end = self._arrive(best, self._floor_at(best.free))
        return _Outcome(max(self.step, t.resume_moves * self.finest), end)


def run_climb(search: Search, bracket: Bracket, tissue: Tissue | None = None,
              tuning: SettleTuning = TUNING) -> SettleResult:
    """Climb from the first exact contact `bracket` to a rest pose (module docstring), of
    the travel, or of the load's work less the energy of the `tissue` acting on the body
    (`kneeseat_core.settle.objective`)."""
    p = search.params
    climb = _Climb.start(search, bracket, tuning, tissue)
    end: End | None = climb.pulled()
    while end is None and search.iterations < p.max_iterations:
        search.iterations += 1
        chosen = climb.choose() if climb.has_step else None
        if chosen is None:
            chosen = climb.resume()
        outcome: _Outcome | None
        if chosen is not None:
            outcome = climb.move(*chosen)
        else:
            end = climb.leap()
            if end is not None:
                break
            outcome = climb.prove()
        if outcome is None:
            end = _at_rest(search, climb)
        else:
            climb.step, end = outcome.step, outcome.end
    status, reason = end or (
        Status.CAP, f'iteration cap ({p.max_iterations}) reached before rest was verified')
    pose, back = search.judge(climb.pose, climb.tuning.finest_tol_res * p.resolution_m)
    return search.result(pose, status, reason, climb.floor, proof_checks=climb.proof_checks,
                         proof_s=climb.proof_s, judged_back_m=back)


def _at_rest(search: Search, climb: _Climb) -> End:
    """The end of a climb whose proof found nothing that gains: a plain rest, or a rest on
    the boundary of an envelope that holds."""
    bound = (search.on_boundary(climb.pose, climb.finest, climb.arm)
             if search.params.envelope_holds else None)
    gain = climb.objective.gain
    if bound:
        return (Status.CONSTRAINED, f'rest on the envelope boundary ({bound}): nothing inside '
                f'the envelope gains more than the resolution {gain}')
    return (Status.REST, 'rest: no slide, spin about the push or combination, short or '
            f'long, gains more than the resolution {gain}')


# The leap's search of the gap field's model: a grid of 5 moves a coordinate across the
# trust box, then a pattern search about the best (26 neighbours, the step halved each time).
_GRID = np.array(list(itertools.product(np.linspace(-1.0, 1.0, 5), repeat=3)))
_NEIGHBOURS = np.array([d for d in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(d)])
_REFINE = 6


def _best_move(gaps: Floats, slopes: Floats, press: float, drive: Floats, radius: float,
               free: Floats) -> tuple[Floats, float, float]:
    """The move x (3,) within `radius` of no move in every free coordinate that the gap
    field says gains most, press min_k (g_k + a_k . x) + drive . x less its value at no
    move: searched on the model (`_GRID`, then `_REFINE` halvings of a pattern search), so
    the move is the model's best to a 64th of the radius; with the travel min_k there and
    the gain it promises."""
    low = float(np.min(gaps))

    def model(moves: Floats) -> tuple[Floats, Floats]:
        travel = np.min(gaps[None, :] + moves @ slopes.T, axis=1)
        return press * (travel - low) + moves @ drive, travel

    moves = _GRID * (radius * free)
    gains, travels = model(moves)
    k = int(np.argmax(gains))
    x, gain, travel = moves[k], float(gains[k]), float(travels[k])
    step = 0.25 * radius
    for _ in range(_REFINE):
        near = np.clip(x + _NEIGHBOURS * (step * free), -radius, radius)
        gains, travels = model(near)
        k = int(np.argmax(gains))
        if gains[k] > gain:
            x, gain, travel = near[k], float(gains[k]), float(travels[k])
        step *= 0.5
    return x, travel, gain

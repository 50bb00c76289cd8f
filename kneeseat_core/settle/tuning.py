"""Every number that steers the default method's climb, in one place (`TUNING`).

`SettleParams` holds what a user asks of one settle (the patent's step and resolution, the
search envelope); these are how the climb (`kneeseat_core.settle.climb`) goes about it. The
lengths are relative: in resolutions (`*_res`), in finest moves (`*_moves`: the finest move
is one resolution of slide, or a spin whose arc at the farthest vertex is one rotation
resolution), in translation steps (`*_steps`) or as shares of another quantity. The tables'
bits depend on every one of them; why each step is what it is: docs/design.md.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ['SettleTuning', 'TUNING']

# How far a place's window must reach beyond the contact tolerance (resolutions): 10 nm at
# the patent's resolution, far above any rounding of the gaps, far below what it costs.
_WINDOW_MARGIN_RES = 1e-3


@dataclass(frozen=True, slots=True)
class SettleTuning:
    """The climb's constants (module docstring).

    Contact:
        standoff_res: a pose at contact stands this far short of touching along the push
            (the travel is exact: the pose is free by this much, python-fcl agrees).
        window_res: a pose's features are those closing within this far beyond contact
            (what the climb uses of them is within `contact_tol_res`: this covers it, with a
            margin of a hundredth of a resolution that no rounding crosses, and the search
            prunes everything beyond; a place that becomes the pool is measured again with
            the pool's window)...
        pool_window_res: ...and the witnesses' pool those within this, taken at the first
            contact and again wherever the climb has moved (at least `window_res`: the pool
            names the pairs a refutation asks, which is exact whichever it asks, and the
            farther features the proof's way up plans with, which it then measures: this
            moves the cost, and a table only where a way up moves differently; a wider pool
            costs a wider first touch and more features to pick from for every move)...
        pool_reach_moves: ...this many finest moves from where it was taken.
        pool_cap: the pool keeps, of its features beyond a place's window, only this many,
            those that close first (ties kept; 0: every one): on conforming surfaces its
            window holds hundreds more that name the same few pairs (the default knee's
            first contacts held 914 on average at 0.6 resolutions, 352 under this cap),
            each of them ranked for every move's witnesses and carried into the proof's
            way up; the search prunes by the ones it keeps as by the window.
        contact_tol_res: the features within this of touching are the near-active ones (the
            model that orders the moves and prunes the proof) and the reported contacts.
        room_share: a move of length l is modelled with the features that hold for a slide
            of at least this share of l.
    The pattern (the climb's moves):
        fine_moves: a move of up to this many finest moves is taken when it gains at
            least...
        move_gain_res: ...this (resolutions, times the objective's precision): anything the
            exact travel measures, so that a shallow slope is followed to its top and the
            proof is left what gains nothing; a longer move must gain the proof's lift.
        first_moves: the first scale (finest moves, per coordinate), or...
        near_first_moves: ...this one where the start is a neighbouring cell's rest
            carried over (`settle(..., near_rest=True)`): that rest is expected within
            about a finest move, and longer first moves overshoot it (on the total knee's
            slice, 5.9 exact travels a cell against 7.2 at 2 finest moves).
        grow: a scale that gained grows by this factor, up to...
        far_moves: ...this scale;
        shrink: one that found nothing shrinks by this factor, down to...
        least_moves: ...this many finest moves; the proof then starts from the finest,
            and tries the way up (below) shorter than that first.
        directions_from_moves: a scale of at least this many finest moves tries the probe
            directions; a shorter one (the first near a rest carried over, or where the
            proof's way up gained) only the way up: the move the contacts say climbs most
            (their first-order model holds that close, and its best move beats every
            direction of the same length).
        every_direction_moves: a scale of up to this many finest moves tries every probe
            direction; a longer one only the...
        far_tries: ...this many most promising (its witnesses, drawn near the pose, say
            little that far out, so a try is mostly a search).
        witnesses: a move is first asked of this many pairs of triangles from the pool, those
            it says close first after the move, and of their moving triangles' vertices
            (a refutation is exact whichever it asks: this moves the cost, never a table;
            the engine ranks 8 in one pass over the pool and sorts it for more, and 8 were
            the cheapest on all three knees, docs/tables.md).
    Proof of rest (D5):
        uphill_probe_moves: the proof first tries the way up at these lengths, each
            needing the lift: it follows a ridge narrower than the probe directions'
            spacing, along which every direction loses...
        probe_scales_moves: ...then the probe directions at these lengths.
        pressed_from: where the objective presses the body on at least this many times
            its load (`Objective.pressing`), the proof probes first at...
        pressed_probe_moves: ...this length: a gain of the proof's lift then needs a
            travel change that many times smaller, and can lie in a crease narrower than
            the finest move. Its hopeless margin is the finest probe's.
        probe_lift_res: a move gains when its objective is this much above the pose's.
        hopeless_res: per probe scale, a probe the near-active features say loses more than
            this (beyond the lift; resolutions of travel, so times how hard ligaments press
            the body on in the objective's terms) is not tried: their curvature cannot hide
            a gain behind such a loss.
        finest_tol_res: python-fcl backs a final pose it finds in collision out to this.
    """

    standoff_res: float = 1.0 / 1024.0
    window_res: float = 0.26
    pool_window_res: float = 0.45
    pool_reach_moves: float = 4.0
    pool_cap: int = 256
    contact_tol_res: float = 0.25
    room_share: float = 0.25
    fine_moves: float = 2.0
    move_gain_res: float = 1e-4
    first_moves: float = 2.0
    near_first_moves: float = 0.5
    grow: float = 2.0
    far_moves: float = 16.0
    shrink: float = 0.25
    least_moves: float = 1.0
    directions_from_moves: float = 1.0
    every_direction_moves: float = 4.0
    far_tries: int = 3
    witnesses: int = 8
    probe_scales_moves: tuple[float, ...] = (1.0, 4.0, 16.0)
    uphill_probe_moves: tuple[float, ...] = (0.25, 0.5)
    pressed_from: float = 8.0
    pressed_probe_moves: float = 0.25
    probe_lift_res: float = 0.25
    hopeless_res: tuple[float, ...] = (1.0, 1.0, 5.0)
    finest_tol_res: float = 1.0 / 1024.0

    def __post_init__(self) -> None:
        # the windows hold what the climb uses: the near-active features within the
        # contact tolerance, and the pool at least a place's features
        if not self.window_res - self.contact_tol_res >= _WINDOW_MARGIN_RES:
            raise ValueError(f'window_res ({self.window_res}) must exceed contact_tol_res '
                             f'({self.contact_tol_res}) by at least {_WINDOW_MARGIN_RES}')
        if self.pool_cap < 0:
            raise ValueError(f'pool_cap ({self.pool_cap}) must not be negative (0: no cap)')
        if not self.pool_window_res >= self.window_res:
            raise ValueError(f'pool_window_res ({self.pool_window_res}) must be at least '
                             f'window_res ({self.window_res})')


TUNING = SettleTuning()

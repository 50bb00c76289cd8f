"""Every number that steers the default method's climb, in one place (`TUNING`).

`SettleParams` holds what a user asks of one settle (the patent's step and resolution, the
search envelope); these are how the climb (`kneeseat_core.settle.climb`) goes about it. The
lengths are relative: in resolutions (`*_res`), in finest moves (`*_moves`: the finest move
is one resolution of slide, or a spin whose arc at the farthest vertex is one rotation
resolution), in translation steps (`*_steps`) or as shares of another quantity. The tables'
bits depend on every one of them; the departures they tune (D1-D7) are in docs/design.md.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ['SettleTuning', 'TUNING']


@dataclass(frozen=True, slots=True)
class SettleTuning:
    """The climb's constants (module docstring).

    Travel by rays:
        near_margin_steps: the near set holds the vertices within this many translation
            steps of the other body; it is drawn again when the body has moved by half of
            it (a cost, not a guess: no answer depends on it).
        ray_window_res: a cast uses first the vertices that may touch within this many
            resolutions of travel, then twice as many, and so on.
    Exact contact:
        contact_tol_res: exact contact along the push is found to this (D3).
        sharpen: before rest is probed, the contact bracket is narrowed to this share of
            the contact tolerance, so that a patch only near contact (it would balance the
            hull by itself) drops out.
    Moves (D3):
        promise: a move must deliver this share of the gain its slope promised or it is
            undone (a move to the crest of a smooth slope keeps half its promise).
        measure: a move's gain is measured to this share of its promise...
        finest_tol_res: ...but never finer than this.
        measurable: a promise below this many finest tolerances is not measured: taken on
            trust while the last measured promise was kept, else the step is cut by...
        untrusted_cut: ...this factor.
        min_move: a move shorter than this share of the finest move is not made: the step
            has run out.
        steep: the slope ahead counts as steep while it keeps this share of the slope the
            move started on; the next step then grows by...
        grow: ...this factor, up to...
        max_move_steps: ...this many translation steps.
        crest_floor: where the slope turns, the next step is cut to the secant estimate of
            the crest, but to no less than this share of the last one...
        blocked_cap: ...and after a move that was blocked, to no more than this share.
    Balance (D1b):
        crest_flat: a patch whose depth gradient is at most this many flat slopes sits at
            its own crest.
    Leap on the gap field (D8):
        leap_window_res: the gap field holds the rays that enter the other body within
            this many resolutions.
        leap_moves: the first trust radius of a leap (finest moves, per coordinate);
        leap_grow_share: it doubles after a move that kept this share of its promise (up
            to the longest move) and halves after one that kept less, down to...
        leap_min_moves: ...this radius. A move that keeps less than `promise` ends the
            leap, as does a field that promises less than the proof's lift, or...
        leap_casts: ...this many casts.
    Proof of rest (D5):
        probe_scales_moves: probe lengths.
        pressed_from: where the objective presses the body on at least this many times
            its load (`Objective.pressing`), the proof probes first at...
        pressed_probe_moves: ...this length: a gain of the proof's lift then needs a
            travel change that many times smaller, and can lie in a crease narrower than
            the finest move (the natural knee's tibia at flexion 0, varus 10, pressed on
            17.5 times: 10-25 um wide). Its hopeless margin is the finest probe's.
        probe_lift_res: a probe gains when the moved body is still free lifted this much.
        probe_bracket_res: before probing, the pose's contact bracket is narrowed to this.
        hopeless_res: per probe scale, a probe that the near-active patches' first-order
            model says loses more than this (beyond the lift; resolutions of travel, so
            times how hard ligaments press the body on in the objective's terms) is not
            sent to python-fcl: normals would have to be off by tens of degrees, or the
            surface fold over within the probe, to hide a gain behind such a loss.
        follow_grow: a probe that gained is followed outward, its length growing by this
            factor while it gains.
        resume_moves: after a followed probe the climb resumes with a step of at least
            this many finest moves.
    """

    near_margin_steps: float = 4.0
    ray_window_res: float = 4.0
    contact_tol_res: float = 0.25
    sharpen: float = 0.25
    promise: float = 0.25
    measure: float = 0.125
    finest_tol_res: float = 1.0 / 1024.0
    measurable: float = 8.0
    untrusted_cut: float = 0.5
    min_move: float = 0.25
    steep: float = 0.5
    grow: float = 2.0
    max_move_steps: float = 4.0
    crest_floor: float = 0.25
    blocked_cap: float = 0.5
    crest_flat: float = 2.0
    leap_window_res: float = 3.0
    leap_moves: float = 2.0
    leap_grow_share: float = 0.75
    leap_min_moves: float = 0.125
    leap_casts: int = 32
    probe_scales_moves: tuple[float, ...] = (1.0, 4.0, 16.0)
    pressed_from: float = 8.0
    pressed_probe_moves: float = 0.25
    probe_lift_res: float = 0.25
    probe_bracket_res: float = 1.0 / 64.0
    hopeless_res: tuple[float, ...] = (1.0, 1.0, 5.0)
    follow_grow: float = 2.0
    resume_moves: float = 2.0


TUNING = SettleTuning()

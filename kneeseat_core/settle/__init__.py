"""Settle one moving rigid body against a fixed one along a push direction (US 6,708,142).

The moving body may translate in any direction and rotate only about axes parallel to the
push direction `Δ` (`push`). Two methods:

`patent` (`kneeseat_core.settle.patent`) - the letter of FIGS. 2-16 on python-fcl's boolean
and contact queries (`kneeseat_core.settle.search`): drop along Δ to exact contact by
dichotomy; torque test (barycentre, each point, the candidates' barycentre); a rotation by
one step's arc about the centre found, else a slide by the component-wise average of the
unit projected normals; stop when that slide is shorter than T2. A zero torque is ignored
(not a change of sign) and python-fcl contacts are mapped to the reference by object
identity. A repeated pose (the slide/rotate cycle) or the iteration cap ends "not
converged".

`default` (`kneeseat_core.settle.climb`) - the same loop carried to a true rest pose: a local
maximum of the travel along Δ over slides and spins, proved by probes. Departures, each
named where it is made:
  D1 exact travel: how far the body goes along Δ before it touches is measured exactly
     from the swept triangles (`kneeseat_core.meshes.sweep`: a vertex on a face or an edge
     across an edge, the least gap over every pair of triangles), not by dichotomy; a
     pose at contact stands a standoff (res/1024) short of touching.
  D2 combined moves on a pattern: the moves are slides, spins and their combinations (26
     directions) at a scale that grows after a move that gained and shrinks after none,
     so slide and spin move together, a shallow slope is climbed in long moves and a
     crease in short ones; a move must gain the proof's lift.
  D3 witnesses: the contact features at a pose (the travel to first order,
     `kneeseat_core.settle.model`) order the moves and name the pairs of triangles likely
     to stop each; a pair, or a vertex of its moving triangle, that meets the fixed body
     short of the travel a move needs refutes it exactly, without a search.
  D4 rotation resolution is an arc at the farthest vertex (resolution / radius) unless
     given explicitly, so a rotation can always be refined below one step.
  D5 rest is proved, not assumed: when no move of the finest scale gains, probes - the 26
     directions at 1, 4 and 16 times the finest move (first a quarter of it where
     ligaments press the body on 8 or more times its load), each needing the proof's lift
     (a quarter resolution) - must all fail, refuted by witnesses or measured; a probe
     that gains is taken and the climb resumes.
  D6 honest ends: "converged" only after D5. Not converged: the iteration cap; lost contact
     (the body slid off the fixed body); leaving the search envelope (`max_slide_m` across
     the push and `max_spin_rad` about it, from the anchor pose): no rest near the start.
     Where the envelope holds (`envelope_holds`, a knee config's soft-tissue stand-in) the
     climb stays inside it and a rest on its boundary is reported as constrained.
  D7 python-fcl judges: a start in collision is backed out along -Δ by python-fcl's
     booleans (asked of every start the exact travel finds in collision or within the
     standoff of touching: one farther from it is free, as every pose the climb stands
     on), and the end pose is asked of python-fcl (one query); one it finds in collision
     is backed out too (`SettleResult.judged_back_m`).
The independent check of "at rest" is `kneeseat_core.referee.judge` (`kneeseat verify`). Why
each departure is made, and what the letter does on real meshes: docs/design.md, "The
settle".
"""
from __future__ import annotations

import numpy as np

from kneeseat_core.errors import NoContactError, SettleError
from kneeseat_core.ligaments import Tissue
from kneeseat_core.meshes import CollisionPair, RigidBody, SweepPair
from kneeseat_core.params import Method, SettleParams
from kneeseat_core.typed import Ints, Pose
from .climb import run_climb
from .patent import run_patent
from .search import Contacts, Search, SettleResult
from .tuning import TUNING

__all__ = ['Method', 'SettleParams', 'Contacts', 'SettleResult', 'settle']


def settle(fixed: RigidBody, moving: RigidBody, start: Pose, params: SettleParams,
           anchor: Pose | None = None, tissue: Tissue | None = None,
           seeds: Ints | None = None, near_rest: bool = False) -> SettleResult:
    """Push `moving` along `params.push` until it rests on `fixed`.

    Args:
        fixed: the reference body, at identity.
        moving: the moving body.
        start: (4, 4) fixed_from_moving start pose (m). A start in collision is backed
            out along -Δ first (reported in `backed_out_m`).
        params: the settle parameters.
        anchor: (4, 4) pose the search envelope is measured from (default: `start`).
        tissue: the ligaments acting on `moving` (`LigamentSet.tissue`), with the load on
            the push in `params.load_n`: the default method then climbs the load's work
            less their energy. The patent's method has no soft tissue and ignores it.
        seeds: (k, 2) pairs of triangles (moving face, fixed face) likely to touch first
            from `start` (a neighbouring settle's `touching`): the default method's first
            search starts from them, which changes how fast it ends, never its answer.
        near_rest: `start` is a neighbouring cell's rest carried to this attitude (a
            sweep's warm start), so the rest is expected within about a finest move: the
            default method's first moves are then short (`SettleTuning.near_first_moves`).
    Returns:
        The settle result; `converged` says whether the method's stop rule was met.
    Raises:
        NoContactError: no contact along Δ within the travel limit.
        SettleError: invalid parameters, a tissue without a load, or a start buried too
            deep to back out.
    """
    params.check()
    if tissue is not None and params.load_n is None:
        raise SettleError('ligaments act on the moving body but no load is given; give the '
                          'load on the push in newtons (load_n)')
    start = np.asarray(start, dtype=np.float64)
    search = Search(CollisionPair(fixed, moving), start, params,
                    start if anchor is None else np.asarray(anchor, dtype=np.float64))
    if params.method == 'patent':
        pose = search.back_out(start)
        limit = search.travel_limit(pose)
        bracket = search.drop(pose, params.resolution_m, limit)
        if bracket is None:
            raise NoContactError(limit)
        return run_patent(search, bracket)
    search.sweep = SweepPair(fixed, moving, search.push)
    return run_climb(search, start, tissue, TUNING, seeds, near_rest)

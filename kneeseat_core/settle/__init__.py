"""Settle one moving rigid body against a fixed one along a push direction (US 6,708,142).

The moving body may translate in any direction and rotate only about axes parallel to the
push direction `Δ` (`push`). Two methods share the primitives of `kneeseat_core.settle.search`
(exact contact by dichotomy, contacts on the reference with its outward normals):

`patent` (`kneeseat_core.settle.patent`) - the letter of FIGS. 2-16: drop along Δ to exact
contact; torque test (barycentre, each point, the candidates' barycentre); a rotation by
one step's arc about the centre found, else a slide by the component-wise average of the
unit projected normals; stop when that slide is shorter than T2. A zero torque is ignored
(not a change of sign) and python-fcl contacts are mapped to the reference by object
identity. A repeated pose (the slide/rotate cycle) or the iteration cap ends "not
converged".

`default` (`kneeseat_core.settle.climb`) - the same loop carried to a true rest pose: a local
maximum of the travel along Δ over slides and spins, proved by probes. Departures, each
named where it is made:
  D1 combined moves: the next motion is the steepest admissible one for the contact set as
     a whole - slide and spin about Δ together - the minimum-norm point of the convex hull
     of the contact patches' depth gradients (first-order quasi-static equilibrium).
  D2 blocked moves teach: a move that loses depth adds the contacts that blocked it to the
     set, so the next direction respects them (this frees a wedged body).
  D3 slope, not gain: a move's length doubles while the slope ahead stays steep and is cut
     to the crest's secant estimate when the slope turns, so a shallow slope is climbed
     whatever each step gains; a move is kept when it delivers a quarter of the gain its
     slope promised, measured to an eighth of the promise (one query: still free lifted by
     that much), and a promise too small to measure is taken on trust only while the last
     measured one was kept. Exact contact is found to a quarter of the resolution.
  D4 rotation resolution is an arc at the farthest vertex (resolution / radius) unless
     given explicitly, so a rotation can always be refined below one step.
  D5 rest is proved, not assumed: when the patches balance (a slope that could not gain
     one resolution across the envelope is flat), probes - 26 directions of slides, spins
     and their combinations at 1, 4 and 16 times the finest move (first a quarter of it
     where ligaments press the body on 8 or more times its load), lifted by a quarter
     resolution from a bracket narrowed to res/64 - must all collide; a probe that gains is
     followed outward while it gains, and the climb resumes. The rays are asked first
     (`RayPair.blocked`, one cast per probe scale from the vertices of the triangles in
     contact): a probe they block is in collision, exactly; python-fcl decides the rest,
     so every gain is python-fcl's. D1b: when the hull balances
     only because one patch sits at its own crest, the body spins about that patch.
  D6 honest ends: "converged" only after D5. Not converged: the iteration cap; lost contact
     (the body slid off the fixed body); leaving the search envelope (`max_slide_m` across
     the push and `max_spin_rad` about it, from the anchor pose): no rest near the start.
     Where the envelope holds (`envelope_holds`, a knee config's soft-tissue stand-in) the
     climb stays inside it and a rest on its boundary is reported as constrained.
  D7 contact patches: contacts are the points where the two surfaces cross (python-fcl),
     with the reference's vertex normals interpolated there; contacts on connected
     triangles form one patch (split at creases) and count once, by their mean point and
     normal, so a conforming patch straddling the rest does not balance the hull by itself.
The independent check of "at rest" is `kneeseat_core.referee.judge` (`kneeseat verify`). Why
each departure is made, and what the letter does on real meshes: docs/design.md, "The
settle".
"""
from __future__ import annotations

import numpy as np

from kneeseat_core.errors import NoContactError, SettleError
from kneeseat_core.ligaments import Tissue
from kneeseat_core.meshes import CollisionPair, RayPair, RigidBody
from kneeseat_core.params import Method, SettleParams
from kneeseat_core.typed import Pose
from .climb import run_climb
from .patent import run_patent
from .search import Contacts, Search, SettleResult
from .tuning import TUNING

__all__ = ['Method', 'SettleParams', 'Contacts', 'SettleResult', 'settle']


def settle(fixed: RigidBody, moving: RigidBody, start: Pose, params: SettleParams,
           anchor: Pose | None = None, tissue: Tissue | None = None) -> SettleResult:
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
    if params.method == 'default':
        search.rays = RayPair(search.pair, search.push, TUNING.near_margin_steps * params.step_m,
                              TUNING.ray_window_res * params.resolution_m)
    pose = search.back_out(start)
    limit = search.travel_limit(pose)
    tol = params.resolution_m if params.method == 'patent' \
        else TUNING.contact_tol_res * params.resolution_m
    bracket = search.drop(pose, tol, limit)
    if bracket is None:
        raise NoContactError(limit)
    if params.method == 'patent':
        return run_patent(search, bracket)
    return run_climb(search, bracket, tissue)

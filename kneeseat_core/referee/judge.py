"""The referee: an independent check that a settled pose is at rest.

A pose is *at rest* when it is a local maximum, to within the resolution, of the travel
s(u, v, phi): how far the moving body goes along the push before it touches the fixed one,
after a lateral state made of slides u, v across the push and a spin phi about an axis
parallel to the push (through the body's centroid; a spin about any other centre is a spin
plus a slide). Started from the reported pose, a local maximiser of s that follows
continuous ascents must not gain more than the resolution.

This module shares no search code with the settle (`kneeseat_core.settle`): it builds its
own python-fcl objects, asks only boolean collision queries, measures s by its own
bracketing and bisection (to a tenth of the resolution or finer), and climbs with scipy's
derivative-free Nelder-Mead from a small simplex (two resolutions on each coordinate) that
grows only while it climbs, so it follows continuous ascents and does not hop a ridge into
another basin. It restarts from the best point until a restart gains nothing; the verdict
is the total gain and the move that produced it.

An envelope (the largest slide across the push and spin about it, measured from an anchor
pose) bounds the climb when given: states outside it are refused, so a rest on the
envelope's boundary is judged within the envelope. Give one only where the envelope holds
(a config's soft-tissue stand-in): a search envelope bounds the settle, never the referee.

With ligaments (`Load`: the load on the push and the fibres acting on the body, with every
point not on the body already placed), the referee climbs what the settle claims to
maximise there, with its own arithmetic: the load's work less the fibres' elastic energy
at the contact pose, per unit load (m): the advance of the body's centroid along the push
(or, for a load that pulls toward a point, minus the centroid's distance from it) less
E / F, with E from the Blankevoort force law integrated here. `extent` says how well a rest is
determined: how far the pose can slide and spin while the objective stays within one
resolution of its value there.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Sequence

import fcl
import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation
import trimesh

from kneeseat_core.errors import NoContactError
from kneeseat_core.typed import Floats, Pose

__all__ = ['Envelope', 'Verdict', 'Referee', 'RefereeTuning', 'REFEREE', 'Load', 'Extent']

# Penalty returned for a lateral state the climb may not take (outside the envelope).
_REFUSED = 1e9
# A gain at least this large counts as "climbs off": no contact within the travel limit.
_OFF = 1e6


@dataclass(frozen=True, slots=True)
class RefereeTuning:
    """Every number that steers the referee, in resolutions of the verdict (`REFEREE`).

    Attributes:
        travel_divisor: the travel is measured to one resolution divided by this
            (bisection on boolean queries).
        bracket_step: the first probe along the push when bracketing the contact...
        bracket_cap: ...doubling up to this, so that no probe tunnels through a thin part.
        simplex: Nelder-Mead starts from a simplex this wide on each coordinate: small
            enough to follow a continuous ascent without hopping a ridge.
        xatol, fatol: Nelder-Mead's stop tolerances on the state and on the travel.
        restart_gain: the climb restarts from its best point until a restart gains no
            more than this.
        max_evaluations: travel evaluations per verdict, over all restarts.
    """

    travel_divisor: float = 10.0
    bracket_step: float = 1.0
    bracket_cap: float = 4.0
    simplex: float = 2.0
    xatol: float = 0.05
    fatol: float = 0.02
    restart_gain: float = 0.02
    max_evaluations: int = 1500


REFEREE = RefereeTuning()


@dataclass(frozen=True, slots=True)
class Envelope:
    """How far the moving body may go from `anchor`: slide across the push, spin about it."""

    anchor: Pose               # (4, 4) fixed_from_moving
    max_slide_m: float
    max_spin_rad: float


@dataclass(frozen=True, slots=True, eq=False)
class Load:
    """The load on the push and the fibres pulling on the moving body (for the referee).

    Each fibre is a path of points; a point either rides on the moving body (its frame) or
    is fixed in the fixed body's frame (already placed).
    """

    load_n: float
    toward: Floats | None                      # (3,) the point the load pulls toward (None:
    #                                            the load acts along the push)
    paths: tuple[tuple[Floats, Floats], ...]   # per fibre: (n, 3) points, (n,) on the body
    slack_m: Floats                            # (f,)
    stiffness_n: Floats                        # (f,) N per unit strain
    transition: Floats                         # (f,) transition strain

    def energy(self, pose: Pose) -> float:
        """Elastic energy (J) with the body at `pose`: Blankevoort's f = k e^2 / (2 e_t)
        below the transition strain, k (e - e_t / 2) above, integrated over the length."""
        lengths = np.empty(len(self.paths))
        for i, (points, on_body) in enumerate(self.paths):
            placed = np.where(on_body[:, None], points @ pose[:3, :3].T + pose[:3, 3], points)
            lengths[i] = np.sqrt(np.sum(np.diff(placed, axis=0) ** 2, axis=1)).sum()
        e = np.maximum(lengths / self.slack_m - 1.0, 0.0)
        k, et, l0 = self.stiffness_n, self.transition, self.slack_m
        toe = l0 * k * e ** 3 / (6.0 * et)
        linear = l0 * k * (e * e / 2.0 - et * e / 2.0 + et * et / 6.0)
        return float(np.sum(np.where(e < et, toe, linear)))


@dataclass(frozen=True, slots=True)
class Extent:
    """How well a rest is determined: the farthest the pose moves while the objective stays
    within one resolution of its value there."""

    slide_m: float             # largest displacement of the centroid across the push
    spin_rad: float            # largest spin about the push
    evaluations: int


@dataclass(frozen=True, slots=True)
class Verdict:
    """What the referee found from one pose."""

    gain_m: float              # travel gained along the push (inf: climbs off the fixed body)
    slide_m: float             # lateral displacement of the centroid to the best state
    spin_rad: float            # spin about the push to the best state
    evaluations: int           # travel evaluations (each a bracketing and a bisection)
    queries: int               # boolean collision queries
    best_pose: Pose            # (4, 4) the best state found, at contact

    def at_rest(self, resolution_m: float) -> bool:
        """True when nothing gains more than `resolution_m`."""
        return self.gain_m <= resolution_m


def _bvh(meshes: Sequence[trimesh.Trimesh]) -> fcl.BVHModel:
    vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in meshes])
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    faces = np.concatenate([np.asarray(m.faces, dtype=np.int64) + o
                            for m, o in zip(meshes, offsets)])
    model = fcl.BVHModel()
    model.beginModel(len(faces), len(vertices))
    model.addSubModel(vertices, faces)
    model.endModel()
    return model


@dataclass(slots=True)
class _Best:
    """The highest objective a climb has found so far, the lateral state that gave it and
    the travel there."""

    value: float
    state: Floats
    travel: float


class Referee:
    """Travel oracle and climber for one fixed and one moving body (each one or more meshes).

    Args:
        fixed: meshes of the fixed body (metres, at identity).
        moving: meshes of the moving body (metres, its own frame).
        push: (3,) push direction, fixed frame.
        resolution_m: the resolution the verdict is judged at; travel is measured to a
            tenth of it.
        locked_slide: (3,) a slide direction the body may not take, or None.
        load: the load and the fibres on the body (the objective is then the load's work
            less their energy, per unit load), or None for the travel alone.
    """

    def __init__(self, fixed: Sequence[trimesh.Trimesh], moving: Sequence[trimesh.Trimesh],
                 push: Floats, resolution_m: float, locked_slide: Floats | None = None,
                 tuning: RefereeTuning = REFEREE, load: Load | None = None) -> None:
        self.tuning = tuning
        self.load = load
        self._fixed = fcl.CollisionObject(_bvh(fixed), fcl.Transform())
        self._moving = fcl.CollisionObject(_bvh(moving), fcl.Transform())
        self._request = fcl.CollisionRequest()
        points = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in moving])
        self._points = points
        self._centroid = points.mean(axis=0)
        push = np.asarray(push, dtype=np.float64)
        self.push = push / np.linalg.norm(push)
        # an in-plane basis; with a locked slide its direction is the first axis (dropped)
        seed = (np.asarray(locked_slide, dtype=np.float64) if locked_slide is not None
                else np.eye(3)[int(np.argmax(np.abs(np.cross(self.push, np.eye(3))).sum(1)))])
        a = seed - (seed @ self.push) * self.push
        self._a = a / np.linalg.norm(a)
        self._b = np.cross(self.push, self._a)
        self._free = np.array([0.0 if locked_slide is not None else 1.0, 1.0, 1.0])
        self._dims = np.flatnonzero(self._free)     # the coordinates the climb moves
        self.resolution_m = float(resolution_m)
        self.tolerance_m = self.resolution_m / tuning.travel_divisor
        self.queries = 0
        extent = np.ptp(points, axis=0).max()
        fixed_pts = np.concatenate([np.asarray(m.vertices) for m in fixed])
        self._limit = float(extent + np.ptp(fixed_pts, axis=0).max())

    # ---- the oracle ---------------------------------------------------------------
    def collides(self, pose: Pose) -> bool:
        """Boolean query: does the moving body at `pose` overlap the fixed body?"""
        self._moving.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
        result = fcl.CollisionResult()
        self.queries += 1
        return bool(fcl.collide(self._moving, self._fixed, self._request, result))

    def _arm(self, pose: Pose) -> float:
        world = self._points @ pose[:3, :3].T + pose[:3, 3]
        rel = world - (pose[:3, :3] @ self._centroid + pose[:3, 3])
        rel -= np.outer(rel @ self.push, self.push)
        return float(np.sqrt(np.max(np.einsum('ij,ij->i', rel, rel))))

    def lateral(self, base: Pose, state: Floats, arm: float) -> Pose:
        """`base` slid by state[0] a + state[1] b and spun by state[2] / arm about the push."""
        u, v, w = np.asarray(state, dtype=np.float64) * self._free
        centre = base[:3, :3] @ self._centroid + base[:3, 3]
        rot = Rotation.from_rotvec((w / arm) * self.push).as_matrix()
        out = np.eye(4)
        out[:3, :3] = rot @ base[:3, :3]
        out[:3, 3] = rot @ (base[:3, 3] - centre) + centre + u * self._a + v * self._b
        return out

    def _along(self, pose: Pose, t: float) -> Pose:
        out = pose.copy()
        out[:3, 3] += t * self.push
        return out

    def travel(self, pose: Pose) -> float:
        """Signed distance along the push from `pose` to first contact (m, to the tolerance).

        Positive: `pose` is free and may advance that far; negative: it overlaps and must
        retreat that far to be free. +inf: no contact within the travel limit.
        """
        tuning = self.tuning
        res = self.resolution_m
        step, cap = tuning.bracket_step * res, tuning.bracket_cap * res   # cap: no tunnelling
        if not self.collides(pose):
            free = 0.0
            while True:
                probe = free + step
                if probe > self._limit:
                    return math.inf
                if self.collides(self._along(pose, probe)):
                    hit = probe
                    break
                free, step = probe, min(2.0 * step, cap)
        else:
            hit = 0.0
            while True:
                probe = hit - step
                if -probe > self._limit:
                    return -math.inf
                if not self.collides(self._along(pose, probe)):
                    free = probe
                    break
                hit, step = probe, 2.0 * step
        while hit - free > self.tolerance_m:
            mid = 0.5 * (free + hit)
            if self.collides(self._along(pose, mid)):
                hit = mid
            else:
                free = mid
        return 0.5 * (free + hit)

    def measure(self, pose: Pose) -> tuple[float, float]:
        """The objective at the lateral pose `pose` and its travel (m): the travel itself
        without a load; with one, l . c - E / F at the contact pose. inf: no contact."""
        travel = self.travel(pose)
        if self.load is None or not math.isfinite(travel):
            return travel, travel
        contact = self._along(pose, travel)
        centre = contact[:3, :3] @ self._centroid + contact[:3, 3]
        work = float(self.push @ centre) if self.load.toward is None \
            else -float(np.linalg.norm(self.load.toward - centre))
        return work - self.load.energy(contact) / self.load.load_n, travel

    # ---- the climb ----------------------------------------------------------------
    def judge(self, pose: Pose, envelope: Envelope | None = None,
              max_evaluations: int | None = None) -> Verdict:
        """Climb the travel from `pose` and report what it gains (see the module).

        Args:
            pose: (4, 4) fixed_from_moving, the pose to judge (m).
            envelope: bounds the climb when given (states outside it are refused).
            max_evaluations: travel evaluations over all restarts (default: the tuning's).
        Raises:
            NoContactError: the pose has no contact along the push: nothing to judge.
        """
        pose = np.asarray(pose, dtype=np.float64)
        tuning = self.tuning
        if max_evaluations is None:
            max_evaluations = tuning.max_evaluations
        arm = max(self._arm(pose), self.resolution_m)
        queries_before = self.queries
        res = self.resolution_m
        base_value, base_travel = self.measure(pose)
        if not math.isfinite(base_travel):
            raise NoContactError(self._limit)      # nothing to judge
        evaluations = 1
        best = _Best(base_value, np.zeros(3), base_travel)

        def value(z: Floats) -> float:
            nonlocal evaluations
            state = np.zeros(3)
            state[self._dims] = np.asarray(z, dtype=np.float64) * res
            cand = self.lateral(pose, state, arm)
            if envelope is not None and not self._inside(cand, envelope):
                return _REFUSED
            evaluations += 1
            v, t = self.measure(cand)
            if t == math.inf:
                v = _OFF
            if v > best.value:
                best.value, best.state, best.travel = v, state, t
            return -v

        start = np.zeros(len(self._dims))
        while evaluations < max_evaluations:
            before = best.value
            simplex = np.vstack([start, start + tuning.simplex * np.eye(len(start))])
            minimize(value, start, method='Nelder-Mead',
                     options={'initial_simplex': simplex, 'xatol': tuning.xatol,
                              'fatol': tuning.fatol,
                              'maxfev': max_evaluations - evaluations})
            if best.value >= _OFF or best.value - before <= tuning.restart_gain * res:
                break
            start = best.state[self._dims] / res
        state = best.state
        moved = self.lateral(pose, state, arm)
        gain = best.value - base_value
        if best.value >= _OFF:
            gain = math.inf
        slide = float(np.hypot(state[0] * self._free[0], state[1]))
        return Verdict(gain, slide, float(state[2] / arm), evaluations,
                       self.queries - queries_before,
                       self._along(moved, best.travel if math.isfinite(gain) else 0.0))

    def extent(self, pose: Pose, top: float | None = None, envelope: Envelope | None = None,
               cap_m: float = 0.02, cap_rad: float = math.radians(45.0)) -> Extent:
        """How far `pose` can move (slides, spins and the pairs of them, each way) while the
        objective stays within one resolution of `top` (default: its value at `pose`): along
        each direction the move doubles from one resolution while it stays within, then
        the edge is bisected to a tenth; up to `cap_m` of slide and `cap_rad` of spin."""
        pose = np.asarray(pose, dtype=np.float64)
        arm = max(self._arm(pose), self.resolution_m)
        res = self.resolution_m
        here = self.measure(pose)[0]
        floor = (here if top is None else max(top, here)) - res
        evaluations = 0

        def within(state: Floats) -> bool:
            nonlocal evaluations
            cand = self.lateral(pose, state, arm)
            if envelope is not None and not self._inside(cand, envelope):
                return False
            evaluations += 1
            value, travel = self.measure(cand)
            return math.isfinite(travel) and value >= floor

        axes = [np.eye(3)[k] for k in self._dims]
        directions = [s * a for a in axes for s in (1.0, -1.0)]
        for i, a in enumerate(axes):
            for b in axes[i + 1:]:
                directions += [(sa * a + sb * b) / math.sqrt(2.0)
                               for sa in (1.0, -1.0) for sb in (1.0, -1.0)]
        slide = spin = 0.0
        for d in directions:
            reach = float(min(cap_m / max(math.hypot(d[0], d[1]), 1e-12),
                              cap_rad * arm / max(abs(d[2]), 1e-12)))
            inside, step = 0.0, res
            while step < reach and within(step * d):
                inside, step = step, 2.0 * step
            if step >= reach and within(reach * d):
                inside = reach
            else:
                out = min(step, reach)
                while out - inside > 0.1 * max(inside, res):
                    mid = 0.5 * (inside + out)
                    if within(mid * d):
                        inside = mid
                    else:
                        out = mid
            slide = max(slide, inside * math.hypot(d[0] * self._free[0], d[1]))
            spin = max(spin, inside * abs(d[2]) / arm)
        return Extent(slide, spin, evaluations)

    def _inside(self, pose: Pose, envelope: Envelope) -> bool:
        anchor = envelope.anchor
        d = (pose[:3, :3] @ self._centroid + pose[:3, 3]
             - anchor[:3, :3] @ self._centroid - anchor[:3, 3])
        if np.linalg.norm(d - (d @ self.push) * self.push) > envelope.max_slide_m:
            return False
        rel = pose[:3, :3] @ anchor[:3, :3].T
        axis_part = 0.5 * np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0],
                                    rel[1, 0] - rel[0, 1]]) @ self.push
        spin = math.atan2(axis_part, 0.5 * (np.trace(rel) - 1.0))
        return abs(spin) <= envelope.max_spin_rad

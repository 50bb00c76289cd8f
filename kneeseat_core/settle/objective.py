"""What the default method climbs: the travel, or the load's work less the soft tissue's energy.

Without soft tissue (`Objective.work` False) rest is a local maximum of the travel s along
the push Δ over the lateral state (slides across Δ, spin about it): the patent's own
measure. With ligaments acting on the body (`work`, a load F on the push and a `Tissue`),
rest is a local maximum of the load's work less the elastic energy E of the ligaments at
the contact pose, per unit load:

    W / F = l . c(pose) - E(pose) / F        (m; c the body's centroid)

for a load along a fixed line l, with the body in contact along Δ as before; for a load
along the push (l = Δ, a tibia) that is the travel less E / F. A load that pulls toward a
point o (a patella's quadriceps toward the femur, its tendon in E holding it against the
pull) does the work -|o - c|, and l is the unit vector from c to o. A lateral move x over
(slide e1, slide e2, arc about the centroid) that changes the travel by dt changes it by

    (l . Δ - dE/ds / F) dt + (l_lateral - dE/dx / F) . x

to first order (press and drive), where dE/ds is the energy's rate along the push and
dE/dx its rate over the lateral state (the spin's, the moment of the fibres' pull about the
axis through the centroid along the push, per arm of arc). The press is how hard the body
is pressed into contact per unit load: where it is not positive the ligaments pull the
body off the fixed body against its load, and the settle says so (`Status.PULLED`).

`Objective` says which of these a climb maximises and with what; the arithmetic (the value
at a pose, the lift each move needs, the first-order terms) is the planner's, compiled
(`kneeseat_core.settle.planner`): a climb asks for it at every pose it weighs, and the
fibres' sums cost a microsecond there against tens in numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneeseat_core.ligaments import Tissue
from kneeseat_core.params import SettleParams
from kneeseat_core.typed import Floats

__all__ = ['Objective', 'objective_for']


@dataclass(frozen=True, slots=True, eq=False)
class Objective:
    """What a climb maximises (module docstring): the load's work less the tissue's energy
    per unit load (`work`), or the travel alone."""

    work: bool                   # the load's work less the tissue's energy (else the travel)
    load_n: float                # N, the load the work and energy are taken per unit of
    toward: Floats | None        # (3,) the point the load pulls toward, or None: the push
    tissue: Tissue | None        # the ligaments acting on the body, if any

    @property
    def gain(self) -> str:
        """What a gain is measured in, for the settle's reasons."""
        return ("in the load's work less the ligaments' energy (per unit load)" if self.work
                else 'along the push')

    @property
    def precision(self) -> float:
        """The share of the resolution the objective is climbed to: a smooth energy's
        maximum lies in a valley the travel's resolution would leave a millimetre wide."""
        return 0.1 if self.work else 1.0

    def pulled_off(self, pull: float, load: float) -> str:
        """Why the body leaves contact (the end's reason), given the ligaments' pull along
        -Δ and the load's along Δ, per unit load."""
        return (f'pulled off: its ligaments pull it away from the fixed body with '
                f'{pull * self.load_n:.0f} N along the push, more than the load presses it '
                f'on ({load * self.load_n:.0f} N along the push); no rest in contact at this '
                'attitude')


def objective_for(params: SettleParams, tissue: Tissue | None) -> Objective:
    """The travel when no tissue acts and the load (if any) is along the push, else the
    load's work less the tissue's energy."""
    if tissue is None and params.load_toward is None:
        return Objective(False, 1.0, None, None)
    toward = None if params.load_toward is None \
        else np.asarray(params.load_toward, dtype=np.float64)
    return Objective(True, float(params.load_n if params.load_n is not None else 1.0), toward,
                     tissue)

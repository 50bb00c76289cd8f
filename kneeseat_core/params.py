"""What one settle is asked to do: the parameters of a settle, SI units.

Shared by everything that poses a settle problem (a knee config, the sweep, `kneeseat
settle`) and by the settle itself (`kneeseat_core.settle`), so that describing a problem
never needs the settle's code: a knee config and the referee read these without loading it.
"""
from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Literal

import numpy as np

from .errors import SettleError
from .geometry import unit

__all__ = ['Method', 'SettleParams']

Method = Literal['default', 'patent']


@dataclass(frozen=True, slots=True)
class SettleParams:
    """Knobs of one settle, SI units; defaults are the patent's numbers for a knee."""

    push: tuple[float, float, float] = (0.0, -1.0, 0.0)   # Δ, fixed frame (normalised)
    step_m: float = 1e-3                    # translation modeling step
    resolution_m: float = 1e-4              # T2, exact-contact tolerance
    rotation_step_rad: float | None = None  # None: arc of one step at the farthest vertex
    rotation_resolution_rad: float | None = None  # None: method's own rule (see settle.py)
    max_iterations: int = 500
    method: Method = 'default'
    # A slide direction (fixed frame) the body may not translate along, e.g. a patella
    # held at its height along the groove by its tendon; None: the whole plane is free.
    locked_slide: tuple[float, float, float] | None = None
    # The search envelope, measured from the settle's anchor pose (its start unless given):
    # how far the body may slide across the push and spin about it. A rest beyond it is
    # "not converged"; with `envelope_holds` the envelope is a constraint instead (soft
    # tissue standing in) and a rest on its boundary is reported as constrained.
    max_slide_m: float = 0.02
    max_spin_rad: float = math.radians(45.0)
    envelope_holds: bool = False
    # The load (N) when soft tissue acts on the body (the settle's `tissue`): rest is then
    # a local maximum of the load's work minus the tissue's energy, per unit load (m).
    # None: geometry alone (the travel). The load acts along the push unless `load_toward`
    # (a point, fixed frame, m) is given: then it pulls the body's centroid toward that
    # point, as a muscle toward its origin (a patella's quadriceps toward the femur, its
    # tendon and retinacula holding it in the trochlea). The push is then only the
    # direction contact is sought along.
    load_n: float | None = None
    load_toward: tuple[float, float, float] | None = None

    def check(self) -> None:
        """Raise SettleError naming the first invalid parameter."""
        unit(np.asarray(self.push, dtype=float), 'push direction')
        for name in ('step_m', 'resolution_m', 'max_slide_m', 'max_spin_rad'):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise SettleError(f'{name}={value} must be a positive number')
        if self.resolution_m > self.step_m:
            raise SettleError(f'resolution {self.resolution_m} m is coarser than the step '
                              f'{self.step_m} m; give a resolution below the step')
        for name in ('rotation_step_rad', 'rotation_resolution_rad'):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and 0 < value < math.pi):
                raise SettleError(f'{name}={value} must be between 0 and pi rad')
        if self.max_spin_rad > math.pi:
            raise SettleError(f'max_spin_rad={self.max_spin_rad} must be at most pi rad')
        if self.max_iterations < 1:
            raise SettleError(f'max_iterations={self.max_iterations} must be at least 1')
        if self.locked_slide is not None:
            lock = unit(np.asarray(self.locked_slide, dtype=float), 'locked slide')
            push = unit(np.asarray(self.push, dtype=float), 'push direction')
            if float(np.linalg.norm(lock - (lock @ push) * push)) < 0.1:
                raise SettleError('the locked slide direction is (nearly) parallel to the push; '
                                  'give a direction across the push')
        if self.load_n is not None and not (math.isfinite(self.load_n) and self.load_n > 0):
            raise SettleError(f'load_n={self.load_n} must be a positive number of newtons')
        if self.load_toward is not None and \
                not np.all(np.isfinite(np.asarray(self.load_toward, dtype=float))):
            raise SettleError(f'load_toward={self.load_toward} must be three finite numbers')
        if self.method not in ('default', 'patent'):
            raise SettleError(f"method '{self.method}' is unknown; use default or patent")

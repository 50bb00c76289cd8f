"""Elementary functions of arrays, computed by the C library element by element.

numpy's vectorised sin, cos, exp, log and pow choose their SIMD code by CPU (AVX-512 or
not) and differ in the last bit between machines. The embedded default knee's meshes must
not: tables record their SHA-256, so a table built on one machine must find the same
meshes on another. Its solids use these instead: the C library's functions give the same
bits on every x86-64 CPU of the last decade (glibc picks one code path for every CPU with
FMA) with the same C library. A compiled loop (`_libm.cpp`) calls them element by element,
the very calls Python's `math` makes, so each element's bits are `math.f(x)`'s: about
0.02 us an element, where going through `math` from Python cost 0.5 us. Square roots,
products and sums are correctly rounded in IEEE arithmetic and need nothing of this.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from kneeseat_core import _libm
from kneeseat_core.typed import Floats

__all__ = ['sin', 'cos', 'exp', 'log', 'log1p', 'power', 'softplus']


def _apply(name: str, x: ArrayLike, p: float = 0.0) -> Floats:
    """The C library's `name` of every element of `x` (same shape, float64); ValueError
    where a finite element has no finite value (where `math.name` raises)."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    out: Floats = np.frombuffer(_libm.elementwise(name, a, p), dtype=np.float64)
    return out.reshape(a.shape)


def _elementwise(name: str) -> Callable[[ArrayLike], Floats]:
    def apply(x: ArrayLike) -> Floats:
        return _apply(name, x)
    apply.__doc__ = f'`math.{name}` of every element (same shape, float64).'
    return apply


sin = _elementwise('sin')
cos = _elementwise('cos')
exp = _elementwise('exp')
log = _elementwise('log')
log1p = _elementwise('log1p')


def power(x: ArrayLike, p: float) -> Floats:
    """`x ** p` of every element by the C library's pow (x >= 0 where p is not integral)."""
    return _apply('pow', x, float(p))


def softplus(x: ArrayLike) -> Floats:
    """log(1 + exp(x)) of every element, without overflow (numpy's logaddexp(0, x))."""
    a = np.asarray(x, dtype=np.float64)
    big = np.maximum(a, 0.0)
    return big + log1p(exp(-np.abs(a)))

"""Elementary functions of arrays, computed by the C library element by element.

numpy's vectorised sin, cos, exp, log and pow choose their SIMD code by CPU (AVX-512 or
not) and differ in the last bit between machines. The embedded default knee's meshes must
not: tables record their SHA-256, so a table built on one machine must find the same
meshes on another. Its solids use these instead: the C library's functions give the same
bits on every x86-64 CPU of the last decade (glibc picks one code path for every CPU with
FMA) with the same C library. They cost about 0.5 us an element, once per process. Square
roots, products and sums are correctly rounded in IEEE arithmetic and need nothing of
this.
"""
from __future__ import annotations

from collections.abc import Callable
import math

import numpy as np
from numpy.typing import ArrayLike

from kneeseat_core.typed import Floats

__all__ = ['sin', 'cos', 'exp', 'log', 'log1p', 'power', 'softplus']


def _elementwise(fn: Callable[[float], float]) -> Callable[[ArrayLike], Floats]:
    def apply(x: ArrayLike) -> Floats:
        a = np.asarray(x, dtype=np.float64)
        out = np.fromiter(map(fn, a.ravel().tolist()), dtype=np.float64, count=a.size)
        return out.reshape(a.shape)
    apply.__doc__ = f'`math.{fn.__name__}` of every element (same shape, float64).'
    return apply


sin = _elementwise(math.sin)
cos = _elementwise(math.cos)
exp = _elementwise(math.exp)
log = _elementwise(math.log)
log1p = _elementwise(math.log1p)


def power(x: ArrayLike, p: float) -> Floats:
    """`x ** p` of every element by the C library's pow (x >= 0 where p is not integral)."""
    a = np.asarray(x, dtype=np.float64)
    out = np.fromiter((math.pow(v, p) for v in a.ravel().tolist()), dtype=np.float64,
                      count=a.size)
    return out.reshape(a.shape)


def softplus(x: ArrayLike) -> Floats:
    """log(1 + exp(x)) of every element, without overflow (numpy's logaddexp(0, x))."""
    a = np.asarray(x, dtype=np.float64)
    big = np.maximum(a, 0.0)
    return big + log1p(exp(-np.abs(a)))

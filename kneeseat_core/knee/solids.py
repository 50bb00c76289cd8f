"""Smooth closed solids from height fields, the building blocks of the embedded knee.

`polar_solid` makes a closed, consistently wound triangle mesh between two height fields
over the unit disc (a polar grid, a fan at each pole and a rim wall); `smooth_max`,
`soft_cap`, `smoothstep` and `superellipse_scale` blend and round the surfaces smoothly,
so that the meshes made from them have no creases a settle would catch on. Their
transcendental functions are `libm`'s, so that the bytes are the same on every machine.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from kneeseat_core import libm
from kneeseat_core.typed import Floats, Ints

__all__ = ['HeightField', 'polar_solid', 'smooth_max', 'soft_cap', 'smoothstep',
           'superellipse_scale']


def smooth_max(parts: list[Floats], k: float) -> Floats:
    """Log-sum-exp maximum of arrays that broadcast together: at most ln(n)/k above the max
    (k in 1/unit of the arrays)."""
    stack = np.stack(np.broadcast_arrays(*parts))
    top = stack.max(axis=0)
    out: Floats = top + libm.log(libm.exp(k * (stack - top)).sum(axis=0)) / k
    return out


def soft_cap(value: Floats, cap: Floats | float, k: float) -> Floats:
    """Smooth minimum of `value` and `cap`: -log(exp(-k value) + exp(-k cap)) / k."""
    return cap - libm.softplus(k * (cap - value)) / k


def smoothstep(t: Floats) -> Floats:
    """C1 step from 0 (t <= 0) to 1 (t >= 1)."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def superellipse_scale(u: Floats, power: float = 4.0) -> Floats:
    """(1 - |u|^p)^(1/p) for |u| < 1, else 0: flat in the middle, rounded at the ends."""
    base = np.clip(1.0 - libm.power(np.abs(u), power), 0.0, None)
    return libm.power(base, 1.0 / power)


HeightField = Callable[[Floats, Floats], Floats]


def polar_solid(top_r: Floats, bottom_r: Floats, n_ang: int, top_h: HeightField,
                bottom_h: HeightField) -> tuple[Floats, Floats, Ints]:
    """A solid between two height fields over the unit disc (polar grid), plus a rim wall.

    Args:
        top_r: (nt,) ring radii in (0, 1], ascending, last = 1 (rim).
        bottom_r: (nb,) the same for the bottom surface.
        n_ang: points per ring.
        top_h, bottom_h: map (r, angle) arrays to heights; top must exceed bottom.
    Returns:
        Unit-disc coordinates (n, 2), heights (n,) and faces (m, 3) of the closed solid.
    """
    ang = np.linspace(0.0, 2.0 * np.pi, n_ang, endpoint=False)
    uv_parts, h_parts, faces, rims = [], [], [], []
    offset = 0
    for rings, height, sign in ((top_r, top_h, 1), (bottom_r, bottom_h, -1)):
        rr, aa = np.meshgrid(rings, ang, indexing='ij')             # (n_rings, n_ang)
        pole_uv = np.zeros((1, 2))
        uv = np.vstack([pole_uv, np.stack([rr * libm.cos(aa), rr * libm.sin(aa)], -1)
                        .reshape(-1, 2)])
        h = np.concatenate([height(np.zeros(1), np.zeros(1)), height(rr, aa).reshape(-1)])
        idx = offset + 1 + np.arange(rr.size).reshape(rr.shape)
        j = np.arange(n_ang)
        fan = np.stack([np.full(n_ang, offset), idx[0, j], idx[0, (j + 1) % n_ang]], -1)
        a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
        c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
        quads = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3),
                                np.stack([a, d, b], -1).reshape(-1, 3)])
        part = np.concatenate([fan, quads])
        faces.append(part if sign > 0 else part[:, ::-1])
        uv_parts.append(uv)
        h_parts.append(h)
        offset += len(uv)
        rims.append(idx[-1])
    a, b = rims[0], np.roll(rims[0], -1)          # top rim
    c, d = rims[1], np.roll(rims[1], -1)          # bottom rim, below it
    faces.append(np.concatenate([np.stack([a, c, d], -1), np.stack([a, d, b], -1)]))
    return np.vstack(uv_parts), np.concatenate(h_parts), np.concatenate(faces).astype(np.int64)

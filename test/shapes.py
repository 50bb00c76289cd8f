"""Watertight test solids with analytic rest poses (metres, surface facing +Y)."""
from __future__ import annotations

from typing import Callable

import numpy as np
import trimesh

Surface = Callable[[np.ndarray, np.ndarray], np.ndarray]


def heightfield_solid(surface: Surface, half_x: float, half_z: float, n: int = 120,
                      bottom: float = -0.03) -> trimesh.Trimesh:
    """A closed solid whose top is y = surface(x, z) on [-half_x, half_x] x [-half_z, half_z].

    Top and bottom are n x n grids; the four sides are stitched between them, so the
    result is watertight with outward normals.
    """
    xs = np.linspace(-half_x, half_x, n)
    zs = np.linspace(-half_z, half_z, n)
    gx, gz = np.meshgrid(xs, zs, indexing='ij')
    top = np.stack([gx, surface(gx, gz), gz], axis=-1).reshape(-1, 3)
    bot = np.stack([gx, np.full_like(gx, bottom), gz], axis=-1).reshape(-1, 3)
    vertices = np.concatenate([top, bot])
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    quads_top = np.stack([a, d, c, b], -1).reshape(-1, 4)       # normal +Y
    faces = [quads_top[:, [0, 1, 2]], quads_top[:, [0, 2, 3]]]
    off = n * n
    faces += [quads_top[:, [0, 2, 1]] + off, quads_top[:, [0, 3, 2]] + off]  # normal -Y
    ring = np.concatenate([idx[:, 0], idx[-1, 1:], idx[-2::-1, -1], idx[0, -2:0:-1]])
    for i in range(len(ring)):
        p, q = ring[i], ring[(i + 1) % len(ring)]
        faces.append(np.array([[p, q, p + off], [q, q + off, p + off]]))
    mesh = trimesh.Trimesh(vertices, np.concatenate(faces), process=True)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    return mesh


def sphere(radius: float, subdivisions: int = 5) -> trimesh.Trimesh:
    """Icosphere centred on the origin."""
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def bowl(radius: float, depth: float, half: float, n: int = 160) -> trimesh.Trimesh:
    """A block with a spherical dish of `radius`, lowest point at y = -depth, origin above."""
    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        r2 = np.minimum(x * x + z * z, radius * radius)
        dish = -depth + radius - np.sqrt(radius * radius - r2)
        return np.minimum(dish, 0.0)
    return heightfield_solid(surface, half, half, n, bottom=-depth - 0.02)


def cone(slope: float, depth: float, half: float, n: int = 161) -> trimesh.Trimesh:
    """A block with a conical pit (wall slope dy/dr), apex at y = -depth on the Y axis."""
    return heightfield_solid(lambda x, z: np.minimum(-depth + slope * np.hypot(x, z), 0.0),
                             half, half, n, bottom=-depth - 0.02)


def v_groove(slope: float, depth: float, half: float, n: int = 161) -> trimesh.Trimesh:
    """Two inclined planes meeting along the Z axis at y = -depth (FIG. 13's groove)."""
    return heightfield_solid(lambda x, z: np.minimum(-depth + slope * np.abs(x), 0.0),
                             half, half, n, bottom=-depth - 0.02)


def key(length: float, width: float, height: float) -> trimesh.Trimesh:
    """An elongated box, long along X, centred on the origin."""
    return trimesh.creation.box((length, height, width))


def key_pocket(length: float, width: float, wall_slope: float, depth: float,
               half: float, n: int = 181) -> trimesh.Trimesh:
    """A pit whose flat floor is a length x width rectangle (long along X) at y = -depth,
    with walls rising at `wall_slope` on every side."""
    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        out_x = np.maximum(np.abs(x) - length / 2, 0.0)
        out_z = np.maximum(np.abs(z) - width / 2, 0.0)
        return np.minimum(-depth + wall_slope * np.maximum(out_x, out_z), 0.0)
    return heightfield_solid(surface, half, half, n, bottom=-depth - 0.02)


def dumbbell(radius: float, separation: float) -> trimesh.Trimesh:
    """Two spheres joined rigidly (centres at x = ±separation/2) by a thin bar."""
    left = sphere(radius)
    left.apply_translation((-separation / 2, 0, 0))
    right = sphere(radius)
    right.apply_translation((separation / 2, 0, 0))
    bar = trimesh.creation.cylinder(radius=radius / 4, height=separation,
                                    transform=trimesh.transformations.rotation_matrix(
                                        np.pi / 2, (0, 1, 0)))
    return trimesh.util.concatenate([left, right, bar])


def two_bowls(radius: float, depths: tuple[float, float], separation: float,
              half_x: float, half_z: float, n: int = 200) -> trimesh.Trimesh:
    """Two spherical dishes centred at x = ±separation/2 with different depths."""
    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        out = np.zeros_like(x)
        for cx, depth in zip((-separation / 2, separation / 2), depths):
            r2 = np.minimum((x - cx) ** 2 + z * z, radius * radius)
            out = np.minimum(out, -depth + radius - np.sqrt(radius * radius - r2))
        return out
    return heightfield_solid(surface, half_x, half_z, n, bottom=-max(depths) - 0.02)


def dumbbell_unequal(radii: tuple[float, float], separation: float,
                     bar_radius: float) -> trimesh.Trimesh:
    """Two spheres of different radii joined rigidly (centres at x = -/+ separation/2)."""
    parts = []
    for radius, x in zip(radii, (-separation / 2, separation / 2)):
        ball = sphere(radius)
        ball.apply_translation((x, 0, 0))
        parts.append(ball)
    parts.append(trimesh.creation.cylinder(
        radius=bar_radius, height=separation,
        transform=trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0))))
    return trimesh.util.concatenate(parts)


def bowls(radii: tuple[float, float], depths: tuple[float, float], separation: float,
          half_x: float, half_z: float, n: int = 241) -> trimesh.Trimesh:
    """Two spherical dishes of their own radius and depth at x = -/+ separation/2."""
    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        out = np.zeros_like(x)
        for cx, radius, depth in zip((-separation / 2, separation / 2), radii, depths):
            r2 = np.minimum((x - cx) ** 2 + z * z, radius * radius)
            out = np.minimum(out, -depth + radius - np.sqrt(radius * radius - r2))
        return out
    return heightfield_solid(surface, half_x, half_z, n, bottom=-max(depths) - 0.02)


def rounded_box(half: tuple[float, float, float], corner: float) -> trimesh.Trimesh:
    """A box of half-sizes `half` (x, y, z) whose edges and corners are rounded by `corner`:
    the convex hull of eight spheres of that radius inset at the corners."""
    inner = np.asarray(half, dtype=float) - corner
    ball = trimesh.creation.icosphere(subdivisions=4, radius=corner)
    points = [ball.vertices + inner * np.array(signs)
              for signs in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3)]
    return trimesh.convex.convex_hull(np.concatenate(points))


def tapered_pocket(half: tuple[float, float], slope: float, depth: float, extent: float,
                   n: int = 241) -> trimesh.Trimesh:
    """A pit with a flat floor of half-sizes `half` (x, z) at y = -depth whose four walls
    rise at `slope` (dy per unit distance outwards) up to the top at y = 0."""
    def surface(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        out_x = np.maximum(np.abs(x) - half[0], 0.0)
        out_z = np.maximum(np.abs(z) - half[1], 0.0)
        return np.minimum(-depth + slope * np.maximum(out_x, out_z), 0.0)
    return heightfield_solid(surface, extent, extent, n, bottom=-depth - 0.02)

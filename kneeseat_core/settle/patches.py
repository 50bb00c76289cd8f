"""Contact patches (the settle's D7): where the surfaces cross, grouped as the body feels them.

The contacts python-fcl reports are the points where a reference triangle and a moving
triangle cross, each with the reference's normal interpolated there from its vertex
normals (barycentric weights). Contacts on connected reference triangles form one patch,
split in two across its widest normal spread while its normals spread more than
`PATCH_SPREAD_RAD` (a crease; at most 8 parts), and each patch counts once: its mean
point and mean normal stand for the one contact point a deeper look would find. So a
conforming patch that straddles the rest, with hundreds of contacts on one side, does not
outweigh a single contact on the other.
"""
from __future__ import annotations

import math

import numpy as np

from kneeseat_core.geometry import TOL
from kneeseat_core.meshes import RigidBody
from kneeseat_core.typed import Floats, Ints

__all__ = ['PATCH_SPREAD_RAD', 'contact_patches']


def contact_patches(body: RigidBody, ids: Ints, points: Floats) -> tuple[Floats, Floats]:
    """The patches of contacts on reference triangles `ids` (k,) at `points` (k, 3).

    Returns:
        (m, 3) mean points and (m, 3) unit mean normals, one row per patch (m = 0 without
        contacts).
    """
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    normals = _interpolated_normals(body, ids, points)
    labels = _components(body, ids)
    out_p, out_n = [], []
    for label in range(int(labels.max()) + 1):
        sel = labels == label
        for pts, nrm in _split(points[sel], normals[sel]):
            out_p.append(pts)
            out_n.append(nrm)
    return np.array(out_p), np.array(out_n)


# Normals within a patch that spread more than this from its mean split it (a crease).
PATCH_SPREAD_RAD = math.radians(12.0)


def _interpolated_normals(body: RigidBody, ids: Ints, points: Floats) -> Floats:
    """Vertex normals of triangles `ids` interpolated (barycentric) at `points` (k, 3)."""
    tri = body.faces[ids]
    a, b, c = (body.vertices[tri[:, i]] for i in range(3))
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (np.einsum('ij,ij->i', x, y) for x, y in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum('ij,ij->i', v2, v0), np.einsum('ij,ij->i', v2, v1)
    denom = d00 * d11 - d01 * d01
    denom = np.where(np.abs(denom) > TOL.degenerate, denom, 1.0)
    wb = (d11 * d20 - d01 * d21) / denom
    wc = (d00 * d21 - d01 * d20) / denom
    w = np.clip(np.stack([1.0 - wb - wc, wb, wc], axis=1), 0.0, None)
    w /= np.maximum(w.sum(axis=1, keepdims=True), TOL.zero_length)
    vn = body.vertex_normals
    n = w[:, 0:1] * vn[tri[:, 0]] + w[:, 1:2] * vn[tri[:, 1]] + w[:, 2:3] * vn[tri[:, 2]]
    length = np.linalg.norm(n, axis=1, keepdims=True)
    bad = length[:, 0] < TOL.normal_length
    n[bad] = body.normals[ids[bad]]
    length[bad] = 1.0
    out: Floats = n / length
    return out


def _components(body: RigidBody, ids: Ints) -> Ints:
    """Label (k,) of the connected set of reference triangles each contact lies on."""
    unique, inverse = np.unique(ids, return_inverse=True)
    indptr, indices = body.adjacency
    starts, ends = indptr[unique], indptr[unique + 1]
    counts = ends - starts
    rows = np.repeat(np.arange(len(unique)), counts)
    flat = np.repeat(starts - np.concatenate([[0], np.cumsum(counts)[:-1]]), counts) \
        + np.arange(int(counts.sum()))
    cols = np.searchsorted(unique, indices[flat])
    cols = np.minimum(cols, len(unique) - 1)
    keep = unique[cols] == indices[flat]
    rows, cols = rows[keep], cols[keep]
    # label propagation: every triangle takes the smallest label among its neighbours
    # until nothing changes (a few rounds: contact patches are small)
    labels = np.arange(len(unique))
    while True:
        smaller = np.minimum(labels[rows], labels[cols])
        updated = labels.copy()
        np.minimum.at(updated, rows, smaller)
        np.minimum.at(updated, cols, smaller)
        updated = updated[updated]
        if np.array_equal(updated, labels):
            break
        labels = updated
    return np.unique(labels, return_inverse=True)[1][inverse]


def _split(points: Floats, normals: Floats, depth: int = 0) -> list[tuple[Floats, Floats]]:
    """A patch as one (mean point, mean normal), or split in two across its widest normal
    spread while the normals spread more than PATCH_SPREAD_RAD (at most 8 parts)."""
    mean = normals.sum(axis=0)
    mean /= max(float(np.linalg.norm(mean)), TOL.zero_length)
    if len(points) == 1 or depth >= 3 or \
            float(np.min(normals @ mean)) >= math.cos(PATCH_SPREAD_RAD):
        return [(points.mean(axis=0), mean)]
    deviation = normals - np.outer(normals @ mean, mean)
    _, _, vt = np.linalg.svd(deviation, full_matrices=False)
    side = deviation @ vt[0] > 0.0
    if side.all() or not side.any():
        return [(points.mean(axis=0), mean)]
    return (_split(points[side], normals[side], depth + 1)
            + _split(points[~side], normals[~side], depth + 1))

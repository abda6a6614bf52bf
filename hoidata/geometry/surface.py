"""Small triangle-mesh operations shared by the hand and object code. Pure numpy."""

from __future__ import annotations

import numpy as np


def signed_volumes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) signed volume (m^3) of the tetrahedron each face spans with the origin."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


def edge_lengths(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) length of the edge from corner k to corner k+1."""
    p = vertices[faces]
    return np.linalg.norm(p[:, [1, 2, 0]] - p, axis=2)


def split_longest_edges(vertices: np.ndarray, faces: np.ndarray, n_splits: int, frozen=None):
    """Add exactly ``n_splits`` vertices by splitting the longest edge at its midpoint, repeatedly.

    A midpoint split replaces each face on the edge by two coplanar halves, so the surface (and
    watertightness) is unchanged; only the vertex count grows, by one per split. Deterministic:
    ties go to the lowest face/corner index. Edges with both ends in ``frozen`` (vertex ids) are
    never split, e.g. a boundary loop whose length must not change.
    """
    is_frozen = np.zeros(len(vertices) + n_splits, dtype=bool)
    if frozen is not None:
        is_frozen[np.asarray(list(frozen), dtype=np.int64)] = True

    def lengths(face_rows):
        out = edge_lengths(V, face_rows)
        out[is_frozen[face_rows] & is_frozen[face_rows[:, [1, 2, 0]]]] = -1.0
        return out

    n_v, n_f = len(vertices), len(faces)
    V = np.vstack([vertices, np.zeros((n_splits, 3))])
    F = np.vstack([faces, np.zeros((2 * n_splits, 3), dtype=np.int64)])
    L = np.zeros((len(F), 3))
    L[:n_f] = lengths(F[:n_f])
    for _ in range(n_splits):
        fi, k = divmod(int(np.argmax(L[:n_f])), 3)
        a, b = F[fi, k], F[fi, (k + 1) % 3]
        V[n_v] = 0.5 * (V[a] + V[b])
        on_edge = np.flatnonzero((F[:n_f] == a).any(1) & (F[:n_f] == b).any(1))
        for g in on_edge:
            j = next(j for j in range(3) if {F[g, j], F[g, (j + 1) % 3]} == {a, b})
            x, y, z = F[g, j], F[g, (j + 1) % 3], F[g, (j + 2) % 3]
            F[g], F[n_f] = (x, n_v, z), (n_v, y, z)
            L[[g, n_f]] = lengths(F[[g, n_f]])
            n_f += 1
        n_v += 1
    return V[:n_v], F[:n_f]

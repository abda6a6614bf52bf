"""Mesh topology of the hand as pure numpy functions: the wrist opening, its cap, and part labels.

MANO's mesh is open at the wrist (778 vertices, 1538 faces, one boundary loop of 16 edges). Signed
distance and rendering need a closed surface, so the opening is capped with a fan around one extra
vertex placed at the mean of the loop. The cap faces take their winding from the faces next to the
boundary, so the cap is consistent for the left hand as well as the right.
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.surface import signed_volumes

NUM_PARTS = 16  # one part per MANO joint, in MANO's native joint order


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Boundary loops of a triangle mesh, each ordered along the face winding.

    Args:
        faces: (F, 3) int vertex indices.

    Returns:
        A list of (L,) int arrays. For a boundary edge a->b as it appears in its only face, b follows a.

    Raises:
        ValueError: an edge is used by more than two faces or a boundary vertex has several outgoing
            boundary edges (non-manifold boundary).
    """
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    if counts.max(initial=0) > 2:
        raise ValueError("non-manifold mesh: an edge is shared by more than two faces")
    border = directed[counts[inverse.ravel()] == 1]
    successor: dict[int, int] = {}
    for a, b in border:
        if int(a) in successor:
            raise ValueError(f"non-manifold boundary at vertex {int(a)}")
        successor[int(a)] = int(b)
    loops = []
    while successor:
        start = min(successor)
        loop = [start]
        nxt = successor.pop(start)
        while nxt != start:
            loop.append(nxt)
            nxt = successor.pop(nxt)
        loops.append(np.asarray(loop, dtype=np.int64))
    return loops


def wrist_loop(faces: np.ndarray) -> np.ndarray:
    """The single boundary loop of an open hand mesh (the wrist), ordered along the face winding."""
    loops = boundary_loops(faces)
    if len(loops) != 1:
        raise ValueError(f"expected one boundary loop (the wrist opening), found {len(loops)}")
    return loops[0]


def cap_faces(loop: np.ndarray, center_index: int) -> np.ndarray:
    """Fan faces (L, 3) closing a boundary loop around a new vertex `center_index`.

    A boundary edge a->b (in face winding) is traversed b->a by the cap face, which keeps the
    orientation of the closed surface consistent.
    """
    nxt = np.roll(loop, -1)
    return np.stack([nxt, loop, np.full_like(loop, center_index)], axis=1)


def close_faces(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Faces of the closed hand: the original faces, then the wrist cap around vertex `n_vertices`.

    Returns:
        closed_faces: (F + L, 3) and the wrist loop (L,) whose mean gives the extra vertex.
    """
    loop = wrist_loop(faces)
    return np.concatenate([faces, cap_faces(loop, n_vertices)]), loop


def close_vertices(vertices, loop: np.ndarray):
    """Append the wrist-cap centre (mean of the loop) to vertices (..., V, 3) -> (..., V+1, 3).

    Works on numpy arrays and torch tensors alike (the centre is differentiable in torch).
    """
    if isinstance(vertices, np.ndarray):
        return np.concatenate([vertices, vertices[..., loop, :].mean(-2, keepdims=True)], axis=-2)
    import torch  # only reached with torch input

    return torch.cat([vertices, vertices[..., loop, :].mean(-2, keepdim=True)], dim=-2)


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive when faces wind counter-clockwise outward)."""
    return float(signed_volumes(vertices, faces).sum())


def vertex_part_labels(weights: np.ndarray) -> np.ndarray:
    """Hand part of each vertex (V,) int64: the joint with the largest skinning weight (MANO order)."""
    return np.argmax(weights, axis=1).astype(np.int64)


def face_part_labels(faces: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Hand part of each face (F,) int64: the joint with the largest summed weight of its 3 vertices.

    Faces that reference vertices beyond `weights` (the wrist cap centre) get part 0, the wrist.
    """
    padded = np.concatenate([weights, np.eye(weights.shape[1])[:1]], axis=0)
    idx = np.where(faces < len(weights), faces, len(weights))
    return np.argmax(padded[idx].sum(axis=1), axis=1).astype(np.int64)

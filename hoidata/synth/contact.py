"""Physical hand-object checks: signed distance, penetration depth, fcl collision and contact.

All positions are in metres in one shared frame (the object's model frame in the grasp
synthesiser). Meshes are closed and wound outward, so a negative signed distance means "inside".

- :func:`signed_distance` and :func:`penetration_depth` are exact distances from libigl, signed
  by the pseudonormal for the clean object and by the winding number for the posed hand, which
  can fold into itself at bent joints;
- :class:`HandObjectCollision` wraps python-fcl: the object's BVH is built once, hands are
  queried against it (collision, separation distance, rigid translations of one hand mesh), and
  it answers the signed-distance and contact queries of the grasp synthesiser;
- :func:`surface_samples` covers a coarse mesh with points between its vertices, so that
  vertex-based checks do not miss thin object parts.
"""

from __future__ import annotations

import fcl
import igl
import numpy as np
import scipy.sparse

from hoidata.geometry import sdf

CONTACT_DISTANCE = 0.005  # a hand vertex this close to the surface (or inside) counts as a contact


def _points(x) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64).reshape(-1, 3))


def _faces(f) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(f, dtype=np.int64).reshape(-1, 3))


def signed_distance(points, vertices, faces, band: float | None = None, robust: bool = False) -> np.ndarray:
    """Exact signed distance of points to a closed, outward-wound triangle mesh.

    Args:
        points: (N, 3) query points, metres.
        vertices: (V, 3) mesh vertices, metres, same frame as ``points``.
        faces: (F, 3) triangle indices into ``vertices``.
        band: if given (m), only distances within [-band, band] are computed; the others come
            back as NaN, sign unknown. The tree search prunes everything farther, which makes
            near-surface queries several times faster.
        robust: take the sign from the generalised winding number
            (:func:`hoidata.geometry.sdf.signed_distance` with ``watertight=False``) instead of the
            pseudonormal; ``band`` is then ignored. The pseudonormal is exact and faster for a clean
            watertight mesh, but a posed hand can fold into itself at a strongly bent joint, and
            there it calls outside points inside.

    Returns:
        (N,) float64 metres: positive outside, negative inside.
    """
    points = _points(points)
    if len(points) == 0:
        return np.zeros(0)
    if robust or band is None:
        # libigl's winding-number sign modes scale the distance by (1 - 2|w|); the shared function
        # takes the unsigned distance and the winding-number sign separately, so depths stay exact.
        return sdf.signed_distance(points, _points(vertices), _faces(faces), watertight=not robust)[0]
    sign = igl.SignedDistanceType.SIGNED_DISTANCE_TYPE_PSEUDONORMAL
    return igl.signed_distance(points, _points(vertices), _faces(faces), sign,
                               lower_bound=-float(band), upper_bound=float(band))[0]


def object_in_hand_depth(obj_vertices, hand_vertices, hand_faces) -> float:
    """How deep (m, >= 0) the deepest object vertex lies inside a closed hand mesh.

    Catches thin object parts (a mug rim, a handle) that pass between the hand's vertices. The
    sign comes from the winding number, which stays right where a posed hand folds into itself
    at a strongly bent joint (the pseudonormal calls points near such folds inside).

    Args:
        obj_vertices: (V, 3) object vertices, metres.
        hand_vertices: (N, 3) closed hand vertices (MANO: ``mano.close(vertices)``, (779, 3)).
        hand_faces: (H, 3) closed, outward-wound hand triangles (MANO: ``mano.closed_faces``).
    """
    obj_vertices, hand_vertices = _points(obj_vertices), _points(hand_vertices)
    # Only object vertices inside the hand's bounding box can be inside the hand.
    near = np.all((obj_vertices >= hand_vertices.min(0)) & (obj_vertices <= hand_vertices.max(0)), axis=1)
    inside = signed_distance(obj_vertices[near], hand_vertices, hand_faces, robust=True)
    return max(0.0, -float(inside.min(initial=np.inf)))


def penetration_depth(hand_vertices, obj_vertices, obj_faces, hand_faces=None) -> float:
    """Deepest interpenetration between a hand and an object, metres (0 when they only touch).

    Two one-sided checks, and the larger wins:

    - hand vertices inside the (watertight) object: how deep the deepest one lies;
    - if ``hand_faces`` is given, object vertices inside the closed hand mesh
      (:func:`object_in_hand_depth`), so that thin object parts through the hand are caught.

    Args:
        hand_vertices: (N, 3) hand vertices, metres, in the object's frame. With ``hand_faces``
            they must be the vertices those faces index (for MANO: ``mano.close(vertices)``,
            (779, 3), with ``mano.closed_faces``).
        obj_vertices: (V, 3) object vertices, metres.
        obj_faces: (F, 3) object triangles, closed and wound outward.
        hand_faces: optional (H, 3) closed, outward-wound hand triangles.

    Returns:
        Penetration depth in metres, >= 0.
    """
    hand_vertices = _points(hand_vertices)
    depth = max(0.0, -float(signed_distance(hand_vertices, obj_vertices, obj_faces).min(initial=np.inf)))
    if hand_faces is not None:
        depth = max(depth, object_in_hand_depth(obj_vertices, hand_vertices, hand_faces))
    return depth


def surface_samples(vertices, faces, spacing: float) -> tuple[scipy.sparse.csr_matrix, np.ndarray]:
    """Points covering a triangle mesh no more than about ``spacing`` apart, as barycentric weights.

    Vertex-only checks miss a thin object part (a 4 mm mug wall) that slips between a coarse
    mesh's vertices; these samples close the gaps. Each face is cut into n x n sub-triangles,
    n = ceil(longest edge / spacing), and its lattice points are kept; points that neighbouring
    faces share are merged.

    Args:
        vertices: (V, 3) vertices of a reference pose (only used for edge lengths and merging).
        faces: (F, 3) triangles.
        spacing: wanted distance between samples, same unit as ``vertices``.

    Returns:
        weights: (S, V) sparse; ``weights @ posed_vertices`` gives the samples (S, 3) of any pose
        of the same mesh (points move linearly with their face's corners);
        face: (S,) index of a face each sample lies on.
    """
    vertices, faces = _points(vertices), _faces(faces)
    tri = vertices[faces]
    longest = np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(1)
    splits = np.maximum(1, np.ceil(longest / spacing)).astype(int)
    rows, cols, vals, face_of = [], [], [], []
    for n in np.unique(splits):
        chosen = np.flatnonzero(splits == n)
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        bary = np.stack([i[keep], j[keep], n - i[keep] - j[keep]], 1) / n  # (P, 3)
        count = len(chosen) * len(bary)
        rows.append(np.repeat(np.arange(count), 3))
        cols.append(np.repeat(faces[chosen], len(bary), axis=0).ravel())
        vals.append(np.tile(bary, (len(chosen), 1)).ravel())
        face_of.append(np.repeat(chosen, len(bary)))
    offsets = np.cumsum([0] + [len(f) for f in face_of[:-1]])
    rows = np.concatenate([r + o for r, o in zip(rows, offsets)])
    weights = scipy.sparse.csr_matrix((np.concatenate(vals), (rows, np.concatenate(cols))),
                                      shape=(offsets[-1] + len(face_of[-1]), len(vertices)))
    # Merge coincident samples (shared corners and edges) by their rounded reference position.
    _, first = np.unique(np.round(weights @ vertices, 9), axis=0, return_index=True)
    first = np.sort(first)
    return weights[first], np.concatenate(face_of)[first]


def mesh_bvh(vertices, faces) -> fcl.BVHModel:
    """An fcl OBB-RSS bounding-volume hierarchy of a triangle mesh (vertices (V, 3) m, faces (F, 3))."""
    vertices, faces = _points(vertices), _faces(faces)
    model = fcl.BVHModel()
    model.beginModel(len(vertices), len(faces))
    model.addSubModel(vertices, faces)
    model.endModel()
    return model


class HandObjectCollision:
    """Collision, distance and contact queries of hand meshes against one fixed object.

    The object's BVH is built once here (about 20 ms for 4k faces); each hand query builds the
    hand's BVH (a few ms for MANO), or reuses it for rigid translations (:meth:`hand_object`
    plus :meth:`translated_distance`), which is what sliding a hand towards the object needs.

    Args:
        obj_vertices: (V, 3) object vertices, metres, in the object's frame.
        obj_faces: (F, 3) triangles, closed and wound outward.
    """

    def __init__(self, obj_vertices, obj_faces):
        self.obj_vertices = _points(obj_vertices)
        self.obj_faces = _faces(obj_faces)
        self._object = fcl.CollisionObject(mesh_bvh(self.obj_vertices, self.obj_faces), fcl.Transform())
        corners = self.obj_vertices[self.obj_faces]
        self._face_lo, self._face_hi = corners.min(1), corners.max(1)

    def hand_object(self, hand_vertices, hand_faces) -> fcl.CollisionObject:
        """fcl object of a hand mesh ((N, 3) m, (H, 3) faces), to move with :meth:`translated_distance`."""
        return fcl.CollisionObject(mesh_bvh(hand_vertices, hand_faces), fcl.Transform())

    def _collides(self, hand: fcl.CollisionObject) -> bool:
        # One contact is enough to answer yes/no, so fcl can stop at the first intersecting pair.
        return fcl.collide(hand, self._object, fcl.CollisionRequest(num_max_contacts=1), fcl.CollisionResult()) > 0

    def _distance(self, hand: fcl.CollisionObject) -> float:
        if self._collides(hand):
            return 0.0
        # fcl's mesh-mesh distance is exact between separated meshes (triangle-triangle distance).
        dist = fcl.distance(hand, self._object, fcl.DistanceRequest(), fcl.DistanceResult())
        return max(0.0, float(dist))

    def translated_distance(self, hand: fcl.CollisionObject, translation) -> float:
        """Distance (m, 0 if colliding) of a hand fcl object moved rigidly by ``translation`` (3,) m."""
        hand.setTranslation(np.asarray(translation, dtype=np.float64))
        return self._distance(hand)

    def distance(self, hand_vertices, hand_faces) -> float:
        """Minimum distance between the hand mesh and the object, metres; 0 if they intersect.

        Args:
            hand_vertices: (N, 3) metres in the object's frame; hand_faces: (H, 3) indices into them.
        """
        return self._distance(self.hand_object(hand_vertices, hand_faces))

    def collides(self, hand_vertices, hand_faces) -> bool:
        """Whether any hand triangle intersects any object triangle (touching surfaces count).

        Note that a hand lying entirely inside the object has no intersecting triangles; the
        signed-distance checks (:func:`penetration_depth`) cover that case.
        """
        return self._collides(self.hand_object(hand_vertices, hand_faces))

    def signed_distances(self, points, band: float | None = None) -> np.ndarray:
        """(N,) signed distance (m, negative inside) of points (N, 3) to the object's surface;
        NaN beyond ``band`` metres when it is given (see :func:`signed_distance`)."""
        points = _points(points)
        if band is None or len(points) == 0:
            return signed_distance(points, self.obj_vertices, self.obj_faces, band)
        # libigl rebuilds its tree and pseudonormals on every call, so hand it only the faces whose
        # boxes meet the points' box grown by 2 band. Faces left out lie wholly outside that box,
        # more than 2 band from every point, so the crop's cut edges and corners can never be the
        # nearest feature of a point within band: distances and signs there are the full mesh's.
        lo, hi = points.min(0) - 2 * band, points.max(0) + 2 * band
        near = np.all(self._face_lo <= hi, axis=1) & np.all(self._face_hi >= lo, axis=1)
        if not near.any():
            return np.full(len(points), np.nan)
        return signed_distance(points, self.obj_vertices, self.obj_faces[near], band)

    def nearest_surface(self, points) -> tuple[np.ndarray, np.ndarray]:
        """Closest surface points (N, 3) m to points (N, 3), and the outward pseudonormals (N, 3)
        there (the face normal inside a face, the angle-weighted mean at edges and corners)."""
        sign = igl.SignedDistanceType.SIGNED_DISTANCE_TYPE_PSEUDONORMAL
        _, _, closest, normals = igl.signed_distance(_points(points), self.obj_vertices, self.obj_faces, sign)
        return closest, normals

    def contact_vertices(self, hand_vertices, within: float = CONTACT_DISTANCE) -> np.ndarray:
        """Indices (K,) int64 of the hand vertices (N, 3) within ``within`` metres of the object's
        surface, vertices inside the object included (their signed distance is negative)."""
        return np.flatnonzero(self.signed_distances(hand_vertices) <= within)

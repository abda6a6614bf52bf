"""Exact volume of a solid inside an axis-aligned cube, where one mesh's surface crosses it (numba kernels).

For a closed mesh, the winding number at a point p is the signed count of faces crossed by the ray from p
upward: w(p) = sum of sign(n_z) over the faces above p (n a face's normal by its vertex order). Integrating over
a cube C = [x0, x1] x [y0, y1] x [z0, z1] of edge h, column by column,

    integral of w over C = sum over faces of the integral, over the face's shadow on the square, of
                           sign(n_z) * clamp(z_face(x, y) - z0, 0, h),

so each face is clipped to the column above the square's lower face (x, y inside the square, z >= z0). Its part
below z1 adds its signed shadow area times its mean height above z0 (z is linear over a face, so the fan
triangles' corner means are exact); its part above z1 adds h times its signed shadow area. Every term is a
continuous function of the vertices: a face on the column's border or at z0 changes nothing discontinuously, so
the sum is exact up to rounding, with no ray that can slip between two faces.

Where every face that meets C separates w = 0 from w = s (s = +1 for an outward-wound mesh, -1 for an
inward-wound one), the solid |w| > 1/2 fills s * integral of w of the cube; :func:`face_parts` finds the parts
for which that cannot be assumed (those that cross another face, or whose front is not at w = 0, resp. -1).
"""

from __future__ import annotations

import numba
import numpy as np

MAX_POLY = 12  # a triangle clipped by 6 planes has at most 9 corners


@numba.njit(cache=True, inline="always")
def _clip(src, n, dst, axis, value, keep_above, strict=False):
    """Sutherland-Hodgman: the part of polygon ``src[:n]`` with coordinate ``axis`` >= value (keep_above) or
    <= value, written to ``dst``; returns its corner count. ``strict``: > value (a polygon lying in the plane
    is dropped, so the two sides of a split never both keep it)."""
    m = 0
    for j in range(n):
        k = j + 1 if j + 1 < n else 0
        dj = src[j, axis] - value if keep_above else value - src[j, axis]
        dk = src[k, axis] - value if keep_above else value - src[k, axis]
        in_j, in_k = (dj > 0, dk > 0) if strict else (dj >= 0, dk >= 0)
        if in_j:
            dst[m, 0], dst[m, 1], dst[m, 2] = src[j, 0], src[j, 1], src[j, 2]
            m += 1
        if in_j != in_k:
            t = dj / (dj - dk)
            for d in range(3):
                dst[m, d] = src[j, d] + t * (src[k, d] - src[j, d])
            dst[m, axis] = value
            m += 1
    return m


@numba.njit(cache=True, inline="always")
def _fan(poly, n, z0):
    """(signed shadow area, integral over the shadow of z - z0) of a planar polygon."""
    area, moment = 0.0, 0.0
    for j in range(1, n - 1):
        a2 = ((poly[j, 0] - poly[0, 0]) * (poly[j + 1, 1] - poly[0, 1])
              - (poly[j, 1] - poly[0, 1]) * (poly[j + 1, 0] - poly[0, 0]))
        area += 0.5 * a2
        moment += 0.5 * a2 * ((poly[0, 2] + poly[j, 2] + poly[j + 1, 2]) / 3.0 - z0)
    return area, moment


@numba.njit(cache=True)
def column_integrals(centres, edge, boxes, left_of, start_of, count_of, tri, out, touched):
    """For each cube (centre, ``edge``): ``out`` = integral of the winding number over it (see the module
    docstring), ``touched`` = some face meets the closed cube. The tree is a :class:`MeshBVH`'s arrays."""
    a, b = np.empty((MAX_POLY, 3)), np.empty((MAX_POLY, 3))
    stack = np.empty(128, np.int64)
    half = edge / 2
    for i in range(len(centres)):
        x0, x1 = centres[i, 0] - half, centres[i, 0] + half
        y0, y1 = centres[i, 1] - half, centres[i, 1] + half
        z0, z1 = centres[i, 2] - half, centres[i, 2] + half
        total, hit = 0.0, False
        stack[0], top = 0, 1
        while top:
            top -= 1
            node = stack[top]
            if (boxes[node, 0] > x1 or boxes[node, 3] < x0 or boxes[node, 1] > y1 or boxes[node, 4] < y0
                    or boxes[node, 5] < z0):
                continue
            left = left_of[node]
            if left >= 0:
                stack[top], stack[top + 1] = left, left + 1
                top += 2
                continue
            for k in range(start_of[node], start_of[node] + count_of[node]):
                for c in range(3):
                    for d in range(3):
                        a[c, d] = tri[k, 3 * c + d]
                n = _clip(a, 3, b, 0, x0, True)
                n = _clip(b, n, a, 0, x1, False)
                n = _clip(a, n, b, 1, y0, True)
                n = _clip(b, n, a, 1, y1, False)
                n = _clip(a, n, b, 2, z0, True)
                if n == 0:
                    continue
                low = _clip(b, n, a, 2, z1, False)  # the part within the cube
                if low:
                    hit = True
                if low >= 3:
                    total += _fan(a, low, z0)[1]
                high = _clip(b, n, a, 2, z1, True, True)  # the part above it: the whole height h
                if high >= 3:
                    total += edge * _fan(a, high, z0)[0]
        out[i] = total
        touched[i] = hit


@numba.njit(cache=True, inline="always")
def _segment_hits(t, i, j, u):
    """Segment from corner i to corner j of triangle ``t`` (9,) meets triangle ``u`` (9,): Moller-Trumbore with
    0 <= t <= 1, the arithmetic of :mod:`hoisdf.scoring.solids`' numpy test."""
    px, py, pz = t[3 * i], t[3 * i + 1], t[3 * i + 2]
    dx, dy, dz = t[3 * j] - px, t[3 * j + 1] - py, t[3 * j + 2] - pz
    e1x, e1y, e1z = u[3] - u[0], u[4] - u[1], u[5] - u[2]
    e2x, e2y, e2z = u[6] - u[0], u[7] - u[1], u[8] - u[2]
    hx, hy, hz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
    det = e1x * hx + e1y * hy + e1z * hz
    if det == 0:
        return False
    inv = 1.0 / det
    sx, sy, sz = px - u[0], py - u[1], pz - u[2]
    uu = inv * (sx * hx + sy * hy + sz * hz)
    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
    v = inv * (dx * qx + dy * qy + dz * qz)
    w = inv * (e2x * qx + e2y * qy + e2z * qz)
    return uu >= 0 and v >= 0 and uu + v <= 1 and w >= 0 and w <= 1


@numba.njit(cache=True)
def crossing_parts(parts, parent, faces, order, boxes, left_of, start_of, count_of, tri):
    """(K,) bool: triangle k of ``parts`` (K, 9: corners a, b, c), a part of face ``parent[k]``, crosses a face
    of the mesh that shares no vertex with its parent: an edge of one meets the other (two triangles that cross
    meet along a segment whose ends lie on edges of one or the other, so the 6 edge-triangle tests find every
    crossing that is not coplanar). Candidates come from the mesh's tree (a :class:`MeshBVH`'s arrays)."""
    n = len(parts)
    out = np.zeros(n, np.bool_)
    stack = np.empty(128, np.int64)
    for i in range(n):
        t, f = parts[i], parent[i]
        lo0, hi0 = min(t[0], t[3], t[6]), max(t[0], t[3], t[6])
        lo1, hi1 = min(t[1], t[4], t[7]), max(t[1], t[4], t[7])
        lo2, hi2 = min(t[2], t[5], t[8]), max(t[2], t[5], t[8])
        stack[0], top = 0, 1
        while top and not out[i]:
            top -= 1
            node = stack[top]
            if (boxes[node, 0] > hi0 or boxes[node, 3] < lo0 or boxes[node, 1] > hi1 or boxes[node, 4] < lo1
                    or boxes[node, 2] > hi2 or boxes[node, 5] < lo2):
                continue
            left = left_of[node]
            if left >= 0:
                stack[top], stack[top + 1] = left, left + 1
                top += 2
                continue
            for k in range(start_of[node], start_of[node] + count_of[node]):
                g = order[k]
                shared = False
                for x in range(3):
                    for y in range(3):
                        shared = shared or faces[g, x] == faces[f, y]
                if shared:
                    continue
                u = tri[k]
                if (_segment_hits(t, 0, 1, u) or _segment_hits(t, 1, 2, u) or _segment_hits(t, 2, 0, u)
                        or _segment_hits(u, 0, 1, t) or _segment_hits(u, 1, 2, t) or _segment_hits(u, 2, 0, t)):
                    out[i] = True
                    break
    return out


def crosses(solid, parts: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """:func:`crossing_parts` for a :class:`hoisdf.scoring.solids.MeshSolid` and parts (K, 3, 3) of its faces."""
    b = solid.bvh
    flat = np.ascontiguousarray(np.asarray(parts, np.float64).reshape(-1, 9))
    return crossing_parts(flat, np.ascontiguousarray(parent, np.int64), solid.faces, b.order, b.boxes, b.left,
                          b.start, b.count, b.tri)


def orientation(vertices: np.ndarray, faces: np.ndarray) -> float:
    """+1 when the closed mesh's signed volume is positive (wound outward), -1 otherwise."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return 1.0 if float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) >= 0 else -1.0


def _front_winding(solid, tri: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """(K,) the winding number just in front of each triangle (K, 3, 3), a part of face ``parent``, rounded."""
    v, f = solid.vertices, solid.faces
    normal = np.cross(v[f[parent, 1]] - v[f[parent, 0]], v[f[parent, 2]] - v[f[parent, 0]])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    step = 1e-7 * float(np.linalg.norm(solid.hi - solid.lo))  # off the face, far below any feature size
    return np.rint(solid.winding(tri.mean(1) + step * normal / length))


def _split(tri: np.ndarray) -> np.ndarray:
    """Each triangle (K, 3, 3) in 4 at its edge midpoints -> (4 K, 3, 3)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    return np.stack([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))], 1).reshape(-1, 3, 3)


def face_parts(solid, sign: float, levels: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Triangle soups (K, 3, 3) of a closed :class:`hoisdf.scoring.solids.MeshSolid`: the *irregular* parts of
    its surface, which may border anything but w = 0 and w = ``sign`` (they cross a face that is not a neighbour
    of theirs, or their front has a winding number other than 0, resp. -1 for an inward-wound mesh), and the
    *boundary*: all but the buried parts, which cross no face and have |w| >= 1 on both sides (front w >= 1 or
    <= -2; w grows by 1 from a part's front to its back), so they border nothing of the solid |w| > 1/2.

    Faces that cross another are split in 4 ``levels`` times, and a part that no longer crosses anything is
    judged by its own front, so what stays irregular hugs the crossing curves. A fold between neighbouring faces
    goes unnoticed."""
    v, f = solid.vertices, solid.faces
    expected = 0.0 if sign > 0 else -1.0
    tri, parent = v[f], np.arange(len(f))
    flat = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) == 0
    irregular, boundary = [tri[flat]], [tri[flat]]
    tri, parent = tri[~flat], parent[~flat]
    for level in range(levels + 1):
        if len(tri) == 0:
            break
        cross = crosses(solid, tri, parent)
        w = _front_winding(solid, tri[~cross], parent[~cross])
        settled = tri[~cross]
        irregular.append(settled[w != expected])
        boundary.append(settled[(w < 1) & (w > -2)])
        tri, parent = tri[cross], parent[cross]
        if level < levels:
            tri, parent = _split(tri), np.repeat(parent, 4)
    irregular.append(tri)
    boundary.append(tri)
    return np.concatenate(irregular), np.concatenate(boundary)

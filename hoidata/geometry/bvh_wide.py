"""The closest-face query of :class:`~hoidata.geometry.bvh.MeshBVH` on a wide view of its tree, in vector lanes.

The binary tree (:func:`hoidata.geometry.bvh.topology`) is read as a tree of wide nodes: each wide node holds the
binary descendants :data:`LEVELS` levels below it (up to 8 children), stopping early at any node with at most
:data:`LANES` faces, which becomes a leaf block. Per frame the children's boxes are gathered into (node, axis,
child) arrays and each leaf block's corners into (block, coordinate, lane) arrays, so the 8 box distances of a
wide node and the 8 face distances of a block are each one loop over independent lanes, which numba (LLVM)
compiles to vector instructions; the binary traversal spent its time on unpredictable branches, one box or one
face at a time (measured: 1.4-1.5x faster on the toy frames, bench/README.md).

Exactness is that of the binary query. A face's squared distance is the same float64 expression as
:func:`hoidata.geometry.bvh.point_triangle` (Ericson's region tests in their order, written as selects instead of
early returns: each region's closest point is formed by the same operations, and the first region that holds
wins), so it is bit for bit the same number; the winner's weights and feature are then taken from
``point_triangle`` itself. A box is skipped only when its distance exceeds the best one found (boxes are padded,
so rounding in the box distance cannot skip a face that attains it), and ties go to the lowest face index, so
the result does not depend on the visiting order.
"""

from __future__ import annotations

import numba
import numpy as np


LEVELS = 3  # binary levels per wide node: up to 2**3 = 8 children
LANES = 8  # faces per leaf block: a binary node with at most this many faces is a leaf of the wide view
STACK = 512  # at most 7 entries per wide level (nearest child popped first), under 30 levels for any tree
EMPTY = np.iinfo(np.int64).min  # the reference of an empty child slot


@numba.njit(cache=True)
def widen(left_of, count_of):
    """The wide view of a binary tree (children after their parent, node 0 the root): (nodes, ref, leaf_of).

    nodes (W, 8) int64: the binary node in each child slot of each wide node (-1 for an empty slot; wide node 0
    holds the root's descendants). ref (W, 8): what a slot points at, >= 0 a wide node, -1 - b leaf block b,
    EMPTY for an empty slot. leaf_of (nodes,): each binary node's leaf block, -1 where it is not a leaf of the
    wide view (a binary leaf, or a node with at most LANES faces)."""
    n = len(left_of)
    width = 1 << LEVELS
    nodes = np.full((n, width), -1, np.int64)
    leaf_of, wide_of = np.full(n, -1, np.int64), np.full(n, -1, np.int64)
    queue = np.empty(n, np.int64)
    queue[0], queue_end, head, n_wide, n_leaf = 0, 1, 0, 0, 0
    cur, nxt = np.empty(width, np.int64), np.empty(width, np.int64)
    while head < queue_end:
        node = queue[head]
        head += 1
        wide_of[node] = n_wide
        cur[0], m = node, 1
        for _ in range(LEVELS):
            k = 0
            for t in range(m):
                c = cur[t]
                if left_of[c] >= 0 and count_of[c] > LANES:
                    nxt[k], nxt[k + 1] = left_of[c], left_of[c] + 1
                    k += 2
                else:  # a leaf of the wide view stays in its slot
                    nxt[k] = c
                    k += 1
            cur[:k] = nxt[:k]
            m = k
        for t in range(m):
            c = cur[t]
            nodes[n_wide, t] = c
            if left_of[c] >= 0 and count_of[c] > LANES and c != node:
                queue[queue_end] = c
                queue_end += 1
            else:
                leaf_of[c] = n_leaf
                n_leaf += 1
        n_wide += 1
    nodes = nodes[:n_wide].copy()
    ref = np.full((n_wide, width), EMPTY, np.int64)
    for w in range(n_wide):
        for t in range(width):
            c = nodes[w, t]
            if c >= 0:
                ref[w, t] = wide_of[c] if leaf_of[c] < 0 else -1 - leaf_of[c]
    return nodes, ref, leaf_of


@numba.njit(cache=True)
def gather(nodes, leaf_of, boxes, tri, start_of, count_of):
    """Per frame, from the binary tree's padded boxes and leaf-ordered corners: the children's boxes lo, hi
    (W, 3, 8) (empty slots: lo = +inf, hi = -inf, infinitely far), each block's corners (B, 9, LANES) (lanes past
    a block's faces repeat its first face), and each block's first face and face count (B,) in leaf order."""
    n_wide, width = nodes.shape
    lo, hi = np.full((n_wide, 3, width), np.inf), np.full((n_wide, 3, width), -np.inf)
    for w in range(n_wide):
        for t in range(width):
            c = nodes[w, t]
            if c >= 0:
                for d in range(3):
                    lo[w, d, t], hi[w, d, t] = boxes[c, d], boxes[c, 3 + d]
    n_leaf = leaf_of.max() + 1
    blocks = np.empty((n_leaf, 9, LANES))
    first, count = np.empty(n_leaf, np.int64), np.empty(n_leaf, np.int64)
    for node in range(len(leaf_of)):
        b = leaf_of[node]
        if b >= 0:
            first[b], count[b] = start_of[node], count_of[node]
            for lane in range(LANES):
                k = start_of[node] + (lane if lane < count_of[node] else 0)
                for q in range(9):
                    blocks[b, q, lane] = tri[k, q]
    return lo, hi, blocks, first, count


@numba.njit(cache=True, inline="always")
def point_triangle(px, py, pz, tri, k):
    """(squared distance, v, w, feature) from p to face k: the closest point is a + v ab + w ac.

    Ericson's region tests in his order, each dot product computed only when a test needs it; the
    closest point and the squared distance are formed as in the numpy reference."""
    ax, ay, az = tri[k, 0], tri[k, 1], tri[k, 2]
    ab0, ab1, ab2 = tri[k, 3] - ax, tri[k, 4] - ay, tri[k, 5] - az
    ac0, ac1, ac2 = tri[k, 6] - ax, tri[k, 7] - ay, tri[k, 8] - az
    ap0, ap1, ap2 = px - ax, py - ay, pz - az
    d1, d2 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2, ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    if d1 <= 0 and d2 <= 0:
        v, w, feature = 0.0, 0.0, 0
    else:
        bp0, bp1, bp2 = px - tri[k, 3], py - tri[k, 4], pz - tri[k, 5]
        d3, d4 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2, ac0 * bp0 + ac1 * bp1 + ac2 * bp2
        if d3 >= 0 and d4 <= d3:
            v, w, feature = 1.0, 0.0, 1
        elif d1 * d4 - d3 * d2 <= 0 and d1 >= 0 and d3 <= 0:
            v, w, feature = d1 / (d1 - d3), 0.0, 2
        else:
            cp0, cp1, cp2 = px - tri[k, 6], py - tri[k, 7], pz - tri[k, 8]
            d5, d6 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2, ac0 * cp0 + ac1 * cp1 + ac2 * cp2
            if d6 >= 0 and d5 <= d6:
                v, w, feature = 0.0, 1.0, 3
            elif d5 * d2 - d1 * d6 <= 0 and d2 >= 0 and d6 <= 0:
                v, w, feature = 0.0, d2 / (d2 - d6), 4
            elif d3 * d6 - d5 * d4 <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
                t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
                v, w, feature = 1 - t, t, 5
            else:
                va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
                total = va + vb + vc
                v, w, feature = vb / total, vc / total, 6
    e0 = px - (ax + v * ab0 + w * ac0)
    e1 = py - (ay + v * ab1 + w * ac1)
    e2 = pz - (az + v * ab2 + w * ac2)
    return e0 * e0 + e1 * e1 + e2 * e2, v, w, feature


@numba.njit(cache=True, inline="always", error_model="numpy")
def _block_distances(px, py, pz, blocks, b, out):
    """Squared distances from p to the faces of block b, one lane each (the loop vectorises: no branches, and
    a division by zero in a region that is not taken gives inf or nan there, discarded by the selects)."""
    for j in range(blocks.shape[2]):  # a run-time trip count: LLVM vectorises it rather than unrolling it
        ax, ay, az = blocks[b, 0, j], blocks[b, 1, j], blocks[b, 2, j]
        ab0, ab1, ab2 = blocks[b, 3, j] - ax, blocks[b, 4, j] - ay, blocks[b, 5, j] - az
        ac0, ac1, ac2 = blocks[b, 6, j] - ax, blocks[b, 7, j] - ay, blocks[b, 8, j] - az
        ap0, ap1, ap2 = px - ax, py - ay, pz - az
        d1, d2 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2, ac0 * ap0 + ac1 * ap1 + ac2 * ap2
        bp0, bp1, bp2 = px - blocks[b, 3, j], py - blocks[b, 4, j], pz - blocks[b, 5, j]
        d3, d4 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2, ac0 * bp0 + ac1 * bp1 + ac2 * bp2
        cp0, cp1, cp2 = px - blocks[b, 6, j], py - blocks[b, 7, j], pz - blocks[b, 8, j]
        d5, d6 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2, ac0 * cp0 + ac1 * cp1 + ac2 * cp2
        va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
        total = va + vb + vc
        t_ab, t_ac, t_bc = d1 / (d1 - d3), d2 / (d2 - d6), (d4 - d3) / ((d4 - d3) + (d5 - d6))
        v, w = vb / total, vc / total  # the interior; then the regions, the earliest test applied last
        in_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        v, w = (1 - t_bc if in_bc else v), (t_bc if in_bc else w)
        in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        v, w = (0.0 if in_ac else v), (t_ac if in_ac else w)
        at_c = (d6 >= 0) & (d5 <= d6)
        v, w = (0.0 if at_c else v), (1.0 if at_c else w)
        in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        v, w = (t_ab if in_ab else v), (0.0 if in_ab else w)
        at_b = (d3 >= 0) & (d4 <= d3)
        v, w = (1.0 if at_b else v), (0.0 if at_b else w)
        at_a = (d1 <= 0) & (d2 <= 0)
        v, w = (0.0 if at_a else v), (0.0 if at_a else w)
        e0 = px - (ax + v * ab0 + w * ac0)
        e1 = py - (ay + v * ab1 + w * ac1)
        e2 = pz - (az + v * ab2 + w * ac2)
        out[j] = e0 * e0 + e1 * e1 + e2 * e2


@numba.njit(cache=True, inline="always", error_model="numpy")
def _box_distances(px, py, pz, lo, hi, node, out):
    """Squared distances from p to the children's boxes of a wide node (0 inside; inf for an empty slot)."""
    for j in range(lo.shape[2]):
        a, b = lo[node, 0, j] - px, px - hi[node, 0, j]
        gx = a if a > b else b
        gx = gx if gx > 0.0 else 0.0
        a, b = lo[node, 1, j] - py, py - hi[node, 1, j]
        gy = a if a > b else b
        gy = gy if gy > 0.0 else 0.0
        a, b = lo[node, 2, j] - pz, pz - hi[node, 2, j]
        gz = a if a > b else b
        gz = gz if gz > 0.0 else 0.0
        out[j] = gx * gx + gy * gy + gz * gz


@numba.njit(cache=True, error_model="numpy")
def closest_wide(points, visit, hint, order, lo, hi, ref, blocks, first, count, tri, dist, face, weights, feature):
    """For each point (in the order ``visit``): its squared-distance minimum over all faces, the face (leaf
    order; lowest ``order`` index on ties), the weights and feature from ``point_triangle``. The first bound is
    face ``hint[i]`` (leaf order) where ``hint`` has one per point and it is not negative, else the previous
    point's face."""
    stack, bound = np.empty(STACK, np.int64), np.empty(STACK)
    box_d, face_d = np.empty(lo.shape[2]), np.empty(blocks.shape[2])
    last, hinted = 0, len(hint) == len(points)
    for i in visit:
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        if hinted and hint[i] >= 0:
            last = hint[i]
        best = point_triangle(px, py, pz, tri, last)[0]
        best_k = last
        stack[0], bound[0], top = 0, 0.0, 1
        while top:
            top -= 1
            if bound[top] > best:
                continue
            r = stack[top]
            if r < 0:  # leaf block -1 - r
                b = -1 - r
                _block_distances(px, py, pz, blocks, b, face_d)
                for j in range(count[b]):
                    d2 = face_d[j]
                    if d2 <= best:
                        k = first[b] + j
                        if d2 < best or order[k] < order[best_k]:
                            best, best_k = d2, k
                continue
            _box_distances(px, py, pz, lo, hi, r, box_d)
            near, near_d = -1, np.inf
            for j in range(lo.shape[2]):  # push the children in reach, the nearest last (on top)
                d = box_d[j]
                if d <= best:  # an empty slot is infinitely far
                    if d < near_d:
                        if near >= 0:
                            stack[top], bound[top] = ref[r, near], near_d
                            top += 1
                        near, near_d = j, d
                    else:
                        stack[top], bound[top] = ref[r, j], d
                        top += 1
            if near >= 0:
                stack[top], bound[top] = ref[r, near], near_d
                top += 1
        d2, v, w, f = point_triangle(px, py, pz, tri, best_k)
        dist[i] = np.sqrt(d2)
        face[i] = best_k
        weights[i, 0], weights[i, 1] = v, w
        feature[i] = f
        last = best_k


@numba.njit(cache=True, error_model="numpy")
def crossings_wide(points, rays, root_box, lo, hi, ref, blocks, count_of_block, count, undecided):
    """:meth:`hoidata.geometry.bvh.MeshBVH.crossings` on the wide view: the same ray per point (the one of ``rays``
    leaving ``root_box`` soonest), the same watertight test per face (Woop, Benthin and Wald), the faces of a
    block in vector lanes; the count is a sum over the faces the ray meets, so the visiting order cannot change
    it, and a padded box the ray misses holds no face it meets."""
    stack = np.empty(STACK, np.int64)
    for i in range(len(points)):
        p0, p1, p2 = points[i, 0], points[i, 1], points[i, 2]
        pick, shortest = 0, np.inf
        for d in range(3):
            for side in range(2):  # rays[2 d] runs along +d, rays[2 d + 1] along -d
                gap = root_box[3 + d] - points[i, d] if side == 0 else points[i, d] - root_box[d]
                if gap < shortest:
                    pick, shortest = 2 * d + side, gap
        ray = rays[pick]
        kz = np.argmax(np.abs(ray))
        kx, ky = (kz + 1) % 3, (kz + 2) % 3
        if ray[kz] < 0:
            kx, ky = ky, kx
        sx, sy, sz = ray[kx] / ray[kz], ray[ky] / ray[kz], 1.0 / ray[kz]
        i0, i1, i2 = 1.0 / ray[0], 1.0 / ray[1], 1.0 / ray[2]
        qx, qy, qz = points[i, kx], points[i, ky], points[i, kz]
        total, flag = 0, False
        stack[0], top = 0, 1
        while top:
            top -= 1
            r = stack[top]
            if r < 0:
                b = -1 - r
                for j in range(count_of_block[b]):  # the faces' contributions: sums over lanes, no branches
                    az, bz, cz = blocks[b, kz, j] - qz, blocks[b, 3 + kz, j] - qz, blocks[b, 6 + kz, j] - qz
                    ax, ay = blocks[b, kx, j] - qx - sx * az, blocks[b, ky, j] - qy - sy * az
                    bx, by = blocks[b, 3 + kx, j] - qx - sx * bz, blocks[b, 3 + ky, j] - qy - sy * bz
                    cx, cy = blocks[b, 6 + kx, j] - qx - sx * cz, blocks[b, 6 + ky, j] - qy - sy * cz
                    u, v, w = cx * by - cy * bx, ax * cy - ay * cx, bx * ay - by * ax
                    inside = ((u >= 0) & (v >= 0) & (w >= 0)) | ((u <= 0) & (v <= 0) & (w <= 0))
                    det = u + v + w
                    edge = (det == 0) | (u == 0) | (v == 0) | (w == 0)
                    t = u * (sz * az) + v * (sz * bz) + w * (sz * cz)  # the hit's ray parameter times det
                    flag |= inside & (edge | (t == 0))
                    ahead = inside & (not edge) & (t != 0) & ((t > 0) == (det > 0))
                    total += (1 if det < 0 else -1) if ahead else 0
                continue
            for j in range(lo.shape[2]):  # slab test of each child box: does the ray p + t ray, t >= 0, meet it?
                ta, tb = (lo[r, 0, j] - p0) * i0, (hi[r, 0, j] - p0) * i0
                t0, t1 = max(0.0, min(ta, tb)), max(ta, tb)
                ta, tb = (lo[r, 1, j] - p1) * i1, (hi[r, 1, j] - p1) * i1
                t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                ta, tb = (lo[r, 2, j] - p2) * i2, (hi[r, 2, j] - p2) * i2
                t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                if t0 <= t1 and ref[r, j] != EMPTY:
                    stack[top] = ref[r, j]
                    top += 1
        count[i] = total
        undecided[i] = flag

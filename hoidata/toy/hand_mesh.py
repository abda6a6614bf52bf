"""Geometry of the procedural hand: a palm with five tubular fingers, MANO's exact mesh topology.

The mesh must look like MANO to every code path: 778 vertices, 1538 faces, genus 0 with one boundary
loop of 16 edges at the wrist. It is built as:

1. a palm: the surface of a 12 x NU x 2 lattice box, rounded into a squircle cross-section, with
   2 x 2 cell holes on its top face (four fingers), its thumb-side face (thumb) and a 6 x 2 hole on
   its bottom face (wrist); every hole is bounded by 8 vertices, the wrist by 16;
2. tubes glued to the holes: 8-vertex rings along each finger ending in a single tip vertex, and one
   16-vertex ring below the wrist hole, which stays open (the MANO wrist opening);
3. midpoint splits of the longest palm edges until the vertex count is exactly 778.

Frame (metres, like MANO's right hand): fingers point to -x, the back of the hand faces +y, the thumb
lies on the +z side. Pure numpy; deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hoidata.geometry.surface import split_longest_edges

PALM_COLS, PALM_THICK = 12, 2  # lattice cells across the knuckles and through the palm
FINGERS = ("index", "middle", "ring", "pinky", "thumb")
# Top-face column ranges of the four finger holes (column 0 is the pinky side, 12 the thumb side).
FINGER_COLUMNS = {"pinky": 0, "ring": 3, "middle": 6, "index": 9}
LENGTH_AXIS = np.array([-1.0, 0.0, 0.0])  # wrist -> fingers
WIDTH_AXIS = np.array([0.0, 0.0, 1.0])  # pinky -> thumb
BACK_AXIS = np.array([0.0, 1.0, 0.0])  # palm -> back of the hand


@dataclass(frozen=True)
class FingerSpec:
    segments: tuple[float, float, float]  # proximal, middle, distal lengths (m), joint to joint
    half_width: float  # m, at the base
    rings: int  # 8-vertex rings after the palm hole


@dataclass(frozen=True)
class HandSpec:
    palm_rows: int = 8
    palm_length: float = 0.088  # wrist to knuckles
    palm_width: float = 0.084
    palm_thickness: float = 0.030
    wrist_width: float = 0.062
    fingers: tuple = (
        ("index", FingerSpec((0.041, 0.024, 0.021), 0.0092, 12)),
        ("middle", FingerSpec((0.045, 0.028, 0.022), 0.0095, 13)),
        ("ring", FingerSpec((0.042, 0.027, 0.021), 0.0089, 12)),
        ("pinky", FingerSpec((0.033, 0.020, 0.019), 0.0080, 12)),
        ("thumb", FingerSpec((0.038, 0.031, 0.027), 0.0105, 12)),
    )


@dataclass
class FingerGeometry:
    """Where a finger's tube vertices are and how its joints sit along it (metres)."""

    name: str
    base: np.ndarray  # centre of the palm hole
    axis: np.ndarray  # unit direction of the finger
    side: np.ndarray  # unit, across the finger (its flexion axis is +/- this)
    joints: np.ndarray  # (4, 3): first joint (MCP, or CMC for the thumb), 2nd, 3rd, tip
    vertex_ids: np.ndarray  # tube vertices (rings then tip), excluding the palm hole loop
    stations: np.ndarray  # distance of each of vertex_ids from joints[0] along axis
    tip_id: int
    last_ring: np.ndarray  # vertex ids of the last ring before the tip


@dataclass
class HandMesh:
    vertices: np.ndarray  # (778, 3)
    faces: np.ndarray  # (1538, 3), outward winding
    palm_ids: np.ndarray  # vertices of the palm and wrist tube
    wrist_center: np.ndarray  # (3,)
    fingers: dict  # name -> FingerGeometry


def _lattice_surface(nx: int, ny: int, nz: int) -> tuple[np.ndarray, list]:
    """Integer lattice points on the surface of an nx x ny x nz box and its unit quads.

    Returns (P, 3) int points and a list of (quad vertex index tuple, outward axis, face id) where
    face id is (axis, 0|1) for the min/max face.
    """
    dims = (nx, ny, nz)
    grid = np.stack(np.meshgrid(*(np.arange(d + 1) for d in dims), indexing="ij"), -1).reshape(-1, 3)
    on_surface = ((grid == 0) | (grid == np.array(dims))).any(1)
    points = grid[on_surface]
    index = {tuple(p): i for i, p in enumerate(points)}
    quads = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for end in (0, 1):
            for a in range(dims[u]):
                for b in range(dims[v]):
                    corners = []
                    for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = [0, 0, 0]
                        p[axis], p[u], p[v] = end * dims[axis], a + du, b + dv
                        corners.append(index[tuple(p)])
                    quads.append((tuple(corners), (axis, end), (a, b)))
    return points, quads


def _is_hole(face: tuple, cell: tuple, spec: HandSpec) -> bool:
    axis, end = face
    a, b = cell
    if axis == 1 and end == 1:  # top face: cells (column, thickness)
        return any(c <= a < c + 2 for c in FINGER_COLUMNS.values())
    if axis == 0 and end == 1:  # thumb-side face: cells (row, thickness)
        return 2 <= a < 4
    if axis == 1 and end == 0:  # bottom face: the wrist opening
        return 3 <= a < 9
    return False


def _palm_position(p: np.ndarray, spec: HandSpec) -> np.ndarray:
    """Lattice points (P, 3) (column, row, thickness) -> metric palm surface points (P, 3)."""
    col, row, thick = p[:, 0].astype(float), p[:, 1].astype(float), p[:, 2].astype(float)
    f = row / spec.palm_rows  # 0 at the wrist, 1 at the knuckles
    half_w = 0.5 * (spec.wrist_width + (spec.palm_width - spec.wrist_width) * np.sqrt(f))
    half_t = 0.5 * spec.palm_thickness * (0.8 + 0.2 * np.sin(np.pi * np.clip(f, 0, 1)))
    w = (col / PALM_COLS * 2.0 - 1.0)  # in [-1, 1]
    t = (thick / PALM_THICK * 2.0 - 1.0)
    # Squircle mapping: the rectangle boundary goes onto |w|^4 + |t|^4 = 1, the interior smoothly.
    rect = np.maximum(np.abs(w), np.abs(t))
    squircle = np.maximum((w ** 4 + t ** 4) ** 0.25, 1e-12)
    scale = np.where(rect > 0, rect / squircle, 1.0)
    w, t = w * scale, t * scale
    knuckle_arc = 0.010 * (1.0 - ((col - 7.0) / 7.0) ** 2) * f ** 2  # middle knuckles reach furthest
    u = f * spec.palm_length + knuckle_arc
    return (u[:, None] * LENGTH_AXIS + (w * half_w)[:, None] * WIDTH_AXIS + (t * half_t)[:, None] * BACK_AXIS)


def _triangulate(quads: list, positions: np.ndarray, outward) -> list:
    """Split quads into triangles wound so that their normals agree with outward(centroid)."""
    tris = []
    for q in quads:
        a, b, c, d = q
        for tri in ((a, b, c), (a, c, d)):
            p0, p1, p2 = positions[list(tri)]
            n = np.cross(p1 - p0, p2 - p0)
            if np.dot(n, outward((p0 + p1 + p2) / 3.0)) < 0:
                tri = (tri[0], tri[2], tri[1])
            tris.append(tri)
    return tris


def _hole_loops(quads: list) -> list[list[int]]:
    """Boundary loops (unordered direction) of a set of quads."""
    count: dict = {}
    for q in quads:
        for i in range(4):
            e = tuple(sorted((q[i], q[(i + 1) % 4])))
            count[e] = count.get(e, 0) + 1
    adjacency: dict = {}
    for (a, b), n in count.items():
        if n == 1:
            adjacency.setdefault(a, []).append(b)
            adjacency.setdefault(b, []).append(a)
    loops, seen = [], set()
    for start in sorted(adjacency):
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        while True:
            seen.add(cur)
            nxt = [n for n in adjacency[cur] if n != prev][0] if prev is not None else min(adjacency[cur])
            if nxt == start:
                break
            loop.append(nxt)
            prev, cur = cur, nxt
        loops.append(loop)
    return loops


def _tube(pos: list, tris: list, loop: list, axis: np.ndarray, side: np.ndarray, spec: FingerSpec,
          depth: float) -> FingerGeometry:
    """Append a finger tube (rings + tip) glued to the 8-vertex palm hole `loop` (in place)."""
    loop_pos = np.array([pos[i] for i in loop])
    base = loop_pos.mean(0)
    back = np.cross(axis, side)
    q = loop_pos - base
    qs, qb = q @ side, q @ back
    angles = np.arctan2(qb / np.abs(qb).max(), qs / np.abs(qs).max())
    joint0 = base - axis * depth
    joints = joint0 + np.cumsum([0.0, *spec.segments])[:, None] * axis
    length = sum(spec.segments) - depth
    start = max(0.0, float((q @ axis).max()))  # a tilted hole (the thumb) reaches up the axis
    step = (length - start) / (spec.rings + 0.55)
    cap = 0.9 * spec.half_width * 0.78
    rings, stations = [list(loop)], []
    for k in range(1, spec.rings + 1):
        s = start + k * step
        r = spec.half_width * (1.0 - 0.22 * s / length)
        over = max(0.0, s - (length - cap)) / cap
        r *= np.sqrt(max(0.0, 1.0 - over ** 2))
        ring = []
        for a in angles:
            ring.append(len(pos))
            pos.append(base + axis * s + r * np.cos(a) * side + 0.82 * r * np.sin(a) * back)
            stations.append(s + depth)
        rings.append(ring)
    tip = len(pos)
    pos.append(base + axis * length)
    stations.append(length + depth)

    def outward(c):
        s = np.clip((c - base) @ axis, 0.0, length - 1.5 * cap)
        return c - (base + axis * s)

    n = len(loop)
    quads = [(r0[i], r0[(i + 1) % n], r1[(i + 1) % n], r1[i]) for r0, r1 in zip(rings[:-1], rings[1:]) for i in range(n)]
    fans = [(rings[-1][i], rings[-1][(i + 1) % n], tip) for i in range(n)]
    arr = np.array(pos)
    tris += _triangulate(quads, arr, outward)
    tris += _triangulate([(a, b, c, c) for a, b, c in fans], arr, outward)[0::2]
    ids = np.arange(rings[1][0], tip + 1)
    return FingerGeometry("", base, axis, side, joints, ids, np.array(stations), tip, np.array(rings[-1]))


def _rotate(v: np.ndarray, axis: np.ndarray, angle_deg: float) -> np.ndarray:
    a = np.deg2rad(angle_deg)
    return v * np.cos(a) + np.cross(axis, v) * np.sin(a) + axis * (axis @ v) * (1 - np.cos(a))


FINGER_SPLAY_DEG = {"index": 6.0, "middle": 0.0, "ring": -5.0, "pinky": -11.0}
THUMB_AXIS = np.array([-0.62, -0.30, 0.72])  # forward, toward the palm, out to the thumb side


def build_hand_mesh(spec: HandSpec = HandSpec(), n_vertices: int = 778) -> HandMesh:
    """Build the procedural hand mesh with exactly `n_vertices` vertices (see the module docstring)."""
    lattice, quads = _lattice_surface(PALM_COLS, spec.palm_rows, PALM_THICK)
    kept = [(q, face) for q, face, cell in quads if not _is_hole(face, cell, spec)]
    used = sorted({i for q, _ in kept for i in q})
    remap = {old: new for new, old in enumerate(used)}
    lat = lattice[used]
    pos = list(_palm_position(lat, spec))
    metric_axes = (WIDTH_AXIS, LENGTH_AXIS, BACK_AXIS)
    tris = []
    for q, (axis, end) in kept:
        normal = metric_axes[axis] * (1 if end else -1)
        tris += _triangulate([tuple(remap[i] for i in q)], np.array(pos), lambda c, n=normal: n)
    loops = _hole_loops([tuple(remap[i] for i in q) for q, _ in kept])
    wrist = next(lp for lp in loops if len(lp) == 16)
    holes = {}
    for lp in loops:
        cols = lat[lp, 0]
        if len(lp) == 16:
            continue
        name = "thumb" if (cols == PALM_COLS).all() else next(n for n, c in FINGER_COLUMNS.items() if cols.min() == c)
        holes[name] = lp
    finger_count = sum(8 * fs.rings + 1 for _, fs in spec.fingers)
    n_splits = n_vertices - (len(pos) + 16 + finger_count)
    if n_splits < 0:
        raise ValueError(f"hand spec has {-n_splits} vertices too many for {n_vertices}")
    split_v, split_f = split_longest_edges(np.array(pos), np.array(tris, dtype=np.int64), n_splits,
                                           frozen={i for lp in loops for i in lp})
    pos, tris = list(split_v), [tuple(f) for f in split_f.tolist()]
    wrist_center = np.array([pos[i] for i in wrist]).mean(0)
    ring = []
    for i in wrist:
        p = pos[i]
        radial = p - LENGTH_AXIS * (p @ LENGTH_AXIS)
        ring.append(len(pos))
        pos.append(0.95 * radial + LENGTH_AXIS * -0.014)
    n = len(wrist)
    tube = [(wrist[i], wrist[(i + 1) % n], ring[(i + 1) % n], ring[i]) for i in range(n)]
    tris += _triangulate(tube, np.array(pos), lambda c: c - LENGTH_AXIS * (c @ LENGTH_AXIS))
    palm_ids = np.arange(len(pos))
    fingers = {}
    for name, fspec in spec.fingers:
        if name == "thumb":
            axis, depth = THUMB_AXIS / np.linalg.norm(THUMB_AXIS), 0.022
        else:
            axis, depth = _rotate(LENGTH_AXIS, BACK_AXIS, FINGER_SPLAY_DEG[name]), 0.008
        side = np.cross(BACK_AXIS, axis)
        side /= np.linalg.norm(side)
        geo = _tube(pos, tris, holes[name], axis, side, fspec, depth)
        geo.name = name
        fingers[name] = geo
    return HandMesh(np.array(pos), np.array(tris, dtype=np.int64), palm_ids, wrist_center, fingers)

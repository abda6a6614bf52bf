"""Procedural stand-ins for YCB object models, written in the real YCB on-disk layout.

The real YCB meshes are licensed, so tests and toy datasets use these instead. Each object keeps
its YCB folder name and a plausible real size in metres, is centred on its bounding-box centre
(YCB model frames sit roughly at the object centre), and is written as ``textured_simple.obj`` +
``textured_simple.obj.mtl`` + ``texture_map.png`` + ``points.xyz``. The OBJ holds one object
(one ``o`` line, no ``g``) whose ``v``/``vt``/``vn`` lists are index-aligned (every face corner is
``f a/a/a``), as the DexYCB toolkit's YCB layer expects; vertices are duplicated along UV seams
and creases, like the real files. Output is byte-identical from run to run (fixed seeds, no
timestamps).
"""

from __future__ import annotations

import os
from pathlib import Path

import manifold3d
import numpy as np
import trimesh
from PIL import Image

from hoidata.objects.meshops import orient_outward, sample_surface
from hoidata.objects.ycb import MESH_FILE, POINTS_FILE, UnknownObjectError, class_id

MTL_FILE = MESH_FILE + ".mtl"
TEXTURE_FILE = "texture_map.png"
N_POINTS = 2048  # surface samples in points.xyz
CREASE_DEG = 40.0  # faces meeting at a sharper angle than this get separate normals


# ---------------------------------------------------------------- geometry (pure functions)

def ring_faces(n_rings: int, n_around: int) -> np.ndarray:
    """Triangles joining consecutive closed rings; vertex (i, j) of ring i is ``i * n_around + j``."""
    i, j = np.meshgrid(np.arange(n_rings - 1), np.arange(n_around), indexing="ij")
    a, b = i * n_around + j, i * n_around + (j + 1) % n_around
    c, d = a + n_around, b + n_around
    return np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])


def close_rings(rings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Watertight surface through rings ``(R, N, 3)``: side bands plus a fan cap at each end
    around the end ring's centroid (the last two vertices). Faces are wound outward."""
    n_rings, n = rings.shape[:2]
    vertices = np.vstack([rings.reshape(-1, 3), rings[0].mean(0), rings[-1].mean(0)])
    j, jn = np.arange(n), (np.arange(n) + 1) % n
    start, end, last = np.full(n, n_rings * n), np.full(n, n_rings * n + 1), (n_rings - 1) * n
    faces = np.concatenate([ring_faces(n_rings, n), np.stack([start, jn, j], 1),
                            np.stack([end, last + j, last + jn], 1)])
    return vertices, orient_outward(vertices, faces)


def revolve(profile_rz, n_around: int) -> np.ndarray:
    """Rings ``(R, N, 3)`` of a profile ``[(r, z), ...]`` (metres) revolved about the z axis.
    Ring vertex j sits at angle 2 pi j / N, so j = 0 lies exactly on the +x half-plane."""
    r, z = np.asarray(profile_rz, dtype=np.float64).T
    theta = 2 * np.pi * np.arange(n_around) / n_around
    return np.stack([r[:, None] * np.cos(theta), r[:, None] * np.sin(theta),
                     np.broadcast_to(z[:, None], (len(z), n_around))], -1)


def sweep(path: np.ndarray, half_a, half_b, binormal, n_around: int) -> np.ndarray:
    """Rings ``(R, N, 3)`` of an elliptical cross-section swept along a planar ``path`` (R, 3).

    ``half_a`` (in the path's plane) and ``half_b`` (along ``binormal``, the plane normal) are
    the semi-axes per path point; a planar path needs no twist-free frame transport."""
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.cross(binormal, tangent)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    phi = 2 * np.pi * np.arange(n_around) / n_around
    a = np.broadcast_to(half_a, len(path))[:, None, None] * np.cos(phi)[None, :, None]
    b = np.broadcast_to(half_b, len(path))[:, None, None] * np.sin(phi)[None, :, None]
    return path[:, None] + a * normal[:, None] + b * np.asarray(binormal, dtype=np.float64)


def union(parts) -> tuple[np.ndarray, np.ndarray]:
    """Boolean union of closed outward-wound meshes ``[(V, F), ...]`` with manifold3d (float64)."""
    result = None
    for vertices, faces in parts:
        m = manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.ascontiguousarray(vertices, np.float64),
                                                  tri_verts=np.ascontiguousarray(faces, np.uint64)))
        if m.status() != manifold3d.Error.NoError:
            raise ValueError(f"union input is not a closed manifold: {m.status()}")
        result = m if result is None else result + m
    mesh = result.to_mesh64()
    return np.asarray(mesh.vert_properties, np.float64)[:, :3], np.asarray(mesh.tri_verts, np.int64)


# ---------------------------------------------------------------- texture coordinates and normals

def wrap_uv(faces: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Corner UVs ``(F, 3, 2)`` from per-vertex ``u`` in [0, 1) (NaN where undefined) and ``v``.

    A face straddling the u seam gets +1 on its small-u corners, so it maps to a thin strip at
    u ~ 1 instead of spanning the whole texture; corners with undefined u (cap centres) take the
    mean of the face's other corners."""
    cu = u[faces].copy()
    lo, hi = np.nanmin(cu, axis=1, keepdims=True), np.nanmax(cu, axis=1, keepdims=True)
    cu = np.where((hi - lo > 0.5) & (cu < 0.5), cu + 1.0, cu)
    cu = np.where(np.isnan(cu), np.nanmean(cu, axis=1, keepdims=True), cu)
    return np.stack([cu, v[faces]], -1)


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) unnormalised normals (length = twice the face area)."""
    p = vertices[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def cylinder_uv(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Corner UVs for objects around the z axis: side faces wrap u = angle / 2 pi and use the top
    70% of the texture; faces facing (nearly) straight up/down are projected onto two discs in the
    bottom 30%."""
    u = np.mod(np.arctan2(vertices[:, 1], vertices[:, 0]) / (2 * np.pi), 1.0)
    zmin, zmax = vertices[:, 2].min(), vertices[:, 2].max()
    uv = wrap_uv(faces, u, 0.3 + 0.7 * (vertices[:, 2] - zmin) / (zmax - zmin))
    n = face_normals(vertices, faces)
    nz = n[:, 2] / np.linalg.norm(n, axis=1)
    cap = np.abs(nz) > 0.9  # flat lids and bottoms only; shoulders and chamfers stay on the side
    xy = vertices[faces[cap]][..., :2]
    xy = xy / np.abs(xy).max()
    centre = np.where(nz[cap] > 0, 0.75, 0.25)[:, None, None] * [1.0, 0.0] + [0.0, 0.15]
    uv[cap] = centre + 0.14 * xy
    return uv


def box_uv(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Corner UVs by box projection: each face goes to one of six atlas cells (3 x 2) by the axis
    and sign of its normal, and is projected along that axis."""
    n = face_normals(vertices, faces)
    axis = np.argmax(np.abs(n), axis=1)
    cell = 2 * axis + (n[np.arange(len(n)), axis] > 0)
    lo, hi = vertices.min(0), vertices.max(0)
    unit = (vertices[faces] - lo) / (hi - lo)  # (F, 3, 3) in [0, 1]
    others = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # the two in-plane axes per face
    st = np.take_along_axis(unit, np.broadcast_to(others[:, None, :], (len(faces), 3, 2)), axis=2)
    offset = np.stack([cell % 3, cell // 3], 1)[:, None, :]
    return (offset + 0.05 + 0.9 * st) / [3.0, 2.0]


def corner_normals(vertices: np.ndarray, faces: np.ndarray, crease_deg: float = CREASE_DEG) -> np.ndarray:
    """(F, 3, 3) unit normals per face corner: the area-weighted mean of the face normals around
    the vertex that are within ``crease_deg`` of this face's normal (smooth, but sharp at creases)."""
    n = face_normals(vertices, faces)
    unit = n / np.linalg.norm(n, axis=1, keepdims=True)
    corner_vertex = faces.ravel()
    order = np.argsort(corner_vertex, kind="stable")
    counts = np.bincount(corner_vertex, minlength=len(vertices))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(len(order)) - starts[corner_vertex[order]]
    incident = np.full((len(vertices), counts.max()), -1)
    incident[corner_vertex[order], slot] = order // 3  # faces around each vertex
    around = incident[corner_vertex]  # (C, D)
    own = np.repeat(np.arange(len(faces)), 3)
    close = np.einsum("cdk,ck->cd", unit[around], unit[own]) >= np.cos(np.radians(crease_deg))
    weight = (around >= 0) & close
    summed = np.einsum("cd,cdk->ck", weight.astype(np.float64), n[around])
    return (summed / np.linalg.norm(summed, axis=1, keepdims=True)).reshape(-1, 3, 3)


# ---------------------------------------------------------------- the objects (metres)

def master_chef_can():
    """Cylinder r 0.051 m, h 0.140 m, chamfered rims and two pressed beads."""
    radius, height, lip = 0.0508, 0.1402, 0.004
    z0, z1 = -height / 2, height / 2
    side = np.linspace(z0 + lip, z1 - lip, 15)
    bead = 1 + 0.012 * np.isin(np.arange(15), [3, 11])
    fractions = (0.25, 0.5, 0.75, 1.0)
    profile = ([(f * (radius - lip), z0) for f in fractions] + list(zip(radius * bead, side))
               + [(f * (radius - lip), z1) for f in fractions[::-1]])
    vertices, faces = close_rings(revolve(profile, 64))
    return vertices, faces, cylinder_uv(vertices, faces)


def cracker_box():
    """Box 0.16 x 0.21 x 0.07 m, midpoint-subdivided three times (flat faces stay exact)."""
    box = trimesh.creation.box(extents=(0.16, 0.21, 0.07))
    vertices, faces = np.asarray(box.vertices, np.float64), np.asarray(box.faces, np.int64)
    for _ in range(3):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    return vertices, faces, box_uv(vertices, faces)


def mustard_bottle():
    """Bottle 0.19 m tall: flattened body (0.086 x 0.052 m), cosine shoulder, neck, cap and nozzle."""
    radius, neck = 0.043, 0.012
    bottom = [(f * radius, 0.0) for f in (0.3, 0.6, 0.85)] + [(radius, 0.006)]
    body = [(radius, z) for z in np.linspace(0.006, 0.115, 10)[1:]]
    t = np.linspace(0, 1, 9)[1:]
    shoulder = list(zip(neck + (radius - neck) * 0.5 * (1 + np.cos(np.pi * t)), 0.115 + 0.035 * t))
    cap = [(0.0145, 0.152), (0.0145, 0.165), (0.0145, 0.178), (0.009, 0.182), (0.004, 0.19)]
    rings = revolve(bottom + body + shoulder + cap, 64) * [1.0, 0.6, 1.0]
    vertices, faces = close_rings(rings)
    return vertices, faces, cylinder_uv(vertices, faces)


def mug():
    """Mug r 0.040 m, h 0.082 m, 4 mm wall, 6 mm base, with a handle tube unioned on at -x."""
    radius, height, wall, base = 0.040, 0.082, 0.004, 0.006
    inner = radius - wall
    profile = ([(0.3 * radius, 0.0), (0.6 * radius, 0.0), (radius - 0.003, 0.0)]
               + [(radius, z) for z in np.linspace(0.003, height, 13)]
               + [(inner, z) for z in np.linspace(height, base + 0.003, 12)]
               + [(inner - 0.003, base), (0.6 * inner, base), (0.3 * inner, base)])
    cup = close_rings(revolve(profile, 48))
    # Handle: a C-shaped path in the xz plane whose straight ends stop inside the 4 mm wall.
    x_in, x_out, zc, half_h, reach = -(radius - wall / 2), -(radius + 0.004), height / 2 + 0.004, 0.024, 0.022
    s = np.linspace(0, np.pi, 33)[1:-1]
    xs = np.concatenate([np.linspace(x_in, x_out, 4), x_out - reach * np.sin(s), np.linspace(x_out, x_in, 4)])
    zs = np.concatenate([np.full(4, zc + half_h), zc + half_h * np.cos(s), np.full(4, zc - half_h)])
    path = np.stack([xs, np.zeros_like(xs), zs], 1)
    handle = close_rings(sweep(path, 0.0055, 0.007, (0.0, 1.0, 0.0), 16))
    vertices, faces = union([cup, handle])
    return vertices, faces, cylinder_uv(vertices, faces)


def banana():
    """Tube 0.22 m along an arc of radius 0.14 m (0.2 m tip to tip), elliptical section up to 0.036 x 0.032 m,
    tapering to ~4 mm closed ends; u runs around the tube, v along it."""
    n_rings, n_around = 49, 28
    t = np.linspace(0, 1, n_rings)
    alpha = 1.55 * (t - 0.5)
    path = np.stack([0.14 * np.sin(alpha), -0.14 * np.cos(alpha), np.zeros(n_rings)], 1)
    taper = np.sin(np.pi * t ** 0.85) ** 0.6
    rings = sweep(path, 0.002 + 0.016 * taper, 0.002 + 0.014 * taper, (0.0, 0.0, 1.0), n_around)
    vertices, faces = close_rings(rings)
    u = np.concatenate([np.tile(np.arange(n_around) / n_around, n_rings), [np.nan, np.nan]])
    v = np.concatenate([np.repeat(t, n_around), [0.0, 1.0]])
    return vertices, faces, wrap_uv(faces, u, v)


# name: (builder, texture noise seed, texture colours (base, band, stripe, lid) as RGB)
TOY_OBJECTS = {
    "002_master_chef_can": (master_chef_can, 2,
                            ((40, 70, 150), (200, 40, 40), (230, 200, 60), (180, 180, 185))),
    "003_cracker_box": (cracker_box, 3, ((200, 30, 30), (240, 210, 60), (250, 250, 240), (200, 30, 30))),
    "006_mustard_bottle": (mustard_bottle, 6,
                           ((235, 200, 30), (40, 60, 160), (240, 240, 240), (235, 200, 30))),
    "011_banana": (banana, 11, ((230, 200, 60), (200, 180, 50), (120, 90, 40), (90, 70, 30))),
    "025_mug": (mug, 25, ((190, 30, 30), (200, 40, 40), (170, 20, 20), (180, 30, 30))),
}


# ---------------------------------------------------------------- writing

def make_texture(colours, seed: int, size: int = 256) -> np.ndarray:
    """(size, size, 3) uint8: base colour, a label band with vertical stripes in the upper
    (side) region, lid colour in the bottom 30% (cap discs), and fixed-seed colour noise."""
    base, band, stripe, lid = (np.asarray(c, np.float64) for c in colours)
    rows = np.arange(size)[:, None, None] / size  # image row 0 is v = 1 (OBJ v points up)
    cols = np.arange(size)[None, :, None] / size
    img = np.broadcast_to(base, (size, size, 3)).copy()
    in_band = (rows > 0.2) & (rows < 0.5)
    img = np.where(in_band, band, img)
    img = np.where(in_band & (np.floor(cols * 16) % 2 == 1) & (rows > 0.28) & (rows < 0.42), stripe, img)
    img = np.where(rows >= 0.7, lid, img)
    noise = np.random.default_rng(seed).normal(0.0, 6.0, (size, size, 3))
    return np.clip(np.round(img + noise), 0, 255).astype(np.uint8)


def obj_arrays(vertices, faces, uv, normals):
    """Index-aligned OBJ arrays: one row per distinct (vertex, uv, normal) corner, first-use order.
    Returns positions (K, 3), uvs (K, 2), normals (K, 3) and faces (F, 3) into them."""
    corner = faces.ravel()
    key = np.column_stack([corner, np.round(uv.reshape(-1, 2), 6), np.round(normals.reshape(-1, 3), 6)])
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    pick = first[order]
    return (vertices[corner[pick]], uv.reshape(-1, 2)[pick], normals.reshape(-1, 3)[pick],
            rank[inverse.ravel()].reshape(-1, 3))


def obj_text(name: str, positions, uvs, normals, faces) -> str:
    """OBJ file text with one object, one material and ``f a/a/a`` faces (1-based)."""
    lines = [f"# hoidata procedural stand-in for YCB {name} (not the real scan), metres",
             f"mtllib {MTL_FILE}", f"o {name}"]
    lines += ["v %.6f %.6f %.6f" % tuple(p) for p in positions]
    lines += ["vt %.6f %.6f" % tuple(t) for t in uvs]
    lines += ["vn %.6f %.6f %.6f" % tuple(n) for n in normals]
    lines += ["usemtl material_0", "s 1"]
    lines += ["f {0}/{0}/{0} {1}/{1}/{1} {2}/{2}/{2}".format(*f) for f in (faces + 1).tolist()]
    return "\n".join(lines) + "\n"


MTL_TEXT = (f"# hoidata procedural material\nnewmtl material_0\nKa 0.200000 0.200000 0.200000\n"
            f"Kd 1.000000 1.000000 1.000000\nKs 0.000000 0.000000 0.000000\nNs 10.000000\n"
            f"illum 2\nmap_Kd {TEXTURE_FILE}\n")


def build_toy_object(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closed geometry of one toy object, centred on its bounding box: vertices (V, 3) m,
    faces (F, 3) wound outward, corner UVs (F, 3, 2)."""
    if name not in TOY_OBJECTS:
        class_id(name)  # a non-YCB name gets the full list of valid names
        raise UnknownObjectError(None, "object name", f"no procedural model for {name!r}; "
                                 f"available: {', '.join(TOY_OBJECTS)}")
    vertices, faces, uv = TOY_OBJECTS[name][0]()
    vertices = vertices - 0.5 * (vertices.min(0) + vertices.max(0))
    return vertices, faces, uv


def write_toy_objects(models_dir: str | os.PathLike, names=None) -> list[Path]:
    """Write toy objects (default: all of TOY_OBJECTS) as ``models_dir/<name>/...`` in the YCB
    layout and return the ``textured_simple.obj`` paths in the order of ``names``."""
    written = []
    for name in TOY_OBJECTS if names is None else names:
        vertices, faces, uv = build_toy_object(name)
        folder = Path(models_dir) / name
        folder.mkdir(parents=True, exist_ok=True)
        normals = corner_normals(vertices, faces)
        # Bytes, not text mode: the files must not change with the platform's newline convention.
        (folder / MESH_FILE).write_bytes(obj_text(name, *obj_arrays(vertices, faces, uv, normals)).encode())
        (folder / MTL_FILE).write_bytes(MTL_TEXT.encode())
        seed, colours = TOY_OBJECTS[name][1:]
        Image.fromarray(make_texture(colours, seed)).save(folder / TEXTURE_FILE, format="PNG")
        points = sample_surface(vertices, faces, N_POINTS, seed=class_id(name))
        (folder / POINTS_FILE).write_bytes("".join("%.6f %.6f %.6f\n" % tuple(p) for p in points).encode())
        written.append(folder / MESH_FILE)
    return written

"""Offscreen rendering with pyrender: RGB, metric depth, label maps and amodal masks.

Inputs live in the OpenCV camera frame (x right, y down, z forward, metres); ``K`` (3, 3) maps a
camera point to pixel ``u = fx x / z + cx``, ``v = fy y / z + cy``, pixel (col, row) centred at
integer (u, v) = (col, row).

Camera conversion. The scene's world frame *is* the OpenCV camera frame and the pyrender camera
sits at the origin with pose ``diag(1, -1, -1)`` (OpenGL cameras look down -z, y up). That is a
proper rotation, so winding and back-face culling are unchanged: meshes must be closed and wound
outward, as the toy objects and the closed MANO mesh are. ``IntrinsicsCamera`` puts a point at
*window* coordinate ``fx x / z + cx``, where OpenGL pixel centres sit at ``i + 0.5`` (rows from the
top after pyrender's vertical flip), so it gets ``cx + 0.5`` and ``cy + 0.5``. No skew support.

Exact labels. Labels and depth come from pyrender's SEG pass, which turns multisampling off: a
pixel is covered by the triangle under its centre, so it gets label L only where a mesh labelled
L is the front surface, and depth is that surface's z. The RGB pass is multisampled (anti-aliased
edges); its coverage is returned as ``alpha`` and used to composite the background.

Same input, same pixels. pyrender keeps a scene's mesh and light nodes in sets and draws the meshes and sums the
lights in the sets' order, which follows the nodes' memory addresses. Our meshes all sit at the identity pose, so
pyrender's sort by distance ties and that order decides which of two surfaces at equal depth shows (the first drawn
wins) and the order of the float sums over the lights: the same frame came out different by one level at a few
pixels from run to run, even twice in one process. Scenes here keep their nodes in insertion order: meshes are
drawn in ``meshes`` order and lights summed in ``lighting``'s order.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hoidata.render.appearance import Lighting, default_lighting
from hoidata.render.egl_guard import prepare_for_egl

prepare_for_egl()  # before any pyrender / OpenGL import (torch's compiler stack first, in a main process)

ZNEAR = 0.01  # metres; 24-bit depth keeps < 0.2 mm resolution out to 5 m with these planes
ZFAR = 20.0
MAX_LABEL = 2 ** 24 - 1  # labels travel through the SEG pass as 8-bit R, G, B
DEFAULT_COLOR = (0.7, 0.7, 0.7)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])  # camera pose: OpenCV camera axes -> OpenGL camera axes


# ---------------------------------------------------------------- pure helpers


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(N, 3) unit area-weighted vertex normals of (N, 3) vertices and (F, 3) outward faces."""
    p = vertices[faces]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 * area, so area-weighted
    normals = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def srgb_to_linear(color) -> np.ndarray:
    """sRGB values in [0, 1] -> linear; pyrender shades in linear light and gamma-encodes output."""
    c = np.asarray(color, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def label_to_rgb(label: int) -> np.ndarray:
    """(3,) uint8-valued colour encoding a label 0..2^24-1 (R = low byte)."""
    return np.array([label & 255, (label >> 8) & 255, (label >> 16) & 255], dtype=np.float64)


def rgb_to_label(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 SEG colours -> (H, W) int32 labels (inverse of :func:`label_to_rgb`)."""
    rgb = rgb.astype(np.int32)
    return rgb[..., 0] | (rgb[..., 1] << 8) | (rgb[..., 2] << 16)


def pyrender_intrinsics(K: np.ndarray) -> tuple[float, float, float, float]:
    """OpenCV K (3, 3) -> (fx, fy, cx, cy) for ``pyrender.IntrinsicsCamera`` (centres shifted +0.5 px)."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"K must be a finite 3x3 matrix, got shape {K.shape}")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0 or abs(K[0, 1]) > 1e-9 * fx or K[1, 0] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}")
    return float(fx), float(fy), float(K[0, 2] + 0.5), float(K[1, 2] + 0.5)


def composite(rgba: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """Premultiplied (H, W, 4) uint8 render over an (H, W, 3) uint8 background (None: black).

    The multisample resolve averages covered samples with the (0, 0, 0, 0) clear colour, so the
    render is premultiplied by coverage: out = rgb + (1 - alpha) * background."""
    if background is None:
        return np.ascontiguousarray(rgba[..., :3])
    alpha = rgba[..., 3:4].astype(np.float32) / 255.0
    out = rgba[..., :3].astype(np.float32) + (1.0 - alpha) * background.astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- scene description

def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


@dataclass
class RenderMesh:
    """One triangle mesh to draw, already placed in the OpenCV camera frame.

    vertices (N, 3) metres; faces (F, 3) int, closed and wound outward (back faces are culled);
    uv (N, 2) OBJ convention (v up) with texture (H, W, 3) uint8, or both None; color sRGB in
    [0, 1] used when there is no texture; label written into label maps (0 = background: a label-0
    mesh still hides what is behind it); normals (N, 3) or None to compute smooth ones.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    texture: np.ndarray | None = None
    color: tuple[float, float, float] = DEFAULT_COLOR
    label: int = 1
    normals: np.ndarray | None = None

    def __post_init__(self):
        v = self.vertices = np.asarray(self.vertices, dtype=np.float64)
        f = self.faces = np.asarray(self.faces, dtype=np.int64)
        n = len(v)
        _require(v.ndim == 2 and v.shape[1] == 3 and np.isfinite(v).all(),
                 f"vertices must be finite (N, 3), got {v.shape}")
        _require(f.ndim == 2 and f.shape[1] == 3 and (f.size == 0 or 0 <= f.min() <= f.max() < n),
                 f"faces must be (F, 3) indices into {n} vertices, got shape {f.shape}")
        _require((self.uv is None) == (self.texture is None), "uv and texture must be given together")
        if self.uv is not None:
            self.uv, self.texture = np.asarray(self.uv, dtype=np.float64), np.asarray(self.texture)
            _require(self.uv.shape == (n, 2), f"uv must be ({n}, 2), got {self.uv.shape}")
            _require(self.texture.ndim == 3 and self.texture.shape[2] == 3 and self.texture.dtype == np.uint8,
                     f"texture must be (H, W, 3) uint8, got {self.texture.shape} {self.texture.dtype}")
        _require(self.normals is None or np.shape(self.normals) == (n, 3), f"normals must be ({n}, 3) or None")
        self.color = tuple(float(c) for c in self.color)
        _require(len(self.color) == 3 and all(0.0 <= c <= 1.0 for c in self.color),
                 f"color must be 3 floats in [0, 1], got {self.color}")
        _require(0 <= int(self.label) <= MAX_LABEL, f"label must be in 0..{MAX_LABEL}, got {self.label}")
        self.label = int(self.label)

    @classmethod
    def from_trimesh(cls, mesh, transform: np.ndarray | None = None, label: int = 1,
                     color: tuple[float, float, float] = DEFAULT_COLOR) -> "RenderMesh":
        """A trimesh (model frame) placed by ``transform`` (4, 4) model->camera, keeping its UV texture.

        A mirroring transform (negative determinant) reverses the faces so they stay outward."""
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        normals = np.asarray(mesh.vertex_normals, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        if transform is not None:
            T = np.asarray(transform, dtype=np.float64)
            vertices = vertices @ T[:3, :3].T + T[:3, 3]
            normals = normals @ np.linalg.inv(T[:3, :3])  # inverse transpose, applied to row vectors
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
            if np.linalg.det(T[:3, :3]) < 0:
                faces = faces[:, ::-1]
        uv, texture = _trimesh_texture(mesh)
        return cls(vertices, faces, uv, texture, color, label, normals)


def _trimesh_texture(mesh) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(uv (N, 2), texture (H, W, 3) uint8) of a trimesh with TextureVisuals, else (None, None)."""
    visual = getattr(mesh, "visual", None)
    material = getattr(visual, "material", None)
    # SimpleMaterial keeps a PIL image in .image, PBRMaterial in .baseColorTexture
    image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    if getattr(visual, "kind", None) != "texture" or getattr(visual, "uv", None) is None or image is None:
        return None, None
    texture = np.asarray(image.convert("RGB") if hasattr(image, "convert") else image)
    return np.asarray(visual.uv, dtype=np.float64), np.ascontiguousarray(texture[..., :3], dtype=np.uint8)


# ---------------------------------------------------------------- renderer

@dataclass
class RenderResult:
    """rgb (H, W, 3) uint8; depth (H, W) float32 metres along +z, 0 where empty; labels (H, W)
    int32 visible label, 0 background; alpha (H, W) float32 anti-aliased coverage of the RGB pass."""

    rgb: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    alpha: np.ndarray


class Renderer:
    """One reusable offscreen pyrender context of ``width`` x ``height`` pixels.

    Use as a context manager or call :meth:`close`. Not thread-safe: one Renderer per thread.
    """

    def __init__(self, width: int, height: int, znear: float = ZNEAR, zfar: float = ZFAR):
        import pyrender

        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self._renderer = pyrender.OffscreenRenderer(self.width, self.height)

    def close(self) -> None:
        """Release the GL context (idempotent)."""
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None

    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def render(self, K: np.ndarray, meshes: list[RenderMesh], background: np.ndarray | None = None,
               lighting: Lighting | None = None) -> RenderResult:
        """Shade ``meshes`` seen through OpenCV intrinsics ``K`` (3, 3).

        Returns rgb over ``background`` ((H, W, 3) uint8, black if None), exact depth and labels
        (see the module docstring) and the RGB pass coverage. ``lighting`` None: default_lighting()."""
        shape = (self.height, self.width, 3)
        _require(background is None or (np.shape(background) == shape and np.asarray(background).dtype == np.uint8),
                 f"background must be {shape} uint8, got {np.shape(background)}")
        scene, nodes = self._scene(K, meshes, default_lighting() if lighting is None else lighting)
        import pyrender

        rgba, _ = self._gl().render(scene, flags=pyrender.RenderFlags.RGBA)
        labels, depth = self._seg(scene, {node: mesh.label for node, mesh in zip(nodes, meshes)})
        alpha = rgba[..., 3].astype(np.float32) / 255.0
        return RenderResult(composite(rgba, background), depth, labels, alpha)

    def masks(self, K: np.ndarray, meshes: list[RenderMesh]) -> tuple[np.ndarray, np.ndarray]:
        """Visible label map (H, W) int32 and amodal masks (len(meshes), H, W) bool.

        Mask i is where mesh i covers the image when rendered alone (unoccluded), so it contains
        every pixel whose visible front surface is mesh i. One flat SEG pass per mesh plus one."""
        scene, nodes = self._scene(K, meshes, None, normals=False)  # the SEG shader reads positions only
        labels, _ = self._seg(scene, {node: mesh.label for node, mesh in zip(nodes, meshes)})
        amodal = np.zeros((len(meshes), self.height, self.width), dtype=bool)
        for i, node in enumerate(nodes):
            _, depth = self._seg(scene, {node: 1})  # nodes missing from the map are not drawn
            amodal[i] = depth > 0
        return labels, amodal

    def _gl(self):
        _require(self._renderer is not None, "Renderer is closed")
        return self._renderer

    def _seg(self, scene, node_labels: dict) -> tuple[np.ndarray, np.ndarray]:
        """(labels (H, W) int32, depth (H, W) float32) from one non-multisampled SEG pass."""
        import pyrender

        seg_map = {node: label_to_rgb(label) for node, label in node_labels.items()}
        color, depth = self._gl().render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
        labels = np.where(depth > 0, rgb_to_label(color), 0).astype(np.int32)
        return labels, np.ascontiguousarray(depth, dtype=np.float32)

    def _scene(self, K, meshes: list[RenderMesh], lighting: Lighting | None, normals: bool = True):
        """A pyrender Scene in the OpenCV camera frame, and the mesh nodes in ``meshes`` order (``normals``
        False: the meshes carry no normals, for SEG passes only)."""
        import pyrender

        fx, fy, cx, cy = pyrender_intrinsics(K)
        ambient = (0.0, 0.0, 0.0) if lighting is None else lighting.ambient
        scene = ordered_scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=np.asarray(ambient, np.float64))
        camera = pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=self.znear, zfar=self.zfar)
        scene.add(camera, pose=CV_TO_GL)
        nodes = [scene.add(_pyrender_mesh(mesh, normals)) for mesh in meshes]
        if lighting is not None:
            for light in lighting.directional:
                scene.add(pyrender.DirectionalLight(color=light.color, intensity=light.intensity),
                          pose=_light_pose(light.direction))
            for light in lighting.point:
                pose = np.block([[np.eye(3), np.reshape(light.position, (3, 1))], [np.zeros((1, 3)), 1.0]])
                scene.add(pyrender.PointLight(color=light.color, intensity=light.intensity), pose=pose)
        return scene, nodes


def _light_pose(direction) -> np.ndarray:
    """4x4 pose whose -z axis is ``direction`` (pyrender directional lights shine along -z)."""
    z = -np.asarray(direction, dtype=np.float64)
    z /= np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return pose


def _pyrender_mesh(mesh: RenderMesh, with_normals: bool = True):
    """A single-primitive pyrender Mesh: textured or plain, single-sided, slightly rough plastic (without
    normals when ``with_normals`` is False: enough for SEG and depth passes, which read positions only)."""
    import pyrender

    normals = None
    if with_normals:
        normals = vertex_normals(mesh.vertices, mesh.faces) if mesh.normals is None else mesh.normals
    if mesh.texture is not None:
        texture = pyrender.Texture(source=mesh.texture, source_channels="RGB")  # uploads rows flipped: v up
        material = pyrender.MetallicRoughnessMaterial(baseColorTexture=texture, metallicFactor=0.0,
                                                      roughnessFactor=0.7)
    else:
        base = np.append(srgb_to_linear(mesh.color), 1.0)
        material = pyrender.MetallicRoughnessMaterial(baseColorFactor=base, metallicFactor=0.0, roughnessFactor=0.7)
    normals = None if normals is None else np.asarray(normals, np.float32)
    primitive = pyrender.Primitive(positions=mesh.vertices.astype(np.float32), normals=normals,
                                   texcoord_0=None if mesh.uv is None else mesh.uv.astype(np.float32),
                                   indices=mesh.faces.astype(np.uint32), material=material)
    return pyrender.Mesh(primitives=[primitive])


class _InsertionOrdered(dict):
    """The part of ``set`` a pyrender Scene uses for its node groups (add, remove, in, len, iteration, |), in
    insertion order."""

    def add(self, node) -> None:
        self[node] = None

    def remove(self, node) -> None:
        del self[node]


def ordered_scene(**kwargs):
    """A pyrender Scene whose mesh and light nodes are drawn and summed in the order they were added."""
    import pyrender

    scene = pyrender.Scene(**kwargs)
    for group in ("_mesh_nodes", "_point_light_nodes", "_spot_light_nodes", "_directional_light_nodes"):
        _require(isinstance(getattr(scene, group, None), set) and not getattr(scene, group),
                 f"pyrender.Scene has no empty {group} set: this pyrender version is not supported")
        setattr(scene, group, _InsertionOrdered())
    return scene

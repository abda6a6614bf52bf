"""Tests for hoidata.render: camera convention, exact depth and labels, occlusion and amodal masks,
textures, background compositing, lighting, backgrounds and determinism."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from hoidata.errors import DataError
from hoidata.objects import load_object_mesh
from hoidata.render import (
    DirectionalLight,
    Lighting,
    PointLight,
    Renderer,
    RenderMesh,
    composite,
    load_background,
    procedural_background,
    random_lighting,
    skin_tone,
)
from hoidata.toy.objects import write_toy_objects

W, H = 640, 480
# Off-centre principal point and fx != fy, so a swapped or mis-shifted term shows up.
K = np.array([[600.0, 0.0, 310.3], [0.0, 610.0, 245.7], [0.0, 0.0, 1.0]])
OBJECT_LABEL, HAND_LABEL = 3, 255 + 7  # a label above 255 exercises the G byte of the SEG encoding
FLAT_LIGHT = Lighting(ambient=(1.0, 1.0, 1.0))  # albedo shown as is: output = texture colour


@pytest.fixture(scope="module")
def renderer():
    with Renderer(W, H) as r:
        yield r


@pytest.fixture(scope="module")
def box_mesh(tmp_path_factory):
    """The toy cracker box (textured), model frame."""
    (path,) = write_toy_objects(tmp_path_factory.mktemp("models"), names=["003_cracker_box"])
    return load_object_mesh(path)


def pose(rotvec, translation) -> np.ndarray:
    """4x4 model->camera transform from an axis-angle (rad) and a translation (m)."""
    T = np.eye(4)
    T[:3, :3] = trimesh.transformations.rotation_matrix(np.linalg.norm(rotvec), rotvec)[:3, :3] \
        if np.linalg.norm(rotvec) > 0 else np.eye(3)
    T[:3, 3] = translation
    return T


@pytest.fixture(scope="module")
def box(box_mesh):
    return RenderMesh.from_trimesh(box_mesh, pose([0.5, 0.6, 0.2], [0.0, 0.0, 0.6]), label=OBJECT_LABEL)


@pytest.fixture(scope="module")
def hand(mano_right):
    """The closed toy MANO hand, flattened toward the camera, partly in front of the box."""
    out = mano_right(torch.zeros(1, 48, dtype=torch.float64))
    vertices = mano_right.close(out.vertices)[0].numpy()
    centred = vertices - vertices.mean(0)
    axes = np.linalg.svd(centred, full_matrices=False)[2]  # rows: principal axes, largest first
    axes[2] *= np.sign(np.linalg.det(axes))  # a proper rotation keeps the faces wound outward
    placed = centred @ axes.T + [0.04, 0.03, 0.45]
    return RenderMesh(placed, mano_right.closed_faces, color=(0.8, 0.6, 0.5), label=HAND_LABEL)


def back_project(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(P, 3) camera points of pixels (OpenCV convention: pixel centres at integer u, v)."""
    z = depth[rows, cols]
    return np.stack([(cols - K[0, 2]) / K[0, 0] * z, (rows - K[1, 2]) / K[1, 1] * z, z], axis=1)


def test_depth_lies_on_surface_and_labels_match(renderer, box):
    res = renderer.render(K, [box])
    assert res.rgb.shape == (H, W, 3) and res.rgb.dtype == np.uint8
    assert res.depth.shape == (H, W) and res.depth.dtype == np.float32
    assert res.labels.dtype == np.int32
    drawn = res.depth > 0
    assert drawn.sum() > 5000
    np.testing.assert_array_equal(res.labels, np.where(drawn, OBJECT_LABEL, 0))
    rows, cols = np.nonzero(drawn)
    pick = np.random.default_rng(0).choice(len(rows), 3000, replace=False)
    points = back_project(res.depth, rows[pick], cols[pick])
    surface = trimesh.Trimesh(box.vertices, box.faces, process=False)
    _, distance, _ = trimesh.proximity.closest_point(surface, points)
    assert distance.max() < 1e-3


@pytest.mark.parametrize("u, v", [(100.0, 380.0), (530.4, 61.7)])
def test_projection_lands_on_rendered_pixel(renderer, u, v):
    z = 0.5
    centre = np.array([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.004)  # ~5 px radius on screen
    res = renderer.render(K, [RenderMesh(sphere.vertices + centre, sphere.faces, label=9)])
    rows, cols = np.nonzero(res.labels == 9)
    assert len(rows) > 40
    # A missing half-pixel shift between OpenGL and OpenCV pixel centres would give 0.5 px here.
    assert abs(cols.mean() - u) < 0.25 and abs(rows.mean() - v) < 0.25


def test_occlusion_follows_depth_and_amodal_masks(renderer, box, hand):
    alone_box, alone_hand = renderer.render(K, [box]), renderer.render(K, [hand])
    both = renderer.render(K, [box, hand])
    overlap = (alone_box.depth > 0) & (alone_hand.depth > 0)
    assert overlap.sum() > 1000  # the hand really covers part of the box
    hand_in_front = alone_hand.depth < alone_box.depth
    assert hand_in_front[overlap].mean() > 0.99
    expected = np.where(overlap, np.where(hand_in_front, HAND_LABEL, OBJECT_LABEL),
                        np.maximum(alone_box.labels, alone_hand.labels))
    np.testing.assert_array_equal(both.labels, expected)
    np.testing.assert_allclose(both.depth, np.where(overlap, np.minimum(alone_box.depth, alone_hand.depth),
                                                    np.maximum(alone_box.depth, alone_hand.depth)), atol=1e-6)

    labels, amodal = renderer.masks(K, [box, hand])
    np.testing.assert_array_equal(labels, both.labels)
    assert amodal.shape == (2, H, W) and amodal.dtype == bool
    np.testing.assert_array_equal(amodal[0], alone_box.depth > 0)
    np.testing.assert_array_equal(amodal[1], alone_hand.depth > 0)
    visible_box = labels == OBJECT_LABEL
    assert not (visible_box & ~amodal[0]).any()  # amodal is a superset of visible
    assert amodal[0].sum() > visible_box.sum() + 500  # strictly larger: the hand hides part of it
    assert not ((labels == HAND_LABEL) & ~amodal[1]).any()


def test_texture_shows(renderer, box):
    plain = RenderMesh(box.vertices, box.faces, color=(0.7, 0.7, 0.7), label=OBJECT_LABEL, normals=box.normals)
    lit = Lighting(ambient=(0.4, 0.4, 0.4))
    textured, flat = renderer.render(K, [box], lighting=lit), renderer.render(K, [plain], lighting=lit)
    np.testing.assert_array_equal(textured.labels, flat.labels)
    textured_px, plain_px = (r.rgb[textured.labels > 0].astype(float) for r in (textured, flat))
    assert textured_px.std(0).mean() > 20 and plain_px.std(0).mean() < 5
    # The toy cracker box is red with a yellow band; the plain render is grey.
    assert textured_px[:, 0].mean() > textured_px[:, 2].mean() + 40
    assert np.abs(textured_px - plain_px).mean() > 30


def test_texture_orientation_follows_obj_uv(renderer):
    """A facing quad with OBJ UVs (v up): the image's top-left quadrant shows at the top left."""
    a, z = 0.05, 0.5
    quad = [[-a, a, z], [a, a, z], [a, -a, z], [-a, -a, z]]  # bottom-left, bottom-right, top-right, top-left
    uv = [[0, 0], [1, 0], [1, 1], [0, 1]]
    texture = np.zeros((64, 64, 3), np.uint8)
    texture[:32, :32] = (255, 0, 0)  # top left red
    texture[:32, 32:] = (0, 255, 0)  # top right green
    texture[32:, :32] = (0, 0, 255)  # bottom left blue
    texture[32:, 32:] = 255  # bottom right white
    mesh = RenderMesh(quad, [[0, 1, 2], [0, 2, 3]], uv=uv, texture=texture, label=1)
    res = renderer.render(K, [mesh], lighting=FLAT_LIGHT)
    u0, v0, d = int(K[0, 2]), int(K[1, 2]), int(0.5 * a / z * K[0, 0])
    expected = {(-1, -1): (255, 0, 0), (1, -1): (0, 255, 0), (-1, 1): (0, 0, 255), (1, 1): (255, 255, 255)}
    for (sx, sy), colour in expected.items():
        np.testing.assert_allclose(res.rgb[v0 + sy * d, u0 + sx * d], colour, atol=3)


def test_background_compositing(renderer, box, hand):
    background = procedural_background(np.random.default_rng(4), W, H)
    plain = renderer.render(K, [box, hand])
    over = renderer.render(K, [box, hand], background=background)
    np.testing.assert_array_equal(over.labels, plain.labels)
    np.testing.assert_array_equal(over.depth, plain.depth)
    full, empty = over.alpha == 1.0, over.alpha == 0.0
    np.testing.assert_array_equal(over.rgb[full], plain.rgb[full])
    np.testing.assert_array_equal(over.rgb[empty], background[empty])
    assert (empty == (plain.labels == 0))[::4, ::4].mean() > 0.98  # coverage differs only on edges
    rgba = np.dstack([plain.rgb, np.round(plain.alpha * 255).astype(np.uint8)])
    np.testing.assert_array_equal(composite(rgba, None), plain.rgb)


def test_random_lighting_keeps_objects_visible(renderer, box):
    for seed in range(6):
        res = renderer.render(K, [box], lighting=random_lighting(np.random.default_rng(seed)))
        px = res.rgb[res.labels > 0].astype(float)
        assert px.mean() > 40, seed
        assert (px.min(1) == 255).mean() < 0.5, seed  # not blown out


def test_deterministic_for_same_rng(renderer, box, hand):
    def draw(seed):
        rng = np.random.default_rng(seed)
        background = procedural_background(rng, W, H)
        lighting = random_lighting(rng)
        coloured = RenderMesh(hand.vertices, hand.faces, color=skin_tone(rng), label=HAND_LABEL)
        return renderer.render(K, [box, coloured], background=background, lighting=lighting)

    first, again, other = draw(11), draw(11), draw(12)
    np.testing.assert_array_equal(first.rgb, again.rgb)
    np.testing.assert_array_equal(first.depth, again.depth)
    assert not np.array_equal(first.rgb, other.rgb)


def _quad(color, label, z=0.5, half=0.05) -> RenderMesh:
    """A square facing the camera at depth ``z``, wound toward it."""
    vertices = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return RenderMesh(vertices, np.array([[0, 2, 1], [0, 3, 2]]), color=color, label=label)


def test_surfaces_at_equal_depth_show_the_first_mesh_every_time(renderer):
    # pyrender draws a set of nodes in address order; the renderer draws ``meshes`` in order, so at equal depth
    # the first mesh wins (depth test "less"), in the colours and in the labels, render after render
    red, blue = (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    centre = (slice(H // 2 - 10, H // 2 + 10), slice(W // 2 - 10, W // 2 + 10))
    for _ in range(6):  # new meshes, new nodes at other addresses each time
        for first, second, channel in [((red, 1), (blue, 2), 0), ((blue, 2), (red, 1), 2)]:
            out = renderer.render(K, [_quad(*first), _quad(*second)], lighting=FLAT_LIGHT)
            assert (out.labels[centre] == first[1]).all()
            assert (out.rgb[centre][..., channel] > 200).all() and (out.rgb[centre][..., 2 - channel] < 30).all()


def test_scene_nodes_keep_the_order_they_were_added():
    import pyrender

    from hoidata.render.renderer import ordered_scene

    scene = ordered_scene()
    meshes = [scene.add(pyrender.Mesh.from_trimesh(trimesh.creation.box())) for _ in range(30)]
    lights = [scene.add(kind(intensity=1.0)) for _ in range(10)
              for kind in (pyrender.DirectionalLight, pyrender.PointLight, pyrender.SpotLight)]
    assert list(scene.mesh_nodes) == meshes
    assert list(scene.light_nodes) == [n for n in lights if isinstance(n.light, pyrender.PointLight)] + \
        [n for n in lights if isinstance(n.light, pyrender.SpotLight)] + \
        [n for n in lights if isinstance(n.light, pyrender.DirectionalLight)]
    scene.remove_node(meshes[3])
    assert list(scene.mesh_nodes) == meshes[:3] + meshes[4:] and meshes[3] not in scene.mesh_nodes


def test_procedural_backgrounds_vary():
    images = [procedural_background(np.random.default_rng(seed), 160, 120) for seed in range(12)]
    assert all(img.shape == (120, 160, 3) and img.dtype == np.uint8 for img in images)
    means = np.array([img.reshape(-1, 3).mean(0) for img in images])
    assert len(np.unique(np.round(means), axis=0)) == len(images)
    assert sum(img.std() > 15 for img in images) >= 6  # most are patterned, not flat


def test_skin_tones_vary_and_are_valid():
    tones = np.array([skin_tone(np.random.default_rng(seed)) for seed in range(50)])
    assert tones.shape == (50, 3) and tones.min() >= 0 and tones.max() <= 1
    assert (tones[:, 0] >= tones[:, 2] - 0.02).all()  # skin is redder than it is blue
    assert np.ptp(tones.mean(1)) > 0.4  # light to dark


def test_load_background(tmp_path):
    pixels = np.random.default_rng(0).integers(0, 256, (300, 500, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "bg.png")
    first = load_background(tmp_path / "bg.png", W, H, np.random.default_rng(1))
    again = load_background(tmp_path / "bg.png", W, H, np.random.default_rng(1))
    assert first.shape == (H, W, 3) and first.dtype == np.uint8
    np.testing.assert_array_equal(first, again)
    Image.fromarray(pixels[:5, :7]).save(tmp_path / "tiny.png")
    assert load_background(tmp_path / "tiny.png", 64, 48, np.random.default_rng(2)).shape == (48, 64, 3)

    (tmp_path / "broken.jpg").write_bytes(b"this is not an image")
    with pytest.raises(DataError, match="broken.jpg"):
        load_background(tmp_path / "broken.jpg", W, H, np.random.default_rng(0))
    with pytest.raises(DataError, match="missing.png"):
        load_background(tmp_path / "missing.png", W, H, np.random.default_rng(0))


def test_bad_inputs_raise(renderer, box):
    skewed = K.copy()
    skewed[0, 1] = 2.0
    with pytest.raises(ValueError, match="K must be"):
        renderer.render(skewed, [box])
    with pytest.raises(ValueError, match="background"):
        renderer.render(K, [box], background=np.zeros((H, W + 1, 3), np.uint8))
    with pytest.raises(ValueError, match="faces"):
        RenderMesh(np.zeros((3, 3)), [[0, 1, 3]])
    with pytest.raises(ValueError, match="uv and texture"):
        RenderMesh(np.zeros((3, 3)), [[0, 1, 2]], uv=np.zeros((3, 2)))


@pytest.mark.parametrize("light", ["directional", "point"])
def test_lights_come_from_where_they_say(renderer, light):
    """A sphere lit only from the camera's left (-x) and above (-y) is brightest up and to the left."""
    centre = np.array([0.0, 0.0, 0.5])
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.08)
    mesh = RenderMesh(sphere.vertices + centre, sphere.faces, color=(0.8, 0.8, 0.8), label=1)
    if light == "directional":
        lighting = Lighting((0.0, 0.0, 0.0), directional=[DirectionalLight((1.0, 1.0, 0.3), intensity=3.0)])
    else:
        lighting = Lighting((0.0, 0.0, 0.0), point=[PointLight((-0.4, -0.4, 0.4), intensity=1.0)])
    res = renderer.render(K, [mesh], lighting=lighting)
    rows, cols = np.nonzero(res.labels == 1)
    brightness = res.rgb[rows, cols].astype(float).sum(1)
    lit = brightness > np.percentile(brightness, 90)
    assert cols[lit].mean() < cols.mean() - 20 and rows[lit].mean() < rows.mean() - 20

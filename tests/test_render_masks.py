"""Tests for hoidata.render.masks.MaskRenderer: the same label maps and amodal masks as pyrender's
Renderer.masks (which build-sdf used before), its limits, and closing renderers independently."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from hoidata.render import Renderer, RenderMesh
from hoidata.render.masks import MAX_MESHES, MaskRenderer
from hoidata.toy.objects import TOY_OBJECTS, build_toy_object

SIZE = 96


def crop_K(rng) -> np.ndarray:
    """Intrinsics of a crop-like view: focal length and principal point vary, fx != fy."""
    f = rng.uniform(120, 260)
    return np.array([[f, 0.0, SIZE / 2 + rng.uniform(-8, 8)], [0.0, f * rng.uniform(0.97, 1.03),
                     SIZE / 2 + rng.uniform(-8, 8)], [0.0, 0.0, 1.0]])


def scene(mano, rng, name: str) -> list[RenderMesh]:
    """A posed closed toy hand and a toy object placed at, and often through, the hand (camera frame, m)."""
    pose = torch.as_tensor(rng.normal(0, 0.4, (1, 48)))
    pose[0, :3] = torch.as_tensor(Rotation.random(random_state=rng).as_rotvec())
    hand = mano.close(mano(pose).vertices)[0].numpy()
    hand = hand - hand.mean(0) + [0.0, 0.0, rng.uniform(0.35, 0.6)]
    vertices, faces, _ = build_toy_object(name)
    R = Rotation.random(random_state=rng).as_matrix()
    placed = (vertices - vertices.mean(0)) @ R.T + hand.mean(0) + rng.normal(0, 0.03, 3)
    return [RenderMesh(hand, mano.closed_faces, label=1), RenderMesh(placed, faces, label=2)]


@pytest.fixture()
def renderers():
    with Renderer(SIZE, SIZE) as reference, MaskRenderer(SIZE, SIZE) as fast:
        yield reference, fast


@pytest.mark.slow
def test_same_masks_as_pyrender(renderers, mano_right):
    reference, fast = renderers
    rng = np.random.default_rng(7)
    names = sorted(TOY_OBJECTS)
    both_visible, ties = 0, 0
    for i in range(24):
        K, meshes = crop_K(rng), scene(mano_right, rng, names[i % len(names)])
        labels, amodal = fast.masks(K, meshes)
        want_labels, want_amodal = reference.masks(K, meshes)
        assert labels.dtype == want_labels.dtype and amodal.dtype == want_amodal.dtype == bool
        np.testing.assert_array_equal(amodal, want_amodal)
        # where both meshes have the very same depth, pyrender's winner depends on the order of a set of scene
        # nodes (it changes between Renderer instances); ours is the first mesh given
        hand_depth, object_depth = (reference.render(K, [mesh]).depth for mesh in meshes)
        tie = amodal[0] & amodal[1] & (hand_depth == object_depth)
        np.testing.assert_array_equal(labels[~tie], want_labels[~tie])
        assert (labels[tie] == 1).all()
        ties += int(tie.sum())
        both_visible += bool((labels == 1).any() and (labels == 2).any() and (amodal[0] & amodal[1]).any())
    assert both_visible >= 12  # most frames have the hand and the object overlapping on screen
    assert ties <= 3  # ties are rare (one pixel in these 24 frames)


def test_other_labels_and_mesh_counts(renderers, mano_right):
    reference, fast = renderers
    rng = np.random.default_rng(3)
    hand, obj = scene(mano_right, rng, "006_mustard_bottle")
    K = crop_K(rng)
    for meshes in ([hand], [RenderMesh(obj.vertices, obj.faces, label=0), RenderMesh(hand.vertices, hand.faces,
                    label=255)], [hand, obj, RenderMesh(obj.vertices + [0.01, 0, 0], obj.faces, label=9)]):
        for got, want in zip(fast.masks(K, meshes), reference.masks(K, meshes)):
            np.testing.assert_array_equal(got, want)


def test_limits_and_closing(renderers, mano_right):
    _, fast = renderers
    hand, obj = scene(mano_right, np.random.default_rng(0), "025_mug")
    K = crop_K(np.random.default_rng(0))
    with pytest.raises(ValueError, match="at most 3 meshes"):
        fast.masks(K, [hand, obj] * 2)
    assert MAX_MESHES == 3
    with pytest.raises(ValueError, match="labels 0..255"):
        fast.masks(K, [RenderMesh(hand.vertices, hand.faces, label=256)])
    other = MaskRenderer(SIZE, SIZE)
    other.close()
    other.close()  # idempotent
    with pytest.raises(ValueError, match="closed"):
        other.masks(K, [hand])
    # closing one MaskRenderer leaves the others (and pyrender's) drawing
    labels, _ = fast.masks(K, [hand, obj])
    assert (labels > 0).any()


def test_draws_on_after_pyrender_terminates_the_display(mano_right):
    """pyrender's close terminates the process's EGL display (every context on it); a MaskRenderer then makes
    itself a new context instead of failing the build."""
    rng = np.random.default_rng(5)
    K, meshes = crop_K(rng), scene(mano_right, rng, "011_banana")
    with MaskRenderer(SIZE, SIZE) as fast:
        before = fast.masks(K, meshes)
        Renderer(8, 8).close()
        after = fast.masks(K, meshes)
    for got, want in zip(after, before):
        np.testing.assert_array_equal(got, want)

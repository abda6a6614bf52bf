"""Tests for hoidata.synth: contact checks (fcl, libigl) and grasp synthesis on the toy objects.

The physical checks here are independent of the code under test: penetration is measured with
trimesh (ray-parity ``contains`` plus nearest-surface distance), contacts with trimesh's nearest
points, and the palm frame is recomputed from the MANO joints.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from hoidata.objects import load_object_mesh, repair_mesh
from hoidata.synth import (
    Grasp,
    HandObjectCollision,
    penetration_depth,
    signed_distance,
    synthesize_grasp,
)
from hoidata.toy.objects import TOY_OBJECTS, write_toy_objects

MAX_PENETRATION = 0.002  # metres
SEED = 7
# MANO-order joints: finger parts for the independent contact count, and the palm landmarks.
FINGER_PARTS = {"thumb": (14, 15), "index": (1, 2, 3), "middle": (4, 5, 6), "ring": (10, 11, 12), "pinky": (7, 8, 9)}
FINGER_POSE_JOINTS = {"index": (1, 2, 3), "middle": (4, 5, 6), "ring": (10, 11, 12), "pinky": (7, 8, 9)}
WRIST, INDEX_MCP, MIDDLE_MCP, PINKY_MCP = 0, 1, 4, 7
TIPS = (4, 8, 12, 16, 20)  # fingertips in the 21-joint DexYCB order


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    models = tmp_path_factory.mktemp("models")
    return {path.parent.name: repair_mesh(load_object_mesh(path))[0] for path in write_toy_objects(models)}


@pytest.fixture(scope="module")
def manos(mano_right, mano_left):
    return {"right": mano_right, "left": mano_left}


@pytest.fixture(scope="module")
def grasps(meshes, manos):
    """One grasp per (object, side), the same seed for all."""
    return {(name, side): synthesize_grasp(mano, mesh.vertices, mesh.faces, np.random.default_rng(SEED), name=name)
            for name, mesh in meshes.items() for side, mano in manos.items()}


def forward(mano, grasp: Grasp):
    """MANO output of a grasp: the hand in the object's frame."""
    as_t = lambda a: torch.as_tensor(a, dtype=torch.float64)[None]
    with torch.no_grad():
        return mano(as_t(grasp.pose), as_t(grasp.betas), as_t(grasp.transl))


def palm(mano_joints: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Palm centre and unit palm normal from MANO-order joints (16, 3), recomputed here."""
    centre = mano_joints[[0, 1, 4, 7, 10]].mean(0)
    normal = np.cross(mano_joints[INDEX_MCP] - mano_joints[PINKY_MCP], mano_joints[MIDDLE_MCP] - mano_joints[WRIST])
    normal *= 1.0 if side == "right" else -1.0
    return centre, normal / np.linalg.norm(normal)


def depth_inside(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Independent penetration of points (N, 3): nearest-surface distance where trimesh says inside."""
    inside = mesh.contains(points)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    return np.where(inside, dist, 0.0)


CASES = [(name, side) for name in TOY_OBJECTS for side in ("right", "left")]


@pytest.mark.parametrize("name,side", CASES)
def test_grasp_does_not_penetrate(grasps, meshes, manos, name, side):
    grasp, mesh = grasps[name, side], meshes[name]
    vertices = forward(manos[side], grasp).vertices[0].numpy()
    assert grasp.side == side
    assert grasp.pose.shape == (48,) and grasp.betas.shape == (10,) and grasp.transl.shape == (3,)
    assert grasp.penetration <= MAX_PENETRATION
    assert depth_inside(mesh, vertices).max() <= MAX_PENETRATION + 1e-4


@pytest.mark.parametrize("name,side", CASES)
def test_grasp_touches_with_fingers(grasps, meshes, manos, name, side):
    grasp, mesh, mano = grasps[name, side], meshes[name], manos[side]
    vertices = forward(mano, grasp).vertices[0].numpy()
    _, dist, _ = trimesh.proximity.closest_point(mesh, vertices)
    assert (dist <= 0.005).sum() >= 20
    assert grasp.n_contacts >= 20
    touching = [finger for finger, parts in FINGER_PARTS.items()
                if dist[np.isin(mano.vertex_parts, parts)].min() <= 0.005]
    assert len(touching) >= 3, touching
    assert len(grasp.fingers_in_contact) >= 3
    assert set(grasp.fingers_in_contact) <= set(touching)


@pytest.mark.parametrize("name,side", CASES)
def test_grasp_is_a_curled_hand_facing_the_object(grasps, meshes, manos, name, side):
    grasp, mesh = grasps[name, side], meshes[name]
    out = forward(manos[side], grasp)
    # Fingers curled: at least two of the four fingers bent by more than ~17 degrees in all.
    bends = [sum(np.linalg.norm(grasp.pose[3 * j:3 * j + 3]) for j in joints) for joints in FINGER_POSE_JOINTS.values()]
    assert sum(b > 0.3 for b in bends) >= 2, bends
    # ... but no fingertip buried in the object, and the hand stays next to it.
    tips = out.joints[0, list(TIPS)].numpy()
    assert depth_inside(mesh, tips).max() <= MAX_PENETRATION
    centre, normal = palm(out.mano_joints[0].numpy(), side)
    _, palm_gap, _ = trimesh.proximity.closest_point(mesh, centre[None])
    assert palm_gap[0] < 0.06  # the palm centre lies ~1.5 cm inside the palm: the hand is at the object
    to_object = mesh.center_mass - centre
    angle = np.degrees(np.arccos(np.clip(normal @ to_object / np.linalg.norm(to_object), -1.0, 1.0)))
    assert angle <= 60.0, angle


def test_palm_normal_points_to_the_curled_fingertips(manos):
    # Axis-free check of the normal's sign on both sides: curled fingertips lie on the palm side.
    for side, mano in manos.items():
        pose = torch.zeros(1, 48, dtype=torch.float64)
        pose[0, 3:] = mano.hands_mean
        out = mano(pose)
        centre, normal = palm(out.mano_joints[0].numpy(), side)
        assert ((out.joints[0, list(TIPS[1:])].numpy() - centre) @ normal > 0.01).all(), side


def test_same_seed_same_grasp(meshes, mano_right):
    mesh = meshes["006_mustard_bottle"]
    a, b, c = (synthesize_grasp(mano_right, mesh.vertices, mesh.faces, np.random.default_rng(seed))
               for seed in (3, 3, 4))
    assert np.array_equal(a.pose, b.pose) and np.array_equal(a.transl, b.transl)
    assert a.fingers_in_contact == b.fingers_in_contact and a.penetration == b.penetration
    assert not np.allclose(a.pose, c.pose)


def test_grasp_with_hand_shape(meshes, mano_left):
    mesh, betas = meshes["025_mug"], np.random.default_rng(1).normal(0.0, 1.0, 10)
    grasp = synthesize_grasp(mano_left, mesh.vertices, mesh.faces, np.random.default_rng(2), betas=betas)
    np.testing.assert_array_equal(grasp.betas, betas)
    assert depth_inside(mesh, forward(mano_left, grasp).vertices[0].numpy()).max() <= MAX_PENETRATION + 1e-4
    assert len(grasp.fingers_in_contact) >= 3


def test_given_approach_is_used(meshes, mano_left):
    mesh = meshes["002_master_chef_can"]
    grasp = synthesize_grasp(mano_left, mesh.vertices, mesh.faces, np.random.default_rng(0), approach=(2.0, 0.0, 0.0))
    np.testing.assert_allclose(grasp.approach, [1.0, 0.0, 0.0])
    centre, normal = palm(forward(mano_left, grasp).mano_joints[0].numpy(), "left")
    assert normal[0] > 0.99  # the palm faces +x ...
    assert centre[0] < -mesh.extents[0] / 2  # ... from beyond the can's -x side


def test_impossible_grasp_names_the_object(meshes, mano_right):
    mesh = meshes["003_cracker_box"]
    with pytest.raises(RuntimeError, match="003_cracker_box.*16.0 x 21.0 x 7.0 cm"):
        synthesize_grasp(mano_right, mesh.vertices, mesh.faces, np.random.default_rng(0), max_penetration=-1.0,
                         max_tries=2, name="003_cracker_box")


# ---------------------------------------------------------------- constructed configurations

def hand_over_box(mano, box: trimesh.Trimesh, height: float) -> np.ndarray:
    """The flat hand, palm down over the box's top face and fingers along +y, placed so that its
    lowest vertex above the face (5 mm inside its edges) is ``height`` metres above the face
    (negative: pushed in). Returns the closed hand vertices (779, 3)."""
    with torch.no_grad():
        out = mano(torch.zeros(1, 48, dtype=torch.float64))
        closed = mano.close(out.vertices)[0].numpy()
    centre, normal = palm(out.mano_joints[0].numpy(), mano.side)
    forward_dir = out.mano_joints[0, MIDDLE_MCP].numpy() - out.mano_joints[0, WRIST].numpy()
    rot, _ = Rotation.align_vectors([[0, 0, -1], [0, 1, 0]], [normal, forward_dir], weights=[100, 1])
    hand = rot.apply(closed - centre)
    lo, hi = box.bounds
    over = np.all((hand[:, :2] > lo[:2] + 0.005) & (hand[:, :2] < hi[:2] - 0.005), axis=1)
    return hand + [0.0, 0.0, hi[2] + height - hand[over, 2].min()]


def test_collision_agrees_with_igl(meshes, mano_right):
    box = meshes["003_cracker_box"]
    check = HandObjectCollision(box.vertices, box.faces)
    faces = mano_right.closed_faces
    for height, colliding in ((-0.01, True), (0.01, False), (0.003, False)):
        hand = hand_over_box(mano_right, box, height)
        sd = signed_distance(hand, box.vertices, box.faces)
        assert (sd.min() < 0) == colliding == check.collides(hand, faces)
        if colliding:
            assert check.distance(hand, faces) == 0.0
        else:
            # The mesh-mesh distance is at most the nearest vertex's, and near it for a flat hand
            # over a box (an edge can come a little closer than any vertex).
            assert sd.min() - 1e-3 < check.distance(hand, faces) <= sd.min() + 1e-9
    near = check.contact_vertices(hand_over_box(mano_right, box, 0.002), within=0.005)
    assert len(near) > 0
    _, dist, _ = trimesh.proximity.closest_point(box, hand_over_box(mano_right, box, 0.002)[near])
    assert dist.max() <= 0.005 + 1e-9
    assert len(check.contact_vertices(hand_over_box(mano_right, box, 0.01))) == 0


def test_penetration_depth_of_a_pushed_hand(meshes, mano_right):
    box = meshes["003_cracker_box"]
    pushed = hand_over_box(mano_right, box, -0.01)
    assert penetration_depth(pushed, box.vertices, box.faces) == pytest.approx(0.01, abs=0.002)
    assert penetration_depth(pushed, box.vertices, box.faces, mano_right.closed_faces) == pytest.approx(0.01, abs=0.002)
    clear = hand_over_box(mano_right, box, 0.003)
    assert penetration_depth(clear, box.vertices, box.faces, mano_right.closed_faces) == 0.0

"""Grasp synthesis: place a MANO hand against an object and close the fingers until contact.

Everything is in the object's model frame, metres: a :class:`Grasp` holds MANO parameters whose
forward pass gives the hand directly in object coordinates. The recipe, per attempt:

1. an approach direction (random over the sphere, or given) and a random roll about it;
2. the open hand is rotated so the palm normal points along the approach, aimed at the object's
   volume centroid, and slid in (fcl distance, conservative advancement) until it is
   ``palm_gap`` from the surface; then it squares up to the surface nearest the palm and slides
   in again, so an oblique approach to a flat face does not leave the palm hovering;
3. each finger is closed independently along a scaled copy of its slice of MANO's ``hands_mean``
   until it touches (:func:`hoidata.synth.closing.close_fingers`);
4. the result is checked (the same two-sided penetration as
   :func:`hoidata.synth.contact.penetration_depth`, contact counts); an attempt that fails is
   retried with a new direction and roll, and a valid one that does not wrap the object (thumb
   plus two curled fingers on it) is kept only if no wrapping one turns up within a few tries.

Nothing depends on the hand's rest axes: the palm frame comes from the MANO joints.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hoidata.synth.closing import (
    CONTACT_JOINTS,
    FINGERS,
    OPEN_SCALES,
    close_fingers,
    finger_basis,
    finger_min_distance,
    finger_samples,
    hand_forward,
)
from hoidata.synth.contact import (
    CONTACT_DISTANCE,
    HandObjectCollision,
    object_in_hand_depth,
)

WRIST, INDEX_MCP, MIDDLE_MCP, RING_MCP, PINKY_MCP = 0, 1, 4, 10, 7  # MANO-order joint ids
PALM_GAP = 0.004  # the open hand stops this far from the surface (m)
FINGER_CONTACT = 0.002  # a finger with a surface point this close (or inside) is "in contact" (m)
MAX_OFF_CENTRE_DEG = 45.0  # a squared-up palm still faces the object's centroid within this angle
WRAP_SCALE = 0.3  # a finger closed at least this far (scale of hands_mean) is curled, not flat


@dataclass
class Grasp:
    """A hand pose on an object, in the object's model frame.

    ``mano(pose[None], betas[None], transl[None]).vertices`` is the hand in object coordinates (m).

    Attributes:
        pose: (48,) float64 flat-hand-mean axis-angle (global rotation, then 15 joints, MANO order).
        betas: (10,) float64 shape coefficients.
        transl: (3,) float64 metres, added after posing.
        penetration: deepest hand-object interpenetration, metres (see ``penetration_depth``).
        n_contacts: hand vertices within 5 mm of the object surface (or inside it).
        fingers_in_contact: names among ``FINGERS`` with a point of the finger within 2 mm of the
            surface (or inside); for the thumb only its two distal segments count, the first is
            the thenar eminence of the palm.
        side: 'right' or 'left'.
        finger_scales: (5,) closing scale of ``hands_mean`` per finger, thumb..pinky.
        approach: (3,) unit approach direction (the palm normal), object frame.
    """

    pose: np.ndarray
    betas: np.ndarray
    transl: np.ndarray
    penetration: float
    n_contacts: int
    fingers_in_contact: list[str]
    side: str
    finger_scales: np.ndarray = field(default_factory=lambda: np.zeros(5))
    approach: np.ndarray = field(default_factory=lambda: np.zeros(3))


# ---------------------------------------------------------------- pure math

def palm_frame(mano_joints: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Palm centre, palm normal and finger direction from MANO-order joints.

    Args:
        mano_joints: (16, 3) MANO-order joints, metres, any frame.
        side: 'right' or 'left'; mirroring flips the handedness of the cross product.

    Returns:
        centre (3,): mean of the wrist and the four MCP joints (inside the palm, metres);
        normal (3,): unit vector out of the palm's inner (grasping) side;
        forward (3,): unit wrist -> middle-MCP direction, orthogonal to ``normal``.
    """
    j = np.asarray(mano_joints, dtype=np.float64)
    centre = j[[WRIST, INDEX_MCP, MIDDLE_MCP, RING_MCP, PINKY_MCP]].mean(0)
    across = j[INDEX_MCP] - j[PINKY_MCP]
    forward = j[MIDDLE_MCP] - j[WRIST]
    normal = np.cross(across, forward) * (1.0 if side == "right" else -1.0)
    normal /= np.linalg.norm(normal)
    forward = forward - (forward @ normal) * normal
    return centre, normal, forward / np.linalg.norm(forward)


def roll_direction(approach: np.ndarray, roll: float) -> np.ndarray:
    """Unit vector (3,) perpendicular to the unit ``approach`` (3,), at angle ``roll`` (radians)
    from a reference built on the world axis least parallel to the approach."""
    approach = np.asarray(approach, dtype=np.float64)
    u = np.cross(approach, np.eye(3)[np.argmin(np.abs(approach))])
    u /= np.linalg.norm(u)
    return np.cos(roll) * u + np.sin(roll) * np.cross(approach, u)


def hand_rotation(normal: np.ndarray, forward: np.ndarray, approach: np.ndarray,
                  target_forward: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) taking the rest palm frame (``normal``, ``forward``: unit, orthogonal, (3,))
    to the frame whose normal is the unit ``approach`` and whose forward is ``target_forward``
    made perpendicular to it (it must not be parallel to the approach)."""
    approach = np.asarray(approach, dtype=np.float64)
    target_forward = target_forward - (target_forward @ approach) * approach
    target_forward = target_forward / np.linalg.norm(target_forward)
    target = np.stack([approach, target_forward, np.cross(approach, target_forward)], 1)
    rest = np.stack([normal, forward, np.cross(normal, forward)], 1)
    return target @ rest.T


def volume_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroid (3,) of the solid bounded by a closed mesh (vertices (V, 3), faces (F, 3)), via
    signed tetrahedra against the origin; falls back to the vertex mean for a degenerate mesh."""
    tri = np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]
    volumes = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    total = volumes.sum()
    if abs(total) < 1e-12:
        return np.asarray(vertices, dtype=np.float64).mean(0)
    return (volumes[:, None] * tri.sum(1) / 4.0).sum(0) / total


def sample_direction(rng: np.random.Generator) -> np.ndarray:
    """A unit vector (3,) uniform over the sphere (normalised isotropic Gaussian)."""
    while True:
        d = rng.normal(size=3)
        n = np.linalg.norm(d)
        if n > 1e-9:
            return d / n


# ---------------------------------------------------------------- the steps

def slide_to_gap(collision: HandObjectCollision, hand, start: np.ndarray, direction: np.ndarray, gap: float,
                 travel: float, tol: float = 3e-4, max_iter: int = 64) -> float | None:
    """Conservative advancement of a rigid hand along ``direction`` until it is ``gap`` from the object.

    Moving by ``delta`` shrinks a distance by at most ``delta``, so stepping by (distance - gap)
    never passes through the surface.

    Args:
        collision: the object's fcl wrapper.
        hand: fcl object of the hand mesh (see ``HandObjectCollision.hand_object``).
        start: (3,) translation of the hand mesh at which it is clear of the object, metres.
        direction: (3,) unit direction of travel.
        gap: target clearance, metres.
        travel: the longest slide, metres.

    Returns:
        The distance slid (m), or None if the hand passes the object or starts in collision.
    """
    s = 0.0
    for _ in range(max_iter):
        d = collision.translated_distance(hand, start + s * direction)
        if d <= 0.0:
            return None
        if d <= gap + tol:
            return s
        s += d - gap
        if s > travel:
            return None
    return None  # a glancing approach that keeps creeping along the surface: try another one


def evaluate_grasp(mano, pose: np.ndarray, betas: np.ndarray, transl: np.ndarray, collision: HandObjectCollision,
                   contact_samples: list | None = None) -> tuple[float, int, list[str]]:
    """Penetration (m), contact count and fingers in contact of MANO parameters pose (48,),
    betas (10,), transl (3,) against the object of ``collision``.

    The count is of hand vertices within 5 mm of the surface (or inside); a finger is in contact
    when a point of its contact parts (``contact_samples``, default
    ``finger_samples(mano, joints=CONTACT_JOINTS)``) lies within 2 mm.
    """
    if contact_samples is None:
        contact_samples = finger_samples(mano, joints=CONTACT_JOINTS)
    ref = mano.v_template
    as_t = lambda a: torch.as_tensor(np.asarray(a)[None], dtype=ref.dtype)
    with torch.no_grad():
        vertices = mano(as_t(pose), as_t(betas), as_t(transl)).vertices
        closed = mano.close(vertices)[0].cpu().numpy().astype(np.float64)
    # The same two checks as penetration_depth, sharing the hand's distances with the contact count.
    sd = collision.signed_distances(closed[: vertices.shape[1]])
    depth = max(0.0, -float(sd.min()), object_in_hand_depth(collision.obj_vertices, closed, mano.closed_faces))
    n_contacts = int((sd <= CONTACT_DISTANCE).sum())
    mins = finger_min_distance(closed[None, : vertices.shape[1]], contact_samples, list(range(len(FINGERS))),
                               collision, band=CONTACT_DISTANCE)[0]
    return depth, n_contacts, [name for name, d in zip(FINGERS, mins) if d <= FINGER_CONTACT]


def place_hand(mano, collision: HandObjectCollision, aim: np.ndarray, direction: np.ndarray,
               target_forward: np.ndarray, betas: np.ndarray, rest, basis: np.ndarray,
               palm_gap: float) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Turn the open hand so its palm faces along ``direction`` (unit, (3,)) with its fingers
    towards ``target_forward`` (3,), and slide it along the line through ``aim`` (3,) until it is
    ``palm_gap`` metres from the object.

    ``rest`` is :func:`palm_frame` of the unposed hand with these ``betas``; ``basis`` is
    ``finger_basis(mano.hands_mean)``. Returns the global axis-angle (3,), transl (3,) m and palm
    centre (3,) m, or None when the hand finds no clear stop on that line.
    """
    _, normal0, forward0 = rest
    rotvec = Rotation.from_matrix(hand_rotation(normal0, forward0, direction, target_forward)).as_rotvec()
    vertices, joints = hand_forward(mano, rotvec, np.asarray(OPEN_SCALES), betas, np.zeros(3), basis)
    centre = palm_frame(joints[0], mano.side)[0]
    with torch.no_grad():
        local = mano.close(torch.as_tensor(vertices)).numpy()[0] - centre  # the open hand about its palm centre
    radius = float(np.linalg.norm(collision.obj_vertices - aim, axis=1).max())
    far = radius + float(np.linalg.norm(local, axis=1).max()) + 2 * palm_gap  # clear of the object from here
    hand = collision.hand_object(local, mano.closed_faces)
    slid = slide_to_gap(collision, hand, aim - far * direction, direction, palm_gap, travel=2 * far)
    if slid is None:
        return None
    palm_centre = aim + (slid - far) * direction
    return rotvec, palm_centre - centre, palm_centre


def _attempt(mano, collision, aim, betas, direction, roll, palm_gap, rest, basis, samples, contact_samples,
             square_up: bool) -> Grasp | str:
    """One placement + closing: a Grasp, or a short reason why the placement failed."""
    forward = roll_direction(direction, roll)
    placed = place_hand(mano, collision, aim, direction, forward, betas, rest, basis, palm_gap)
    if placed is None:
        return "the open hand found no clear stop along the approach"
    if square_up:
        # Face the surface under the palm squarely: an oblique approach to a flat face otherwise
        # stops on the heel of the hand or the fingertips, with the palm hovering centimetres away.
        closest, normal = collision.nearest_surface(placed[2][None])
        squared = -normal[0] / np.linalg.norm(normal[0])
        if squared @ direction < np.cos(np.radians(2.0)) and abs(squared @ forward) < 0.99:
            again = place_hand(mano, collision, closest[0], squared, forward, betas, rest, basis, palm_gap)
            # Keep the palm turned towards the object as a whole: squaring up to the far end of a
            # banana would leave the palm facing past the object.
            if again is not None and _facing(squared, aim - again[2]) >= np.cos(np.radians(MAX_OFF_CENTRE_DEG)):
                placed, direction = again, squared
    rotvec, transl, _ = placed
    scales = close_fingers(mano, rotvec, betas, transl, collision, samples=samples)
    pose = np.concatenate([rotvec, scales @ basis])
    depth, n_contacts, fingers = evaluate_grasp(mano, pose, betas, transl, collision, contact_samples)
    return Grasp(pose, betas.copy(), transl, depth, n_contacts, fingers, mano.side, scales, direction.copy())


def _facing(normal: np.ndarray, to_centre: np.ndarray) -> float:
    """Cosine between a unit palm normal (3,) and the direction (3,) to the object centre."""
    return float(normal @ to_centre) / max(float(np.linalg.norm(to_centre)), 1e-12)


def _problem(grasp: Grasp | str, max_penetration: float, min_fingers: int, min_contacts: int) -> str:
    """Why an attempt is not a valid grasp ('' when it is)."""
    if isinstance(grasp, str):
        return grasp
    if grasp.penetration > max_penetration:
        return f"penetration above {max_penetration * 1000:.1f} mm"
    if len(grasp.fingers_in_contact) < min_fingers:
        return f"fewer than {min_fingers} fingers in contact"
    if grasp.n_contacts < min_contacts:
        return f"fewer than {min_contacts} hand vertices within 5 mm"
    return ""


def _wraps(grasp: Grasp) -> bool:
    """A grasp proper rather than a touch: the thumb on the object, opposing at least two other
    fingers that touch it curled (scale >= WRAP_SCALE) instead of lying flat along a face."""
    curled = [name for name, scale in zip(FINGERS[1:], grasp.finger_scales[1:])
              if name in grasp.fingers_in_contact and scale >= WRAP_SCALE]
    return "thumb" in grasp.fingers_in_contact and len(curled) >= 2


def _score(grasp: Grasp) -> tuple:
    # Opposition first, then how many fingers touch, then how much of the hand does.
    return ("thumb" in grasp.fingers_in_contact, len(grasp.fingers_in_contact), grasp.n_contacts)


@contextmanager
def _torch_threads(n: int | None):
    """Run the block with ``n`` torch intra-op threads (None: leave them), restoring them after."""
    before = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def synthesize_grasp(mano, obj_vertices, obj_faces, rng: np.random.Generator, betas=None, approach=None,
                     max_penetration: float = 0.002, min_fingers: int = 3, min_contacts: int = 20,
                     max_tries: int = 24, wrap_tries: int = 6, palm_gap: float = PALM_GAP, square_up: bool = True,
                     name: str = "object", collision: HandObjectCollision | None = None,
                     torch_threads: int | None = 1) -> Grasp:
    """A physically checked grasp of a MANO hand on one object, in the object's frame.

    Args:
        mano: ``hoidata.hand.MANO`` layer, either side (float64 recommended).
        obj_vertices: (V, 3) object vertices, metres, model frame.
        obj_faces: (F, 3) triangles; the mesh must be watertight and wound outward
            (``hoidata.objects.repair_mesh``).
        rng: ``np.random.Generator``; all randomness comes from it, so a seed fixes the grasp.
        betas: (10,) hand shape, default zeros.
        approach: optional (3,) direction the palm faces and moves along (object frame), aimed at
            the object's volume centroid; default random over the sphere. Retries then only
            change the roll about it.
        max_penetration: accepted interpenetration, metres (see ``penetration_depth``).
        min_fingers: fingers that must touch (within 2 mm); min_contacts: hand vertices that must
            lie within 5 mm of the surface.
        max_tries: attempts (new direction and roll each) before giving up.
        wrap_tries: a valid grasp that wraps the object (the thumb and at least two curled
            fingers on it) is returned at once; after this many attempts the best valid one so
            far (thumb contact, then most fingers, then contacts) is taken instead.
        palm_gap: clearance of the open hand when it stops, metres.
        square_up: once the hand has stopped, turn it to face the surface nearest the palm
            centre squarely (against its normal) and slide it in again; ``Grasp.approach`` is
            then that direction.
        name: object name for error messages.
        collision: a prebuilt ``HandObjectCollision`` of this object, to reuse its BVH.
        torch_threads: torch intra-op threads while synthesising (restored after; None leaves
            them alone). MANO batches here are small (<= 16 hands), so one thread is as fast,
            and it avoids the large slowdowns of oversubscribed cores when several generator
            processes share a machine.

    Returns:
        A :class:`Grasp` that passes every check.

    Raises:
        RuntimeError: no attempt passed; the message names the object, its size and the reasons.
    """
    vertices = np.asarray(obj_vertices, dtype=np.float64)
    collision = collision if collision is not None else HandObjectCollision(vertices, obj_faces)
    betas = np.zeros(10) if betas is None else np.asarray(betas, dtype=np.float64).reshape(10)
    aim = volume_centroid(vertices, collision.obj_faces)
    best, reasons = None, []
    with _torch_threads(torch_threads):
        basis = finger_basis(mano.hands_mean.cpu().numpy())
        rest = palm_frame(hand_forward(mano, np.zeros(3), np.zeros(5), betas, np.zeros(3), basis)[1][0], mano.side)
        samples, contact_samples = finger_samples(mano), finger_samples(mano, joints=CONTACT_JOINTS)
        for attempt in range(max_tries):
            if approach is None:
                direction = sample_direction(rng)
            else:
                direction = np.asarray(approach, dtype=np.float64) / np.linalg.norm(approach)
            roll = rng.uniform(0.0, 2.0 * np.pi)
            grasp = _attempt(mano, collision, aim, betas, direction, roll, palm_gap, rest, basis, samples,
                             contact_samples, square_up)
            reason = _problem(grasp, max_penetration, min_fingers, min_contacts)
            if not reason:
                if _wraps(grasp):
                    return grasp
                best = grasp if best is None or _score(grasp) > _score(best) else best
                reason = "valid, but the fingers do not wrap the object"
            if best is not None and attempt + 1 >= wrap_tries:
                return best
            reasons.append(reason)
    size = " x ".join(f"{e * 100:.1f}" for e in vertices.max(0) - vertices.min(0))
    summary = "; ".join(f"{r} ({reasons.count(r)}x)" for r in dict.fromkeys(reasons))
    raise RuntimeError(f"no valid {mano.side}-hand grasp of {name} ({size} cm, {len(collision.obj_faces)} faces) "
                       f"in {max_tries} tries: {summary}")

"""Closing MANO fingers onto an object, each finger independently, batched through MANO.

A finger's closure is one number: the scale of its slice of MANO's ``hands_mean`` (a relaxed,
curled grasp), so scale 0 is the flat finger and ~2.5 a tight fist. A finger closes until its
surface touches the object; fingers are kinematically independent in MANO (each chain hangs off
the root), so one batched forward pass evaluates every finger at many closures at once.

Positions are metres in the frame of the MANO output (the object's frame in grasp synthesis).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import torch

from hoidata.synth.contact import HandObjectCollision, surface_samples

FINGERS = ("thumb", "index", "middle", "ring", "pinky")
# MANO-order joint ids of each finger's three joints (MANO order: index, middle, pinky, ring, thumb).
FINGER_JOINTS = {"thumb": (13, 14, 15), "index": (1, 2, 3), "middle": (4, 5, 6), "ring": (10, 11, 12),
                 "pinky": (7, 8, 9)}
# A finger touches the object with these parts; the thumb's first segment is the thenar
# eminence, part of the palm, so touching with it alone is not a thumb contact.
CONTACT_JOINTS = {**FINGER_JOINTS, "thumb": (14, 15)}

# Scales of hands_mean per finger (thumb..pinky). The open thumb is swung slightly backwards (it
# would otherwise hang ~1 cm below the palm and meet the object first); the other fingers open flat.
OPEN_SCALES = (-0.5, 0.0, 0.0, 0.0, 0.0)
# Beyond ~1.5 the procedural thumb folds back towards the wrist; 2.5 is a tight fist.
CLOSED_SCALES = (1.5, 2.5, 2.5, 2.5, 2.5)
TOUCH = 0.0015  # a finger stops once a point of its surface is this close to the object (m)
STEP_PENETRATION = 0.001  # deepest penetration a single closing step may end with (m)
LADDER_BAND = 0.005  # a closing step moves a point <= 3.6 mm (5 mm for betas = 2), under twice this (m)
SAMPLE_SPACING = 0.01  # finger faces with longer edges are probed between their corners too (m)


# ---------------------------------------------------------------- pure math

def finger_basis(hands_mean: np.ndarray) -> np.ndarray:
    """(5, 45) rows: ``hands_mean`` (45,) masked to each finger (thumb..pinky), so that
    ``scales (B, 5) @ basis`` is the 45 finger pose values with each finger closed by its scale."""
    hands_mean = np.asarray(hands_mean, dtype=np.float64).reshape(15, 3)
    basis = np.zeros((len(FINGERS), 15, 3))
    for i, name in enumerate(FINGERS):
        rows = [j - 1 for j in FINGER_JOINTS[name]]  # pose joint j >= 1 sits at row j - 1 of the 45
        basis[i, rows] = hands_mean[rows]
    return basis.reshape(len(FINGERS), 45)


def first_touch(min_distance: np.ndarray, touch: float, step_penetration: float) -> tuple[int, int]:
    """Index of the first ladder level (of (L,) increasing closure) that touches, and the level to
    keep: the touching one if it penetrates at most ``step_penetration``, else the one before
    (-1 when there is none). Returns (-1, L - 1) when no level touches."""
    touching = np.flatnonzero(min_distance <= touch)
    if len(touching) == 0:
        return -1, len(min_distance) - 1
    k = int(touching[0])
    return k, k if min_distance[k] >= -step_penetration else k - 1


# ---------------------------------------------------------------- MANO and object queries

def hand_forward(mano, rotvec: np.ndarray, scales: np.ndarray, betas: np.ndarray, transl: np.ndarray,
                 basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One batched MANO pass: global rotation ``rotvec`` (3,), per-finger closing ``scales`` (B, 5),
    ``betas`` (10,), ``transl`` (3,) m -> vertices (B, 778, 3) and MANO joints (B, 16, 3), metres."""
    scales = np.atleast_2d(scales)
    batch = len(scales)
    pose = np.concatenate([np.broadcast_to(rotvec, (batch, 3)), scales @ basis], 1)
    ref = mano.v_template
    with torch.no_grad():
        out = mano(torch.as_tensor(pose, dtype=ref.dtype), torch.as_tensor(np.tile(betas, (batch, 1)), dtype=ref.dtype),
                   torch.as_tensor(np.tile(transl, (batch, 1)), dtype=ref.dtype))
    return out.vertices.cpu().numpy().astype(np.float64), out.mano_joints.cpu().numpy().astype(np.float64)


def finger_samples(mano, spacing: float = SAMPLE_SPACING, joints: dict = FINGER_JOINTS) -> list:
    """Per finger (thumb..pinky), sparse (S_f, 778) weights of surface samples about ``spacing``
    metres apart on the faces skinned to the finger's ``joints`` (see ``contact.surface_samples``)."""
    weights, face = surface_samples(mano.v_template.cpu().numpy(), mano.faces, spacing)
    parts = np.asarray(mano.face_parts)[face]
    return [weights[np.isin(parts, joints[name])] for name in FINGERS]


def finger_min_distance(vertices: np.ndarray, samples: list, fingers: list[int], collision: HandObjectCollision,
                        band: float | None = LADDER_BAND) -> np.ndarray:
    """Closest signed distance (m) of each listed finger to the object at each level:
    vertices (L, 778, 3) -> (L, len(fingers)), all levels and fingers in one libigl call.

    The finger surfaces are probed at the ``samples`` (see :func:`finger_samples`). Distances
    beyond ``band`` are not computed and read as +inf (clear of the object). That is safe for a
    finger closing from a clear pose in steps much shorter than 2 * band: no point can jump from
    beyond +band to below -band without a level in between being seen."""
    empty = [f for f in fingers if samples[f].shape[0] == 0]
    if empty:  # reduceat would hand an empty finger its neighbour's distances
        raise ValueError(f"no surface samples on finger(s) {empty}: increase the sampling density")
    weights = scipy.sparse.vstack([samples[f] for f in fingers]).tocsr()
    n_levels, n_vertices = vertices.shape[:2]
    points = (weights @ vertices.transpose(1, 0, 2).reshape(n_vertices, -1)).reshape(-1, n_levels, 3)
    sd = collision.signed_distances(points.transpose(1, 0, 2).reshape(-1, 3), band).reshape(n_levels, -1)
    sd = np.where(np.isnan(sd), np.inf, sd)
    starts = np.cumsum([0] + [samples[f].shape[0] for f in fingers[:-1]])
    return np.minimum.reduceat(sd, starts, axis=1)


# ---------------------------------------------------------------- closing

def _closing_ladder(mano, rotvec, betas, transl, basis, samples, collision, t_grid, open_s, span, chunk: int,
                    touch: float, step_penetration: float) -> tuple[np.ndarray, np.ndarray]:
    """Coarse pass: per finger, the closure t of its last clear level and of its first touching
    level (NaN if it never touches). Levels are evaluated ``chunk`` at a time and only for the
    fingers that have not touched yet, so most fingers cost a chunk or two."""
    clear, hit = np.zeros(len(FINGERS)), np.full(len(FINGERS), np.nan)
    pending = list(range(len(FINGERS)))
    for start in range(0, len(t_grid), chunk):
        if not pending:
            break
        ts = t_grid[start:start + chunk]
        vertices, _ = hand_forward(mano, rotvec, open_s + ts[:, None] * span, betas, transl, basis)
        mins = finger_min_distance(vertices, samples, pending, collision)
        for j, f in enumerate(pending):
            k, _ = first_touch(mins[:, j], touch, step_penetration)
            if k < 0:
                clear[f] = ts[-1]
                continue
            hit[f] = ts[k]
            if k > 0:
                clear[f] = ts[k - 1]
            elif start == 0:
                clear[f] = 0.0  # touching while fully open: nothing to close
        pending = [f for f in pending if np.isnan(hit[f])]
    return clear, hit


def close_fingers(mano, rotvec: np.ndarray, betas: np.ndarray, transl: np.ndarray, collision: HandObjectCollision,
                  open_scales=OPEN_SCALES, closed_scales=CLOSED_SCALES, n_steps: int = 64, n_fine: int = 8,
                  chunk: int = 16, touch: float = TOUCH, step_penetration: float = STEP_PENETRATION,
                  samples: list | None = None) -> np.ndarray:
    """Close each finger independently until it touches the object (or is fully closed).

    A finger's closure t in [0, 1] maps to the scale ``open + t (closed - open)`` of its slice of
    ``hands_mean``. A coarse ladder of ``n_steps`` steps (about 3 mm of fingertip travel each) finds
    the first touching level; a fine ladder of ``n_fine`` steps between it and the last clear level
    pins the touch to about half a millimetre, backing off a step if the touch is a penetration.

    Args:
        mano: the MANO layer; rotvec (3,) global axis-angle; betas (10,); transl (3,) metres.
        collision: the object's wrapper (its signed distances decide touch and penetration).
        open_scales, closed_scales: (5,) scales of the open and fully closed fingers, thumb..pinky.
        samples: precomputed :func:`finger_samples` of ``mano`` (computed here when None).

    Returns:
        (5,) closing scales, thumb..pinky.
    """
    basis = finger_basis(mano.hands_mean.cpu().numpy())
    samples = finger_samples(mano) if samples is None else samples
    open_s = np.asarray(open_scales, dtype=np.float64)
    span = np.asarray(closed_scales, dtype=np.float64) - open_s
    t_grid = np.linspace(0.0, 1.0, n_steps + 1)
    clear, hit = _closing_ladder(mano, rotvec, betas, transl, basis, samples, collision, t_grid, open_s, span, chunk,
                                 touch, step_penetration)
    final = np.where(np.isnan(hit), 1.0, clear)
    refine = [f for f in range(len(FINGERS)) if not np.isnan(hit[f]) and hit[f] > clear[f]]
    if refine:
        # Fine levels between the last clear and the first touching coarse level, every finger
        # refined in the same MANO batch (fingers are independent, the others are held still).
        u = np.linspace(0.0, 1.0, n_fine + 1)[1:]
        ts = np.tile(final, (n_fine, 1))
        for f in refine:
            ts[:, f] = clear[f] + u * (hit[f] - clear[f])
        vertices, _ = hand_forward(mano, rotvec, open_s + ts * span, betas, transl, basis)
        mins = finger_min_distance(vertices, samples, refine, collision)
        for j, f in enumerate(refine):
            _, keep = first_touch(mins[:, j], touch, step_penetration)
            final[f] = ts[keep, f] if keep >= 0 else clear[f]
    return open_s + final * span

"""The MANO hand model: reading MANO_{RIGHT,LEFT}.pkl and a batched, differentiable forward pass.

Conventions (docs/conventions.md, "The MANO pose" and "Joint orders and fingertip vertices"):

- pose: (B, 48) full axis-angle, joint 0 the global rotation, in the *flat hand mean* convention
  (the 45 finger values are used as they are; MANO's ``hands_mean`` is not added);
- betas: (B, 10); transl: (B, 3) metres, added after posing (the global rotation pivots about the rest
  wrist joint, so ``transl`` is not the wrist position);
- outputs in metres: vertices (B, 778, 3) and joints (B, 21, 3) in DexYCB/manopth order (wrist, then
  thumb, index, middle, ring, little, four joints each), fingertips taken from vertices.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse
import torch
from torch import nn

from hoidata.errors import DataError
from hoidata.hand import lbs as lbs_math
from hoidata.hand import topology
from hoidata.safe_pickle import load_pickle

NUM_VERTICES = 778
NUM_FACES = 1538
NUM_JOINTS = 16  # MANO native: wrist, index x3, middle x3, pinky x3, ring x3, thumb x3
NUM_BETAS = 10
NUM_POSE = 48
MANO_PARENTS = [-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14]

# Fingertip vertices in (thumb, index, middle, ring, pinky) order.
# manopth (and so DexYCB, gSDF, HOISDF) uses 444 for the right middle tip and 445 for the left one.
TIP_VERTICES = {
    ("manopth", "right"): (745, 317, 444, 556, 673),
    ("manopth", "left"): (745, 317, 445, 556, 673),
    ("ho3d", "right"): (744, 333, 444, 555, 672),  # HO-3D's patched loader, its ground truth and challenge
    ("ho3d", "left"): (744, 333, 444, 555, 672),
}
# 16 MANO joints + 5 tips (thumb..pinky) -> DexYCB/manopth order; and its inverse.
MANO_TO_DEXYCB = [0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20]
DEXYCB_TO_MANO = [int(i) for i in np.argsort(MANO_TO_DEXYCB)]

_EXPECTED_SHAPES = {
    "v_template": (NUM_VERTICES, 3),
    "posedirs": (NUM_VERTICES, 3, (NUM_JOINTS - 1) * 9),
    "J_regressor": (NUM_JOINTS, NUM_VERTICES),
    "weights": (NUM_VERTICES, NUM_JOINTS),
    "kintree_table": (2, NUM_JOINTS),
    "f": (NUM_FACES, 3),
    "hands_components": (45, 45),
    "hands_mean": (45,),
}


@dataclass
class ManoData:
    """The arrays of a MANO model file, validated, float64 (faces int64). ``side`` is 'right' or 'left'."""

    path: str
    side: str
    v_template: np.ndarray
    shapedirs: np.ndarray  # (778, 3, 10)
    posedirs: np.ndarray
    j_regressor: np.ndarray  # dense (16, 778)
    weights: np.ndarray
    parents: list[int]
    faces: np.ndarray
    hands_components: np.ndarray
    hands_mean: np.ndarray
    extras: dict = field(default_factory=dict)


def mano_file(path: str | os.PathLike, side: str) -> Path:
    """Resolve a MANO file from a file path or a folder holding MANO_RIGHT.pkl / MANO_LEFT.pkl."""
    if side not in ("right", "left"):
        raise ValueError(f"side must be 'right' or 'left', got {side!r}")
    path = Path(path)
    if path.is_dir():
        path = path / f"MANO_{side.upper()}.pkl"
    if not path.is_file():
        raise DataError(path, None, f"MANO {side} model file not found (expected MANO_{side.upper()}.pkl, v1.2)")
    return path


def read_mano_file(path: str | os.PathLike, side: str = "right", fix_left_shapedirs: bool = True) -> ManoData:
    """Read and validate a MANO v1.2 pickle without chumpy.

    Args:
        path: MANO_RIGHT.pkl / MANO_LEFT.pkl, or the folder that holds them.
        side: 'right' or 'left'.
        fix_left_shapedirs: MANO_LEFT.pkl ships the right hand's shape directions for x, so the same
            betas give mismatched shapes for the two hands (dex-ycb-toolkit#28, smplx#48). The fix
            negates ``shapedirs[:, 0, :]`` of the left model; it is on by default.

    Raises:
        DataError: missing file, unreadable pickle, missing key or wrong shape (the message names both).
    """
    path = mano_file(path, side)
    raw = load_pickle(path)
    if not isinstance(raw, dict):
        raise DataError(path, None, f"expected a dict of MANO arrays, got {type(raw).__name__}")
    arrays = {key: _array(raw, key, path) for key in list(_EXPECTED_SHAPES) + ["shapedirs"]}
    for key, shape in _EXPECTED_SHAPES.items():
        if arrays[key].shape != shape:
            raise DataError(path, key, f"expected shape {shape}, got {arrays[key].shape}")
    shapedirs = arrays["shapedirs"]
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (NUM_VERTICES, 3) or shapedirs.shape[2] < NUM_BETAS:
        raise DataError(path, "shapedirs", f"expected shape (778, 3, >=10), got {shapedirs.shape}")
    shapedirs = shapedirs[:, :, :NUM_BETAS].astype(np.float64).copy()
    if side == "left" and fix_left_shapedirs:
        shapedirs[:, 0, :] *= -1.0
    faces = arrays["f"].astype(np.int64)
    if faces.min() < 0 or faces.max() >= NUM_VERTICES:
        raise DataError(path, "f", f"face indices must lie in [0, {NUM_VERTICES}), got [{faces.min()}, {faces.max()}]")
    parents = _parents(arrays["kintree_table"], path)
    extras = {k: v for k, v in raw.items() if k in ("hands_coeffs", "J", "bs_style", "bs_type")}
    return ManoData(str(path), side, arrays["v_template"].astype(np.float64), shapedirs,
                    arrays["posedirs"].astype(np.float64), arrays["J_regressor"].astype(np.float64),
                    arrays["weights"].astype(np.float64), parents, faces,
                    arrays["hands_components"].astype(np.float64), arrays["hands_mean"].astype(np.float64), extras)


def _array(raw: dict, key: str, path: Path) -> np.ndarray:
    if key not in raw:
        raise DataError(path, key, "missing key in MANO model file")
    value = raw[key]
    if scipy.sparse.issparse(value):
        value = value.toarray()
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as e:
        raise DataError(path, key, f"cannot convert {type(value).__name__} to an array: {e}") from e


def _parents(kintree: np.ndarray, path: Path) -> list[int]:
    # kintree_table[0] holds the parents; the root is stored as uint32(-1) = 4294967295.
    parents = [int(p) for p in kintree[0]]
    parents[0] = -1
    if parents != MANO_PARENTS:
        raise DataError(path, "kintree_table", f"expected MANO parents {MANO_PARENTS}, got {parents}")
    return parents


@dataclass
class MANOOutput:
    """Result of :meth:`MANO.forward`. All positions in metres in the input frame.

    vertices: (B, 778, 3); joints: (B, 21, 3) DexYCB/manopth order; mano_joints: (B, 16, 3) MANO order;
    transforms: (B, 16, 4, 4) per-joint skinning transforms (rest -> posed, without ``transl``).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    mano_joints: torch.Tensor
    transforms: torch.Tensor


class MANO(nn.Module):
    """Batched, differentiable MANO layer (see the module docstring for conventions).

    Buffers follow ``.to(device/dtype)``; inputs are cast to the model's dtype and device.
    """

    def __init__(self, data: ManoData, tips: str = "manopth", dtype: torch.dtype = torch.float32):
        super().__init__()
        if (tips, data.side) not in TIP_VERTICES:
            raise ValueError(f"tips must be 'manopth' or 'ho3d', got {tips!r}")
        self.side, self.tips, self.path = data.side, tips, data.path
        self.parents = list(data.parents)
        faces = data.faces
        closed, loop = topology.close_faces(faces, NUM_VERTICES)
        if topology.signed_volume(topology.close_vertices(data.v_template, loop), closed) < 0:
            faces = faces[:, ::-1].copy()  # the file winds inward; render and SDF need outward faces
            closed, loop = topology.close_faces(faces, NUM_VERTICES)
        self.faces, self.closed_faces, self.wrist_loop = faces, closed, loop
        self.vertex_parts = topology.vertex_part_labels(data.weights)
        self.face_parts = topology.face_part_labels(faces, data.weights)
        self.closed_face_parts = topology.face_part_labels(closed, data.weights)
        self.tip_vertices = TIP_VERTICES[(tips, data.side)]
        as_t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
        self.register_buffer("v_template", as_t(data.v_template))
        self.register_buffer("shapedirs", as_t(data.shapedirs))
        self.register_buffer("posedirs", as_t(data.posedirs))
        self.register_buffer("j_regressor", as_t(data.j_regressor))
        self.register_buffer("lbs_weights", as_t(data.weights))
        self.register_buffer("hands_components", as_t(data.hands_components))
        self.register_buffer("hands_mean", as_t(data.hands_mean))

    def forward(self, pose: torch.Tensor, betas: torch.Tensor | None = None,
                transl: torch.Tensor | None = None) -> MANOOutput:
        """Pose (B, 48) flat-hand-mean axis-angle, betas (B, 10), transl (B, 3) metres -> MANOOutput.

        ``pose`` may also be (B, 16, 3, 3) rotation matrices (MANO joint order), e.g. from a network head.
        """
        ref = self.v_template
        if torch.is_tensor(pose) and pose.ndim == 4 and pose.shape[1:] == (NUM_POSE // 3, 3, 3):
            pose = pose.to(ref)
        else:
            pose = self._check(pose, NUM_POSE, "pose").to(ref)
        batch = pose.shape[0]
        betas = ref.new_zeros(batch, NUM_BETAS) if betas is None else self._check(betas, NUM_BETAS, "betas", batch).to(ref)
        transl = ref.new_zeros(batch, 3) if transl is None else self._check(transl, 3, "transl", batch).to(ref)
        verts, mano_joints, rel = lbs_math.lbs(pose, betas, self.v_template, self.shapedirs, self.posedirs,
                                               self.j_regressor, self.parents, self.lbs_weights)
        tips = verts[:, list(self.tip_vertices)]
        joints = torch.cat([mano_joints, tips], dim=1)[:, MANO_TO_DEXYCB]
        offset = transl[:, None]
        return MANOOutput(verts + offset, joints + offset, mano_joints + offset, rel)

    @staticmethod
    def _check(x: torch.Tensor, width: int, name: str, batch: int | None = None) -> torch.Tensor:
        if not torch.is_tensor(x) or x.ndim != 2 or x.shape[1] != width or (batch is not None and x.shape[0] != batch):
            got = tuple(x.shape) if hasattr(x, "shape") else type(x).__name__
            want = f"({batch if batch is not None else 'B'}, {width})"
            raise ValueError(f"MANO {name}: expected a tensor of shape {want}, got {got}")
        return x

    def rest_joints(self, betas: torch.Tensor) -> torch.Tensor:
        """Rest-pose MANO joints (B, 16, 3) for betas (B, 10): the pivots of the joint rotations."""
        betas = self._check(betas, NUM_BETAS, "betas").to(self.v_template)
        v_shaped = self.v_template[None] + lbs_math.blend_shapes(betas, self.shapedirs)
        return lbs_math.vertices_to_joints(self.j_regressor, v_shaped)

    def rest_wrist(self, betas) -> np.ndarray:
        """Rest wrist joint J0 (3,) float64 for one shape betas (10,): the pivot ``change_frame`` needs."""
        with torch.no_grad():
            return self.rest_joints(torch.as_tensor(np.asarray(betas).reshape(1, NUM_BETAS)))[0, 0].double().numpy()

    def close(self, vertices: torch.Tensor) -> torch.Tensor:
        """Vertices (B, 778, 3) -> closed-mesh vertices (B, 779, 3), to use with ``closed_faces``."""
        return topology.close_vertices(vertices, torch.as_tensor(self.wrist_loop, device=vertices.device))

    def extra_repr(self) -> str:
        return f"side={self.side}, tips={self.tips}, path={self.path}"


def load_mano(path: str | os.PathLike, side: str = "right", tips: str = "manopth",
              fix_left_shapedirs: bool = True, dtype: torch.dtype = torch.float32) -> MANO:
    """Load MANO_RIGHT.pkl / MANO_LEFT.pkl (v1.2; chumpy not needed) as a :class:`MANO` layer.

    Args:
        path: the model file, or a folder holding ``MANO_RIGHT.pkl`` and ``MANO_LEFT.pkl``.
        side: 'right' or 'left'.
        tips: fingertip vertices, 'manopth' (DexYCB, HOISDF) or 'ho3d' (HO-3D ground truth).
        fix_left_shapedirs: apply the known MANO_LEFT shape-direction fix (see :func:`read_mano_file`).
        dtype: buffer dtype, float32 or float64 (cast from the file's float64 once, here).

    Example:
        >>> mano = load_mano("mano/", side="right")
        >>> out = mano(torch.zeros(1, 48), torch.zeros(1, 10), torch.zeros(1, 3))
        >>> out.vertices.shape, out.joints.shape
        (torch.Size([1, 778, 3]), torch.Size([1, 21, 3]))
    """
    return MANO(read_mano_file(path, side, fix_left_shapedirs), tips=tips, dtype=dtype)

"""Numeric precision of the HOISDF forward pass: where bf16 autocast may act and where the model stays fp32.

Under ``torch.autocast(..., dtype=torch.bfloat16)`` (CUDA training by default, evaluation with
``--precision bf16``) the model keeps every geometric quantity in full precision (fp32, or fp64 for an fp64
model) and lets bf16 act only on learned feature transforms:

================================  =======  =====================================================================
stage                             dtype    why
================================  =======  =====================================================================
backbone, U-Net, 2D heads         bf16     convolutions: learned features, tolerant of 8-bit mantissas
point projection (``K @ X``)      fp32     a bf16 pixel is off by up to 1 px of a 256 crop (187.78 -> 188.0)
grid / pixel -> sampling coords   fp32     same; ``grid_sample`` runs on fp32 features at fp32 coordinates
inference grid, box test          fp32     the lattice and its projection decide which points are candidates
feature MLPs, SDF decoder body    bf16     learned transforms (their inputs are rounded to bf16 there)
SDF decoder output, clamp, rank   fp32     the last layer, tanh, clamp and the |SDF| ranking / top-k
densities, tokens (xyz, Fourier)  fp32     built from fp32 points and fp32 SDFs
transformers                      bf16     attention and feed-forward matmuls
head outputs (last layer)         fp32     6D rotations, betas, votes, logits, object rotation / translation
MANO skinning, IK                 fp32     (``heads.wrist_centred_mano``)
================================  =======  =====================================================================

:func:`trace_dtypes` records what actually ran (``metrics.json["precision"]`` of ``hoisdf.evaluate``).
"""

from __future__ import annotations

import functools
from contextlib import contextmanager

import torch

PRECISIONS = {"fp32": None, "bf16": torch.bfloat16}
"""A precision setting -> the autocast dtype (None: no autocast)."""

STAGES = {"backbone": "backbone", "sdf_in": "features.sdf_in", "token_in": "features.token_in",
          "hand_sdf": "fields.hand_sdf", "obj_sdf": "fields.obj_sdf", "hand_encoder": "pose.hand_encoder",
          "obj_encoder": "pose.obj_encoder", "hand_decoder": "pose.regressor.hand_decoder",
          "mano_head": "pose.regressor.mano_head", "shape_head": "pose.regressor.shape_head",
          "vote_head": "pose.regressor.vote_head", "obj_head": "pose.obj_head"}
"""Sub-modules of :class:`hoisdf.model.HOISDF` whose output dtype :func:`trace_dtypes` records: the name it records
-> the module's path in the model (a variant without it is skipped)."""

OUTPUT_KEYS = ("hand_query", "hand_query_sdf", "obj_query", "obj_translation", "obj_rotation", "joints", "verts",
               "vote_offsets", "rotations", "obj_trans_points")
"""Model outputs whose dtype :func:`trace_dtypes` records (the geometry the model hands back)."""


def full(x: torch.Tensor) -> torch.Tensor:
    """``x`` in full precision: fp32, or unchanged when it already is fp32 or fp64."""
    return x if x.dtype in (torch.float32, torch.float64) else x.float()


@contextmanager
def no_autocast(like: torch.Tensor):
    """Autocast off for ``like``'s device type inside the block (a no-op outside autocast)."""
    with torch.autocast(like.device.type, enabled=False):
        yield


def full_precision(fn):
    """Decorator for geometric functions: run ``fn`` with autocast off (for the device of its first tensor
    argument) and its bf16 / fp16 tensor arguments cast to fp32."""
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        first = next((a for a in (*args, *kwargs.values()) if torch.is_tensor(a)), None)
        if first is None:
            return fn(*args, **kwargs)

        def up(a):
            return full(a) if torch.is_tensor(a) and a.is_floating_point() else a

        with no_autocast(first):
            return fn(*[up(a) for a in args], **{k: up(v) for k, v in kwargs.items()})
    return wrapper


def autocast(device: torch.device | str, precision: str):
    """The autocast context of a precision setting: bf16 autocast on ``device``'s type, or none for fp32."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    dtype = PRECISIONS[precision]
    return torch.autocast(torch.device(device).type, dtype=dtype or torch.bfloat16, enabled=dtype is not None)


def _first_dtype(value) -> str | None:
    if torch.is_tensor(value):
        return str(value.dtype).replace("torch.", "")
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, (list, tuple)):
        for item in value:
            found = _first_dtype(item)
            if found:
                return found
    return None


@contextmanager
def trace_dtypes(model: torch.nn.Module):
    """Record, while the block runs, the dtype of every :data:`STAGES` module's first output tensor and of
    the :data:`OUTPUT_KEYS` outputs; yields the dict it fills (``{"stage:NAME": dtype, "output:KEY": dtype}``)."""
    seen: dict[str, str] = {}
    handles = []

    def record(key):
        def hook(module, args, output):
            dtype = _first_dtype(output)
            if dtype:
                seen.setdefault(key, dtype)
        return hook

    for name, path in STAGES.items():
        try:
            module = model.get_submodule(path)
        except AttributeError:
            continue
        handles.append(module.register_forward_hook(record(f"stage:{name}")))

    def outputs(module, args, kwargs, output):
        for key in OUTPUT_KEYS:
            if isinstance(output, dict) and torch.is_tensor(output.get(key)):
                seen.setdefault(f"output:{key}", str(output[key].dtype).replace("torch.", ""))

    handles.append(model.register_forward_hook(outputs, with_kwargs=True))
    try:
        yield seen
    finally:
        for handle in handles:
            handle.remove()

"""The authors' released checkpoints (amathislab/HOISDF ``snapshot_<epoch>_<iter>.pth.tar``) -> a run folder.

An upstream snapshot is ``{"epoch", "network", "optimizer", "lr_scheduler"}`` written by ``torch.save`` from
``main/train.py``; ``network`` is the state dict of ``nn.DataParallel(Model)``, so every key starts with
``module.``. :func:`convert_network` renames every key onto :class:`hoisdf.model.HOISDF` (rules in
:data:`RULES`, table in docs/released-weights.md) or drops it deliberately (:data:`DROPPED`: three modules the
released forward never calls, ``mano_head.coord_change_mat``, and the nine ``mano_head.mano_layer.th_*`` MANO
buffers, which are licensed data: they are compared with the user's MANO files, never copied).

Two value edits: the density widths are ``[1]`` upstream and ``[]`` here, and the last bias of
``linear_pose`` loses ``[1, 0, 0, 0, 1, 0]`` because this model predicts the 6D code as an offset from the
identity (``hoisdf.model.heads.ManoHead``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from hoidata.errors import DataError
from hoidata.reading import file_digest
from hoidata.reading_media import read_torch

SETTINGS = {
    # upstream main/config.py: use_big_decoder only for "ho3d", use_inverse_kinematics only for "ho3d_render"
    "dexycb": {"decoder": "small", "pose_regressor": "mano"},
    "dexycb_full": {"decoder": "small", "pose_regressor": "mano"},
    "ho3d": {"decoder": "big", "pose_regressor": "mano"},
    "ho3d_render": {"decoder": "small", "pose_regressor": "ik"},
}
RELEASED_MODEL = {
    # what upstream's forward computes (docs/model.md explains each switch)
    "depth": 50, "weights": "", "normalize_input": False, "pixel_convention": "upstream", "sheared_grid": True,
    "density_sign": "code", "object_rotation": "axis_angle", "sampling": "absolute", "feature_augmentation": "density",
    "cross_field": "sdf", "test_boxes": "gt", "fixed_shape": False, "image_size": 256, "hand_queries": 600,
    "object_queries": 200, "grid_resolution": 64,
}
MANO_BUFFERS = ("th_betas", "th_shapedirs", "th_posedirs", "th_v_template", "th_J_regressor", "th_weights",
                "th_faces", "th_hands_mean", "th_selected_comps")
DROPPED = ("norm1.", "linear_objvote.", "linear_objcls.", "mano_head.coord_change_mat", "mano_head.mano_layer.")
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)
_HAND = "pose.regressor"  # the hand regressor's heads
_MLPS = {"linear_transformerin": "features.token_in", "linear_sdfin": "features.sdf_in",
         "linear_pose": f"{_HAND}.mano_head.pose", "linear_handvote": f"{_HAND}.vote_head.vote",
         "linear_handcls": f"{_HAND}.vote_head.cls", "linear_obj_rot": "pose.obj_head.rot",
         "linear_obj_rel_trans": "pose.obj_head.trans"}
_UP = {"1": "up16", "2": "up8", "3": "up4", "4": "up2"}
_HEADS = {"hm": "heatmap_head", "hand_seg": "hand_mask_head", "obj_seg": "obj_mask_head"}
_LAYER = r"(self_attn|norm\d|inter_norm)"
RULES: list[tuple[str, object]] = [
    # (upstream regex, project key: a template for re.sub or a function of the match)
    (r"^backbone_net\.resnet\.(.+)$", r"backbone.backbone.\1"),
    (r"^decoder_net\.resnet_decoder\.conv0d\.(.+)$", r"backbone.decoder.top.\1"),
    (r"^decoder_net\.resnet_decoder\.conv(\d)d\.(.+)$", lambda m: f"backbone.decoder.{_UP[m[1]]}.lateral.{m[2]}"),
    (r"^decoder_net\.resnet_decoder\.deconv(\d)\.(.+)$", lambda m: f"backbone.decoder.{_UP[m[1]]}.up.{m[2]}"),
    (r"^decoder_net\.resnet_decoder\.conv(\d)\.(.+)$", lambda m: f"backbone.decoder.{_UP[m[1]]}.fuse.{m[2]}"),
    (r"^decoder_net\.resnet_decoder\.convOut_(hm|hand_seg|obj_seg)\.(\d+)\.(.+)$",
     lambda m: f"backbone.{_HEADS[m[1]]}.{int(m[2]) // 3}.{int(m[2]) % 3}.{m[3]}"),
    (r"^(hand|obj)_sdf_decoder\.linh([0-3])\.weight_g$",
     r"fields.\1_sdf.hidden_layers.\2.parametrizations.weight.original0"),
    (r"^(hand|obj)_sdf_decoder\.linh([0-3])\.weight_v$",
     r"fields.\1_sdf.hidden_layers.\2.parametrizations.weight.original1"),
    (r"^(hand|obj)_sdf_decoder\.linh([0-3])\.bias$", r"fields.\1_sdf.hidden_layers.\2.bias"),
    (r"^(hand|obj)_sdf_decoder\.linh4\.(weight|bias)$", r"fields.\1_sdf.out_layer.\2"),
    (r"^(hand|obj)_transformer\.encoder\.layers\.(\d+)\.linear([12])\.(.+)$",
     r"pose.\1_encoder.layers.\2.ffn.linear\3.\4"),
    (rf"^(hand|obj)_transformer\.encoder\.layers\.(\d+)\.{_LAYER}\.(.+)$", r"pose.\1_encoder.layers.\2.\3.\4"),
    (r"^(hand|obj)_transformer\.encoder\.inter_norm\.(.+)$", r"pose.\1_encoder.inter_norm.\2"),
    (r"^hand_transformer\.decoder\.layers\.(\d+)\.multihead_attn\.(.+)$",
     rf"{_HAND}.hand_decoder.layers.\1.cross_attn.\2"),
    (r"^hand_transformer\.decoder\.layers\.(\d+)\.linear([12])\.(.+)$",
     rf"{_HAND}.hand_decoder.layers.\1.ffn.linear\2.\3"),
    (rf"^hand_transformer\.decoder\.layers\.(\d+)\.{_LAYER}\.(.+)$", rf"{_HAND}.hand_decoder.layers.\1.\2.\3"),
    (r"^hand_transformer\.decoder\.norm\.(.+)$", rf"{_HAND}.hand_decoder.norm.\1"),
    (r"^mano_query_embed\.weight$", f"{_HAND}.hand_decoder.query_embed.weight"),
    (r"^(hand|obj)_sigmoid_beta$", r"widths.\1_beta"),
    # the project's MLPs interleave ReLU modules: upstream layer i is the project's 2i
    (r"^(linear_\w+)\.layers\.(\d+)\.(weight|bias)$", None),
]


def project_key(key: str, ik: bool = False) -> str | None:
    """The project's name of an upstream key (without ``module.``); None when no rule matches.

    ``ik``: the inverse-kinematics variant (``ho3d_render``), whose ``linear_shape`` is ``shape_head.shape``.
    """
    for pattern, target in RULES:
        m = re.match(pattern, key)
        if m is None:
            continue
        if target is None:
            mlps = {**_MLPS, "linear_shape": f"{_HAND}.shape_head.shape" if ik else f"{_HAND}.mano_head.shape"}
            return f"{mlps[m[1]]}.layers.{2 * int(m[2])}.{m[3]}" if m[1] in mlps else None
        return target(m) if callable(target) else m.expand(target)
    return None


def is_dropped(key: str) -> bool:
    """Upstream keys that are deliberately not copied (see the module docstring)."""
    return key.startswith(DROPPED)


def read_snapshot(path: Path) -> tuple[dict, str]:
    """(payload, sha256) of an upstream snapshot, read with ``weights_only=True`` on the CPU (no code in the
    file runs; tensors saved on CUDA load on a CPU-only machine). Errors are one DataError line."""
    path = Path(path)
    payload = read_torch(path, "PyTorch checkpoint")  # not found, not a checkpoint, damaged, holding code
    digest = file_digest(path, "PyTorch checkpoint")[1]
    if not isinstance(payload, dict) or not isinstance(payload.get("network"), dict):
        raise DataError(path, "network", "missing: not an upstream HOISDF snapshot "
                                         "({'epoch', 'network', 'optimizer', ...} from its main/train.py)")
    bad = [k for k, v in payload["network"].items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        raise DataError(path, f"network[{bad[0]!r}]", "expected a state dict of tensors")
    return payload, digest


def mano_buffers(mano_dir) -> dict[str, torch.Tensor]:
    """The nine buffers upstream's manopth ``ManoLayer(side="right", flat_hand_mean=True, use_pca=False,
    ncomps=45)`` registers, computed from the user's MANO_RIGHT.pkl (hoidata's chumpy-free reader)."""
    from hoidata.hand.model import read_mano_file

    d = read_mano_file(mano_dir, side="right")
    f32 = lambda a: torch.tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731 - manopth's torch.Tensor(...)
    return {"th_betas": torch.zeros(1, d.shapedirs.shape[-1]), "th_shapedirs": f32(d.shapedirs),
            "th_posedirs": f32(d.posedirs), "th_v_template": f32(d.v_template)[None],
            "th_J_regressor": f32(d.j_regressor), "th_weights": f32(d.weights),
            "th_faces": torch.tensor(d.faces.astype(np.int32)).long(),
            "th_hands_mean": torch.zeros(1, d.hands_components.shape[1]),
            "th_selected_comps": f32(d.hands_components[:45])}


def check_mano(network: dict, mano_dir, path) -> None:
    """Refuse a snapshot whose MANO buffers differ from the user's MANO files (one line naming the buffer)."""
    present = {k.rpartition(".")[2]: v for k, v in network.items() if k.startswith("mano_head.mano_layer.")}
    if not present:
        return  # the IK variant has no MANO layer in its state dict
    expected = mano_buffers(mano_dir)
    for name in MANO_BUFFERS:
        field = f"network['module.mano_head.mano_layer.{name}']"
        if name not in present:
            raise DataError(path, field, "missing: the snapshot's MANO layer is incomplete")
        got, want = present[name], expected[name]
        if got.shape != want.shape or not torch.allclose(got.double(), want.double(), rtol=0, atol=1e-6):
            diff = (got.double() - want.double()).abs().max().item() if got.shape == want.shape else None
            what = (f"max |difference| {diff:.3g}" if diff is not None
                    else f"shape {tuple(got.shape)} vs {tuple(want.shape)}")
            raise DataError(path, field, f"differs from the MANO_RIGHT.pkl in {mano_dir} ({what}): "
                                         "the snapshot was trained with other MANO files")


def checked_weight(value: torch.Tensor, dtype: torch.dtype, path, field: str) -> torch.Tensor:
    """``value`` cast to the model's ``dtype``, refused naming ``field`` where it is of another kind (a float
    weight stored as integers or booleans: cast in silence it would be garbage) or holds NaN or infinity, before
    or after the cast (every prediction of the run would be NaN). A narrower float (float16) is cast."""
    kind = "float" if value.is_floating_point() else "complex" if value.is_complex() else \
        "bool" if value.dtype == torch.bool else "integer"
    want = "float" if dtype.is_floating_point else "integer"
    if kind != want:
        raise DataError(path, field, f"{value.dtype} values where the model holds {dtype} ones ({kind} values where "
                                     f"{want} ones belong: a damaged or converted file); refused, not cast")
    cast = value.to(dtype)
    if want == "float":
        nan, inf = int(torch.isnan(cast).sum()), int(torch.isinf(cast).sum())
        if nan or inf:
            what = " and ".join(p for p in (f"{nan} NaN" if nan else "", f"{inf} infinite" if inf else "") if p)
            raise DataError(path, field, f"{cast.numel()} values, {what} (as {dtype}): every prediction of the run "
                                         "would be NaN; refused")
    return cast


def convert_network(network: dict, expected: dict, path, ik: bool = False, raw_6d: bool = False) -> dict:
    """Upstream ``network`` (``module.`` prefix optional) -> the project's state dict.

    ``raw_6d``: for a model that predicts the raw 6D code (``model.rot6d = "raw"``): ``linear_pose``'s last bias is
    copied as it is.

    ``expected``: the target model's ``state_dict()`` (keys and shapes). Unexpected keys (no rule, not dropped,
    or a name the target model lacks), missing ones and shape mismatches are one DataError naming the key.
    """
    out = {}
    for raw, value in network.items():
        key = raw[len("module."):] if raw.startswith("module.") else raw
        if is_dropped(key):
            continue
        new = project_key(key, ik)
        if new is None or new not in expected:
            raise DataError(path, f"network[{raw!r}]", "unexpected key for this setting (not an upstream HOISDF "
                                                       "snapshot of this --setting?)")
        value = checked_weight(value.detach().clone(), expected[new].dtype, path, f"network[{raw!r}]")
        if key.endswith("sigmoid_beta"):
            value = value.reshape(())
        if re.fullmatch(r"linear_pose\.layers\.2\.bias", key) and not raw_6d:
            value = value - torch.tensor(IDENTITY_6D, dtype=value.dtype)
        if value.shape != expected[new].shape:
            raise DataError(path, f"network[{raw!r}]", f"shape {tuple(value.shape)}, the model expects "
                                                       f"{tuple(expected[new].shape)} (another --setting?)")
        out[new] = value
    missing = [k for k in expected if k not in out]
    if missing:
        raise DataError(path, "network", f"{len(missing)} weights missing, first: no upstream key gives "
                                         f"{missing[0]!r} (truncated, or another --setting?)")
    return out

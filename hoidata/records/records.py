"""One Frame -> one training record: crop, masks, heatmap, SDF samples and labels (schema v1).

Everything here is per frame and deterministic: the random generator for the SDF samples is seeded
from the record key, so a record's bytes do not depend on which worker built it or in what order.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

import cv2
import numpy as np
import torch

from hoidata import schema
from hoidata.datasets.frame import Frame
from hoidata.errors import DataError
from hoidata.geometry import crop as crop_ops
from hoidata.geometry.crop import project
from hoidata.geometry.sampling import SdfSampling
from hoidata.geometry.upstream_crop import pixel_affine
from hoidata.geometry.mirror import (
    mirror_axis_angle,
    mirror_intrinsics,
    mirror_mesh,
    mirror_pixels,
    mirror_points,
    mirror_transform,
)
from hoidata.records.upstream import CropPolicy, crop_meta, region_view, upstream_view
from hoidata.records.upstream import crop_box as upstream_crop_box


@dataclass(frozen=True)
class RecordSettings:
    """Per-record settings (``[record]`` in ``pipelines/<name>.toml``)."""

    crop_size: int = 512  # px: side of the stored square crop (img.jpg; masks and heatmap at half of it)
    context: float = crop_ops.DEFAULT_CONTEXT  # stored crop / hand-object box side: room for jitter, zoom, rotation
    sdf_samples_hand: int = 4096  # SDF samples stored per record around the hand surface (sdf.npy rows)
    sdf_samples_object: int = 2048  # SDF samples stored per record around the object surface
    uniform_fraction: float = 0.1  # fraction of each count drawn uniformly in the cube instead of near the surface
    cube: float = 0.64  # metres: side of the uniform-sample cube around the hand root
    sigmas: tuple[float, float] = (0.010, 0.003)  # metres: std of the two near-surface Gaussian offsets
    part_radius: float = 0.05  # metres: samples farther than this from the hand get no part label (-1)
    heatmap_sigma: float = schema.HEATMAP_SIGMA  # px (at the heatmap's resolution): Gaussian of each joint in hm.png
    sdf_backend: str = "bvh"  # hoidata.geometry.sdf.signed_distance backend: "bvh", or "igl" (the previous path)
    # "project": the crop above (crop_size, context, bilinear, JPEG); "upstream": crop_splits' records are upstream
    # HOISDF's test crop exactly (256 px, PIL nearest from the original frame, lossless img.png, its K, grid boxes
    # and object anchor in meta), what the released weights expect
    crop: str = "project"  # "project" | "upstream" (upstream HOISDF's exact test crop, docs/stores.md)
    crop_splits: tuple[str, ...] = ("test", "evaluation")  # splits whose records follow `crop` (others: "project")
    # "project": the hand, object and uniform sets above; "deepsdf": the authors' AlignSDF/DeepSDF blocks,
    # sdf_samples_hand and sdf_samples_object rows per entity in the frames' joint normalisation
    # (hoidata.geometry.sampling_deepsdf, docs/stores.md)
    sdf_points: str = "project"  # "project" | "deepsdf"
    masks: str = "rendered"  # visible mask targets: "rendered" from the meshes | "dataset": the dataset's own masks
    # splits whose full records keep, in place of the crop, the original frame's file as shipped (frame.jpg / .png;
    # readers get its square at native resolution that upstream HOISDF's training augmentation samples) and
    # upstream's inputs to it (docs/stores.md)
    upstream_region: tuple[str, ...] = ()  # e.g. ["train"]; empty: off
    LIMITS: ClassVar[dict] = {"crop_size": (">= 32", "<= 4096"), "context": ("> 0",), "sdf_samples_hand": (">= 1",),
                              "sdf_samples_object": (">= 1",), "uniform_fraction": (">= 0", "<= 1"), "cube": ("> 0",),
                              "sigmas": ("> 0",), "part_radius": ("> 0",), "heatmap_sigma": ("> 0",)}

    # old key -> its new name: an old key in a file or override is one line naming the new one, and a store whose
    # build.json holds the old name resumes (hoidata.records.fingerprint.current_names)
    RENAMED: ClassVar[dict] = {"n_hand": "sdf_samples_hand", "n_object": "sdf_samples_object"}

    def sdf_sampling(self) -> SdfSampling:
        """The SDF sampling settings of these record settings (the one place they are mapped)."""
        return SdfSampling(n_hand=self.sdf_samples_hand, n_object=self.sdf_samples_object,
                           uniform_fraction=self.uniform_fraction, cube=self.cube, sigmas=tuple(self.sigmas),
                           part_radius=self.part_radius, backend=self.sdf_backend)

    def crop_policy(self) -> CropPolicy:
        """Which crop each frame's record gets (the one place ``crop``, ``crop_splits`` and ``upstream_region`` are
        read): :class:`hoidata.records.upstream.CropPolicy`."""
        return CropPolicy(self.crop_size, self.crop == "upstream", tuple(self.crop_splits), tuple(self.upstream_region))


@dataclass
class ObjectAsset:
    """An object's geometry for SDF and masks: repaired full-resolution mesh, model frame."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    watertight: bool
    box21: np.ndarray  # (21, 3) model frame
    upstream_box21: np.ndarray | None = None  # (21, 3) model frame, of points.xyz as upstream builds it (crop upstream)


def frame_seed(key: str) -> int:
    """A 64-bit seed from the record key (stable across processes and Python versions)."""
    return int.from_bytes(hashlib.sha256(key.encode()).digest()[:8], "little")


def mirror_frame(frame: Frame) -> Frame:
    """A left-hand frame as the mirrored right hand (labels only; the image is flipped when read).

    The object model is mirrored along with the scene: ``object_pose`` becomes [M R M | M t], which
    poses the x-mirrored model. Records keep ``mirrored: true`` so users can undo it.
    """
    width = frame.image_size[0]
    return replace(
        frame, side="right", mirror=True, K=mirror_intrinsics(frame.K, width),
        root_3d=mirror_points(frame.root_3d), object_pose=mirror_transform(frame.object_pose),
        mano_pose=mirror_axis_angle(frame.mano_pose), mano_transl=mirror_points(frame.mano_transl),
        joints_3d=mirror_points(frame.joints_3d), joints_2d=mirror_pixels(frame.joints_2d, width),
    )


def summed_heatmap(joints_uv: np.ndarray, size: int, sigma: float) -> np.ndarray:
    """(size, size) uint8: sum of Gaussians at joints (N, 2) pixels, clipped to 1, times 255."""
    grid = np.arange(size, dtype=np.float64)
    gx = np.exp(-((grid[None, :] - joints_uv[:, :1]) ** 2) / (2 * sigma ** 2))  # (N, size)
    gy = np.exp(-((grid[None, :] - joints_uv[:, 1:2]) ** 2) / (2 * sigma ** 2))
    total = np.einsum("ny,nx->yx", gy, gx)
    return np.round(np.clip(total, 0.0, 1.0) * 255).astype(np.uint8)


def pack_masks(labels: np.ndarray, amodal: np.ndarray) -> np.ndarray:
    """Visible label map (hand = 1, object = 2) and amodal masks (2, H, W) -> seg.png bits (H, W) uint8."""
    seg = np.zeros(labels.shape, np.uint8)
    seg |= np.where(labels == 1, schema.SEG_HAND_VISIBLE, 0).astype(np.uint8)
    seg |= np.where(labels == 2, schema.SEG_OBJECT_VISIBLE, 0).astype(np.uint8)
    seg |= np.where(amodal[0], schema.SEG_HAND_AMODAL, 0).astype(np.uint8)
    seg |= np.where(amodal[1], schema.SEG_OBJECT_AMODAL, 0).astype(np.uint8)
    return seg


def posed_hand(frame: Frame, mano) -> np.ndarray:
    """Closed hand vertices (779, 3), camera frame, metres, from the frame's MANO parameters."""
    with torch.no_grad():
        out = mano(torch.as_tensor(frame.mano_pose)[None], torch.as_tensor(frame.mano_betas)[None],
                   torch.as_tensor(frame.mano_transl)[None])
        return mano.close(out.vertices)[0].double().numpy()


def posed_object(frame: Frame, obj: ObjectAsset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (F, 3), box21 (21, 3)) of the object under the frame's pose, camera frame, metres.

    A mirrored frame's ``object_pose`` poses the x-mirrored model (see :func:`mirror_frame`), so its object is
    the mirror image of the scene's, as in the flipped image (faces flipped to stay outward wound).
    """
    verts, faces, box21 = obj.vertices, obj.faces, obj.box21
    if frame.mirror:
        (verts, faces), box21 = mirror_mesh(verts, faces), mirror_points(box21)
    R, t = frame.object_pose[:3, :3], frame.object_pose[:3, 3]
    return verts @ R.T + t, faces, box21 @ R.T + t


def build_record(frame: Frame, mano, obj: ObjectAsset, renderer, key: str, settings: RecordSettings) -> dict:
    """Build the schema members of one frame (a right hand, or a left one with ``mirror`` set).

    `mano` is the hand model the frame's labels were made with (its own side and, for left hands,
    shape convention); a mirrored frame's mesh is that model's mesh, reflected, which is exact
    whatever the shape convention. Returns a dict with the decoded arrays (``img``, ``seg``,
    ``heatmap``, ``sdf``, ``meta``; ``frame``: the frame file's bytes of a record.upstream_region record, else None)
    that :func:`hoidata.store.encode_record` turns into bytes.
    """
    from hoidata.geometry.sampling import build_sdf_record
    from hoidata.geometry.sampling_deepsdf import deepsdf_record
    from hoidata.render import RenderMesh

    raw = frame
    hand, faces = posed_hand(frame, mano), mano.closed_faces
    if frame.mirror:
        frame = mirror_frame(frame)
        hand, faces = mirror_mesh(hand, faces)
    obj_verts, obj_faces, obj_box21 = posed_object(frame, obj)
    view = crop_view(raw, frame, obj, project(obj_box21, frame.K), frame.joints_2d, settings)
    K_crop, size = view["K"], view["img"].shape[0]
    half = size // 2
    to_mask = crop_ops.resize_affine(size, half) @ view["to_pixels"]  # masks sit on the stored pixels
    K_mask = crop_ops.resize_affine(size, half) @ (view["to_pixels"] @ frame.K)
    meshes = [RenderMesh(vertices=hand, faces=faces, label=1), RenderMesh(vertices=obj_verts, faces=obj_faces, label=2)]
    labels, amodal = renderer.masks(K_mask, meshes)
    sample = deepsdf_record if settings.sdf_points == "deepsdf" else build_sdf_record
    sdf, counts = sample(hand, faces, mano.closed_face_parts, obj_verts, obj_faces, obj.watertight,
                                   frame.root_3d, np.random.default_rng(frame_seed(key)), settings.sdf_sampling())
    meta = {**record_meta(frame, key, view["box"], K_crop, hand, obj_verts, counts), **view["meta"]}
    meta["seg_iou"] = dataset_mask_iou(frame, labels, to_mask, amodal)
    seg = pack_masks(labels, amodal)
    if settings.masks == "dataset":  # the dataset's own masks become the visible planes (the amodal ones stay rendered)
        seg = with_dataset_masks(seg, frame, to_mask)
    return {
        "img": view["img"],
        "seg": seg,
        "heatmap": summed_heatmap(project(frame.joints_3d, K_mask), half, settings.heatmap_sigma),
        "sdf": sdf,
        "meta": meta,
        "frame": view.get("frame_bytes"),  # a record.upstream_region record stores the frame's file, not img
    }


def crop_view(raw: Frame, frame: Frame, obj: ObjectAsset, object_uv: np.ndarray, hand_uv: np.ndarray,
              settings: RecordSettings) -> dict:
    """The stored crop of a frame: ``img`` (S, S, 3) uint8, ``K`` (3, 3) its intrinsics, ``box`` (x1, y1, side) in
    source pixels, ``to_pixels`` (3, 3) the source -> crop pixel map (centres at integers), ``to_K`` (3, 3) the
    map K follows (``K = to_K @ frame.K``; upstream's sits 0.5 (1 - a) px off ``to_pixels``, see
    hoidata.geometry.upstream_crop) and ``meta``: the schema.CROP_FIELDS of an upstream crop, else nothing.

    ``raw``: the frame as read; ``frame``: the same, mirrored when it is a left hand; ``object_uv`` (21, 2) and
    ``hand_uv`` (N, 2): the project crop's object and hand points in ``frame``'s pixels."""
    crops = settings.crop_policy()
    if crops.upstream_crop(raw):
        if obj.upstream_box21 is None:
            raise DataError(raw.image_path, "record.crop", f"no points.xyz box for {obj.name} (the upstream crop's)")
        view = upstream_view(raw, obj.upstream_box21)
        return {"img": view.image, "K": np.asarray(view.K, np.float64), "box": upstream_crop_box(view),
                "to_pixels": pixel_affine(view.affine), "to_K": np.asarray(view.affine, np.float64),
                "meta": crop_meta(view)}
    if crops.upstream_region(raw):
        region = region_view(raw, obj.upstream_box21)
        x0, y0 = region["meta"]["region_origin"]
        return {**region, "K": region["to_pixels"] @ frame.K, "box": np.array([x0, y0, region["img"].shape[0]]),
                "to_K": region["to_pixels"]}
    box = crop_ops.square_crop_box(hand_uv, object_uv, settings.context)
    to_crop = crop_ops.crop_affine(box, settings.crop_size)
    image = frame.load_image() if frame is raw else cv2.flip(raw.load_image(), 1)  # flip: image[:, ::-1], faster
    return {"img": crop_ops.warp_image(image, to_crop, settings.crop_size), "K": to_crop @ frame.K, "box": box,
            "to_pixels": to_crop, "to_K": to_crop, "meta": {}}


HAND_BIT, OBJECT_BIT = 1, 2  # dataset_masks' bit code


def dataset_masks(frame: Frame) -> np.ndarray | None:
    """The dataset's own hand and object masks at image resolution (before any mirroring), if it has them,
    as one (H, W) uint8 map: bit HAND_BIT where the dataset says hand, OBJECT_BIT where it says object."""
    if frame.labels is not None:  # a synthetic render's own label map
        return _bits(frame.labels == 1, frame.labels == 2)
    path = frame.segmentation_path
    if path is None:
        return None
    if frame.dataset == "dexycb":
        from hoidata.datasets.dexycb_layout import read_labels

        # the reader checked every key of this file when it listed the frame; only the label map is decoded here
        seg = read_labels(path, int(frame.source["num_objects"]), keys=("seg",), check_rest=False)["seg"]
        return _bits(seg == 255, seg == frame.object_id)
    if frame.dataset == "ho3d":  # rendered at 1/4 resolution: hand in red, object in blue
        import cv2

        from hoidata.datasets.frame import read_rgb

        seg = read_rgb(path)
        bits = _bits(seg[..., 0] > 200, seg[..., 2] > 200)
        return cv2.resize(bits, frame.image_size, interpolation=cv2.INTER_NEAREST)
    return None


def _bits(hand: np.ndarray, obj: np.ndarray) -> np.ndarray:
    return (hand.view(np.uint8) * np.uint8(HAND_BIT)) | (obj.view(np.uint8) * np.uint8(OBJECT_BIT))


AMODAL_ONLY = ("hot3d_clips",)  # datasets whose own masks are amodal object masks, without a hand mask


def warped_dataset_masks(frame: Frame, to_mask: np.ndarray, size: int) -> np.ndarray | None:
    """The dataset's masks (:func:`dataset_masks` bits) on the record's (size, size) mask grid, or None if it has
    none: flipped for a mirrored frame, then one nearest-neighbour warp through ``to_mask`` (each output pixel takes
    the bits of one source pixel, as upstream's nearest warp does)."""
    masks = dataset_masks(frame)
    if masks is None:
        return None
    masks = cv2.flip(masks, 1) if frame.mirror else masks
    return crop_ops.warp_image(masks, to_mask, size, nearest=True)


def with_dataset_masks(seg: np.ndarray, frame: Frame, to_mask: np.ndarray) -> np.ndarray:
    """``seg`` (packed bits) with its visible hand and object bits replaced by the dataset's own masks, as upstream's
    loader reads them (DexYCB ``label["seg"]``: 255 hand, the grasped object's id; HO-3D's seg JPEG: R > 200 hand,
    B > 200 object, resized nearest to the frame), warped into the crop. A frame whose mask file is missing is a
    DataError naming the file (the build skips the frame and counts it); datasets without hand masks are refused."""
    if frame.dataset in AMODAL_ONLY:
        raise DataError(frame.image_path, "record.masks", f"{frame.dataset} has no hand masks: use record.masks = "
                                                          '"rendered"')
    warped = warped_dataset_masks(frame, to_mask, seg.shape[0])
    if warped is None:
        raise DataError(expected_mask_path(frame), "record.masks", "the dataset's mask file of this frame is missing")
    visible = np.uint8(schema.SEG_HAND_VISIBLE | schema.SEG_OBJECT_VISIBLE)
    out = seg & ~visible
    out |= np.where(warped & HAND_BIT, schema.SEG_HAND_VISIBLE, 0).astype(np.uint8)
    out |= np.where(warped & OBJECT_BIT, schema.SEG_OBJECT_VISIBLE, 0).astype(np.uint8)
    return out


def expected_mask_path(frame: Frame):
    """Where a frame's dataset mask file is (or should be): the reader's path, or HO-3D's ``<seq>/seg/<id>.jpg``."""
    if frame.segmentation_path is not None:
        return frame.segmentation_path
    if frame.dataset == "ho3d":
        image = Path(frame.image_path)
        return image.parents[1] / "seg" / f"{image.stem}.jpg"
    return frame.image_path


def dataset_mask_iou(frame: Frame, labels: np.ndarray, to_mask: np.ndarray, amodal: np.ndarray | None = None
                     ) -> np.ndarray:
    """IoU (2,) of our visible hand / object masks (label map 1 / 2) with the dataset's; -1 if it has none.
    HOT3D-Clips has amodal object masks only: the hand's is -1 and the object's compares our amodal object mask
    (``amodal[1]``), read at the mask's pixels (:func:`hoidata.datasets.hot3d.object_mask_iou`).

    Both masks travel as bits of one map through one nearest-neighbour warp: each output pixel takes the
    bits of one source pixel, so this equals warping each mask on its own."""
    if frame.dataset == "hot3d_clips":
        from hoidata.datasets.hot3d import object_mask_iou

        return np.array([-1.0, object_mask_iou(frame, amodal[1], to_mask)])
    warped = warped_dataset_masks(frame, to_mask, labels.shape[0])
    if warped is None:
        return np.array([-1.0, -1.0])
    out = []
    for bit, label in ((HAND_BIT, 1), (OBJECT_BIT, 2)):
        theirs, ours = (warped & bit) > 0, labels == label
        union = np.count_nonzero(ours | theirs)
        out.append(np.count_nonzero(ours & theirs) / union if union else 1.0)
    return np.array(out)


def _common_meta(frame: Frame, key: str, kind: str, box: np.ndarray, K_crop: np.ndarray, obj_verts: np.ndarray) -> dict:
    """The meta.json fields every record kind has (arrays stay numpy until encoding)."""
    x1, y1, side = box
    return {
        "schema_version": schema.SCHEMA_VERSION, "kind": kind, "key": key, "dataset": frame.dataset,
        "split": frame.split, "frame_id": frame.frame_id, "side": frame.side, "mirrored": bool(frame.mirror),
        "tip_convention": frame.tip_convention, "K": K_crop, "crop_box": np.array([x1, y1, x1 + side, y1 + side]),
        "hand_root": frame.root_3d, "object_name": frame.object_name, "object_id": int(frame.object_id),
        "object_pose": frame.object_pose, "object_box": crop_ops.box_from_points(project(obj_verts, K_crop)),
        "sample_index": int(frame.sample_index), "source": frame.source,
    }


def record_meta(frame: Frame, key: str, box: np.ndarray, K_crop: np.ndarray, hand: np.ndarray,
                obj_verts: np.ndarray, counts) -> dict:
    """The meta.json content of a full record (see ``schema.META_FIELDS``; ``seg_iou`` is added by the caller)."""
    return {
        **_common_meta(frame, key, schema.FULL, box, K_crop, obj_verts),
        "joints_3d": frame.joints_3d, "joints_2d": project(frame.joints_3d, K_crop),
        "mano_pose": frame.mano_pose, "mano_betas": frame.mano_betas, "mano_transl": frame.mano_transl,
        "hand_box": crop_ops.box_from_points(project(hand, K_crop)), "sdf_counts": np.asarray(counts, dtype=np.int64),
    }


def build_eval_record(frame: Frame, obj: ObjectAsset, key: str, settings: RecordSettings) -> dict:
    """A frame whose hand pose the dataset withholds (HO-3D's evaluation split) -> an ``eval`` record.

    The crop is squared around the dataset's given hand box and the posed object's 21-point box, each
    expanded by ``crop.BOX_EXPAND``, times ``settings.context``: the training crop's rule with the given box in
    place of the joints (with ``settings.crop = "upstream"``: upstream's crop, see :func:`crop_view`).
    ``hand_root`` is the given root joint, ``hand_box`` the given box in crop pixels. Returns the dict
    :func:`build_record` returns, with ``seg``, ``heatmap`` and ``sdf`` None.
    """
    if frame.hand_box is None:
        raise DataError(frame.source.get("meta", frame.image_path), "hand_box",
                        "a frame without hand labels needs the dataset's hand box for its crop")
    if frame.mirror:
        raise DataError(frame.image_path, "side", "a left-hand frame without hand labels cannot be mirrored")
    obj_verts, _, obj_box21 = posed_object(frame, obj)
    corners = np.asarray(frame.hand_box, np.float64).reshape(2, 2)
    view = crop_view(frame, frame, obj, project(obj_box21, frame.K), corners, settings)
    meta = {**_common_meta(frame, key, schema.EVAL, view["box"], view["K"], obj_verts), **view["meta"]}
    meta["hand_box"] = crop_ops.apply_affine(view["to_K"], corners).reshape(4)
    return {"img": view["img"], "seg": None, "heatmap": None, "sdf": None, "meta": meta}

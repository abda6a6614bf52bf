"""HOT3D-Clips reader: one Frame per (frame, stream, hand), in that hand's pinhole crop camera.

Layout and fields: :mod:`hoidata.datasets.hot3d_format` and docs/datasets.md, "HOT3D-Clips". For each frame of a
clip, each hand with a crop camera in ``hand_crops.json`` and each of its streams, the Frame is the crop camera's
view: the image is the fisheye image remapped into the crop (:mod:`hoidata.geometry.crop_camera`, read lazily, when
the record is built), K is the crop camera's, and every pose is in the crop camera's frame (OpenCV axes, metres).

The hand: ``mano_pose.thetas`` are 15 PCA coefficients of MANO's ``hands_components`` with ``flat_hand_mean=False``
(the mean pose added), ``wrist_xform`` the global orientation (axis-angle about the rest wrist) and the translation,
world frame; betas are the clip's ``__hand_shapes.json__`` ``mano``, shared by both hands. MANO poses are read
only where ``umetrack_pose`` is present (the official reader's rule); other hands are skipped with that reason.
Left hands use MANO_LEFT with the shape-direction fix (as the official reader's model does) and are mirrored when
``mirror_left`` is set. The object of a record is the annotated object nearest to the hand (object origin to the
mean of the hand's joints), named ``obj_<bop id>`` as in ``object_models_eval``.

Splits: HOT3D-Clips' test clips withhold hands.json, so both splits come from the training clips
(``train_aria/``, ``train_quest3/``): ``val`` holds the clips whose number is a multiple of ``VAL_EVERY``, ``train``
the others.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from hoidata.datasets.frame import Frame, Skip
from hoidata.datasets.hot3d_format import (
    SIDES,
    ClipMembers,
    crop_camera,
    list_members,
    numbers,
    read_betas,
    rle_decode,
    stream_camera,
    transform,
)
from hoidata.errors import DataError
from hoidata.geometry.crop import project
from hoidata.geometry.crop_camera import crop_maps, fisheye_grid, remap_crop
from hoidata.geometry.fisheye624 import Fisheye624
from hoidata.hand.pose import change_frame, pca_to_axis_angle
from hoidata.reading import parse_json
from hoidata.reading_media import decode_image
from hoidata.shapes import ANY, Integer, MapOf, check

CLIP_FOLDERS = ("train_aria", "train_quest3")
SPLITS = ("train", "val")
VAL_EVERY = 10  # val: clips whose number is a multiple of this
CROP_SIZE = 256  # pixels of the crop camera's image (the official reader's default is 128)
IMAGES_KEPT = 4  # decoded fisheye images kept per process (a frame's 2-3 streams, read for each hand in turn)


def clip_paths(root: Path, split: str) -> list[Path]:
    """The clip tars of a split, in folder then name order."""
    if split not in SPLITS:
        raise ValueError(f"unknown HOT3D-Clips split {split!r}; expected one of {SPLITS}")
    found = [p for folder in CLIP_FOLDERS for p in sorted((Path(root) / folder).glob("clip-*.tar"))]
    if not found:
        raise DataError(root, None, f"no clip-*.tar in {' or '.join(CLIP_FOLDERS)}: not a HOT3D-Clips folder")
    out = []
    for p in found:
        number = p.stem.split("-", 1)[1]
        if not number.isdigit():
            raise DataError(p, None, "clip file name must be clip-<number>.tar")
        if (int(number) % VAL_EVERY == 0) == (split == "val"):
            out.append(p)
    return out


@dataclass(frozen=True)
class CropImage:
    """The crop camera's RGB image (size, size, 3) uint8, made on call from the clip's fisheye JPEG (picklable)."""

    tar: str
    where: tuple  # (offset, size) of the JPEG member's bytes in the tar
    member: str
    camera: Fisheye624
    world_from_camera: np.ndarray
    K: np.ndarray
    world_from_crop: np.ndarray
    size: int

    def __call__(self) -> np.ndarray:
        import cv2

        stat = os.stat(self.tar)  # in the key: a tar rewritten in place is decoded again
        image = fisheye_image(self.tar, tuple(self.where), stat.st_mtime_ns, stat.st_size, self.member)
        if image.shape[:2] != (self.camera.height, self.camera.width):
            raise DataError(self.tar, self.member, f"image is {image.shape[1]}x{image.shape[0]}, the camera's "
                            f"calibration says {self.camera.width}x{self.camera.height}")
        # remapped as decoded (grey or BGR), then converted: the same pixels as converting the whole image first
        crop = remap_crop(image, crop_maps(self.camera, self.world_from_camera, self.K, self.world_from_crop,
                                           self.size))
        return cv2.cvtColor(crop, cv2.COLOR_GRAY2RGB if crop.ndim == 2 else cv2.COLOR_BGR2RGB)


@lru_cache(maxsize=IMAGES_KEPT)
def fisheye_image(tar: str, where: tuple, mtime_ns: int, file_size: int, member: str) -> np.ndarray:
    """A stream's JPEG as decoded (grey or BGR, read-only); empty, cut short or not decodable is a DataError naming
    the member. Kept for the next ``IMAGES_KEPT`` calls: a frame's streams are read once for both hands' crops."""
    import cv2

    image = decode_image(ClipMembers(Path(tar)).read(where, member), tar, member, cv2.IMREAD_UNCHANGED, "JPEG image")
    image.flags.writeable = False
    return image


@dataclass
class HOT3DClipsReader:
    """Frames of HOT3D-Clips' ``train`` or ``val`` clips. Iterate with :meth:`frames`, then read ``skipped``.

    Args:
        root: the HOT3D-Clips folder (``train_aria/``, ``train_quest3/``).
        mano_dir: folder with MANO_RIGHT.pkl and MANO_LEFT.pkl.
        split: 'train' | 'val' (see the module docstring).
        crop_size: pixels of the crop camera's image.
        mirror_left: mirror left hands to right hands (as DexYCB-Full's setting does).
        on_error: 'skip' records a malformed member in ``skipped`` and goes on; 'raise' stops.
    """

    root: Path
    mano_dir: Path
    split: str = "train"
    crop_size: int = CROP_SIZE
    mirror_left: bool = True
    on_error: str = "skip"
    skipped: list[Skip] = field(default_factory=list)

    def __post_init__(self):
        self.root, self.mano_dir = Path(self.root), Path(self.mano_dir)
        self.clips = clip_paths(self.root, self.split)
        self._manos = {}

    def __len__(self) -> int:
        return len(self.clips)

    def published_ids(self, frames) -> list[int]:
        """HOT3D has no published frame ids: -1 for each frame."""
        return [-1] * len(frames)

    def mano(self, side: str):
        import torch

        from hoidata.hand import load_mano

        if side not in self._manos:
            self._manos[side] = load_mano(self.mano_dir, side=side, fix_left_shapedirs=True, dtype=torch.float64)
        return self._manos[side]

    def _fail(self, error: DataError, frame_id: str, path) -> None:
        if self.on_error == "raise":
            raise error
        self.skipped.append(Skip(frame_id, str(error), str(path)))

    def frames(self) -> Iterator[Frame]:
        for path in self.clips:
            try:
                clip = list_members(path)
                betas = read_betas(clip)
            except DataError as e:
                self._fail(e, path.stem, path)
                continue
            for key in sorted(clip.frames):
                try:
                    yield from self._frame(clip, key, betas)
                except DataError as e:
                    self._fail(e, f"{path.stem}_{key}", path)
            if clip.truncated:  # the frames before the cut were read
                self._fail(DataError(path, None, clip.truncated), f"{path.stem}_truncated", path)

    def _frame(self, clip: ClipMembers, key: str, betas: np.ndarray) -> Iterator[Frame]:
        hands, crops = clip.json(key, "hands.json"), clip.json(key, "hand_crops.json")
        cameras, objects = clip.json(key, "cameras.json"), clip.json(key, "objects.json")
        for side in SIDES:
            streams = sorted((crops.get(side) or {}).items())
            ids = [f"{clip.path.stem}_{key}_{stream}_{side}" for stream, _ in streams]
            hand = (hands or {}).get(side)
            reason = None if hand is None else hand_reason(hand)
            if hand is None or reason:
                self.skipped += [Skip(i, reason or "no hands.json entry for this hand", str(clip.path)) for i in ids]
                continue
            world = self._world_hand(clip, key, side, hand, betas)
            obj = nearest_object(objects, world["joints"].mean(0), clip.path, f"{key}.objects.json")
            for frame_id, (stream, crop) in zip(ids, streams):
                try:
                    yield self._crop_frame(clip, key, side, stream, crop, cameras, world, obj, frame_id)
                except DataError as e:
                    self._fail(e, frame_id, clip.path)

    def _world_hand(self, clip: ClipMembers, key: str, side: str, hand: dict, betas: np.ndarray) -> dict:
        import torch

        name = f"{key}.hands.json: {side}.mano_pose"
        thetas = numbers(hand["mano_pose"].get("thetas"), 15, clip.path, f"{name}.thetas")
        wrist = numbers(hand["mano_pose"].get("wrist_xform"), 6, clip.path, f"{name}.wrist_xform")
        mano = self.mano(side)
        pose = pca_to_axis_angle(np.concatenate([wrist[:3], thetas]), mano.hands_components.double().numpy(),
                                 mano.hands_mean.double().numpy())
        with torch.no_grad():
            out = mano(torch.as_tensor(pose)[None], torch.as_tensor(betas)[None], torch.as_tensor(wrist[3:])[None])
        return {"pose": pose, "transl": wrist[3:], "joints": out.joints[0].double().numpy(),
                "rest_wrist": mano.rest_wrist(betas), "betas": betas}

    def _crop_frame(self, clip, key, side, stream, crop, cameras, world, obj, frame_id) -> Frame:
        member = f"{key}.image_{stream}.jpg"
        if stream not in cameras:
            raise DataError(clip.path, f"{key}.cameras.json: {stream}", "no camera for this stream")
        clip.refuse_duplicate(member)
        where = clip.frames[key].get(f"image_{stream}.jpg")
        if where is None:
            raise DataError(clip.path, member, "member missing")
        cam = stream_camera(cameras[stream], clip.path, f"{key}.cameras.json: {stream}")
        K, world_from_crop = crop_camera(crop, self.crop_size, clip.path, f"{key}.hand_crops.json: {side}.{stream}")
        crop_from_world = np.linalg.inv(world_from_crop)
        R, t = crop_from_world[:3, :3], crop_from_world[:3, 3]
        pose, transl = change_frame(world["pose"], world["transl"], world["rest_wrist"], R, t)
        joints = world["joints"] @ R.T + t
        bop_id, world_from_object, uid = obj
        return Frame(
            dataset="hot3d_clips", split=self.split, frame_id=frame_id, image_path=clip.path,
            image_size=(self.crop_size, self.crop_size), K=K, side=side, root_3d=joints[0],
            object_name=f"obj_{bop_id:06d}", object_id=bop_id, object_pose=crop_from_world @ world_from_object,
            mano_pose=pose, mano_betas=world["betas"], mano_transl=transl, joints_3d=joints,
            joints_2d=project(joints, K), tip_convention="manopth", mirror=self.mirror_left and side == "left",
            fix_left_shapedirs=True,
            source={"clip": str(clip.path), "key": key, "stream": stream, "object_uid": uid, "rgb": cam.is_rgb,
                    "objects_json": list(clip.frames[key]["objects.json"])},
            image_source=CropImage(str(clip.path), where, member, cam.camera, cam.world_from_camera, K,
                                   world_from_crop, self.crop_size))


def object_mask_iou(frame: Frame, ours: np.ndarray, to_mask: np.ndarray) -> float:
    """IoU of our amodal object mask ``ours`` (M, M) bool on a record's mask grid with the clip's amodal RLE mask of
    the frame's object in the frame's stream; -1 where the clip has no mask for that stream. ``to_mask`` (3, 3): the
    frame's crop pixels (mirrored when the frame is) -> mask pixels.

    The RLE mask is read once, straight at the mask pixels' rays (bilinear, >= 0.5), and compared where the mask
    grid sees the crop camera's image and the fisheye image. One resampling, not two: remapping into the crop and
    then warping that (thresholded) mask nearest-neighbour onto the mask grid moved its edges by up to half a crop
    pixel more (toy: mean IoU 0.975 that way; the HOT3D section of docs/datasets.md)."""
    import cv2

    src = frame.image_source
    name = f"{frame.source['key']}.objects.json"
    objects = parse_json(ClipMembers(Path(src.tar)).read(tuple(frame.source["objects_json"]), name), src.tar, name)
    uid = frame.source["object_uid"]
    instances = check(objects, MapOf(ANY), src.tar, name).get(uid)
    if not isinstance(instances, list) or not instances or not isinstance(instances[0], dict):
        raise DataError(src.tar, f"{name}: {uid}", "no instance of the frame's object (the clip changed?)")
    masks = instances[0].get("masks_amodal", {})
    rle = masks.get(frame.source["stream"]) if isinstance(masks, dict) else None
    if rle is None:
        return -1.0
    mask = rle_decode(rle, src.tar, f"{name}: {frame.source['object_uid']}.masks_amodal.{frame.source['stream']}")
    cam = src.camera
    if mask.shape != (cam.height, cam.width):
        raise DataError(src.tar, name, f"mask is {mask.shape[1]}x{mask.shape[0]}, the image {cam.width}x{cam.height}")
    size = ours.shape[0]
    v, u = np.mgrid[0:size, 0:size].astype(np.float64)
    back = np.linalg.inv(to_mask)  # mask pixels -> the (mirrored when the frame is) crop's pixels
    if frame.mirror:
        back = np.array([[-1.0, 0.0, src.size - 1], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ back
    uv = np.stack([u, v], -1) @ back[:2, :2].T + back[:2, 2]  # the crop pixels under the mask's pixel centres
    pix = fisheye_grid(cam, src.world_from_camera, src.K, src.world_from_crop, (size, size), back).astype(np.float32)
    seen = (uv > -0.5).all(-1) & (uv < src.size - 0.5).all(-1)
    seen &= (pix >= 0).all(-1) & (pix[..., 0] <= cam.width - 1) & (pix[..., 1] <= cam.height - 1)
    theirs = np.zeros(seen.shape, bool)
    if seen.any():  # read from the window of the mask that the seen pixels and their right/lower neighbours cover
        lo = np.floor(pix[seen].min(0)).astype(np.int64)
        hi = np.floor(pix[seen].max(0)).astype(np.int64) + 2
        window = mask[lo[1]:hi[1], lo[0]:hi[0]].astype(np.float32)
        shifted = pix - lo.astype(np.float32)  # exact: whole numbers off float32 values of the same or finer ulp
        theirs = cv2.remap(window, shifted[..., 0], shifted[..., 1], cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0) >= 0.5
    theirs, ours = theirs & seen, ours & seen
    union = np.count_nonzero(theirs | ours)
    return float(np.count_nonzero(theirs & ours) / union) if union else 1.0


def hand_reason(hand: dict) -> str | None:
    """Why a hands.json entry gives no MANO hand, or None: no ``umetrack_pose`` (the official reader then reads no
    MANO pose either), or no ``mano_pose`` (MANO registration failed in that frame)."""
    if not isinstance(hand, dict) or "umetrack_pose" not in hand:
        return "no umetrack_pose: the hand was not tracked in this frame (its MANO pose is not read)"
    if not isinstance(hand.get("mano_pose"), dict):
        return "no mano_pose: MANO registration failed in this frame"
    return None


def nearest_object(objects: dict, point: np.ndarray, path, name: str) -> tuple[int, np.ndarray, str]:
    """(BOP id, object -> world (4, 4), object uid) of the annotated object whose origin is nearest ``point``."""
    best = None
    for uid, instances in (objects or {}).items():
        for inst in instances if isinstance(instances, list) else [instances]:
            if not isinstance(inst, dict) or "object_bop_id" not in inst:
                raise DataError(path, f"{name}: {uid}.object_bop_id", "missing")
            check(inst["object_bop_id"], Integer(0), path, f"{name}: {uid}.object_bop_id")
            pose = transform(inst.get("T_world_from_object"), path, f"{name}: {uid}.T_world_from_object")
            d = float(np.linalg.norm(pose[:3, 3] - point))
            if best is None or d < best[0]:
                best = (d, int(inst["object_bop_id"]), pose, str(uid))
    if best is None:
        raise DataError(path, name, "no annotated object in this frame")
    return best[1:]

"""Upstream HOISDF's training augmentation, per sample (``data/dexycb.py`` / ``data/ho3d.py`` ``data_aug`` with the
helpers of ``data/dataset_util.py``), reproduced operation for operation on a record that keeps the original frame's
region (hoidata's ``record.upstream_region``).

What it does, in upstream's order and arithmetic (dtypes included, since a different rounding moves a nearest pixel):

* the base square: the union of the 2D joints' box x1.5 and the 21-point object box x1.5, clipped to the frame,
  made square, integer centre (:func:`hoidata.geometry.upstream_crop.base_square`);
* the centre moves by ``0.1 side U(-1, 1)`` per axis, the side by ``clip(0.2 N(0, 1) + 1, 0.8, 1.2)``, and the crop
  turns by the draw's angle (DexYCB: with probability 0.6, ``clip(N(0, 1), -2, 2) 30`` degrees; HO-3D:
  ``U(-pi, pi)``) about the optical axis;
* ONE nearest-neighbour warp of the frame with Pillow (``Image.transform`` AFFINE, black outside the frame), then
  Pillow's ``GaussianBlur(radius)``, then torchvision's functional brightness, saturation, hue (HSV) and contrast
  on the PIL image in the draw's order (upstream shuffles them per sample);
* K' = post-rotation affine @ K, joints, the 21 points and every 3D label rotated; the grid-filter boxes are the
  warped joints' box x1.1 (HO-3D x1.2) and the warped 21-point box; the object anchor is the latter's integer
  centre back-projected at the hand root's depth (HO-3D: at 0.5244322 m).

:class:`UpstreamDraw` holds every random number, so a test can replay upstream's own draws; :func:`draw_upstream`
draws one from a numpy Generator with upstream's distributions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hoidata.geometry import upstream_crop as up

COLOR_OPS = ("brightness", "saturation", "hue", "contrast")  # upstream's list, before its per-sample shuffle
COLOR_RANGE = {"brightness": 0.5, "contrast": 0.5, "saturation": 0.5, "hue": 0.15}
BLUR_MAX = 0.5  # Pillow GaussianBlur radius U(0, BLUR_MAX)
ROT_PROB, ROT_STEP_DEG = 0.6, 30  # DexYCB: p <= ROT_PROB, clip(N(0, 1), -2, 2) * ROT_STEP_DEG degrees
ROTATIONS = {"dexycb": "dexycb", "ho3d": "uniform"}  # dataset -> upstream's rotation rule
HAND_GRID_FACTOR = {"dexycb": 1.1, "ho3d": 1.2}
HEATMAP_RES = 128  # upstream's heatmap / mask side


@dataclass(frozen=True)
class UpstreamDraw:
    """One sample's random numbers: ``jitter`` (2,) U(-1, 1); ``scale`` the clipped side factor; ``rotation``
    radians; ``blur`` Pillow radius; the four colour factors; ``order``: COLOR_OPS in the order applied."""

    jitter: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0
    rotation: float = 0.0
    blur: float = 0.0
    brightness: float = 1.0
    contrast: float = 1.0
    saturation: float = 1.0
    hue: float = 0.0
    order: tuple[str, ...] = COLOR_OPS

    def __post_init__(self):
        if sorted(self.order) != sorted(COLOR_OPS):
            raise ValueError(f"order must be a permutation of {COLOR_OPS}, got {self.order}")


def draw_upstream(rng: np.random.Generator, rotation: str) -> UpstreamDraw:
    """A draw with upstream's distributions (``rotation``: "dexycb", "uniform" or "none"), in upstream's order."""
    jitter = rng.uniform(-1, 1, size=2)
    scale = np.clip(up.SCALE_JITTER * rng.standard_normal() + 1, 1 - up.SCALE_JITTER, 1 + up.SCALE_JITTER)
    if rotation == "dexycb":
        angle = np.clip(rng.standard_normal(), -2.0, 2.0) * ROT_STEP_DEG if rng.random() <= ROT_PROB else 0
        angle = angle * np.pi / 180
    elif rotation == "uniform":
        angle = rng.uniform(-np.pi, np.pi)
    elif rotation == "none":
        angle = 0.0
    else:
        raise ValueError(f"rotation must be 'dexycb', 'uniform' or 'none', got {rotation!r}")
    blur = rng.random() * BLUR_MAX
    factors = {name: rng.uniform(-r, r) if name == "hue" else rng.uniform(max(0.0, 1 - r), 1 + r)
               for name, r in COLOR_RANGE.items()}  # upstream's order: brightness, contrast, saturation, hue
    order = tuple(COLOR_OPS[i] for i in rng.permutation(len(COLOR_OPS)))
    return UpstreamDraw(tuple(float(j) for j in jitter), float(scale), float(angle), float(blur),
                        order=order, **{k: float(v) for k, v in factors.items()})


def warp_frame(region: np.ndarray, origin, frame_size, affine: np.ndarray, size: int = up.INPUT_SIZE):
    """PIL RGB (size, size): the frame (``frame_size`` (W, H), black) holding ``region`` (n, n, 3) uint8 at
    ``origin`` (x0, y0), warped by ``affine`` as upstream's ``transform_img`` (:func:`~hoidata.geometry.upstream_crop.
    warp_pil`). The frame is rebuilt so that Pillow samples the very coordinates it samples in upstream's whole frame;
    a ``region`` (H, W, 3) that is the whole frame at origin (0, 0) is warped as it is."""
    from PIL import Image

    size_wh = tuple(int(v) for v in frame_size)
    if tuple(int(v) for v in origin) == (0, 0) and region.shape[1::-1] == size_wh:
        return up.warp_pil(Image.fromarray(np.ascontiguousarray(region)), affine, size)
    frame = Image.new("RGB", size_wh)
    frame.paste(Image.fromarray(np.ascontiguousarray(region)), tuple(int(v) for v in origin))
    return up.warp_pil(frame, affine, size)


def blur_and_color(image, draw: UpstreamDraw):
    """Pillow's GaussianBlur(draw.blur), then torchvision's functional colour ops on the PIL image in draw.order."""
    import torchvision.transforms.functional as TF
    from PIL import ImageFilter

    image = image.filter(ImageFilter.GaussianBlur(draw.blur))
    ops = {"brightness": TF.adjust_brightness, "saturation": TF.adjust_saturation, "hue": TF.adjust_hue,
           "contrast": TF.adjust_contrast}
    for name in draw.order:
        image = ops[name](image, getattr(draw, name))
    return image


def footprint_inside(affine: np.ndarray, origin, n: int, frame_size, size: int = up.INPUT_SIZE) -> bool:
    """Whether every frame pixel the warp can sample lies in the stored region or outside the frame (black in both)."""
    corners = np.array([[0, 0], [size, 0], [0, size], [size, size]], np.float64)
    src = up.transform_points(corners, np.linalg.inv(affine.astype(np.float64)))
    lo = np.maximum(np.floor(src.min(0)) - 1, 0)
    hi = np.minimum(np.ceil(src.max(0)) + 1, np.asarray(frame_size, np.float64) - 1)
    return bool((lo >= np.asarray(origin)).all() and (hi <= np.asarray(origin) + n - 1).all())


@dataclass
class UpstreamView:
    """One augmented sample, upstream's values: image (before colour) and image (after blur and colour) PIL;
    K (3, 3); joints_uv (21, 2) crop px; box21_uv (21, 2) crop px; hand_box, object_box (4,) grid-filter boxes;
    anchor (3,) float32 m; rot (3, 3) float32; affine (3, 3) float32 frame -> crop (upstream's convention);
    side: the jittered crop side (frame px); joints_3d turned; size: the output side (px)."""

    plain: object
    image: object
    K: np.ndarray
    joints_uv: np.ndarray
    box21_uv: np.ndarray
    hand_box: np.ndarray
    object_box: np.ndarray
    anchor: np.ndarray
    rot: np.ndarray
    affine: np.ndarray
    side: float
    joints_3d: np.ndarray  # (21, 3) float32, turned by rot
    size: int = up.INPUT_SIZE


def augment_view(region: np.ndarray, origin, frame_size, K: np.ndarray, joints_uv: np.ndarray,
                 box21_uv: np.ndarray, joints_3d: np.ndarray, dataset: str, draw: UpstreamDraw) -> UpstreamView:
    """Upstream's ``data_aug`` for one frame, given in upstream's dtypes (DexYCB: K float64, joints float32; HO-3D:
    both float32): ``region`` (n, n, 3) uint8 at ``origin`` in the frame of ``frame_size``; joints_3d (21, 3) float32
    camera frame (joint 0 the hand root, whose turned depth places the DexYCB anchor). ``region`` may be the whole
    frame (H, W, 3) at origin (0, 0)."""
    centre, side = up.base_square(joints_uv, box21_uv, tuple(frame_size))
    centre = centre + up.CENTER_JITTER * side * np.asarray(draw.jitter, np.float64)
    side = side * np.float64(draw.scale)
    affine, affine_k, rot = up.rotated_crop_affines(centre, side, draw.rotation, K)
    uv, box_uv = up.transform_points(joints_uv, affine), up.transform_points(box21_uv, affine)
    K_new = affine_k.dot(K)
    hand_box, object_box = up.joints_box(uv, HAND_GRID_FACTOR[dataset]), up.joints_box(box_uv, up.OBJECT_GRID_FACTOR)
    joints_3d = np.asarray(joints_3d, np.float32).dot(rot.T)
    depth = joints_3d[0][-1] if dataset == "dexycb" else up.HO3D_ANCHOR_DEPTH
    plain = warp_frame(region, origin, frame_size, affine)
    return UpstreamView(plain, blur_and_color(plain, draw), K_new, uv, box_uv, hand_box, object_box,
                        up.centre_camera(object_box, depth, K_new), rot, affine, float(side), joints_3d)

"""Loader batch -> network input batch: crop, in-plane rotation, colour and blur, batched on the batch's device.

Geometry, per sample (B = batch size, S = stored crop side, R = ``input_size``). An in-plane rotation ``rot``
about the optical axis (z) rotates every camera-frame quantity. Because ``rot`` keeps z, the stored pixels
move by the affine map ``H = K rot K^-1``. A square crop of side ``s`` (stored pixels) whose centre ``c`` is
taken to ``H c`` is then resized to R px by ``A`` (scale ``a = R / s``, translation putting ``H c`` at the
output centre ``(R - 1) / 2``). The new intrinsics are ``K' = A K``; stored pixels map to output pixels by
``M = A H``, and every image-like tensor is resampled once through ``M^-1``.

Pixel convention (OpenCV): pixel (col, row) is centred at integer (u, v); an image of n px spans
[-0.5, n - 0.5]. Half-resolution grids (masks, heatmap) relate to full ones by ``u_half = 0.5 u - 0.25``.
With ``grid_sample(align_corners=False)`` that convention gives both resolutions the same normalised
coordinates, so one sampling matrix serves the image and the masks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F

from hoidata.geometry.rotation import axis_angle_to_matrix, matrix_to_axis_angle

POINT_KEYS = ("hand_points", "obj_points", "hand_near_points", "obj_near_points")
ROTATIONS = ("dexycb", "uniform", "none")
UPSTREAM_SIZE = 256  # upstream's input side (px), what augment.upstream samples come at
HEATMAP_TARGETS = ("clipped", "upstream")
_GREY = (0.299, 0.587, 0.114)  # ITU-R 601 luma, as in torchvision's rgb_to_grayscale
_RGB_TO_YIQ = ((0.299, 0.587, 0.114), (0.595716, -0.274453, -0.321263), (0.211456, -0.522591, 0.311135))


@dataclass(frozen=True)
class AugmentSettings:
    """Augmentation of HOISDF (docs/upstream.md, "Augmentation"); sizes in pixels, angles in radians unless noted."""

    input_size: int = 256  # output image side R (px); masks and heatmap come out at R // 2
    context: float = 2.0  # the store's crop context: the network crop is the central S_store / context square
    center_jitter: float = 0.1  # centre + jitter * side * U(-1, 1) per axis
    scale_sigma: float = 0.2  # side * clip(N(1, sigma), scale_min, scale_max)
    scale_min: float = 0.8  # lower clip of the crop-side scale factor
    scale_max: float = 1.2  # upper clip of the crop-side scale factor
    rotation: str = "dexycb"  # "dexycb": p=rot_prob, clip(N(0,1), -2, 2) * 30 deg; "uniform": U(-pi, pi); "none"
    rot_prob: float = 0.6  # probability of an in-plane rotation (rotation = dexycb)
    color: bool = True  # brightness, contrast, saturation U(0.5, 1.5), hue shift U(-0.15, 0.15) of a turn
    blur_max: float = 0.5  # Gaussian blur sigma U(0, blur_max), output pixels (0 disables)
    heatmap_sigma: float = 1.25  # px at the R // 2 resolution
    # true: upstream HOISDF's augmentation, per sample in the loader's workers, from record.upstream_region records
    # (hoisdf.data.upstream_augment: its fixed ranges and per-dataset rotation rule; the keys above do not apply)
    upstream: bool = False
    heatmap_target: str = "clipped"  # clipped: sum of Gaussians clipped at 1, pixel centres | upstream (see below)
    LIMITS: ClassVar[dict] = {"input_size": (">= 32",), "context": ("> 0",), "center_jitter": (">= 0",),
                              "scale_sigma": (">= 0",), "scale_min": ("> 0",), "scale_max": ("> 0",),
                              "rot_prob": (">= 0", "<= 1"), "blur_max": (">= 0",), "heatmap_sigma": ("> 0",)}

    def __post_init__(self):
        if self.rotation not in ROTATIONS:
            raise ValueError(f"rotation must be one of {ROTATIONS}, got {self.rotation!r}")
        if self.heatmap_target not in HEATMAP_TARGETS:
            raise ValueError(f"heatmap_target must be one of {HEATMAP_TARGETS}, got {self.heatmap_target!r}")
        if self.input_size < 2 or self.context <= 0:
            raise ValueError(f"need input_size >= 2 and context > 0, got {self.input_size}, {self.context}")
        if self.upstream and self.input_size != UPSTREAM_SIZE:
            raise ValueError(f"augment.upstream makes upstream's {UPSTREAM_SIZE} px inputs: input_size (model.image_size) "
                             f"must be {UPSTREAM_SIZE}, got {self.input_size}")


def draw_params(batch_size: int, settings: AugmentSettings, generator: torch.Generator | None,
                train: bool) -> dict[str, torch.Tensor]:
    """Per-sample random parameters, drawn on the CPU (reproducible for a seed on any device).

    Returns shift (B, 2) centre offset in units of the crop side, scale (B,) side factor, angle (B,) radians,
    color (B, 4) brightness, contrast, saturation factors and hue shift (turns), order (4,) colour-op order,
    blur (B,) sigma in output pixels. ``train=False``: the identity (central crop, nothing else).
    """
    b, cpu = batch_size, {"device": "cpu"}  # explicit: a default device set by the user must not move these
    if not train:
        return {"shift": torch.zeros(b, 2, **cpu), "scale": torch.ones(b, **cpu), "angle": torch.zeros(b, **cpu),
                "color": torch.tensor([1.0, 1.0, 1.0, 0.0], **cpu).repeat(b, 1), "order": torch.arange(4, **cpu),
                "blur": torch.zeros(b, **cpu)}
    shift = settings.center_jitter * (2 * torch.rand(b, 2, generator=generator, **cpu) - 1)
    scale = (1 + settings.scale_sigma * torch.randn(b, generator=generator, **cpu)).clamp(settings.scale_min,
                                                                                         settings.scale_max)
    if settings.rotation == "dexycb":
        angle = torch.randn(b, generator=generator, **cpu).clamp(-2, 2) * (math.pi / 6)
        angle = angle * (torch.rand(b, generator=generator, **cpu) < settings.rot_prob)
    elif settings.rotation == "uniform":
        angle = (2 * torch.rand(b, generator=generator, **cpu) - 1) * math.pi
    else:
        angle = torch.zeros(b, **cpu)
    factors = 0.5 + torch.rand(b, 3, generator=generator, **cpu)
    hue = 0.15 * (2 * torch.rand(b, 1, generator=generator, **cpu) - 1)
    identity = torch.tensor([1.0, 1.0, 1.0, 0.0], **cpu).repeat(b, 1)
    color = torch.cat([factors, hue], 1) if settings.color else identity
    order = torch.randperm(4, generator=generator, **cpu)
    blur = settings.blur_max * torch.rand(b, generator=generator, **cpu)
    return {"shift": shift, "scale": scale, "angle": angle, "color": color, "order": order, "blur": blur}


def rotation_z(theta: torch.Tensor) -> torch.Tensor:
    """Angles (B,) radians -> rotations (B, 3, 3) about the camera z axis (x towards y for theta > 0)."""
    c, s = torch.cos(theta), torch.sin(theta)
    zero, one = torch.zeros_like(theta), torch.ones_like(theta)
    return torch.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)


def crop_intrinsics(K: torch.Tensor, centre: torch.Tensor, side: torch.Tensor, size: int) -> torch.Tensor:
    """(B, 3, 3) A @ K: the square of ``side`` (B,) px centred at ``centre`` (B, 2), in K's pixels, resized to
    ``size`` px so that ``centre`` lands on the output centre ((size - 1) / 2, (size - 1) / 2)."""
    a = size / side
    A = torch.zeros_like(K)
    A[:, 0, 0], A[:, 1, 1], A[:, 2, 2] = a, a, 1.0
    A[:, :2, 2] = (size - 1) / 2 - a[:, None] * centre
    return A @ K


def pixel_affine(K: torch.Tensor, rot: torch.Tensor, centre: torch.Tensor, side: torch.Tensor,
                 size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """New intrinsics and the stored-pixel -> output-pixel map of a rotated crop.

    K (B, 3, 3) intrinsics of the stored image; rot (B, 3, 3) z-rotations; centre (B, 2) crop centre and
    side (B,) crop side in stored pixels (before rotation); size: output px. Returns (K' (B, 3, 3),
    M (B, 3, 3)) with K' = A K and M = A K rot K^-1 (affine), so that M (K X) ~ K' (rot X).
    """
    to_rays = rot @ torch.linalg.inv(K)
    centre_rot = transform_pixels(K @ to_rays, centre[:, None])[:, 0]
    K_new = crop_intrinsics(K, centre_rot, side, size)
    return K_new, K_new @ to_rays


def transform_pixels(M: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Pixels (B, N, 2) through affine maps (B, 3, 3) -> (B, N, 2)."""
    return uv @ M[:, :2, :2].transpose(1, 2) + M[:, None, :2, 2]


def back_project(uv: torch.Tensor, K: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Pixels (B, 2) at depths (B,) m -> camera-frame points (B, 3) m."""
    ray = torch.linalg.solve(K, torch.cat([uv, torch.ones_like(uv[:, :1])], 1)[..., None])[..., 0]
    return ray * (depth / ray[:, 2])[:, None]


def transform_boxes(M: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Boxes (B, 4) x1, y1, x2, y2 -> axis-aligned boxes (B, 4) of their 4 corners through M (B, 3, 3)."""
    x1, y1, x2, y2 = boxes.unbind(1)
    corners = torch.stack([torch.stack(c, -1) for c in ((x1, y1), (x2, y1), (x1, y2), (x2, y2))], 1)
    moved = transform_pixels(M, corners)
    return torch.cat([moved.amin(1), moved.amax(1)], 1)


def warp_theta(M: torch.Tensor, src_size: int, out_size: int) -> torch.Tensor:
    """(B, 2, 3) ``affine_grid`` matrix (align_corners=False) resampling a src_size image by pixel map M."""
    def to_norm(n: int) -> torch.Tensor:  # pixel u -> (2 u + 1) / n - 1
        return M.new_tensor([[2 / n, 0, 1 / n - 1], [0, 2 / n, 1 / n - 1], [0, 0, 1]])

    return (to_norm(src_size) @ torch.linalg.inv(M) @ torch.linalg.inv(to_norm(out_size)))[:, :2]


def warp(images: torch.Tensor, theta: torch.Tensor, size: int) -> torch.Tensor:
    """Images (B, C, h, w) resampled (bilinear, zeros outside) to (B, C, size, size) by ``warp_theta``."""
    grid = F.affine_grid(theta, [images.shape[0], images.shape[1], size, size], align_corners=False)
    return F.grid_sample(images, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def render_heatmap(uv: torch.Tensor, size: int, sigma: float, clip: bool = True) -> torch.Tensor:
    """Joints (B, J, 2) in heatmap pixels -> (B, 1, size, size): sum of Gaussians (peak 1 each), clipped to 1
    unless ``clip=False`` (the reference's target / 255: where two joints are close the sum exceeds 1)."""
    grid = torch.arange(size, dtype=uv.dtype, device=uv.device)
    gx = torch.exp(-(grid - uv[..., :1]) ** 2 / (2 * sigma ** 2))  # (B, J, size)
    gy = torch.exp(-(grid - uv[..., 1:]) ** 2 / (2 * sigma ** 2))
    total = torch.einsum("bjy,bjx->byx", gy, gx)
    return (total.clamp(max=1.0) if clip else total)[:, None]


def heatmap_target(uv: torch.Tensor, size: int, half: int, sigma: float, target: str) -> torch.Tensor:
    """The heatmap target (B, 1, half, half) of joints (B, J, 2) in output pixels of a ``size`` image.

    ``"clipped"``: pixel centres map to pixel centres (``u_half = a u + (a - 1) / 2``, a = half / size) and the
    sum is clipped at 1. ``"upstream"``: the reference's ``uv / 256 * 128`` on the integer grid (0.25 heatmap px
    from the centres mapping) and the sum of the Gaussians not clipped (``Model.render_gaussian_heatmap`` / 255).
    """
    a = half / size
    if target == "upstream":
        return render_heatmap(a * uv, half, sigma, clip=False)
    return render_heatmap(a * uv + (a - 1) / 2, half, sigma)


def _grey(img: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> luma (B, 1, H, W)."""
    return torch.einsum("c,bchw->bhw", img.new_tensor(_GREY), img)[:, None]


def adjust_hue(img: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Rotate the chroma of RGB images (B, 3, H, W) by ``shift`` (B,) turns in YIQ space (luma kept)."""
    to_yiq = img.new_tensor(_RGB_TO_YIQ)
    c, s = torch.cos(2 * math.pi * shift), torch.sin(2 * math.pi * shift)
    one, zero = torch.ones_like(c), torch.zeros_like(c)
    turn = torch.stack([one, zero, zero, zero, c, -s, zero, s, c], -1).reshape(-1, 3, 3)  # rotates (I, Q)
    mix = torch.linalg.inv(to_yiq) @ turn @ to_yiq  # (B, 3, 3)
    return torch.einsum("bij,bjhw->bihw", mix, img)


def color_jitter(img: torch.Tensor, color: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Brightness, contrast, saturation (factors ``color[:, :3]``) and hue (``color[:, 3]`` turns) applied to
    (B, 3, H, W) in [0, 1] in the order ``order`` (4,), each clamped to [0, 1] like torchvision."""
    for op in order.tolist():
        f = color[:, op, None, None, None]
        if op == 0:
            img = img * f
        elif op == 1:
            mean = _grey(img).mean((2, 3), keepdim=True)
            img = f * img + (1 - f) * mean
        elif op == 2:
            img = f * img + (1 - f) * _grey(img)
        else:
            img = adjust_hue(img, color[:, 3])
        img = img.clamp(0.0, 1.0)
    return img


def gaussian_blur(img: torch.Tensor, sigma: torch.Tensor, radius: int) -> torch.Tensor:
    """Separable Gaussian blur of (B, C, H, W) with per-sample sigma (B,) px, kernel 2 radius + 1, reflect pad."""
    b, c, h, w = img.shape
    x = torch.arange(-radius, radius + 1, dtype=img.dtype, device=img.device)
    kernel = torch.exp(-x ** 2 / (2 * sigma.clamp_min(1e-3)[:, None] ** 2))
    kernel = (kernel / kernel.sum(1, keepdim=True)).repeat_interleave(c, 0)  # (B C, 2 r + 1)
    flat = F.pad(img.reshape(1, b * c, h, w), (radius,) * 4, mode="reflect")
    flat = F.conv2d(flat, kernel[:, None, None, :], groups=b * c)
    flat = F.conv2d(flat, kernel[:, None, :, None], groups=b * c)
    return flat.reshape(b, c, h, w)


def rotate_mano_global(pose: torch.Tensor, rot: torch.Tensor) -> torch.Tensor:
    """MANO pose (B, 48) axis-angle -> same with the global rotation (first 3) replaced by rot @ Rot(global)."""
    glob = matrix_to_axis_angle(rot @ axis_angle_to_matrix(pose[:, :3]))
    return torch.cat([glob, pose[:, 3:]], 1)


def unpack_masks(bits: torch.Tensor) -> torch.Tensor:
    """The loader's ``seg_bits`` (B, H, W) uint8 -> (B, 4, H, W) float32 {0, 1} planes on the same device: visible
    hand, visible object, amodal hand, amodal object (bits 0-3, hoidata.schema.SEG_*)."""
    shifts = torch.arange(4, dtype=torch.uint8, device=bits.device)[:, None, None]
    return ((bits[:, None] >> shifts) & 1).float()


def mask_planes(batch: dict) -> torch.Tensor:
    """(B, 4, H, W) float32 mask planes of a batch: unpacked from ``seg_bits`` (the loader's layout) or from a
    ``seg`` (B, 4, H, W) bool/float batch (the loader's layout before issue 17, batches built by hand)."""
    return unpack_masks(batch["seg_bits"]) if "seg_bits" in batch else batch["seg"].float()


def float_image(img: torch.Tensor) -> torch.Tensor:
    """A loader image batch (B, 3, S, S) uint8 in [0, 255] -> float32 in [0, 1] (img / 255, on img's device);
    a float batch (already in [0, 1]) passes through as float32."""
    return img.float() / 255.0 if img.dtype == torch.uint8 else img.float()


def augment_batch(batch: dict, settings: AugmentSettings, generator: torch.Generator | None, train: bool) -> dict:
    """A loader batch (see ``hoisdf.data.build_dataset``) -> the network input batch, on the batch's device.

    ``train=False``: the central S / context crop resized to R (test-time input); an upstream-crop record
    (``upstream_crop``, hoidata's ``record.crop = "upstream"``) is used whole, as stored when S = R (no resampling),
    with its own grid boxes and object anchor (``grid_hand_box``, ``grid_object_box``, ``object_anchor``). ``train=True``: random
    centre, scale, rotation, colour and blur per sample, drawn on the CPU from ``generator``.
    Replaces img (B, 3, R, R), seg (B, 4, R/2, R/2) float {0, 1} (from ``seg_bits``, which is dropped, or a
    4-plane ``seg``), heatmap (B, 1, R/2, R/2) (rendered from the joints, whether the batch has one or not),
    K, joints_3d, joints_2d, hand_root, *_points, mano_pose, object_pose, hand_box, object_box; adds
    obj_center (B, 3) m (object box centre back-projected at the hand root's depth), rotation (B, 3, 3)
    and crop_scale (B,) = R / s. Every other entry is passed through unchanged.
    """
    if _upstream_augmented(batch):
        return upstream_batch(batch, settings)
    img = float_image(batch["img"])  # on the device: uint8 crosses the worker queue and the bus
    device, b, size = img.device, img.shape[0], settings.input_size
    half, store_size = size // 2, img.shape[-1]
    params = {k: v.to(device) for k, v in draw_params(b, settings, generator, train).items()}
    upstream = _upstream_crops(batch, b, device)
    # an upstream crop is the network input itself: its whole square, not the central 1 / context of a wider one
    side0 = torch.where(upstream, float(store_size), store_size / settings.context)
    centre = (store_size - 1) / 2 + side0[:, None] * params["shift"]
    side = side0 * params["scale"]
    rot = rotation_z(params["angle"].float())
    K_new, M = pixel_affine(batch["K"].float(), rot, centre.float(), side.float(), size)
    theta = warp_theta(M, store_size, size)

    img = warp(img, theta, size)
    if train and settings.blur_max > 0:
        img = gaussian_blur(img, params["blur"].float(), math.ceil(3 * settings.blur_max))
    if train and settings.color:
        img = color_jitter(img, params["color"].float(), params["order"])
    out = {k: v for k, v in batch.items() if k != "seg_bits"}
    out["img"] = img
    out["seg"] = (warp(mask_planes(batch), theta, half) >= 0.5).float()
    out["K"] = K_new
    out["joints_3d"] = batch["joints_3d"].float() @ rot.transpose(1, 2)
    out["joints_2d"] = transform_pixels(M, batch["joints_2d"].float())
    out["heatmap"] = heatmap_target(out["joints_2d"], size, half, settings.heatmap_sigma, settings.heatmap_target)
    out["hand_root"] = (rot @ batch["hand_root"].float()[..., None])[..., 0]
    for key in POINT_KEYS:
        if key in batch:
            out[key] = batch[key].float() @ rot.transpose(1, 2)
    rot4 = torch.eye(4, device=device, dtype=rot.dtype).repeat(b, 1, 1)
    rot4[:, :3, :3] = rot
    out["object_pose"] = rot4 @ batch["object_pose"].float()
    out["mano_pose"] = rotate_mano_global(batch["mano_pose"].float(), rot)
    out["hand_box"] = transform_boxes(M, batch["hand_box"].float())
    out["object_box"] = transform_boxes(M, batch["object_box"].float())
    box = out["object_box"]
    out["obj_center"] = back_project(0.5 * (box[:, :2] + box[:, 2:]), K_new, out["hand_root"][:, 2])
    out["rotation"] = rot
    out["crop_scale"] = size / side.float()
    if upstream.any():
        as_is = upstream if not train and store_size == size else torch.zeros_like(upstream)
        _use_upstream_crop(out, batch, M, rot, as_is)
    return out


def _upstream_crops(batch: dict, b: int, device) -> torch.Tensor:
    """(B,) bool: which samples are upstream crops (the loader's ``upstream_crop``; none when the batch lacks it)."""
    flags = batch.get("upstream_crop")
    return flags.to(device).bool() if flags is not None else torch.zeros(b, dtype=torch.bool, device=device)


def _use_upstream_crop(out: dict, batch: dict, M: torch.Tensor, rot: torch.Tensor, as_is: torch.Tensor) -> None:
    """Upstream-crop samples take the record's grid boxes and object anchor instead of the ones made from the mesh
    boxes (moved by ``M`` / ``rot`` like every label); ``as_is`` (B,) samples (test time, stored size = input size)
    take the stored image, K, boxes and anchor exactly, with no resampling (``grid_sample`` at the identity would
    still round)."""
    up = batch["upstream_crop"].to(M.device).bool()
    for name, grid in (("hand_box", "grid_hand_box"), ("object_box", "grid_object_box")):
        stored = batch[grid].float()
        moved = torch.where(as_is[:, None], stored, transform_boxes(M, stored))
        out[name] = torch.where(up[:, None], moved, out[name])
    anchor = batch["object_anchor"].float()
    anchor = torch.where(as_is[:, None], anchor, (rot @ anchor[..., None])[..., 0])
    out["obj_center"] = torch.where(up[:, None], anchor, out["obj_center"])
    if as_is.any():
        out["K"] = torch.where(as_is[:, None, None], batch["K"].float(), out["K"])
        out["img"] = torch.where(as_is[:, None, None, None], float_image(batch["img"]), out["img"])


def _upstream_augmented(batch: dict) -> bool:
    """Whether the loader augmented this batch as upstream does (``upstream_aug``: all samples or none)."""
    flags = batch.get("upstream_aug")
    if flags is None or not bool(flags.any()):
        return False
    if not bool(flags.all()):
        raise ValueError("a batch mixes samples augmented by the loader (augment.upstream) with others")
    return True


def upstream_batch(batch: dict, settings: AugmentSettings) -> dict:
    """A batch the loader augmented as upstream HOISDF does (:mod:`hoisdf.data.upstream_samples`) -> the network input
    batch: images, K, joints, boxes and 3D labels as they are; seg from ``seg_bits``; the heatmap from the joints
    (``augment.heatmap_target``; ``"upstream"`` is upstream's ``uv / 256 * 128`` summed); obj_center = upstream's anchor; rotation the identity (already applied)."""
    img = float_image(batch["img"])
    size = img.shape[-1]
    out = {k: v for k, v in batch.items() if k != "seg_bits"}
    out["img"], out["seg"] = img, mask_planes(batch)
    out["heatmap"] = heatmap_target(batch["joints_2d"].float(), size, size // 2, settings.heatmap_sigma,
                                    settings.heatmap_target)
    out["obj_center"] = batch["object_anchor"].float()
    out["rotation"] = torch.eye(3, device=img.device).repeat(img.shape[0], 1, 1)
    return out

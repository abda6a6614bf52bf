"""HOT3D-Clips' pinhole hand-crop camera and the remap of a FISHEYE624 image into it. Pure numpy (+ cv2.remap).

The crop camera of one hand in one stream (``hand_crops.json``; docs/datasets.md, "HOT3D-Clips") is a square
pinhole of ``size`` pixels with ``f = size / 2 / tan(fov / 2)``, ``c = (size - 1) / 2`` (pixel centres at whole
numbers), the field of view ``crop_camera_fov`` in radians, and the pose ``T_world_from_crop_camera`` (crop camera ->
world). Its pixels: each pixel's ray (pinhole) -> world -> the fisheye camera's frame -> FISHEYE624 pixels ->
bilinear ``cv2.remap``; rays that arrive behind the fisheye camera (z < 0) read black.
"""

from __future__ import annotations

import numpy as np

from hoidata.geometry.fisheye624 import Fisheye624


def crop_intrinsics(size: int, fov: float) -> np.ndarray:
    """K (3, 3) of a square crop camera of ``size`` pixels and field of view ``fov`` (radians, 0 < fov < pi)."""
    if not 0.0 < fov < np.pi:
        raise ValueError(f"crop camera field of view must be in (0, pi) radians, got {fov!r}")
    f = size / 2.0 / np.tan(fov / 2.0)
    c = (size - 1) / 2.0
    return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])


def crop_maps(camera: Fisheye624, world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
              size: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (size, size) float32 of the crop: for each crop pixel, the fisheye pixel it reads.

    Args:
        camera: the fisheye camera's intrinsics.
        world_from_camera: (4, 4) fisheye camera -> world.
        K: (3, 3) the crop camera's intrinsics (:func:`crop_intrinsics`).
        world_from_crop: (4, 4) crop camera -> world.
        size: the crop's width and height, pixels.
    Rays behind the fisheye camera map to (-1, -1), which ``cv2.remap`` reads as black.
    """
    u, v = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    pix = crop_to_fisheye(camera, world_from_camera, K, world_from_crop, np.stack([u, v], -1))
    return pix[..., 0].astype(np.float32), pix[..., 1].astype(np.float32)


def crop_to_fisheye(camera: Fisheye624, world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
                    uv: np.ndarray) -> np.ndarray:
    """Crop camera pixels (..., 2) (any, not only whole ones) -> the fisheye pixels (..., 2) their rays reach;
    (-1, -1) where a ray arrives behind the fisheye camera. Arguments as :func:`crop_maps`."""
    uv = np.asarray(uv, np.float64)
    rays = np.stack([(uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1], np.ones(uv.shape[:-1])], -1)
    # each ray's point at unit distance, as the official reader takes it (HOT3D's crop cameras sit at the fisheye
    # camera's centre, where the distance does not matter)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    camera_from_crop = np.linalg.inv(world_from_camera) @ world_from_crop
    eye = rays @ camera_from_crop[:3, :3].T + camera_from_crop[:3, 3]
    pix = camera.project(eye)
    pix[eye[..., 2] < 0] = -1.0
    return pix


def remap_crop(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], interpolation: int | None = None) -> np.ndarray:
    """The crop (size, size[, C]) of ``image`` (H, W[, C]) through :func:`crop_maps`; bilinear by default, black
    outside the image."""
    import cv2

    flag = cv2.INTER_LINEAR if interpolation is None else interpolation
    return cv2.remap(image, maps[0], maps[1], flag, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def pinhole_to_crop_frame(points_world: np.ndarray, world_from_crop: np.ndarray) -> np.ndarray:
    """World points (..., 3) -> the crop camera's frame (OpenCV axes), metres."""
    crop_from_world = np.linalg.inv(world_from_crop)
    return np.asarray(points_world, np.float64) @ crop_from_world[:3, :3].T + crop_from_world[:3, 3]

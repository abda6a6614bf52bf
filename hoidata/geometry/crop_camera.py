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


GRID_STEP = 8  # crop pixels between the nodes where the maps are computed exactly
MAP_TOLERANCE = 0.01  # fisheye pixels: the interpolated maps' largest error allowed at the cells' centres


def crop_maps(camera: Fisheye624, world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
              size: int) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (size, size) float32 of the crop: for each crop pixel, the fisheye pixel it reads.

    Args:
        camera: the fisheye camera's intrinsics.
        world_from_camera: (4, 4) fisheye camera -> world.
        K: (3, 3) the crop camera's intrinsics (:func:`crop_intrinsics`).
        world_from_crop: (4, 4) crop camera -> world.
        size: the crop's width and height, pixels.
    Rays behind the fisheye camera map to (-1, -1), which ``cv2.remap`` reads as black. Computed as
    :func:`fisheye_grid` does: exact at every ``GRID_STEP``-th pixel, cubic in between, within ``MAP_TOLERANCE``.
    """
    pix = fisheye_grid(camera, world_from_camera, K, world_from_crop, (size, size))
    return pix[..., 0].astype(np.float32), pix[..., 1].astype(np.float32)


def fisheye_grid(camera: Fisheye624, world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
                 shape: tuple[int, int], grid_to_crop: np.ndarray | None = None, step: int = GRID_STEP,
                 tolerance: float = MAP_TOLERANCE) -> np.ndarray:
    """:func:`crop_to_fisheye` at every pixel of a (H, W) grid -> (H, W, 2) fisheye pixels; ``grid_to_crop``
    (3, 3), an affine map from the grid's pixels to crop pixels (default: the crop's own pixels).

    The map is smooth, so it is computed exactly at nodes ``step`` pixels apart (one ring beyond the grid) and
    interpolated between them with the 4 x 4-node cubic (Lagrange, separable: error of order step^4 times the
    map's 4th derivatives), then checked: the exact map at every cell's centre, where that error peaks, must lie
    within ``tolerance`` fisheye pixels of the interpolated one. Where it does not, the same at half the step; where
    that fails too, or where any node's ray arrives behind the fisheye camera, every pixel is computed exactly
    (:func:`crop_to_fisheye`). At 256 x 256 and step 8: 2,400 rays instead of 65,536."""
    H, W = shape
    A = np.eye(3) if grid_to_crop is None else np.asarray(grid_to_crop, np.float64)

    def exact(v: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, bool]:  # (len(v), len(u), 2), all in front
        uu, vv = np.meshgrid(u, v)
        uv = np.stack([uu, vv], -1) @ A[:2, :2].T + A[:2, 2]
        eye = crop_rays_in_camera(world_from_camera, K, world_from_crop, uv)
        pix = camera.project(eye)
        front = bool((eye[..., 2] > 0).all())
        pix[eye[..., 2] < 0] = -1.0
        return pix, front

    for h in (step, step // 2) if step >= 2 else (step,):  # half the step: 16 times less error, 4 times the rays
        nv, nu = (H - 1) // h + 4, (W - 1) // h + 4  # nodes at -h, 0, h, ...: the 4-node stencil's ring
        nodes, front = exact(h * (np.arange(nv) - 1.0), h * (np.arange(nu) - 1.0))
        if not front:
            break
        cv, cu = h * (np.arange(nv - 3) + 0.5), h * (np.arange(nu - 3) + 0.5)
        centres, front = exact(cv, cu)
        guess = _interpolate(nodes, _cubic_weights(cv, h, nv), _cubic_weights(cu, h, nu))
        if front and np.abs(guess - centres).max() <= tolerance:
            return _interpolate_pixels(nodes, H, W, h)
    return exact(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64))[0]


def _cubic_weights(x: np.ndarray, step: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """For each ``x[i]`` (>= 0) with nodes at ``step * (j - 1)``, j = 0..n-1: the first of its 4 nodes (len(x),)
    and their cubic Lagrange weights (len(x), 4)."""
    cell = np.minimum(np.floor(x / step).astype(np.int64), n - 4)
    t = x / step - cell
    return cell, np.stack([-t * (t - 1) * (t - 2) / 6, (t + 1) * (t - 1) * (t - 2) / 2, -(t + 1) * t * (t - 2) / 2,
                           (t + 1) * t * (t - 1) / 6], -1)


def _interpolate(nodes: np.ndarray, rows: tuple, cols: tuple) -> np.ndarray:
    """(nv, nu, C) node values -> (len(rows), len(cols), C), each value from its 4 x 4 nodes (``_cubic_weights``
    of the rows and the columns). Elementwise, not a matrix product: no BLAS threads, the same sums everywhere."""
    (cv, wv), (cu, wu) = rows, cols
    along_u = sum(nodes[:, cu + k] * wu[None, :, k, None] for k in range(4))  # (nv, len(cols), C)
    return sum(along_u[cv + k] * wv[:, k, None, None] for k in range(4))


def _interpolate_pixels(nodes: np.ndarray, H: int, W: int, step: int) -> np.ndarray:
    """:func:`_interpolate` at every pixel of an (H, W) grid, faster: row ``cell * step + p`` takes the weights of
    phase ``p`` from nodes ``cell .. cell + 3``, so the rows are made ``step`` at a time by broadcasting."""
    cu, wu = _cubic_weights(np.arange(W, dtype=np.float64), step, nodes.shape[1])
    along_u = sum(nodes[:, cu + k] * wu[None, :, k, None] for k in range(4))  # (nv, W, C)
    cells = -(-H // step)
    phase = _cubic_weights(np.arange(step, dtype=np.float64), step, nodes.shape[0])[1]  # (step, 4)
    rows = sum(along_u[k:k + cells, None] * phase[None, :, k, None, None] for k in range(4))
    return rows.reshape(cells * step, W, -1)[:H]


def crop_rays_in_camera(world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
                        uv: np.ndarray) -> np.ndarray:
    """Crop pixels (..., 2) -> the points (..., 3) at unit distance along their rays, in the fisheye camera's
    frame."""
    uv = np.asarray(uv, np.float64)
    rays = np.stack([(uv[..., 0] - K[0, 2]) / K[0, 0], (uv[..., 1] - K[1, 2]) / K[1, 1], np.ones(uv.shape[:-1])], -1)
    # each ray's point at unit distance, as the official reader takes it (HOT3D's crop cameras sit at the fisheye
    # camera's centre, where the distance does not matter)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    camera_from_crop = np.linalg.inv(world_from_camera) @ world_from_crop
    return rays @ camera_from_crop[:3, :3].T + camera_from_crop[:3, 3]


def crop_to_fisheye(camera: Fisheye624, world_from_camera: np.ndarray, K: np.ndarray, world_from_crop: np.ndarray,
                    uv: np.ndarray) -> np.ndarray:
    """Crop camera pixels (..., 2) (any, not only whole ones) -> the fisheye pixels (..., 2) their rays reach,
    exactly; (-1, -1) where a ray arrives behind the fisheye camera. Arguments as :func:`crop_maps`."""
    eye = crop_rays_in_camera(world_from_camera, K, world_from_crop, uv)
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

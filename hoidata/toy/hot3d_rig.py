"""The toy HOT3D headset: FISHEYE624 streams with non-zero distortion, images rendered through them, crop cameras.

pyrender draws pinhole images only, so a fisheye view is drawn as a wide pinhole image from the same centre and
axes, then resampled: each fisheye pixel's ray (:meth:`~hoidata.geometry.fisheye624.Fisheye624.unproject`) reads
the pinhole pixel it hits (colour bilinear, labels nearest; the pinhole image has ``OVERSAMPLE`` times the
fisheye's focal length, so a mask's edge is placed to half a pinhole pixel, at most half a fisheye pixel: the
pinhole magnifies off its axis). Rays more than ``RENDER_ANGLE`` off the axis stay black,
like the vignette of the real fisheye corners. Labels and pixels come from the same poses, so annotations and images
agree by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from hoidata.geometry.fisheye624 import Fisheye624

RENDER_ANGLE = 1.0  # radians off the axis that a fisheye view shows (57 degrees); beyond it: black
OVERSAMPLE = 1  # the pinhole image is drawn at this many times the fisheye's focal length


@dataclass(frozen=True)
class Stream:
    """One camera of the toy headset: its stream id, label, calibration and mount on the device."""

    stream_id: str
    label: str  # 'rgb' in it: an RGB stream (the official reader's rule); else monochrome
    camera: Fisheye624
    device_from_camera: np.ndarray  # (4, 4)

    @property
    def is_rgb(self) -> bool:
        return "rgb" in self.label


def _mount(x: float, yaw: float) -> np.ndarray:
    """Camera -> device: shifted ``x`` metres sideways, turned ``yaw`` radians about the device's y axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.eye(4)
    out[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    out[0, 3] = x
    return out


COEFFS = (0.30, -0.20, 0.05, 0.01, -0.005, 0.001, 1.0e-3, -5.0e-4, 5.0e-4, -2.0e-4, 3.0e-4, 1.0e-4)


def device_streams(device: str) -> list[Stream]:
    """The toy headset's streams: Aria has an RGB stream ``214-1`` (15 projection values: one focal length) and two
    monochrome ``1201-1`` / ``1201-2``; Quest 3 the two monochrome ones with 16 values (fx, fy). Sizes: RGB 1216 x
    1216 (HOT3D's: 1408 x 1408), monochrome 960 x 720 (Aria's SLAM cameras: 640 x 480; Quest 3's: 1280 x 1024). At
    half these (an earlier toy) an object covered ~700 pixels of a monochrome image, and the clip's RLE mask, a sample
    at those pixels, limited the build's mask IoU to ~0.979 even for a perfect mask (docs/datasets.md)."""
    mono = [(-0.05, -0.15, "1201-1", "left"), (0.05, 0.15, "1201-2", "right")]
    if device == "Aria":
        out = [Stream("214-1", "camera-rgb", Fisheye624(1216, 1216, 500.0, 500.0, 607.1, 608.9, COEFFS), np.eye(4))]
        return out + [Stream(sid, f"camera-slam-{side}", Fisheye624(960, 720, 360.0, 360.0, 479.7, 360.1, COEFFS),
                             _mount(x, yaw)) for x, yaw, sid, side in mono]
    if device == "Quest3":
        scaled = tuple(c * 0.8 for c in COEFFS)
        return [Stream(sid, f"camera-mono-{side}", Fisheye624(960, 720, 356.0, 357.8, 481.3, 358.7, scaled),
                       _mount(x, yaw))
                for x, yaw, sid, side in mono]
    raise ValueError(f"unknown toy device {device!r}; expected 'Aria' or 'Quest3'")


def wide_side(camera: Fisheye624) -> int:
    """The side (pixels) of a square pinhole image at the camera's focal length that holds RENDER_ANGLE."""
    return 2 * (int(np.ceil(OVERSAMPLE * max(camera.fx, camera.fy) * np.tan(RENDER_ANGLE))) + 2)


@dataclass
class FisheyeView:
    """Resampling of one stream's wide pinhole render into its fisheye image."""

    K: np.ndarray  # (3, 3) the wide pinhole camera drawn
    size: tuple[int, int]  # its (width, height)
    maps: tuple[np.ndarray, np.ndarray]  # cv2.remap maps fisheye pixel -> pinhole pixel, (-1, -1) where black

    @classmethod
    def of(cls, camera: Fisheye624, side: int | None = None) -> FisheyeView:
        """The view of ``camera`` drawn as a square pinhole image of ``side`` pixels (None: just wide enough)."""
        f = max(camera.fx, camera.fy) * OVERSAMPLE
        side = wide_side(camera) if side is None else side
        K = np.array([[f, 0.0, side / 2 - 0.5], [0.0, f, side / 2 - 0.5], [0.0, 0.0, 1.0]])
        v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
        rays = camera.unproject(np.stack([u, v], -1))
        inside = rays[..., 2] > np.cos(RENDER_ANGLE)
        pix = (rays / np.where(inside, rays[..., 2], 1.0)[..., None]) @ K.T
        pix[~inside] = -1.0
        return cls(K, (side, side), (pix[..., 0].astype(np.float32), pix[..., 1].astype(np.float32)))

    def image(self, wide: np.ndarray) -> np.ndarray:
        return cv2.remap(wide, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def labels(self, wide: np.ndarray) -> np.ndarray:
        return cv2.remap(wide.astype(np.float32), *self.maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0).astype(np.int32)


def crop_camera_for(points_eye: np.ndarray, world_from_camera: np.ndarray, margin: float = 1.25,
                    ) -> tuple[np.ndarray, float]:
    """A crop camera for points (N, 3) seen by a fisheye camera: at the camera's centre, its axis through the
    points' centroid, its x axis as close to the camera's as that allows; the field of view (radians) holds every
    point with ``margin``. Returns (crop camera -> world (4, 4), fov)."""
    z = points_eye.mean(0)
    z = z / np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z], axis=1)  # columns: the crop axes in the camera frame
    dirs = points_eye / np.linalg.norm(points_eye, axis=1, keepdims=True)
    half = np.max(np.arccos(np.clip(dirs @ z, -1.0, 1.0)))
    camera_from_crop = np.eye(4)
    camera_from_crop[:3, :3] = rot
    return world_from_camera @ camera_from_crop, float(min(2.0 * half * margin + 0.05, 2.5))


def box(pixels: np.ndarray) -> list[float]:
    """[x1, y1, x2, y2] of pixels (N, 2)."""
    return [float(v) for v in (*pixels.min(0), *pixels.max(0))]

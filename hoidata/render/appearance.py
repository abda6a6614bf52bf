"""How toy and synthetic scenes look: lighting, skin tones and backgrounds. Deterministic given an rng."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hoidata.reading import read_bytes
from hoidata.reading_media import MAX_IMAGE_BYTES, decode_pil


@dataclass
class DirectionalLight:
    """A sun-like light; direction (3,) is where the light travels, camera frame (+z: into the scene)."""

    direction: tuple[float, float, float]
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 3.0


@dataclass
class PointLight:
    """A point light at position (3,) metres, camera frame; irradiance falls off as intensity / d^2."""

    position: tuple[float, float, float]
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    intensity: float = 0.5


@dataclass
class Lighting:
    """Ambient RGB (linear, added as albedo * ambient) plus directional and point lights.

    A directional light of intensity pi facing a surface head-on shows its albedo unchanged."""

    ambient: tuple[float, float, float] = (0.3, 0.3, 0.3)
    directional: list[DirectionalLight] = field(default_factory=list)
    point: list[PointLight] = field(default_factory=list)


def default_lighting() -> Lighting:
    """Fixed lighting: ambient 0.35 and a key light from the upper left of the camera."""
    return Lighting((0.35, 0.35, 0.35), [DirectionalLight((0.3, 0.4, 1.0), (1.0, 1.0, 1.0), 3.0)])


def _cone_direction(rng: np.random.Generator, max_deg: float) -> np.ndarray:
    """Unit vector uniformly distributed within ``max_deg`` of +z."""
    cos_t = rng.uniform(np.cos(np.radians(max_deg)), 1.0)
    phi = rng.uniform(0.0, 2 * np.pi)
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    return np.array([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])


def _tint(rng: np.random.Generator, warmth: float) -> tuple[float, float, float]:
    """Near-white light colour, warm (orange) or cool (blue) by up to ``warmth``."""
    w = rng.uniform(-warmth, warmth)
    rgb = np.array([1.0 + w, 1.0, 1.0 - w]) + rng.uniform(-0.03, 0.03, 3)
    return tuple(float(c) for c in rgb / rgb.max())


def random_lighting(rng: np.random.Generator, scene_depth: float = 0.6) -> Lighting:
    """Varied, plausible lighting for objects about ``scene_depth`` metres in front of the camera.

    Always an ambient term >= 0.15 and a key light travelling into the scene within 50 degrees of
    the viewing axis, so the visible side of objects is lit; plus 0-2 fill lights from wider
    angles and 0-2 point lights near the camera."""
    ambient = np.asarray(_tint(rng, 0.1)) * rng.uniform(0.15, 0.5)
    lights = [DirectionalLight(tuple(_cone_direction(rng, 50.0)), _tint(rng, 0.15), rng.uniform(2.0, 4.0))]
    for _ in range(rng.integers(0, 3)):
        lights.append(DirectionalLight(tuple(_cone_direction(rng, 85.0)), _tint(rng, 0.2), rng.uniform(0.4, 1.8)))
    points = []
    for _ in range(rng.integers(0, 3)):
        position = np.array([rng.uniform(-0.8, 0.8), rng.uniform(-0.8, 0.8), rng.uniform(-0.3, 0.3)])
        dist2 = float(np.sum((position - [0.0, 0.0, scene_depth]) ** 2))
        # intensity scaled by the squared distance, so the irradiance at the scene is controlled
        points.append(PointLight(tuple(position), _tint(rng, 0.2), rng.uniform(0.3, 1.5) * dist2))
    return Lighting(tuple(float(a) for a in ambient), lights, points)


# Anchor skin colours (sRGB), light to dark; skin_tone interpolates between neighbours.
_SKIN_ANCHORS = np.array([[255, 224, 196], [241, 194, 160], [224, 172, 130], [198, 134, 96],
                          [161, 102, 70], [120, 75, 50], [85, 55, 40]], dtype=np.float64) / 255.0


def skin_tone(rng: np.random.Generator) -> tuple[float, float, float]:
    """A plausible skin colour, sRGB in [0, 1], anywhere from very light to very dark."""
    t = rng.uniform(0.0, len(_SKIN_ANCHORS) - 1)
    i = min(int(t), len(_SKIN_ANCHORS) - 2)
    rgb = (1 - (t - i)) * _SKIN_ANCHORS[i] + (t - i) * _SKIN_ANCHORS[i + 1]
    rgb = rgb * rng.uniform(0.92, 1.05) + rng.uniform(-0.02, 0.02, 3)
    return tuple(float(c) for c in np.clip(rgb, 0.0, 1.0))


def _pattern(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float32 in [0, 255]: one of gradient, blurred noise, stripes, checker, clutter."""
    import cv2

    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    angle = rng.uniform(0.0, np.pi)
    along = np.cos(angle) * xx + np.sin(angle) * yy  # pixels along a random direction
    c0, c1 = rng.uniform(0.0, 255.0, (2, 3)).astype(np.float32)  # float32 throughout: full-size arrays
    kind = rng.integers(0, 5)
    if kind == 0:  # linear gradient
        t = (along - along.min()) / max(float(np.ptp(along)), 1.0)
    elif kind == 1:  # smooth noise: a coarse random grid upsampled
        coarse = rng.uniform(0.0, 255.0, (int(rng.integers(2, 12)), int(rng.integers(2, 12)), 3)).astype(np.float32)
        return cv2.GaussianBlur(cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC), (0, 0), 3.0)
    elif kind == 2:  # stripes, hard or soft
        wave = np.sin(2 * np.pi * along / rng.uniform(8.0, 80.0))
        t = (wave > 0).astype(np.float32) if rng.random() < 0.5 else 0.5 + 0.5 * wave
    elif kind == 3:  # rotated checker tiles
        across = -np.sin(angle) * xx + np.cos(angle) * yy
        cell = rng.uniform(10.0, 80.0)
        t = ((np.floor(along / cell) + np.floor(across / cell)) % 2).astype(np.float32)
    else:  # clutter: random rectangles and ellipses on a flat colour
        img = np.broadcast_to(c0, (height, width, 3)).astype(np.float32).copy()
        for _ in range(int(rng.integers(3, 12))):
            x0, y0 = int(rng.integers(0, width)), int(rng.integers(0, height))
            w, h = int(rng.integers(10, width // 2 + 11)), int(rng.integers(10, height // 2 + 11))
            colour = tuple(float(c) for c in rng.uniform(0.0, 255.0, 3))
            if rng.random() < 0.5:
                cv2.rectangle(img, (x0, y0), (x0 + w, y0 + h), colour, -1)
            else:
                cv2.ellipse(img, (x0, y0), (w // 2, h // 2), float(rng.uniform(0, 180)), 0, 360, colour, -1)
        return cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.5, 3.0)))
    return (1.0 - t[..., None]) * c0 + t[..., None] * c1


def procedural_background(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8 random background: a pattern (gradient, blurred noise, stripes,
    checker, clutter), sometimes blended with a second one, plus mild pixel noise."""
    img = _pattern(rng, width, height)
    if rng.random() < 0.3:
        mix = np.float32(rng.uniform(0.2, 0.5))
        img = (1.0 - mix) * img + mix * _pattern(rng, width, height)
    img = img + np.float32(rng.uniform(0.0, 5.0)) * rng.standard_normal(img.shape, dtype=np.float32)  # sensor noise
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def load_background(path: str | os.PathLike, width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """(height, width, 3) uint8: a random crop (45-100% of the largest crop with the output's aspect
    ratio, random position, flipped left-right half the time) of an image file, resized.

    Raises DataError naming the file when it is missing or not a readable image."""
    import cv2

    path = Path(path)
    pixels = np.asarray(decode_pil(read_bytes(path, "background image", MAX_IMAGE_BYTES), path, None,
                                   "background image"))
    src_h, src_w = pixels.shape[:2]
    scale = rng.uniform(0.45, 1.0)
    crop_w = max(1, int(round(min(src_w, src_h * width / height) * scale)))
    crop_h = max(1, min(src_h, int(round(crop_w * height / width))))
    x0 = int(rng.integers(0, src_w - crop_w + 1))
    y0 = int(rng.integers(0, src_h - crop_h + 1))
    crop = pixels[y0:y0 + crop_h, x0:x0 + crop_w]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    shrink = crop_w > width
    return cv2.resize(np.ascontiguousarray(crop), (width, height),
                      interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)

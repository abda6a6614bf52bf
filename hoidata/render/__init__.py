"""Offscreen rendering (:mod:`hoidata.render.renderer`, pyrender on EGL) and how scenes look
(:mod:`hoidata.render.appearance`: lighting, skin tones, backgrounds). The common names are re-exported."""

from hoidata.render.appearance import (
    DirectionalLight,
    Lighting,
    PointLight,
    default_lighting,
    load_background,
    procedural_background,
    random_lighting,
    skin_tone,
)
from hoidata.render.renderer import (
    CV_TO_GL,
    Renderer,
    RenderMesh,
    RenderResult,
    composite,
    label_to_rgb,
    pyrender_intrinsics,
    rgb_to_label,
    vertex_normals,
)

__all__ = [
    "CV_TO_GL", "DirectionalLight", "Lighting", "PointLight", "RenderMesh", "RenderResult", "Renderer",
    "composite", "default_lighting", "label_to_rgb", "load_background", "procedural_background",
    "pyrender_intrinsics", "random_lighting", "rgb_to_label", "skin_tone", "vertex_normals",
]

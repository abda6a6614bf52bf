"""Object models: the YCB class table and layout, loading, repair, simplification, box keypoints.

The procedural stand-ins written in the YCB layout live with the other toy writers, in
:mod:`hoidata.toy.objects`."""

from hoidata.objects.meshops import (
    MeshReport,
    check_mesh,
    repair_mesh,
    sample_surface,
    simplify_mesh,
    surface_error,
)
from hoidata.objects.ycb import (
    BOX_EDGES,
    MESH_FILE,
    POINTS_FILE,
    SIMPLIFY_VERSION,
    YCB_CLASSES,
    UnknownObjectError,
    box21,
    box_corners,
    class_id,
    class_name,
    default_cache_dir,
    list_objects,
    load_object_mesh,
    load_points,
    load_simplified,
    object_mesh_path,
    object_points_path,
    simplify_cache_key,
)

__all__ = [
    "YCB_CLASSES", "UnknownObjectError", "class_id", "class_name", "MESH_FILE", "POINTS_FILE",
    "object_mesh_path", "object_points_path", "list_objects", "load_object_mesh", "load_points",
    "MeshReport", "check_mesh", "repair_mesh", "simplify_mesh", "surface_error", "sample_surface",
    "SIMPLIFY_VERSION", "default_cache_dir", "simplify_cache_key", "load_simplified",
    "box_corners", "box21", "BOX_EDGES",
]

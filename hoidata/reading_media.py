"""The guarded door's images, meshes and PyTorch checkpoints (:mod:`hoidata.reading` for the rest): an empty,
cut-short or undecodable image, a mesh that its decoder refuses and a file that is not a checkpoint are each one
DataError naming the file (and member), never the decoder's own exception (OpenCV's ``cv2.error`` on an empty
buffer, Pillow's ``OSError``, trimesh's many, torch's ``weights_only`` advice).
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

from hoidata.errors import DataError, decoding
from hoidata.reading import describe_head, file_size, head_bytes, read_bytes

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
PNG_END = b"IEND\xaeB`\x82"  # the IEND chunk's type and CRC, the last bytes of every PNG
MAX_IMAGE_BYTES = 256 << 20
MAX_MESH_BYTES = 2 << 30
TORCH_HEADS = (b"PK\x03\x04", b"\x80")  # torch.save's zip archive; its legacy format, a pickle
_ANSI = re.compile(r"\x1b\[[0-9;?]*[ -/]*[@-~]")  # terminal colour / bold codes


def incomplete_image(data: bytes) -> str | None:
    """Why a JPEG or PNG file is cut short (None when it ends as it should, or is neither format).

    OpenCV decodes a truncated JPEG without an error (it fills the rest with grey and only prints a warning),
    so the end is checked here: a JPEG must end with its end-of-image marker (trailing zero padding allowed),
    a PNG with its IEND chunk.
    """
    data = bytes(data)
    if data[:2] == b"\xff\xd8":
        return None if data.rstrip(b"\0").endswith(b"\xff\xd9") else "truncated JPEG (no end-of-image marker)"
    if data[:8] == PNG_MAGIC:
        return None if data.rstrip(b"\0").endswith(PNG_END) else "truncated PNG (no IEND chunk)"
    return None


def image_problem(data: bytes, what: str = "image") -> str | None:
    """What makes ``data`` no image before any decoder sees it: empty, or a JPEG / PNG cut short; else None."""
    if not len(data):
        return f"empty {what} (0 bytes)"
    problem = incomplete_image(data)
    return f"{problem}: the {what} is cut short" if problem else None


def decode_image(data: bytes, path, field: str | None = None, flags: int | None = None,
                 what: str = "image") -> np.ndarray:
    """``data`` decoded by OpenCV (``flags``: ``cv2.IMREAD_COLOR`` when None, so BGR); empty, cut short or not
    decodable is a DataError naming the file and field."""
    import cv2

    problem = image_problem(data, what)
    if problem:
        raise DataError(path, field, problem)
    with decoding(path if field is None else f"{path}: {field!r}", what):  # cv2.error on some bad buffers
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR if flags is None else flags)
    if image is None:
        raise DataError(path, field, f"cannot decode the {what} (corrupt or not an image)")
    return image


def read_image(path, flags: int | None = None, what: str = "image", max_bytes: int = MAX_IMAGE_BYTES) -> np.ndarray:
    """The image file at ``path`` decoded by OpenCV (see :func:`decode_image`)."""
    return decode_image(read_bytes(path, what, max_bytes), path, None, flags, what)


def decode_pil(data: bytes, path, field: str | None = None, what: str = "image", mode: str = "RGB"):
    """``data`` decoded by Pillow and converted to ``mode`` (decoded in full here, so a damaged file fails here and
    nowhere later); empty, cut short or not decodable is a DataError naming the file and field."""
    from PIL import Image, UnidentifiedImageError

    problem = image_problem(data, what)
    if problem:
        raise DataError(path, field, problem)
    try:
        with Image.open(io.BytesIO(bytes(data))) as img:
            out = img.convert(mode)
            out.load()
            return out
    except (OSError, UnidentifiedImageError, ValueError, Image.DecompressionBombError, SyntaxError) as exc:
        raise DataError(path, field, f"Pillow cannot decode this {what} ({exc})") from None


def decode_mesh(data: bytes, path, file_type: str, what: str = "mesh", **options):
    """What trimesh loads from ``data`` (a Trimesh, a Scene or a PointCloud, as trimesh returns it) with
    ``options``; any failure of trimesh on these bytes is a DataError naming the file. Materials and textures are
    looked up beside ``path`` unless ``options`` gives a resolver."""
    import trimesh

    if not len(data):
        raise DataError(path, None, f"empty {what} file (0 bytes)")
    options.setdefault("resolver", trimesh.resolvers.FilePathResolver(str(path)))
    try:
        return trimesh.load(io.BytesIO(bytes(data)), file_type=file_type, **options)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many exception types on malformed files
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        detail = f"{type(exc).__name__}: {lines[-1][:200]}" if lines else type(exc).__name__
        raise DataError(path, None, f"cannot read {what} ({detail})") from exc


def read_mesh(path, what: str = "mesh", max_bytes: int = MAX_MESH_BYTES, **options):
    """The mesh file at ``path`` as trimesh loads it (its format from the suffix; see :func:`decode_mesh`)."""
    suffix = Path(path).suffix.lower().lstrip(".")
    if not suffix:
        raise DataError(path, None, f"a {what} file needs a suffix that names its format (.ply, .obj, ...)")
    return decode_mesh(read_bytes(path, what, max_bytes), path, suffix, what, **options)



# ---------------------------------------------------------------- PyTorch checkpoints


def refusal_text(exc: BaseException) -> str:
    """One plain line for an error of ``torch.load(..., weights_only=True)`` (checkpoints, weights files): the
    terminal codes stripped, and for a refused pickle what it held, without torch's advice to load it with
    ``weights_only=False`` or to allow-list a global (either would run the code in the file)."""
    text = _ANSI.sub("", str(exc))
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if "weights only load failed" not in text.lower() and "weightsunpickler" not in text.lower():
        return lines[0] if lines else type(exc).__name__
    findings = []
    for line in lines:
        if line.startswith(("Weights only load failed", "Check the documentation", "Please file", "(1)", "(2)")):
            continue  # torch's advice, not what it found
        line = line.split("WeightsUnpickler error:", 1)[-1].strip()
        if line:
            findings.append(re.split(r"\.(?:\s|$)", line)[0])  # the finding, not the advice that follows it
    what = findings[0] if findings else "a pickle torch does not accept"
    if "GLOBAL" in what or "global" in what:
        return (f"it holds more than tensors and plain values ({what}); it was not loaded, since loading it "
                "would run code from the file")
    return f"not a file torch reads safely ({what}): damaged, or not a checkpoint"


def read_torch(path, what: str = "PyTorch checkpoint", map_location="cpu"):
    """``torch.load(path, weights_only=True)``: no code in the file runs. A file that does not start as a
    checkpoint does (JSON, text, an image) is refused before torch sees it, saying what it looks like; a damaged
    one, or one holding more than tensors and plain values, is one DataError line without torch's advice."""
    import torch

    file_size(path, what, 1 << 62)  # present and a file (torch reads it)
    head = head_bytes(path, 16)
    if not head.startswith(TORCH_HEADS):
        raise DataError(path, None, f"not a {what}: {describe_head(head)}, where a checkpoint starts with a zip "
                                    "or pickle header; damaged, or another kind of file")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a damaged or crafted file: one line naming it
        raise DataError(path, None, f"not a readable {what} ({refusal_text(exc)})") from None

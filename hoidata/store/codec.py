"""The record codec: one record's members <-> bytes, every field checked against :mod:`hoidata.schema`.

:func:`encode_record` turns arrays and a meta dict into the member bytes a shard stores (pinned JPEG and
PNG settings, so equal records give equal bytes); :func:`decode_record` turns member bytes back into
arrays, trusting nothing: member names, sizes, image headers, decoded shapes and dtypes and every meta
field are checked, and a problem is a :class:`~hoidata.errors.DataError` naming the shard and the key.
"""

from __future__ import annotations

import io
import json

import cv2
import numpy as np

from hoidata.errors import DataError
from hoidata.geometry.upstream_crop import cut_region
from hoidata.reading import decode_npy, parse_json
from hoidata.reading_media import PNG_MAGIC, decode_image, decode_pil, incomplete_image
from hoidata.shapes import first_non_number, kind_of
from hoidata.schema import (
    CROP_FIELDS,
    FRAME_JPG,
    FRAME_MEMBERS,
    FRAME_PNG,
    FULL,
    HEATMAP,
    IMG,
    IMG_LOSSLESS,
    META,
    META_FIELDS,
    META_TYPES,
    NO_PART,
    OBJECT_IDS,
    RECORD_KINDS,
    REGION_FIELDS,
    SCHEMA_VERSION,
    SDF,
    SDF_COLUMNS,
    SDF_DTYPE,
    SEG,
    UPSTREAM_CROP,
    UPSTREAM_REGION,
    check_key,
    image_member,
    kind_of_members,
)
from hoidata.store.index import to_jsonable

JPEG_QUALITY = 95
PNG_COMPRESSION = 3  # pinned so the bytes do not depend on OpenCV's default
MAX_MEMBER_BYTES = 64 << 20  # refuse absurd members before reading them into memory
MAX_IMAGE_SIDE = 4096  # refuse absurd image headers before decoding (decompression bombs)
KEY = "__key__"  # the record key in decoded records, as WebDataset names it
FRAME_IMAGE = "frame_image"  # decoded upstream-region records with a frame member: the whole (flipped) frame, RGB
N_PARTS = 16  # hand part labels 0..15 in sdf.npy's last column
FLOAT32_MAX = float(np.finfo(np.float32).max)


# --------------------------------------------------------------------------------------------------
# records


def check_record_key(key, where) -> None:
    """schema.check_key, as a DataError naming ``where`` and the field "key"."""
    try:
        check_key(key)
    except ValueError as exc:
        raise DataError(where, "key", str(exc)) from None


def is_record_key(key) -> bool:
    """Whether ``key`` passes schema.check_key."""
    try:
        check_key(key)
    except ValueError:
        return False
    return True


def _check_images(where, key, img, seg, hm, image: str = IMG) -> None:
    """img (S, S, 3) uint8; seg and hm (S // 2, S // 2) uint8 (None: not there or not decoded; the members a record
    has are checked against its kind before)."""
    if not (isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3
            and img.shape[2] == 3 and img.shape[0] == img.shape[1] >= 2):
        raise DataError(where, _field(key, image), f"expected square (S, S, 3) uint8, got {_describe(img)}")
    half = img.shape[0] // 2
    masks = [(member, arr) for member, arr in ((SEG, seg), (HEATMAP, hm)) if isinstance(arr, np.ndarray)]
    if len(masks) == 2 and seg.shape == hm.shape != (half, half) and seg.ndim == 2 and seg.shape[0] == seg.shape[1]:
        # both masks agree with each other: the image is the odd one out
        side = 2 * seg.shape[0]
        raise DataError(where, _field(key, image), f"{img.shape[1]}x{img.shape[0]} px, but {SEG} and {HEATMAP} are "
                                                 f"{seg.shape[1]}x{seg.shape[0]}: expected a {side}x{side} image")
    for member, arr in ((SEG, seg), (HEATMAP, hm)):
        if arr is not None and not (isinstance(arr, np.ndarray) and arr.dtype == np.uint8 and arr.shape == (half, half)):
            raise DataError(where, _field(key, member), f"expected ({half}, {half}) uint8, got {_describe(arr)}")


def _check_sdf(where, key, sdf) -> None:
    """int16 (N, 6) with part labels in -1..15."""
    width = len(SDF_COLUMNS)
    if not (isinstance(sdf, np.ndarray) and sdf.dtype == SDF_DTYPE and sdf.ndim == 2 and sdf.shape[1] == width):
        want = f"{np.dtype(SDF_DTYPE).name} (N, {width})"
        raise DataError(where, _field(key, SDF), f"expected {want}, got {_describe(sdf)}")
    part = sdf[:, -1]
    if part.size and (part.min() < NO_PART or part.max() >= N_PARTS):
        raise DataError(where, _field(key, SDF), f"part labels must lie in {NO_PART}..{N_PARTS - 1}")


def _field(key, member: str) -> str:
    """The tar member name ``<key>.<member>`` an error refers to (just the member when the key is unknown)."""
    return member if key is None else f"{key}.{member}"


def _describe(arr) -> str:
    return f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr).__name__


def _check_meta(meta, where, key, n_sdf: int | None, kind: str | None = None, image: str | None = None) -> dict:
    """Check a JSON-level meta dict against META_FIELDS and its kind's fields (``kind``: the kind its members
    say, checked against the meta's own), and the CROP_FIELDS group (all or none; present exactly when the image
    member ``image`` is img.png, when given); return it with shaped fields as numpy arrays."""
    name = _field(key, META)
    if not isinstance(meta, dict):
        raise DataError(where, name, f"expected a JSON object, got {type(meta).__name__}")
    # the version first: a record of another schema version differs in its fields too
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION or isinstance(version, bool):
        raise DataError(where, name, f"'schema_version': {version!r}, this reader knows {SCHEMA_VERSION}")
    given = meta.get("kind")
    if given not in RECORD_KINDS or (kind is not None and given != kind):
        raise DataError(where, name, f"'kind': {given!r}, expected {kind!r}" if kind and given in RECORD_KINDS
                        else f"'kind': {given!r}, expected one of {sorted(RECORD_KINDS)}")
    fields = RECORD_KINDS[given][1]
    crop = [f for f in CROP_FIELDS if f in meta]
    if crop:
        if len(crop) != len(CROP_FIELDS):
            raise DataError(where, name, f"upstream-crop fields {sorted(CROP_FIELDS)} come together; missing "
                                         f"{sorted(set(CROP_FIELDS) - set(crop))}")
        if meta["crop"] != UPSTREAM_CROP:
            raise DataError(where, name, f"'crop': {meta['crop']!r}, expected {UPSTREAM_CROP!r}")
        fields = (*fields, *CROP_FIELDS)
    region = [f for f in REGION_FIELDS if f in meta]
    if region:
        if len(region) != len(REGION_FIELDS) or crop:
            raise DataError(where, name, f"upstream-region fields {sorted(REGION_FIELDS)} come together, without "
                                         f"upstream-crop fields; missing {sorted(set(REGION_FIELDS) - set(region))}")
        if meta["region"] != UPSTREAM_REGION:
            raise DataError(where, name, f"'region': {meta['region']!r}, expected {UPSTREAM_REGION!r}")
        fields = (*fields, *REGION_FIELDS)
    if image is not None and (bool(crop or region) != (image != IMG) or crop and image != IMG_LOSSLESS):
        raise DataError(where, _field(key, image), f"an upstream-crop record ('crop' in {META}) stores its image as "
                                                   f"{IMG_LOSSLESS}, an upstream-region record ('region') as "
                                                   f"{' or '.join(FRAME_MEMBERS)} (or {IMG_LOSSLESS}), any other "
                                                   f"record as {IMG}")
    missing, extra = sorted(set(fields) - set(meta)), sorted(set(meta) - set(fields))
    if missing or extra:
        raise DataError(where, name, f"missing fields {missing}, unexpected fields {extra} (kind {given!r})")
    out = {}
    for field_name in fields:
        shape, value = {**META_FIELDS, **CROP_FIELDS, **REGION_FIELDS}[field_name][0], meta[field_name]
        if field_name in ("crop", "region"):
            out[field_name] = value
            continue
        if shape is None:
            want = META_TYPES.get(field_name)
            # bool is an int in Python; a flag where a number belongs (or back) is still wrong
            if want is not None and (not isinstance(value, want) or (want is int and isinstance(value, bool))):
                raise DataError(where, name, f"{field_name!r}: expected {want.__name__}, got {type(value).__name__}")
            if field_name == "object_id" and value not in OBJECT_IDS:
                raise DataError(where, name, f"'object_id': {value} is not a DexYCB class id "
                                             f"({OBJECT_IDS.start}..{OBJECT_IDS.stop - 1})")
            out[field_name] = value
            continue
        bad = first_non_number(value)  # numpy would take "1" and true for numbers
        if bad is not None:
            raise DataError(where, name, f"{field_name!r}: expected numbers, got {kind_of(bad[1])}")
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise DataError(where, name, f"{field_name!r}: expected numbers of shape {shape}") from None
        # finite as float32 too: the loader hands float32 tensors on (1e300 would become inf there)
        if arr.shape != shape or not (np.isfinite(arr).all() and (np.abs(arr) <= FLOAT32_MAX).all()):
            raise DataError(where, name, f"{field_name!r}: expected finite float32 numbers of shape {shape}, "
                                         f"got {arr.shape}")
        out[field_name] = arr
    if key is not None and out["key"] != key:
        raise DataError(where, name, f"'key': {out['key']!r} differs from the record key")
    if given != FULL:
        return out
    counts = out["sdf_counts"]
    if (counts < 0).any() or (counts != np.round(counts)).any() or counts.sum() != n_sdf:
        raise DataError(where, name, f"'sdf_counts': {counts.tolist()} must be counts summing to {n_sdf} rows")
    out["sdf_counts"] = counts.astype(np.int64)
    return out


def encode_record(key: str, img: np.ndarray, seg: np.ndarray | None, heatmap: np.ndarray | None,
                  sdf: np.ndarray | None, meta: dict, frame: bytes | None = None) -> dict[str, bytes]:
    """Arrays and labels -> {member name: bytes} of the record's kind; the same inputs always give the same bytes.

    img is RGB, stored as JPEG, or as lossless PNG (``img.png``) when meta holds the upstream-crop or upstream-region
    fields (schema.CROP_FIELDS, REGION_FIELDS). ``frame`` (an upstream-region record): the original frame file's
    bytes, stored as they are (``frame.jpg`` / ``frame.png`` by their format) in place of img, which is then the
    square of that frame the record's meta places (its header is checked against ``frame_size``, not decoded).
    meta must hold exactly its kind's fields (``meta["kind"]``, schema.RECORD_KINDS; numpy values allowed); seg,
    heatmap and sdf are None exactly for a kind without those members. It is checked as a reader would check it, so a
    record that encodes also decodes.
    """
    check_record_key(key, None)
    kind = meta.get("kind") if isinstance(meta, dict) else None
    members_of_kind = RECORD_KINDS[kind][0] if kind in RECORD_KINDS else ()
    arrays = {SEG: seg, HEATMAP: heatmap, SDF: sdf}
    given = {IMG, META} | {m for m, arr in arrays.items() if arr is not None}
    if kind in RECORD_KINDS and given != set(members_of_kind):
        raise DataError(None, key, f"a {kind!r} record has members {list(members_of_kind)}, got {sorted(given)}")
    image = IMG_LOSSLESS if isinstance(meta, dict) and ("crop" in meta or "region" in meta) else IMG
    if frame is not None:
        image = FRAME_PNG if bytes(frame[:8]) == PNG_MAGIC else FRAME_JPG
    _check_images(None, key, img, seg, heatmap, image)
    if sdf is not None:
        _check_sdf(None, key, sdf)
    plain = to_jsonable(meta, None, _field(key, META))
    _check_meta(plain, None, key, None if sdf is None else len(sdf), image=image)
    if frame is not None:
        _check_frame_header(frame, None, key, image, plain["frame_size"])
    bgr = np.ascontiguousarray(img[..., ::-1])
    members = {image: bytes(frame) if frame is not None else
               _imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION]) if image == IMG_LOSSLESS
               else _imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])}
    for member, arr in ((SEG, seg), (HEATMAP, heatmap)) if seg is not None else ():
        members[member] = _imencode(".png", np.ascontiguousarray(arr), [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if sdf is not None:
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(sdf), allow_pickle=False)  # C order, so the header is always the same
        members[SDF] = buf.getvalue()
    # sorted keys and fixed separators: byte-identical JSON for equal labels
    text = json.dumps(plain, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    members[META] = text.encode()
    return {member: members[member] for member in (image if m == IMG else m for m in members_of_kind)}


def _imencode(ext: str, arr: np.ndarray, params: list[int]) -> bytes:
    ok, buf = cv2.imencode(ext, arr, params)
    if not ok:
        raise RuntimeError(f"OpenCV could not encode a {arr.shape} {arr.dtype} image as {ext}")
    return buf.tobytes()


def _image_size(data: bytes, member: str) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's SOF header without decoding; None if not found."""
    if member == IMG_LOSSLESS and data[24:26] != b"\x08\x02":  # the crop: 8-bit RGB PNG, nothing else
        return None
    if member not in (IMG, FRAME_JPG):
        if data[:8] == PNG_MAGIC and data[12:16] == b"IHDR" and len(data) >= 24:
            return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        return None
    pos = 2 if data[:2] == b"\xff\xd8" else len(data)
    while pos + 9 <= len(data) and data[pos] == 0xFF:
        marker, length = data[pos + 1], int.from_bytes(data[pos + 2:pos + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # start of frame, not DHT/JPG/DAC
            return int.from_bytes(data[pos + 7:pos + 9], "big"), int.from_bytes(data[pos + 5:pos + 7], "big")
        pos += 2 + length
    return None


def _decode_image(data: bytes, where, key, member: str) -> np.ndarray:
    """JPEG or the crop's PNG -> RGB (H, W, 3) uint8, mask PNG -> (H, W) uint8; the header is checked before
    decoding."""
    size = _image_size(data, member)
    kind = {IMG: "JPEG", IMG_LOSSLESS: "8-bit RGB PNG"}.get(member, "8-bit grey PNG")
    if size is None or not 0 < max(size) <= MAX_IMAGE_SIDE:
        raise DataError(where, _field(key, member), f"not a {kind} of at most {MAX_IMAGE_SIDE} px (header: {size})")
    # RGB straight from the decoder: the values of BGR then cvtColor (or [..., ::-1]), without the extra pass (the
    # door refuses a JPEG or PNG cut short)
    flag = cv2.IMREAD_COLOR_RGB if member in (IMG, IMG_LOSSLESS) else cv2.IMREAD_UNCHANGED
    return decode_image(data, where, _field(key, member), flag, kind)


def _check_frame_header(data, where, key, member: str, frame_size) -> None:
    """An upstream-region record's frame member: a JPEG (frame.jpg) or PNG (frame.png) whose header says
    ``frame_size`` (W, H) px, not cut short."""
    data = bytes(data)
    size, kind = _image_size(data, member), "JPEG" if member == FRAME_JPG else "PNG"
    if size is None or not 0 < max(size) <= MAX_IMAGE_SIDE:
        raise DataError(where, _field(key, member), f"not a {kind} of at most {MAX_IMAGE_SIDE} px (header: {size})")
    if size != tuple(int(v) for v in frame_size):
        raise DataError(where, _field(key, member), f"{size[0]}x{size[1]} px, but the record's 'frame_size' is "
                                                    f"{[int(v) for v in frame_size]}")
    problem = incomplete_image(data)
    if problem:
        raise DataError(where, _field(key, member), problem)


def _read_frame(data, where, key, member: str, meta: dict) -> np.ndarray:
    """An upstream-region record's frame member -> the whole frame (H, W, 3) uint8 as upstream's loader reads it:
    Pillow's decode in RGB, flipped left to right for a mirrored (left-hand) record."""
    _check_frame_header(data, where, key, member, meta["frame_size"])
    rgb = np.asarray(decode_pil(data, where, _field(key, member), "image"))
    return np.ascontiguousarray(rgb[:, ::-1]) if meta["mirrored"] else rgb


def _png_unread(data: bytes, where, key, member: str) -> np.ndarray:
    """What can be checked of a PNG member without decoding it: an 8-bit grey PNG header (IHDR bit depth 8, colour
    type 0) of a sane size, not cut short. Returns a read-only zero view of the header's (H, W), so the size checks
    of the decoded members apply to it (the loader skips decoding what training does not use; ``hoidata verify``
    decodes everything)."""
    size = _image_size(data, member)
    if size is None or not 0 < max(size) <= MAX_IMAGE_SIDE or data[24:26] != b"\x08\x00":
        raise DataError(where, _field(key, member), f"not an 8-bit grey PNG of at most {MAX_IMAGE_SIDE} px "
                                                    f"(header: {size})")
    problem = incomplete_image(data)
    if problem:
        raise DataError(where, _field(key, member), problem)
    return np.broadcast_to(np.zeros((), np.uint8), (size[1], size[0]))


def decode_record(members: dict[str, bytes], where: str, undecoded: tuple[str, ...] = ()) -> dict:
    """{member name: bytes} (plus an optional ``__key__``, as WebDataset samples have) -> decoded record.

    Returns {"__key__": key, IMG: RGB uint8, SEG: uint8, HEATMAP: uint8, SDF: int16 (N, 6), META: dict}
    with META's shaped fields as numpy arrays; a record of a kind without some members (schema.RECORD_KINDS)
    has only its own (an ``eval`` record: IMG and META). An upstream-crop record's ``img.png`` is returned under
    IMG too, pixel for pixel as stored. An upstream-region record's frame member (``frame.jpg`` / ``frame.png``) is
    decoded with Pillow as upstream decodes it and flipped for a mirrored record: the whole frame is returned under
    FRAME_IMAGE, its square at ``region_origin`` (side twice the masks') under IMG. Other ``__*__`` entries
    (``__url__``...) are ignored.
    ``undecoded``: PNG members (SEG, HEATMAP) to check without decoding (present, within the size limit, a PNG
    header of the right size, not cut short) and leave out of the result, for readers that do not use them.
    Any deviation from the schema raises DataError naming ``where`` (the shard) and the key/member.
    """
    key = members.get(KEY)
    if key is not None and not isinstance(key, str):
        raise DataError(where, KEY, f"expected a string, got {type(key).__name__}")
    given = {name for name in members if not (name.startswith("__") and name.endswith("__"))}
    kind = kind_of_members(given)
    if kind is None:
        kinds = "; ".join(f"{k}: {list(m)}" for k, (m, _) in RECORD_KINDS.items())
        raise DataError(where, key, f"members {sorted(given)}, expected exactly those of a record kind ({kinds})")
    for name in given:
        if not isinstance(members[name], (bytes, bytearray, memoryview)) or len(members[name]) > MAX_MEMBER_BYTES:
            raise DataError(where, _field(key, name), f"expected at most {MAX_MEMBER_BYTES} bytes")
    image = image_member(given)  # decoded under IMG whatever its member name, so readers need not care
    frame = image in FRAME_MEMBERS  # its square is cut once the meta has placed it
    if frame and kind != FULL:
        raise DataError(where, _field(key, image), f"only a {FULL!r} upstream-region record holds a frame member")
    out = {} if frame else {IMG: _decode_image(members[image], where, key, image)}
    if kind == FULL:
        for member in (SEG, HEATMAP):
            read = _png_unread if member in undecoded else _decode_image
            out[member] = read(members[member], where, key, member)
    if not frame:
        _check_images(where, key, out[IMG], out.get(SEG), out.get(HEATMAP), image)
    if SDF in given:
        out[SDF] = decode_npy(members[SDF], where, _field(key, SDF))
        _check_sdf(where, key, out[SDF])
    plain = parse_json(bytes(members[META]), where, _field(key, META))
    out[META] = _check_meta(plain, where, key, len(out[SDF]) if SDF in out else None, kind, image)
    if frame:  # the square at region_origin, its side twice the masks'
        out[FRAME_IMAGE] = _read_frame(members[image], where, key, image, out[META])
        x0, y0 = (int(v) for v in out[META]["region_origin"])
        out[IMG] = cut_region(out[FRAME_IMAGE], x0, y0, 2 * out[SEG].shape[0])
        _check_images(where, key, out[IMG], out[SEG], out[HEATMAP], image)
    for member in undecoded:
        out.pop(member, None)
    return {KEY: out[META]["key"], IMG: out.pop(IMG), **out}

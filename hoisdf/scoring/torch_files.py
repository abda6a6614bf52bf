"""``.pt`` files (``torch.save``'s zip format) read without torch: tensors become numpy arrays, lists and strings stay
what they are, and nothing else a pickle can name is built (a file that asks for any other class is refused).

Each tensor comes back as a :class:`TensorArray` that keeps its torch dtype name, so a submission check can say
what a file holds (:func:`describe`) before anything is computed from it.
"""

from __future__ import annotations

import io
import pickle
import zipfile
from collections import OrderedDict

import numpy as np

from hoidata.errors import DataError
from hoidata.reading import is_zip, open_zip, read_bytes, zip_read

# torch storage class -> numpy dtype (the storages torch.save names; BFloat16 has no numpy twin)
STORAGES = {"HalfStorage": np.float16, "FloatStorage": np.float32, "DoubleStorage": np.float64,
            "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8,
            "ByteStorage": np.uint8, "BoolStorage": np.bool_}
TORCH_DTYPES = {np.float16: "float16", np.float32: "float32", np.float64: "float64", np.int64: "int64",
                np.int32: "int32", np.int16: "int16", np.int8: "int8", np.uint8: "uint8", np.bool_: "bool"}


class TensorArray(np.ndarray):
    """A numpy array that was a torch tensor in the file (``.torch_dtype`` names its dtype)."""

    torch_dtype: str = ""


def _storage_class(name: str):
    def make():  # never called: the class only names a dtype inside a persistent id
        raise pickle.UnpicklingError(name)
    make.dtype = STORAGES[name]
    return make


def _rebuild_tensor(storage, offset, size, stride, *rest):
    data, dtype, where = storage
    buf = np.frombuffer(data, dtype)
    size, stride = tuple(int(n) for n in size), tuple(int(n) for n in stride)
    if len(size) != len(stride) or min(size + stride + (offset,), default=0) < 0:
        raise DataError(where, None, "a tensor with a malformed size or stride")
    last = offset + sum((n - 1) * s for n, s in zip(size, stride)) if all(size) else offset - 1
    if last >= len(buf):
        raise DataError(where, None, "a tensor reaches past the end of its storage")
    view = np.lib.stride_tricks.as_strided(buf[offset:] if all(size) else buf[:0], shape=size,
                                           strides=tuple(s * buf.itemsize for s in stride)) if all(size) \
        else np.zeros(size, dtype)
    arr = np.array(view, copy=True).view(TensorArray)
    arr.torch_dtype = TORCH_DTYPES[dtype]
    return arr


ALLOWED = {("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor, ("collections", "OrderedDict"): OrderedDict}


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, archive: zipfile.ZipFile, prefix: str, where):
        super().__init__(file)
        self.archive, self.prefix, self.where, self.cache = archive, prefix, where, {}

    def find_class(self, module, name):
        if module == "torch" and name in STORAGES:
            return _storage_class(name)
        if (module, name) in ALLOWED:
            return ALLOWED[(module, name)]
        raise DataError(self.where, None, f"holds a {module}.{name}, not tensors or lists (a torch.save of "
                                          "torch tensors is expected)")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) >= 5 and pid[0] == "storage"):
            raise DataError(self.where, None, f"unknown storage record {pid!r:.60}")
        _, storage_type, key, _location, numel = pid[:5]
        dtype = getattr(storage_type, "dtype", None)
        if dtype is None:
            raise DataError(self.where, None, "a tensor of a dtype this reader does not know")
        if key not in self.cache:
            data = zip_read(self.archive, f"{self.prefix}data/{key}", self.where)  # absent or damaged: named
            if len(data) < numel * np.dtype(dtype).itemsize:
                raise DataError(self.where, None, f"storage {key} is truncated")
            self.cache[key] = (data, dtype, self.where)
        return self.cache[key]


def read_pt(path, data: bytes | None = None):
    """The value saved in a ``.pt`` file (or its bytes ``data``; ``path`` names it in errors): tensors as
    :class:`TensorArray`, lists, tuples, dicts, strings and numbers as they are."""
    where = path
    raw = read_bytes(path, "torch file") if data is None else data
    if not is_zip(raw):
        raise DataError(where, None, "not a torch.save zip file (torch >= 1.6 writes one; an older legacy file or "
                                     "another format cannot be read here: re-save it with torch.save)")
    try:
        with open_zip(where, "torch.save zip file", raw) as archive:
            pkl = [n for n in archive.namelist() if n.endswith("data.pkl") and n.count("/") == 1]
            if not pkl:
                raise DataError(where, None, "no data.pkl inside: not a torch.save file")
            prefix = pkl[0][: -len("data.pkl")]
            names = archive.namelist()
            order = zip_read(archive, f"{prefix}byteorder", where).decode() if f"{prefix}byteorder" in names \
                else "little"
            if order != "little":
                raise DataError(where, None, f"{order}-endian tensors cannot be read here")
            return _Unpickler(io.BytesIO(zip_read(archive, pkl[0], where)), archive, prefix, where).load()
    except DataError:
        raise
    except (zipfile.BadZipFile, pickle.UnpicklingError, EOFError, ValueError, TypeError) as e:
        raise DataError(where, None, f"not a readable torch file ({e})") from None


def describe(value) -> str:
    """Short words for what a file held: ``float16 tensor (44, 16, 3, 3)``, ``list of 44 str``, ``int``."""
    if isinstance(value, TensorArray):
        return f"{value.torch_dtype} tensor {tuple(value.shape)}"
    if isinstance(value, (list, tuple)):
        kinds = sorted({type(v).__name__ for v in value})
        return f"{type(value).__name__} of {len(value)} {'/'.join(kinds) or 'items'}"
    return type(value).__name__

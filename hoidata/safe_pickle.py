"""Load the pickles users download (MANO models, HO-3D annotations) without running code from them.

A pickle can call any importable function while loading. The files we read only ever need numpy
arrays, scipy sparse matrices, chumpy arrays and plain containers, so the unpickler resolves exactly
those globals and refuses everything else with an error naming the file and the class.

Two stand-ins keep the readers free of optional, unmaintained dependencies:

- chumpy: the MANO v1.2 files hold ``chumpy.ch.Ch`` (an array in its ``x`` attribute) and
  ``chumpy.reordering.Select`` (``a.ravel()[idxs].reshape(preferred_shape)``) objects. They are
  captured as :class:`ChumpyNode` and evaluated to numpy arrays after loading.
- scipy sparse: the Python 2 files name ``scipy.sparse.csc.csc_matrix``, a module recent scipy no longer
  has; the pickled state (data, indices, indptr, shape) is captured and rebuilt with today's scipy.
"""

from __future__ import annotations

import codecs
import io
import os
import pickle
from typing import Any

import numpy as np
import scipy.sparse

from hoidata.errors import DataError, decoding
from hoidata.reading import decode_npy, read_bytes


class ChumpyNode:
    """The pickled state of a chumpy object, kept as a plain dict until it is evaluated."""

    def __init__(self, class_path: str):
        self.class_path = class_path
        self.state: dict = {}

    def __setstate__(self, state):
        self.state = dict(state)


class SparseNode:
    """The pickled state of a scipy sparse matrix of any scipy version."""

    def __init__(self, fmt: str):
        self.fmt = fmt
        self.state: dict = {}

    def __setstate__(self, state):
        self.state = dict(state)


def _reconstructor(cls, base, state):
    """copy_reg._reconstructor for protocol 0/1 pickles: only our stand-ins may be built this way."""
    if not getattr(cls, "_hoidata_standin", False):
        raise pickle.UnpicklingError(f"refusing to reconstruct {cls!r}")
    return cls.__new__(cls)


def _standin(node_cls, tag):
    """A class object whose construction (NEWOBJ or _reconstructor) yields node_cls(tag)."""

    def __new__(cls, *args, **kwargs):
        return node_cls(tag)

    return type(f"StandIn[{tag}]", (), {"__new__": __new__, "_hoidata_standin": True})


_SPARSE_CLASSES = {"csc_matrix": "csc", "csr_matrix": "csr", "coo_matrix": "coo", "csc_array": "csc", "csr_array": "csr"}
_SPARSE_MODULES = {"scipy.sparse", "scipy.sparse.csc", "scipy.sparse.csr", "scipy.sparse.coo",
                   "scipy.sparse._csc", "scipy.sparse._csr", "scipy.sparse._coo", "scipy.sparse.compressed"}
_NUMPY_GLOBALS = {
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("numpy.core.multiarray", "_reconstruct"): np._core.multiarray._reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): np._core.multiarray._reconstruct,
    ("numpy.core.multiarray", "scalar"): np._core.multiarray.scalar,
    ("numpy._core.multiarray", "scalar"): np._core.multiarray.scalar,
    ("numpy", "float64"): np.float64,
    ("numpy", "int64"): np.int64,
}
_BUILTIN_GLOBALS = {
    "set": set, "frozenset": frozenset, "object": object, "list": list, "dict": dict,
    "tuple": tuple, "slice": slice, "complex": complex,
}


class RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that resolves only an allow-list of globals; see the module docstring."""

    def __init__(self, file, path: str):
        super().__init__(file, encoding="latin1")
        self.path = path

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _NUMPY_GLOBALS:
            return _NUMPY_GLOBALS[(module, name)]
        if module in ("__builtin__", "builtins") and name in _BUILTIN_GLOBALS:
            return _BUILTIN_GLOBALS[name]
        if (module, name) == ("_codecs", "encode"):  # how protocol 2 written by Python 3 stores bytes
            return codecs.encode
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _reconstructor
        if module == "chumpy" or module.startswith("chumpy."):
            return _standin(ChumpyNode, f"{module}.{name}")
        if module in _SPARSE_MODULES and name in _SPARSE_CLASSES:
            return _standin(SparseNode, _SPARSE_CLASSES[name])
        raise DataError(self.path, None, f"refusing to load global {module}.{name}: not on the allow-list "
                        "of a data pickle (numpy arrays, scipy sparse matrices, chumpy arrays, builtins)")


def load_pickle(path: str | os.PathLike) -> Any:
    """Load a data pickle safely and evaluate chumpy and sparse stand-ins to numpy / scipy objects.

    Raises:
        DataError: the file is missing, truncated or corrupt, or it references a global outside the
            allow-list.
    """
    path = os.fspath(path)
    data = read_bytes(path, "pickle file")
    if not data:
        raise DataError(path, None, "empty file (0 bytes), not a pickle")
    with decoding(path, "pickle (truncated or corrupt?)"):  # whatever the unpickler or a stand-in raises
        return resolve(RestrictedUnpickler(io.BytesIO(data), path).load(), path)


def load_npy(path: str | os.PathLike) -> Any:
    """An ``.npy`` file: a plain array as numpy reads it, or one that holds pickled objects (``np.save`` of a dict,
    as ARCTIC ships its sequences) unpickled with this module's allow-list. ``np.load(allow_pickle=True)`` would
    run whatever code such a file holds."""
    data = read_bytes(path, ".npy file")
    stream = io.BytesIO(data)
    with decoding(path, ".npy file (truncated or corrupt?)"):
        version = np.lib.format.read_magic(stream)
        header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in header:
            raise DataError(path, None, f"an .npy format version {version} this reader does not know")
        _, _, dtype = header[version](stream)
    if not np.dtype(dtype).hasobject:
        return decode_npy(data, path)
    with decoding(path, "pickled .npy (truncated or corrupt?)"):
        return resolve(RestrictedUnpickler(stream, os.fspath(path)).load(), os.fspath(path))


def resolve(obj: Any, path: str = "<pickle>") -> Any:
    """Recursively replace chumpy and sparse stand-ins inside containers by real arrays."""
    if isinstance(obj, ChumpyNode):
        return _eval_chumpy(obj, path)
    if isinstance(obj, SparseNode):
        return _build_sparse(obj, path)
    if isinstance(obj, dict):
        return {k: resolve(v, path) for k, v in obj.items()}
    if isinstance(obj, list):
        return [resolve(v, path) for v in obj]
    if isinstance(obj, tuple):
        return tuple(resolve(v, path) for v in obj)
    return obj


def _eval_chumpy(node: ChumpyNode, path: str) -> np.ndarray:
    """Evaluate the chumpy node types that data files contain: Ch, Select and Reshape."""
    state, kind = node.state, node.class_path.rsplit(".", 1)[-1]
    if kind == "Ch" and "x" in state:
        return np.asarray(resolve(state["x"], path))
    if kind == "Select" and "a" in state and "idxs" in state:
        out = np.asarray(resolve(state["a"], path)).ravel()[np.asarray(state["idxs"])]
        return out.reshape(state["preferred_shape"]) if "preferred_shape" in state else out
    if kind == "Reshape" and "a" in state and "newshape" in state:
        return np.asarray(resolve(state["a"], path)).reshape(state["newshape"])
    raise DataError(path, None, f"unsupported chumpy object {node.class_path} with fields {sorted(state)}")


def _build_sparse(node: SparseNode, path: str) -> scipy.sparse.spmatrix:
    """Rebuild a sparse matrix from its pickled fields, whatever scipy version wrote it."""
    st = node.state
    shape = st.get("_shape", st.get("shape"))
    try:
        if node.fmt == "coo":
            return scipy.sparse.coo_matrix((st["data"], (st["row"], st["col"])), shape=shape)
        cls = scipy.sparse.csc_matrix if node.fmt == "csc" else scipy.sparse.csr_matrix
        return cls((st["data"], st["indices"], st["indptr"]), shape=shape)
    except (KeyError, ValueError, TypeError) as e:
        raise DataError(path, None, f"malformed {node.fmt} sparse matrix in pickle: {e}") from e

"""Loading untrusted pickles: chumpy and sparse stand-ins, the allow-list, and clear errors."""

from __future__ import annotations

import os
import pickle
import pickletools
import sys

import numpy as np
import pytest
import scipy.sparse

from hoidata.errors import DataError
from hoidata.safe_pickle import load_pickle
from hoidata.toy.hand import chumpy_stand_ins, wrap_shapedirs


def _write_chumpy_pickle(path, protocol):
    arr = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 3, 4)
    with chumpy_stand_ins() as (ch, select):
        obj = {"sel": wrap_shapedirs(arr, ch, select, n=2), "sparse": scipy.sparse.csc_matrix(np.eye(3)),
               "names": ["a", "b"], "flag": {1, 2}}
        path.write_bytes(pickle.dumps(obj, protocol=protocol))
    return arr


@pytest.mark.parametrize("protocol", [0, 1, 2])
def test_chumpy_select_and_sparse_load_without_chumpy(tmp_path, protocol):
    path = tmp_path / "model.pkl"
    arr = _write_chumpy_pickle(path, protocol)
    globals_used = {arg for op, arg, _ in pickletools.genops(path.read_bytes()) if op.name == "GLOBAL"}
    assert "chumpy.reordering Select" in globals_used and "chumpy.ch Ch" in globals_used
    assert "chumpy" not in sys.modules
    out = load_pickle(path)
    assert "chumpy" not in sys.modules
    np.testing.assert_array_equal(out["sel"], arr[:, :, :2])
    assert scipy.sparse.issparse(out["sparse"]) and out["sparse"].format == "csc"
    np.testing.assert_array_equal(out["sparse"].toarray(), np.eye(3))
    assert out["names"] == ["a", "b"] and out["flag"] == {1, 2}


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_code_execution_is_refused_naming_file_and_global(tmp_path):
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"v_template": _Evil()}, protocol=2))
    with pytest.raises(DataError, match=r"evil\.pkl.*(posix|os)\.system"):
        load_pickle(path)


def test_truncated_and_missing_files(tmp_path):
    path = tmp_path / "model.pkl"
    _write_chumpy_pickle(path, 2)
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(DataError, match=r"model\.pkl.*truncated or corrupt"):
        load_pickle(path)
    with pytest.raises(DataError, match=r"nope\.pkl.*file not found"):
        load_pickle(tmp_path / "nope.pkl")
    (tmp_path / "text.pkl").write_text("hello, I am not a pickle")
    with pytest.raises(DataError, match=r"text\.pkl"):
        load_pickle(tmp_path / "text.pkl")


def test_bad_chumpy_contents_and_huge_arrays_give_clear_errors(tmp_path):
    arr = np.zeros((2, 3, 4))
    with chumpy_stand_ins() as (ch, select):
        sel = wrap_shapedirs(arr, ch, select, n=2)
        sel.__dict__["idxs"] = np.array([10 ** 6])
        (tmp_path / "idx.pkl").write_bytes(pickle.dumps({"s": sel}, protocol=2))
    with pytest.raises(DataError, match=r"idx\.pkl.*IndexError"):
        load_pickle(tmp_path / "idx.pkl")

"""docs/stores.md's recipe for reading a store with plain ``webdataset`` (no hoisdf, no hoidata), run as written.

The recipe is taken from the page, run in a fresh interpreter on a built store (a default one, and one of
upstream-region records holding ``frame.jpg``), and what it decodes is compared, member by member, with hoidata's own
strict reader (``hoidata.store.iter_records``): pixels, arrays and labels exactly.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hoidata import schema, store

DOC = Path(__file__).resolve().parents[1] / "docs" / "stores.md"

DRIVER = """
import json, sys
import numpy as np
arrays, metas, keys = {}, {}, []
for key, img, seg, hm, sdf, meta in hoidata_webdataset(sys.argv[1:-1]):
    keys.append(key)
    for name, value in (("img", img), ("seg", seg), ("hm", hm), ("sdf", sdf)):
        arrays[f"{key}/{name}"] = value
    metas[key] = meta
np.savez(sys.argv[-1] + ".npz", **arrays)
loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("hoidata", "hoisdf"))
json.dump({"keys": keys, "metas": metas, "loaded": loaded}, open(sys.argv[-1] + ".json", "w"))
"""


def recipe() -> str:
    text = DOC.read_text()
    section = text[text.index("## Streaming a store with plain `webdataset`"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["default", "upstream_region"])
def test_the_documented_recipe_reads_every_member(kind, request, tmp_path):
    tiny_store = request.getfixturevalue("tiny_store" if kind == "default" else "tiny_region_store")
    urls = [str(p) for p in sorted(tiny_store.glob("shard-*.tar"))]
    result = tmp_path / "decoded"
    code = recipe() + DRIVER
    subprocess.run([sys.executable, "-c", code, *urls, str(result)], check=True, cwd=tmp_path, timeout=300)
    got = json.loads(result.with_suffix(".json").read_text())
    arrays = np.load(result.with_suffix(".npz"))
    assert got["loaded"] == []  # webdataset (which brings torch), numpy and Pillow; no hoidata, no hoisdf
    ours = list(store.iter_records(tiny_store))
    assert got["keys"] == [r[store.KEY] for r in ours] and len(ours) > 1
    for rec in ours:
        key = rec[store.KEY]
        img = arrays[f"{key}/img"]
        assert img.dtype == np.uint8 and img.shape == rec[schema.IMG].shape  # RGB, (S, S, 3)
        # Pillow's and OpenCV's libjpeg-turbo decode these JPEGs alike (0 of 468 toy crops differ); frames: Pillow's
        np.testing.assert_array_equal(img, rec[schema.IMG])
        for name, member in (("seg", schema.SEG), ("hm", schema.HEATMAP), ("sdf", schema.SDF)):
            np.testing.assert_array_equal(arrays[f"{key}/{name}"], rec[member])
            assert arrays[f"{key}/{name}"].dtype == rec[member].dtype
        meta = got["metas"][key]
        assert set(meta) == set(schema.META_FIELDS) | (set(schema.REGION_FIELDS) if kind != "default" else set())
        for field, (shape, _) in {**schema.META_FIELDS, **schema.REGION_FIELDS}.items():
            if field not in meta:
                continue
            if shape is None:
                assert meta[field] == rec[schema.META][field]
            else:
                np.testing.assert_array_equal(np.asarray(meta[field]), rec[schema.META][field])
        sdf = arrays[f"{key}/sdf"]
        xyz, sdf_h, _, part = schema.dequantize_sdf(sdf)  # the table's "* 2e-5 gives metres"
        np.testing.assert_allclose(sdf[:, :5] * 2e-5, np.c_[xyz, sdf_h, _], rtol=1e-6)
        assert sum(meta["sdf_counts"]) == len(sdf) and (part >= -1).all()
        assert (arrays[f"{key}/seg"] & ~np.uint8(15)).max() == 0  # four bit planes

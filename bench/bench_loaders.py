"""Other stacks' loaders on one store, beside the project's: samples/s of one pass over every record.

Usage: python -m bench.bench_loaders [--store STORE] [--frames 96] [--loaders NAME ...]

Without ``--store`` a toy DexYCB of about ``--frames`` frames is written and its train split built (256 px crops,
8 records per shard). Each loader reads every record once, in one process (no workers), decoding every member as
the project does: the recipes of docs/other-loaders.md and docs/stores.md, run as written. Measured:

- ``iter_records``: ``hoidata.store.iter_records`` (the strict reader: every member decoded and checked);
- ``hoisdf loader``: ``make_loader(build_dataset(...))``, the training loader (batches of 8, 600 + 200 SDF rows
  drawn per record; masks left packed, as training reads them), one epoch of the store's records;
- ``webdataset``: the stores.md recipe; ``wids``: by index, in order (its shard copies into a cache made before
  timing); ``dali (cpu)``: the reader with the store's index files, members decoded in Python; ``energon``: the
  cooker after ``energon prepare`` (run on a copy, untimed); ``hf streaming`` and ``hf arrow`` (``load_dataset``
  then a pass with ``with_format("numpy", dtype=None)``; the Arrow copy's preparation timed on its own line).

A loader whose package is not installed prints "not installed". Per core: every loader here runs in one process.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

DOCS = Path(__file__).resolve().parents[1] / "docs"
LOADERS = ("iter_records", "hoisdf loader", "webdataset", "wids", "dali (cpu)", "energon", "hf streaming", "hf arrow")


def recipe(page: str, heading: str) -> str:
    text = (DOCS / page).read_text()
    return re.search(r"```python\n(.*?)```", text[text.index(f"## {heading}"):], re.S).group(1)


def names(*headings: str) -> dict:
    """The decoding block of docs/other-loaders.md and the named sections' blocks, run."""
    space: dict = {}
    exec(recipe("other-loaders.md", "The project's decoding, for the loaders below")
         + "".join(recipe("other-loaders.md", h) for h in headings), space)
    return space


def members_of(store: Path) -> list[str]:
    from hoidata.store import read_shard_members

    found = set()
    for path in sorted(store.glob("shard-*.tar")):
        for raw in read_shard_members(path):
            found |= {m for m in raw if not m.startswith("__")}
    return sorted(found)


def run_loader(name: str, store: Path, work: Path) -> tuple[int, float, str]:
    """(records read, seconds, a note) of one pass of loader ``name``."""
    if name == "iter_records":
        from hoidata.store import iter_records

        start = time.perf_counter()
        return sum(1 for _ in iter_records(store)), time.perf_counter() - start, ""
    if name == "hoisdf loader":
        from hoidata.store import read_index
        from hoisdf.data import StoreSpec, build_dataset, make_loader

        n = len(read_index(store).keys)
        data = build_dataset([StoreSpec(store)], 8, n, 0, 600, 200, 0.05, 64, training=True, progress=False)
        start = time.perf_counter()
        return sum(len(b["key"]) for b in make_loader(data, 0)), time.perf_counter() - start, "batches of 8"
    if name == "webdataset":
        space: dict = {}
        exec(recipe("stores.md", "Streaming a store with plain `webdataset`"), space)
        urls = [str(p) for p in sorted(store.glob("shard-*.tar"))]
        start = time.perf_counter()
        return sum(1 for _ in space["hoidata_webdataset"](urls)), time.perf_counter() - start, ""
    if name == "wids":
        space = names("`wids` (indexed random access)")
        dataset = space["hoidata_wids"](str(store), str(work / "wids"))
        for i in range(len(dataset)):  # the shards copied into wids' cache, untimed
            dataset[i]
        start = time.perf_counter()
        n = sum(1 for i in range(len(dataset)) if space["wids_record"](dataset, i))
        return n, time.perf_counter() - start, "shards in its cache"
    if name == "dali (cpu)":
        space = names("NVIDIA DALI")
        members = members_of(store)
        pipe = space["hoidata_dali"](store, members)
        pipe.build()
        total = pipe.epoch_size("store")
        start = time.perf_counter()
        for _ in range(total):
            outputs = pipe.run()
            space["decode_sample"]({m: bytes(o.as_array()[0]) for m, o in zip(members, outputs) if o.as_array().size})
        return total, time.perf_counter() - start, "bytes by DALI, decoded in Python"
    if name == "energon":
        from megatron.energon import WorkerConfig, get_loader, get_val_dataset

        copy = work / "energon"
        shutil.copytree(store, copy)
        subprocess.run([sys.executable, "-c", "from megatron.energon.cli.main import main; main()", "prepare",
                        "--non-interactive", "--split-ratio", "1,0,0", "--sample-type", "CrudeWebdataset",
                        "--no-progress", str(copy)], check=True, capture_output=True)
        space = names("Megatron-Energon")
        data = get_val_dataset(str(copy), split_part="train", batch_size=1, task_encoder=space["HoidataTaskEncoder"](),
                               worker_config=WorkerConfig(rank=0, world_size=1, num_workers=0))
        start = time.perf_counter()
        return sum(len(b) for b in get_loader(data)), time.perf_counter() - start, "after energon prepare"
    import datasets

    if name == "hf streaming":
        start = time.perf_counter()
        n = sum(1 for _ in datasets.load_dataset(str(store), split="train", streaming=True))
        return n, time.perf_counter() - start, ""
    start = time.perf_counter()
    records = datasets.load_dataset(str(store), split="train", cache_dir=str(work / "hf"))
    prepared = time.perf_counter() - start
    arrays = records.with_format("numpy", dtype=None)
    start = time.perf_counter()
    n = sum(1 for _ in arrays)
    return n, time.perf_counter() - start, f"after {prepared:.1f} s preparing the Arrow copy"


def _installed(name: str) -> bool:
    import importlib.util

    module = {"wids": "wids", "dali (cpu)": "nvidia.dali", "energon": "megatron.energon", "hf streaming": "datasets",
              "hf arrow": "datasets"}.get(name)
    return module is None or importlib.util.find_spec(module) is not None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", type=Path, default=None, help="a store (default: a toy store built here)")
    parser.add_argument("--frames", type=int, default=96, help="toy frames when no --store is given")
    parser.add_argument("--loaders", nargs="+", default=list(LOADERS), choices=LOADERS)
    args = parser.parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    print(f"load average (1 min): {os.getloadavg()[0]:.2f}")
    with tempfile.TemporaryDirectory(prefix="bench_loaders_") as tmp:
        work, store = Path(tmp), args.store
        if store is None:
            from bench.common import toy_root
            from hoidata.build_sdf import build_store
            from hoidata.records.settings import load_build_config

            root, store = toy_root(args.frames, work), work / "store"
            cfg = load_build_config("toy", ['dataset.splits=["train"]', "record.crop_size=256",
                                            "store.records_per_shard=8"])
            build_store(cfg, root, root / "mano", root / "models", store, workers=1, progress=False)
        print(f"| loader | records | seconds | samples/s | note |\n|---|---|---|---|---|")
        for name in args.loaders:
            if not _installed(name):
                print(f"| {name} | | | not installed | |")
                continue
            n, seconds, note = run_loader(name, Path(store), work)
            print(f"| {name} | {n} | {seconds:.2f} | {n / seconds:.1f} | {note} |", flush=True)
        print(f"load average (1 min): {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

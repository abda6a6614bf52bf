"""Shuffle modes side by side: batch composition and loader throughput of ``train.shuffle = "stream"`` and
``"global"`` on one store, in one run (issue 31, item 2).

Usage: python -m bench.bench_shuffle [--store DIR] [--sequences 10] [--frames 6] [--crop 128]
       [--records-per-shard 24] [--batch 22] [--workers 2] [--epochs 2] [--rounds 2] [--remote] [--latency-ms 0]

Without ``--store`` a toy DexYCB is written and its s0 training split built into a store (sequences x 3 cameras x
frames, stored sequence -> camera -> frame as the real builds store them). For each mode, over ``--epochs`` whole
epochs (epoch = the store's size, as training has it), the loader the trainer builds (``build_dataset`` +
``make_loader``, batch ``--batch``, ``--workers`` workers, 600 + 200 SDF points) gives:

- per batch: distinct sequence-camera groups, distinct sequences and distinct cameras (mean), and beside them what
  a uniform permutation of the same records gives (exact: sum over groups of 1 - C(N - n_g, B) / C(N, B));
- per epoch: records delivered, distinct records, records delivered twice or more;
- samples/s from the second batch of an epoch to its end (worker start-up excluded), median over ``--rounds``
  rounds that alternate the modes; "start s": building the dataset (opening the store; for global also finding
  every record's byte span, also timed alone).

``--remote`` also serves the store on 127.0.0.1 (a Range-capable static server, ``--latency-ms`` added before every
answer to stand in for a network) and measures both modes from its URL: samples/s, requests and bytes per record.
The load average (1 min) is printed before and after: the machine is shared, rates move with it.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import os
import statistics
import tempfile
import threading
import time
from math import comb
from pathlib import Path

import numpy as np

from hoidata import store
from hoidata.build_sdf import build_store
from hoidata.records.settings import load_build_config
from hoidata.toy.dexycb import ToyDexYCBSize, write_toy_dexycb
from hoidata.toy.make import write_assets
from hoisdf.data import StoreSpec, build_dataset, make_loader
from hoisdf.data.global_shuffle import record_table
from hoisdf.data.shards import store_shards

N_HAND, N_OBJECT, NEAR, SEED = 600, 200, 0.05, 0
MODES = ("stream", "global")


def toy(work: Path, sequences: int, frames: int, crop: int, per_shard: int) -> Path:
    """A toy DexYCB's s0 training split (subject 0, 3 cameras) built into ``work/store``."""
    root = work / "data"
    mano, models = write_assets(root)
    size = ToyDexYCBSize(subjects=(0,), sequences=sequences, serials=(0, 6, 7), frames=frames)
    write_toy_dexycb(root, mano, models, size, workers=2, progress=False)
    cfg = load_build_config("toy", ['dataset.splits=["train"]', f"record.crop_size={crop}",
                                    f"store.records_per_shard={per_shard}"])
    build_store(cfg, root, mano, models, work / "store", workers=2, progress=False)
    return work / "store"


def groups_of(path) -> dict[str, tuple[str, str, str]]:
    """key -> (sequence-camera group, sequence, camera) from the index's frame ids (``..._<serial>_<frame>``)."""
    index = store.read_index(path)
    out = {}
    for key, frame in zip(index.keys, index.labels["frame_id"].tolist()):
        group = frame.rsplit("_", 1)[0]
        sequence, _, camera = group.rpartition("_")
        out[key] = (group, sequence, camera)
    return out


def uniform_expectation(labels: list[str], batch: int) -> float:
    """Mean distinct labels in a batch of a uniform permutation of records with these labels (exact)."""
    n = len(labels)
    sizes = np.unique(labels, return_counts=True)[1]
    return float(sum(1 - comb(n - int(g), batch) / comb(n, batch) for g in sizes))


def one_epoch(data, workers: int, epoch: int) -> tuple[list[list[str]], float]:
    """(the epoch's batches' keys, samples/s from the second batch on)."""
    data.set_epoch(epoch)
    keys, it = [], iter(make_loader(data, workers))
    keys.append(next(it)["key"])
    start = time.perf_counter()
    for batch in it:
        keys.append(batch["key"])
    seconds = time.perf_counter() - start
    return keys, sum(map(len, keys[1:])) / max(seconds, 1e-9)


def composition(batches: list[list[str]], groups: dict) -> dict[str, float]:
    """Mean distinct groups, sequences and cameras per batch; records delivered, distinct, repeated."""
    out = {name: float(np.mean([len({groups[k][i] for k in b}) for b in batches]))
           for i, name in enumerate(("groups", "sequences", "cameras"))}
    flat = [k for b in batches for k in b]
    counts = np.unique(flat, return_counts=True)[1]
    out.update(delivered=len(flat), distinct=len(counts), repeated=int((counts > 1).sum()))
    return out


class _RangeServer(http.server.SimpleHTTPRequestHandler):
    """A static server that answers Range requests (206), counts requests and bytes, and waits ``latency`` s."""

    protocol_version = "HTTP/1.1"
    stats: dict
    latency: float

    def log_message(self, *args):
        pass

    def do_HEAD(self):
        time.sleep(self.latency)
        super().do_HEAD()

    def do_GET(self):
        time.sleep(self.latency)
        try:
            with open(self.translate_path(self.path.partition("?")[0]), "rb") as f:
                data = f.read()
        except OSError:
            self.send_error(404)
            return
        asked = self.headers.get("Range", "").removeprefix("bytes=").split("-")
        first, last = 0, len(data) - 1
        if len(asked) == 2 and asked[0].isdigit():
            first, last = int(asked[0]), min(int(asked[1] or last), last)
        body = data[first:last + 1]
        self.send_response(206 if self.headers.get("Range") else 200)
        self.send_header("Content-Length", str(len(body)))
        if self.headers.get("Range"):
            self.send_header("Content-Range", f"bytes {first}-{last}/{len(data)}")
        self.end_headers()
        self.wfile.write(body)
        if self.path.endswith(".tar"):
            self.stats["requests"] += 1
            self.stats["bytes"] += len(body)


def serve(folder: Path, latency: float):
    """(server, its base URL, its counters) serving ``folder``'s parent on 127.0.0.1."""
    stats = {"requests": 0, "bytes": 0}
    handler = type("Handler", (_RangeServer,), {"stats": stats, "latency": latency})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(handler, directory=str(folder.parent)))
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/{folder.name}", stats


def offsets_seconds(location) -> float:
    """Seconds the global mode's start spends finding every record's byte span (after opening the store)."""
    _, expected = store_shards(location)
    tick = time.perf_counter()
    record_table(expected, str(location), progress=False)
    return time.perf_counter() - tick


def dataset(location, mode: str, batch: int):
    return build_dataset([StoreSpec(location)], batch, None, SEED, N_HAND, N_OBJECT, NEAR, 64, training=True,
                         shuffle=mode, progress=False)


def measure(location, groups: dict, args) -> dict:
    """{mode: {composition means over the epochs, "rate": median samples/s, "start": s}} at ``location``."""
    data, results = {}, {m: {"rates": [], "batches": []} for m in MODES}
    for mode in MODES:
        tick = time.perf_counter()
        data[mode] = dataset(location, mode, args.batch)
        results[mode]["start"] = time.perf_counter() - tick
    for r in range(args.rounds):
        for mode in MODES:
            for epoch in range(args.epochs):
                keys, rate = one_epoch(data[mode], args.workers, epoch)
                results[mode]["rates"].append(rate)
                if r == 0:
                    results[mode]["batches"].append(keys)
    for mode, res in results.items():
        parts = [composition(b, groups) for b in res["batches"]]
        res.update({k: float(np.mean([p[k] for p in parts])) for k in parts[0]})
        res["rate"] = statistics.median(res["rates"])
    return results


def table(results: dict, groups: dict, batch: int, remote: dict | None = None) -> list[str]:
    labels = list(groups.values())
    uniform = {name: uniform_expectation([g[i] for g in labels], batch)
               for i, name in enumerate(("groups", "sequences", "cameras"))}
    lines = [f"| mode | groups/batch | sequences/batch | cameras/batch | delivered / distinct / repeated per epoch "
             f"| samples/s | start s |" + (" requests/record | bytes/record |" if remote else ""),
             "|---|---|---|---|---|---|---|" + ("---|---|" if remote else "")]
    for mode, res in results.items():
        line = (f"| {mode} | {res['groups']:.2f} | {res['sequences']:.2f} | {res['cameras']:.2f} | "
                f"{res['delivered']:.0f} / {res['distinct']:.0f} / {res['repeated']:.0f} | {res['rate']:.1f} | "
                f"{res['start']:.2f} |")
        if remote:
            line += f" {remote[mode]['requests']:.2f} | {remote[mode]['bytes']:.0f} |"
        lines.append(line)
    lines.append(f"| uniform permutation (exact) | {uniform['groups']:.2f} | {uniform['sequences']:.2f} | "
                 f"{uniform['cameras']:.2f} | {len(labels)} / {len(labels)} / 0 | | |" + (" | |" if remote else ""))
    return lines


def remote_run(path: Path, groups: dict, args) -> tuple[dict, dict]:
    """measure() from a loopback URL of the store, and each mode's shard requests and bytes per delivered record
    (the global mode's one-off offset scan counted apart, in its start time)."""
    server, url, stats = serve(path, args.latency_ms / 1000)
    try:
        costs, results = {}, {}
        for mode in MODES:
            one = argparse.Namespace(**{**vars(args), "rounds": 1})
            stats.update(requests=0, bytes=0)
            tick = time.perf_counter()
            data = dataset(url, mode, args.batch)
            start = time.perf_counter() - tick
            stats.update(requests=0, bytes=0)
            batches, rates = [], []
            for epoch in range(one.epochs):
                keys, rate = one_epoch(data, args.workers, epoch)
                batches.append(keys)
                rates.append(rate)
            delivered = sum(len(b) for bs in batches for b in bs)
            costs[mode] = {"requests": stats["requests"] / delivered, "bytes": stats["bytes"] / delivered}
            parts = [composition(b, groups) for b in batches]
            results[mode] = {**{k: float(np.mean([p[k] for p in parts])) for k in parts[0]},
                             "rate": statistics.median(rates), "start": start}
        return results, costs
    finally:
        server.shutdown()
        server.server_close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", type=Path, default=None, help="an existing store (default: a toy one is built)")
    p.add_argument("--sequences", type=int, default=10, help="toy: sequences of subject 0 (8 of 10 are s0 train)")
    p.add_argument("--frames", type=int, default=6, help="toy: frames per sequence and camera")
    p.add_argument("--crop", type=int, default=128, help="toy: crop size in pixels")
    p.add_argument("--records-per-shard", type=int, default=24)
    p.add_argument("--batch", type=int, default=22)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--remote", action="store_true", help="also from a 127.0.0.1 server")
    p.add_argument("--latency-ms", type=float, default=0.0, help="remote: delay before every answer")
    args = p.parse_args()
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench_shuffle_") as work:
        path = args.store or toy(Path(work), args.sequences, args.frames, args.crop, args.records_per_shard)
        groups = groups_of(path)
        index = store.read_index(path)
        print(f"store {path}: {len(groups)} records in {len({g[0] for g in groups.values()})} sequence-camera groups, "
              f"{len(index.shards)} shards; batch {args.batch}, {args.workers} workers, {args.epochs} epochs x "
              f"{args.rounds} rounds; load {load:.2f}")
        print(f"global mode's record offsets: {offsets_seconds(path):.3f} s from the folder")
        for line in table(measure(path, groups, args), groups, args.batch):
            print(line)
        if args.remote:
            results, costs = remote_run(Path(path), groups, args)
            server, url, _ = serve(Path(path), args.latency_ms / 1000)
            scan = offsets_seconds(url)
            server.shutdown()
            print(f"\nfrom http://127.0.0.1 ({args.latency_ms:g} ms before every answer), one round; start s: opening "
                  f"the store (index, shard sizes), and for global also the record offsets ({scan:.3f} s alone):")
            for line in table(results, groups, args.batch, costs):
                print(line)
    print(f"load average (1 min): {load:.2f} before, {os.getloadavg()[0]:.2f} after")


if __name__ == "__main__":
    main()

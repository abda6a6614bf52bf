"""render-synthetic throughput: synthetic records per second per core with the default settings.

Usage: python -m bench.bench_synthetic [--count 48] [--workers 1 2]

Writes a small toy HO-3D as the grasp source, then renders --count samples with 1 worker and the
same samples with 2 workers, default record settings (512 px crops, 4096 + 2048 SDF samples), and
reports the rate and the physical check's rejection rate.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from hoidata import store
from hoidata.render_synthetic import render_synthetic
from hoidata.toy.ho3d import ToyHO3DSize, write_toy_ho3d
from hoidata.toy.make import write_assets


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--count", type=int, default=48)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts, one run each")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_synth_"))
    try:
        source = work / "ho3d"
        mano, models = write_assets(source)
        write_toy_ho3d(source, mano, models, ToyHO3DSize(train_sequences=3, eval_sequences=0, frames=4), progress=False)
        print(f"{'workers':>7} {'records':>8} {'seconds':>8} {'renders/s':>10} {'per core':>9}")
        for workers in args.workers:
            out = work / f"store{workers}"
            start = time.perf_counter()
            s = render_synthetic(source, out, args.count, mano, models, workers=workers, records_per_shard=8,
                                 progress=False)
            seconds = time.perf_counter() - start
            print(f"{workers:>7} {s.written:>8} {seconds:>8.1f} {s.written / seconds:>10.2f} {s.written / seconds / workers:>9.2f}")
        print(f"physical check: {store.read_index(work / f'store{args.workers[0]}').provenance['synthetic']}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

"""Disk the test suite holds, side by side in one run: pytest's default (every folder kept to the end of the
session, ``-o tmp_path_retention_policy=all``, which also turns the fixture hooks of tests/conftest.py off) against
the suite's own settings (a passed test's folder removed when it ends, a fixture's folders when it is torn down).

Both sessions run at once on the same tests, each with its own ``TMPDIR``; a thread reads each folder's size every
``--every`` seconds. The table gives the peak, what is left when the session ends (before pytest's own clean-up of
a passed session, which only the suite's setting does) and the sessions' outcome, with the load average.

Run: ``python -m bench.bench_suite_disk [--every 2] [TESTS ...]`` (default: the upstream parity and training tests,
the suite's biggest writers).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

DEFAULT_TESTS = ["tests/test_import_upstream.py", "tests/test_train.py"]
VARIANTS = {"kept to the end (pytest default)": ["-o", "tmp_path_retention_policy=all"], "the suite's settings": []}


def folder_bytes(root: Path) -> int:
    """Bytes of the regular files under ``root`` (files vanishing while it walks are skipped)."""
    total = 0
    for folder, _, files in os.walk(root):
        for name in files:
            try:
                total += os.lstat(os.path.join(folder, name)).st_size
            except FileNotFoundError:
                pass
    return total


def run_side_by_side(tests: list[str], every: float, work: Path) -> dict[str, dict]:
    """Start one pytest session per variant, sample their temporary folders until all end."""
    runs = {}
    for number, (name, extra) in enumerate(VARIANTS.items()):
        tmp = work / f"tmp{number}"
        tmp.mkdir()
        log = (work / f"session{number}.log").open("w")
        # the session's base folder is kept after it ends (--basetemp): "left" is what the session itself left
        base = tmp / "base"
        proc = subprocess.Popen([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--basetemp={base}",
                                 *extra, *tests], stdout=log, stderr=subprocess.STDOUT,
                                env={**os.environ, "TMPDIR": str(tmp)})
        runs[name] = {"proc": proc, "tmp": tmp, "log": log, "peak": 0}

    def sample():
        while any(r["proc"].poll() is None for r in runs.values()):
            for r in runs.values():
                r["peak"] = max(r["peak"], folder_bytes(r["tmp"]))
            time.sleep(every)

    thread = threading.Thread(target=sample)
    thread.start()
    start = time.perf_counter()
    for r in runs.values():
        r["code"] = r["proc"].wait()
        r["seconds"] = time.perf_counter() - start
    thread.join()
    for number, r in enumerate(runs.values()):
        r["log"].close()
        r["left"] = folder_bytes(r["tmp"])
        lines = (work / f"session{number}.log").read_text().strip().splitlines()
        r["summary"] = "; ".join([line for line in lines if line.startswith(("FAILED", "ERROR"))] + lines[-1:])
    return runs


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("tests", nargs="*", default=DEFAULT_TESTS)
    parser.add_argument("--every", type=float, default=2.0, help="seconds between size readings")
    args = parser.parse_args(argv)
    load = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="bench-suite-disk-") as work:
        runs = run_side_by_side(args.tests, args.every, Path(work))
    print(f"tests: {' '.join(args.tests)}; load average before {load[0]:.2f}, after {os.getloadavg()[0]:.2f}")
    print("| variant | peak GiB | left at the end GiB | session |")
    print("|---|---|---|---|")
    for name, r in runs.items():
        print(f"| {name} | {r['peak'] / 2**30:.2f} | {r['left'] / 2**30:.2f} | {r['summary']} (exit {r['code']}) |")
    return max(r["code"] for r in runs.values())


if __name__ == "__main__":
    sys.exit(main())

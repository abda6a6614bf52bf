"""Store integrity: verify every record against the index, find the shards a resumed build keeps, and open a store
a command reads from (:func:`opened_store`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hoidata.errors import DataError, redact_urls
from hoidata.reading import file_digest, read_json
from hoidata.schema import META, META_FIELDS
from hoidata.store.codec import KEY
from hoidata.store.index import ShardInfo, StoreIndex, read_index
from hoidata.store.paths import is_stale_token, local_folder, local_store, stale_temps
from hoidata.store.shards import iter_records, sidecar_name


@dataclass
class VerifyReport:
    """What verify_store found: one line per problem, each starting with the file it is about."""

    store_dir: str
    shards: int = 0
    records: int = 0
    empty_shards: int = 0  # shards whose frames were all skipped at build time (listed in the index's skips)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # not problems of the store: leftovers safe to delete

    @property
    def ok(self) -> bool:
        return not self.problems

    def __str__(self) -> str:
        state = "OK" if self.ok else f"{len(self.problems)} problem(s)"
        empty = f" ({self.empty_shards} empty: every frame skipped)" if self.empty_shards else ""
        return "\n".join([f"{self.store_dir}: {self.records} records in {self.shards} shards{empty}: {state}",
                          *(f"  {p}" for p in self.problems), *(f"  note: {n}" for n in self.notes)])


MAX_LABEL_PROBLEMS = 5  # per shard: one broken conversion would otherwise print a line per record


def _label_mismatches(index: StoreIndex, row: int, meta: dict) -> list[str]:
    """Names of the index columns that are meta fields too and disagree with the record's meta."""
    bad = []
    for name, column in index.labels.items():
        if name not in META_FIELDS or name == "key":
            continue
        if name not in meta:  # the record's kind lacks the field: the index holds NaN (sdf_counts 0, 0, 0)
            stored = np.asarray(column[row], np.float64)
            if not (np.isnan(stored).all() or (name == "sdf_counts" and not stored.any())):
                bad.append(name)
            continue
        stored, value = column[row], meta[name]
        if column.dtype.kind == "U":
            same = isinstance(value, str) and str(stored) == value
        else:
            try:  # the index holds float32: compare to float32 precision
                same = np.allclose(np.asarray(value, np.float64), stored.astype(np.float64), rtol=1e-6, atol=1e-6)
            except (TypeError, ValueError):
                same = False
        if not same:
            bad.append(name)
    return bad


def _verify_records(path: Path, info: ShardInfo, index: StoreIndex, report: VerifyReport) -> int:
    """Decode every record of one shard against the index's keys and labels; returns the record count."""
    rows = index.shard_rows(info.number)
    expected, count, label_problems, order_ok = index.keys[rows], 0, 0, True
    try:
        for record in iter_records([path]):
            key = record[KEY]
            if order_ok and (count >= len(expected) or key != expected[count]):
                there = expected[count] if count < len(expected) else "no record"
                report.problems.append(f"{path}: record {count} is {key!r}, the index has {there!r} there")
                order_ok = False
            if order_ok and (bad := _label_mismatches(index, rows.start + count, record[META])):
                if label_problems < MAX_LABEL_PROBLEMS:
                    report.problems.append(f"{path}: {key!r}: labels differ from the index: {bad}")
                label_problems += 1
            count += 1
    except DataError as exc:
        report.problems.append(str(exc))
    if label_problems > MAX_LABEL_PROBLEMS:
        report.problems.append(f"{path}: ... {label_problems - MAX_LABEL_PROBLEMS} more records with differing labels")
    return count


def verify_store(store_dir) -> VerifyReport:
    """Check a whole store: every shard's size, sha256 and record count against the index, every record
    decoded and its key and labels matching the index, in order; shard files the index does not list."""
    report = VerifyReport(redact_urls(str(store_dir)))  # a URL (refused below) prints without its password
    try:
        store_dir = local_store(store_dir, "hoidata verify")
    except DataError as exc:
        report.problems.append(str(exc))
        return report
    try:
        index = read_index(store_dir)
    except DataError as exc:
        report.problems.append(str(exc))
        return report
    for info in index.shards:
        path = store_dir / info.name
        report.shards += 1
        if not path.is_file():
            report.problems.append(f"{path}: missing")
            continue
        size, sha256 = file_digest(path)
        if size != info.size:
            report.problems.append(f"{path}: {size} bytes, the index says {info.size}")
        if sha256 != info.sha256:
            report.problems.append(f"{path}: sha256 {sha256} differs from the index's {info.sha256}")
        count = _verify_records(path, info, index, report)
        report.records += count
        if count != info.count:
            report.problems.append(f"{path}: {count} readable records, the index says {info.count}")
    listed = {info.name for info in index.shards}
    strays = [p for p in sorted(store_dir.glob("shard-*.tar")) if p.name not in listed]
    report.problems += [f"{p}: shard file not in the index" for p in strays]
    report.empty_shards = sum(info.count == 0 for info in index.shards)
    if not report.records and not report.problems:
        report.problems.append(f"{store_dir}: the store holds no records (every frame was skipped; see the index's skips)")
    leftovers = [*stale_temps(store_dir), *sorted(store_dir.glob("shard-*.tmp")), *sorted(store_dir.glob(".*.tmp"))]
    report.notes += [f"{p}: left over from a write that did not finish (safe to delete)" for p in leftovers]
    return report


def read_sidecar(store_dir, number: int) -> ShardInfo:
    """The ShardInfo written next to shard ``number`` when it was completed."""
    path = Path(store_dir) / sidecar_name(number)
    value = read_json(path, "shard sidecar")
    info = ShardInfo.from_dict(value, path)
    if info.number != number:
        raise DataError(path, "number", f"{info.number}, expected {number}")
    return info


def _leftovers(store_dir: Path, plan: ShardInfo) -> list[Path]:
    """Temporary files of a planned shard whose writer is gone: ``<name>.tmp`` (older versions) and
    ``<name>.<host>-<pid>.tmp`` of a dead process of this host (paths.is_stale_token)."""
    found = [store_dir / f"{plan.name}.tmp"] if (store_dir / f"{plan.name}.tmp").exists() else []
    for path in store_dir.glob(f"{plan.name}.*.tmp"):
        if is_stale_token(path.name[len(plan.name) + 1:-len(".tmp")]):
            found.append(path)
    return found


def completed_shards(store_dir, expected: Sequence[ShardInfo], clean: bool = True, check_bytes: bool = True) -> set[int]:
    """Numbers of the planned shards that are already written intact, so a resumed build skips them.

    A shard counts when its sidecar matches every field the plan sets (count, keys; sha256/size if
    given) and the file's size and (with ``check_bytes``) sha256 match the sidecar. With ``clean``, leftover
    temporary files of the *planned* shards whose writer is gone (an interrupted run) are removed: call it before
    this job's writers start, with only the shards this job owns, so parallel ``--part`` jobs never delete each
    other's files (a writer still running, here or on another node, keeps its own).
    """
    store_dir = Path(store_dir)
    if clean:
        for plan in expected:
            for leftover in _leftovers(store_dir, plan):  # only what is there: a complete store may be read-only
                leftover.unlink(missing_ok=True)
    done = set()
    for plan in expected:
        try:
            info = read_sidecar(store_dir, plan.number)
        except DataError:
            continue  # no or damaged sidecar: the shard is written again
        fields = ("name", "count", "sha256", "size", "first_key", "last_key")
        if any(getattr(plan, f) is not None and getattr(plan, f) != getattr(info, f) for f in fields):
            continue
        path = store_dir / info.name
        if path.is_file() and path.stat().st_size == info.size and (not check_bytes or file_digest(path)[1] == info.sha256):
            done.add(plan.number)
    return done


def opened_store(location, what: str) -> Path:
    """A store a command reads from (``export --store``): a local folder whose index opens, checked before the
    command writes anything; else one DataError naming the store (a mistyped, unfinished or damaged one never
    becomes a run where every frame is skipped)."""
    where = local_folder(location, what)
    if not where.is_dir():
        raise DataError(where, None, f"{what}: no such store folder")
    read_index(where)  # a DataError naming the index when it is missing or damaged
    return where

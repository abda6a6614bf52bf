"""The shard engine (hoidata.engine.engine) on a task of its own: serial and pooled runs write the same units,
a resumed run keeps the done ones, the worker context is opened once per process and closed, and a worker that
cannot start is one WorkerError line. The pipelines on it (build-sdf, render-synthetic, export, the toy writer)
have their own tests; this one needs no dataset, GL or MANO."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import pytest

from hoidata.errors import DataError, WorkerError
from hoidata.engine.engine import Plan, ShardTask, run_task


@dataclass(frozen=True)
class SquaresSpec:
    """Worker spec: where the contexts log their opening and closing (one file per process and event)."""

    log: str
    fail: str = ""  # open() raises this message when set

    def open(self):
        if self.fail:
            raise RuntimeError(self.fail)
        return SquaresWorker(self.log)


class SquaresWorker:
    def __init__(self, log: str):
        self.log = Path(log)
        (self.log / f"{os.getpid()}.opened").write_text("")
        self.closed = False

    def run(self, job):
        number, items, out = job
        if -1 in items:
            raise DataError(out, None, "item -1 cannot be squared (test)")
        skips = [{"frame_id": str(i), "reason": "odd"} for i in items if i % 7 == 3]
        kept = [i * i for i in items if i % 7 != 3]
        (Path(out) / f"unit-{number:03d}.json").write_text(json.dumps(kept))
        return number, len(kept), skips

    def close(self):
        (self.log / f"{os.getpid()}.closed").write_text("")


@dataclass
class SquaresTask(ShardTask):
    """Unit n squares the items n*per .. (n+1)*per-1 into out/unit-n.json; done when that file exists."""

    out: Path
    worker: SquaresSpec
    plan: Plan
    desc: str = "squares"
    refuse: bool = False

    def job(self, number: int):
        start = number * self.plan.per
        return number, list(range(start, start + self.plan.size(number))), str(self.out)

    def done(self, numbers, starting):
        return {n for n in numbers if (self.out / f"unit-{n:03d}.json").is_file()}

    def check_kept(self, numbers):
        if self.refuse and numbers:
            raise DataError(self.out, None, f"inputs changed since units {numbers} were written")


def _task(tmp_path: Path, name: str, items: int = 23, per: int = 5, **spec) -> SquaresTask:
    out, log = tmp_path / name, tmp_path / f"{name}-log"
    out.mkdir()
    log.mkdir(exist_ok=True)
    return SquaresTask(out, SquaresSpec(str(log), **spec), Plan(items, per))


def _units(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("unit-*.json"))}


def test_the_plan_cuts_items_into_units_and_parts():
    plan = Plan(23, 5)
    assert plan.units == [0, 1, 2, 3, 4] and [plan.size(n) for n in plan.units] == [5, 5, 5, 5, 3]
    assert plan.owned((1, 2)) == [1, 3] and Plan(0, 5).units == []
    with pytest.raises(ValueError, match="per >= 1"):
        Plan(3, 0)
    assert isinstance(SquaresTask(Path("."), SquaresSpec(""), plan), ShardTask)


@pytest.mark.slow  # starts a worker pool
def test_serial_and_two_pool_workers_write_the_same_units(tmp_path):
    serial = run_task(_task(tmp_path, "serial"), workers=1, progress=False)
    pooled = run_task(_task(tmp_path, "pool"), workers=2, progress=False)
    assert _units(tmp_path / "serial") == _units(tmp_path / "pool") and len(_units(tmp_path / "pool")) == 5
    for result in (serial, pooled):
        assert result.all_done and result.units_written == 5 and result.units_kept == 0
        assert result.written == 23 - 3 and sorted(s["frame_id"] for s in result.skipped) == ["10", "17", "3"]
    assert json.loads((tmp_path / "serial" / "unit-004.json").read_text()) == [400, 441, 484]


@pytest.mark.slow  # starts a worker pool
def test_each_pool_process_opens_one_context_and_closes_it_at_exit(tmp_path):
    run_task(_task(tmp_path, "pool", items=40, per=2), workers=2, progress=False)
    log = tmp_path / "pool-log"
    opened = sorted(p.stem for p in log.glob("*.opened"))
    assert 1 <= len(opened) <= 2 and str(os.getpid()) not in opened  # one per worker process, none here
    assert sorted(p.stem for p in log.glob("*.closed")) == opened  # the processes closed theirs when they ended


def test_a_resumed_run_keeps_the_done_units_and_builds_the_rest(tmp_path):
    """Serial runs (the pool gives the same units: the test above)."""
    task = _task(tmp_path, "store")
    first = run_task(task, part=(0, 2), progress=False)
    assert first.units_written == 3 and not first.all_done  # units 0, 2, 4; the other part's are missing
    before = {p.name: p.stat().st_mtime_ns for p in task.out.glob("unit-*.json")}
    second = run_task(task, progress=False)
    assert second.units_kept == 3 and second.units_written == 2 and second.all_done
    assert all(task.out.joinpath(name).stat().st_mtime_ns == t for name, t in before.items())
    assert _units(task.out) == _units(_run_whole(tmp_path))
    third = run_task(task, progress=False)  # nothing left: no worker is opened at all
    assert third.units_written == 0 and third.units_kept == 5 and third.all_done


def _run_whole(tmp_path: Path) -> Path:
    task = _task(tmp_path, "whole")
    run_task(task, progress=False)
    return task.out


def test_check_kept_may_refuse_a_resume(tmp_path):
    task = _task(tmp_path, "store")
    run_task(task, part=(1, 2), progress=False)
    task.refuse = True
    with pytest.raises(DataError, match=r"units \[1, 3\] were written"):
        run_task(task, progress=False)


def test_the_serial_context_is_closed_at_the_end_and_after_an_error(tmp_path):
    task = _task(tmp_path, "ok")
    run_task(task, progress=False)
    me = str(os.getpid())
    assert [p.stem for p in (tmp_path / "ok-log").glob("*.closed")] == [me]

    bad = _task(tmp_path, "bad")
    bad.job = lambda n: (n, [-1], str(bad.out))  # the first unit raises
    with pytest.raises(DataError, match="item -1"):
        run_task(bad, progress=False)
    assert [p.stem for p in (tmp_path / "bad-log").glob("*.closed")] == [me]


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.slow)])  # 2: starts a worker pool
def test_a_worker_that_cannot_start_is_one_worker_error_line(tmp_path, workers):
    task = _task(tmp_path, "store", fail="no GL here (test)\nsecond line")
    with pytest.raises(WorkerError) as info:
        run_task(task, workers=workers, progress=False)
    text = str(info.value)
    assert "\n" not in text and "could not start a worker process" in text and "no GL here (test)" in text
    assert "SquaresSpec.open" in text and "RuntimeError" in text
    assert not _units(task.out)


@dataclass
class PlainSquaresTask(ShardTask):
    """The same units without ``done`` or ``check_kept``: the base's defaults (nothing done, nothing refused)."""

    out: Path
    worker: SquaresSpec
    plan: Plan
    desc: str = "plain squares"

    def job(self, number: int):
        start = number * self.plan.per
        return number, list(range(start, start + self.plan.size(number))), str(self.out)


def test_a_task_with_the_base_defaults_runs_every_unit_and_is_complete_only_when_it_ran_them_all(tmp_path):
    task = PlainSquaresTask(_task(tmp_path, "plain").out, SquaresSpec(str(tmp_path / "plain-log")), Plan(23, 5))
    half = run_task(task, part=(0, 2), progress=False)
    assert (half.units_written, half.units_kept, half.all_done) == (3, 0, False)
    whole = run_task(task, progress=False)  # no resume: every unit again
    assert (whole.units_written, whole.units_kept, whole.all_done) == (5, 0, True)
    assert whole.written == 20 and whole.items == 23 and whole.units == [0, 1, 2, 3, 4]
    assert _units(task.out) == _units(_run_whole(tmp_path))


def test_a_task_must_define_its_jobs():
    with pytest.raises(NotImplementedError, match="defines no job"):
        ShardTask().job(0)


@pytest.mark.parametrize("order", [(0, 1), (1, 0)])
def test_merged_parts_report_the_part_that_wrote_the_last_step(order):
    """Two array parts that finish together both end ``finished``; the one that waited for the index lock found the
    index written (``finish_kept``). Whatever the parts' order, the merged summary is the writer's (the build then
    prints "index.zarr written", not "nothing written": a race a loaded machine showed), with the counts summed."""
    from hoidata.engine import RunSummary
    from hoidata.engine.launch import merge

    parts = [RunSummary(written=7, units_written=2, finished=True, finish_kept=False),
             RunSummary(written=9, units_written=2, finished=True, finish_kept=True)]
    merged = merge([parts[i] for i in order])
    assert merged.finished and not merged.finish_kept
    assert (merged.written, merged.units_written) == (16, 4)
    assert merge([RunSummary(written=3), RunSummary(written=4)]).finished is False

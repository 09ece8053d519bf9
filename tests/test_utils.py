"""The utils layer: atomic files with one file mode, and worker processes driven over pipes."""

from __future__ import annotations

import os
import stat
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from sb3_formation.utils.files import FILE_MODE, atomic_directory, atomic_path, atomic_write
from sb3_formation.utils.processes import WorkerProcess, gather


@pytest.fixture
def strict_umask() -> Iterator[None]:
    """A umask that would make plain files 0600: the package's files must still be 0644."""
    previous = os.umask(0o077)
    try:
        yield
    finally:
        os.umask(previous)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_atomic_write_replaces_the_file_with_mode_0644(tmp_path: Path, strict_umask: None) -> None:
    path = tmp_path / "deep" / "summary.json"
    atomic_write(path, "first")
    atomic_write(path, b"second \x00 bytes")
    assert path.read_bytes() == b"second \x00 bytes"
    assert mode(path) == FILE_MODE == 0o644
    assert [file.name for file in path.parent.iterdir()] == ["summary.json"]  # no temporary file left


def test_atomic_path_keeps_the_old_file_when_writing_fails(tmp_path: Path) -> None:
    path = tmp_path / "model.zip"
    path.write_text("old")
    with pytest.raises(RuntimeError, match="disk full"), atomic_path(path) as temporary:
        assert temporary.parent == tmp_path and temporary.suffix == ".zip" and temporary.name.startswith(".model.")
        temporary.write_text("half")
        raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert [file.name for file in tmp_path.iterdir()] == ["model.zip"]


def test_atomic_directory_swaps_whole_folders(tmp_path: Path, strict_umask: None) -> None:
    target = tmp_path / "checkpoints" / "iteration_000002"
    with atomic_directory(target) as folder:
        (folder / "state.json").write_text("{}")
    assert mode(target / "state.json") == 0o644
    with pytest.raises(KeyboardInterrupt), atomic_directory(target) as folder:
        (folder / "state.json").write_text("new")
        raise KeyboardInterrupt  # killed half-way: the old checkpoint stays whole
    assert (target / "state.json").read_text() == "{}"
    assert [path.name for path in target.parent.iterdir()] == ["iteration_000002"]
    with atomic_directory(target) as folder:
        (folder / "model.zip").write_text("model")
    assert sorted(path.name for path in target.iterdir()) == ["model.zip"]  # replaced, not merged
    assert [path.name for path in target.parent.iterdir()] == ["iteration_000002"]


class Counter:
    """A worker object: adds, fails on request, reports progress."""

    def __init__(self, start: int) -> None:
        self.total = start

    def add(self, value: int) -> int:
        self.total += value
        return self.total

    def fail(self, message: str) -> None:
        raise ValueError(message)

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def count_to(self, stop: int, report: Callable[[int], None]) -> str:
        for value in range(stop):
            report(value)
        return "done"


def test_a_worker_keeps_its_object_and_answers_calls() -> None:
    worker = WorkerProcess(Counter, (10,), "counter worker")
    lambda_worker = WorkerProcess(lambda: {"built": "by a lambda"}, name="lambda worker")  # cloudpickle
    try:
        assert worker.call("add", 5) == 15
        assert worker.call("add", 1) == 16  # the same object, its state kept
        with pytest.raises(ValueError, match="bad value"):
            worker.call("fail", "bad value")  # the worker's own exception type, raised here
        assert worker.call("add", 0) == 16  # and the worker still serves
        assert lambda_worker.call("get", "built") == "by a lambda"
        worker.send("count_to", 4, progress=True)
        reported: list[int] = []
        assert worker.receive(reported.append) == "done"
        assert reported == [0, 1, 2, 3]
    finally:
        worker.close()
        lambda_worker.close()
    assert not worker.process.is_alive() and worker.process.exitcode == 0


def test_a_dead_worker_is_named_with_its_exit_code() -> None:
    worker = WorkerProcess(Counter, (0,), "counter worker")
    try:
        worker.process.kill()
        worker.process.join()
        with pytest.raises(RuntimeError, match=r"counter worker \(pid \d+\) died, exit code -9"):
            worker.call("add", 1)
    finally:
        worker.close()


def test_gather_drains_every_worker_or_fails_fast() -> None:
    workers = [WorkerProcess(Counter, (start,), f"worker {start}") for start in (0, 100)]
    try:
        workers[0].send("fail", "first")
        workers[1].send("add", 1)
        with pytest.raises(ValueError, match="first"):
            gather(workers)
        assert [worker.call("add", 0) for worker in workers] == [0, 101]  # no stale reply left in a pipe
        for worker in workers:
            worker.send("count_to", 3, progress=True)
        progress: list[tuple[int, int]] = []
        assert gather(workers, on_progress=lambda index, item: progress.append((index, item))) == ["done", "done"]
        assert sorted(progress) == [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2)]
        workers[0].send("fail", "stop all")
        workers[1].send("sleep", 60)  # busy for a minute: fail_fast must not wait for it
        started = time.monotonic()
        with pytest.raises(ValueError, match="stop all"):
            gather(workers, fail_fast=True)
        assert time.monotonic() - started < 30
        assert not workers[1].process.is_alive()  # terminated
    finally:
        for worker in workers:
            worker.close(timeout=1)

"""The utils layer: atomic files with one file mode, and worker processes driven over pipes."""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from multiprocessing import shared_memory
from pathlib import Path

import numpy as np
import pytest

from sb3_formation.utils import files
from sb3_formation.utils.checks import check_path
from sb3_formation.utils.files import FILE_MODE, atomic_directory, atomic_path, atomic_write, restore_directory
from sb3_formation.utils.processes import SharedArrays, WorkerProcess, gather
from sb3_formation.utils.yaml_files import read_yaml_file


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
    atomic_write(path, "first, ünïcode")
    assert path.read_bytes() == "first, ünïcode".encode()  # text is written as UTF-8
    assert mode(path) == 0o644
    os.chmod(path, 0o600)  # an existing file's own mode is not kept: the new file has FILE_MODE
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


def test_atomic_path_renames_the_written_file_into_place(tmp_path: Path, strict_umask: None) -> None:
    path = tmp_path / "stats.pkl"
    path.write_text("old")
    with atomic_path(path) as temporary:
        assert temporary.exists() and mode(temporary) == 0o644  # created empty, umask or not
        assert temporary.name.startswith(".stats.") and temporary.suffix == ".pkl"
        assert path.read_text() == "old"  # nothing replaced before the block ends
        with open(temporary, "w") as stream:  # a writer that opens the path itself
            stream.write("new")
    assert path.read_text() == "new" and mode(path) == 0o644
    assert not temporary.exists()
    assert [file.name for file in tmp_path.iterdir()] == ["stats.pkl"]


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


def test_a_kill_between_the_two_renames_of_a_folder_swap_is_undone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The old folder renamed aside, the process killed before the new one took its place."""
    target = tmp_path / "iteration_000004"
    with atomic_directory(target) as folder:
        (folder / "state.json").write_text("old")
    renames = []

    def killed_at_the_second_rename(source: str, destination: str) -> None:
        renames.append(destination)
        if len(renames) == 2:
            raise SystemExit("killed")
        os.rename(source, destination)

    monkeypatch.setattr(files.os, "replace", killed_at_the_second_rename)
    with pytest.raises(SystemExit), atomic_directory(target) as folder:
        (folder / "state.json").write_text("new")
    monkeypatch.undo()
    assert not target.exists() and Path(renames[0]).name == "iteration_000004"  # the window: only the hidden copy
    assert restore_directory(target) and (target / "state.json").read_text() == "old"
    assert [path.name for path in tmp_path.iterdir()] == ["iteration_000004"]  # the hidden folders are gone
    assert not restore_directory(target)  # nothing left to put back
    with atomic_directory(target) as folder:  # the next write of it goes through
        (folder / "state.json").write_text("new")
    assert (target / "state.json").read_text() == "new"


def test_atomic_directory_folder_is_readable_like_its_files(tmp_path: Path, strict_umask: None) -> None:
    """Files get 0644 so others can read them; the folders holding them get 0755, whatever the umask (077 here)."""
    with atomic_directory(tmp_path / "swapped") as folder:
        (folder / "state.json").write_text("{}")
        (folder / "inner").mkdir()
        (folder / "inner" / "deep.txt").write_text("deep")
    assert mode(tmp_path / "swapped") == mode(tmp_path / "swapped" / "inner") == 0o755
    assert mode(tmp_path / "swapped" / "state.json") == mode(tmp_path / "swapped" / "inner" / "deep.txt") == 0o644


class Counter:
    """A worker object: adds, fails on request, reports progress."""

    def __init__(self, start: int) -> None:
        self.total = start

    def add(self, value: int) -> int:
        self.total += value
        return self.total

    def fail(self, message: str) -> None:
        raise ValueError(message)

    def fail_after(self, seconds: float, message: str) -> None:
        time.sleep(seconds)
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


def test_a_worker_of_a_local_class() -> None:
    """A class defined in a function (pickled by value by cloudpickle) with a closure over a local list."""
    unit = [" m"]

    class Ruler:
        def __init__(self, scale: float) -> None:
            self.scale = scale

        def measure(self, length: float) -> str:
            return f"{length * self.scale}{unit[0]}"

        def check(self, length: float) -> float:
            if length < 0:
                raise ValueError(f"negative length {length}")
            return length

    worker = WorkerProcess(Ruler, (2.0,), "ruler")
    try:
        assert worker.call("measure", 1.5) == "3.0 m"
        with pytest.raises(ValueError, match="negative length -1"):
            worker.call("check", -1)
        assert worker.call("check", 4.0) == 4.0
        with pytest.raises(AttributeError, match="no_such_method"):
            worker.call("no_such_method")  # also an exception of the worker's, sent back
        assert worker.call("measure", 0.25) == "0.5 m"
    finally:
        worker.close()
    assert worker.process.exitcode == 0


class TwoPartError(Exception):
    """An exception that pickles but cannot be rebuilt from its args (its __init__ takes two)."""

    def __init__(self, first: str, second: str) -> None:
        super().__init__(f"{first} and {second}")


class Awkward:
    def raise_two_part(self) -> None:
        raise TwoPartError("left", "right")

    def unpicklable(self) -> object:
        return (x for x in ())  # a generator: no pickler takes it


def test_errors_and_results_that_do_not_pickle_reach_the_parent_as_messages() -> None:
    worker = WorkerProcess(Awkward, (), "awkward worker")
    try:
        with pytest.raises(RuntimeError, match="TwoPartError: left and right"):
            worker.call("raise_two_part")
        with pytest.raises(TypeError, match="cannot pickle 'generator' object"):
            worker.call("unpicklable")
        assert worker.process.is_alive()  # the worker survived both
    finally:
        worker.close()


def test_a_dead_worker_is_named_with_its_exit_code() -> None:
    worker = WorkerProcess(Counter, (0,), "counter worker")
    try:
        worker.process.kill()
        worker.process.join()
        with pytest.raises(RuntimeError, match=r"counter worker \(pid \d+\) died, exit code -9"):
            worker.call("add", 1)
    finally:
        worker.close()


def test_a_worker_killed_during_a_call_is_named_by_receive() -> None:
    worker = WorkerProcess(Counter, (0,), "sleeper")
    try:
        worker.send("sleep", 60)
        worker.process.kill()
        worker.process.join()
        with pytest.raises(RuntimeError, match=rf"sleeper \(pid {worker.process.pid}\) died, exit code -9"):
            worker.receive()
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
        assert workers[1].process.exitcode == -signal.SIGTERM
    finally:
        for worker in workers:
            worker.close(timeout=1)


def test_gather_waits_for_the_slow_workers_and_raises_the_first_error() -> None:
    """Without fail_fast every reply is read: the slow worker's result is consumed, the earliest error raised."""
    workers = [WorkerProcess(Counter, (start,), f"worker {start}") for start in (0, 10, 20)]
    try:
        workers[0].send("sleep", 0.5)
        workers[1].send("fail", "early")
        workers[2].send("count_to", 2, progress=True)
        progress: list[tuple[int, int]] = []
        started = time.monotonic()
        with pytest.raises(ValueError, match="early"):
            gather(workers, on_progress=lambda index, item: progress.append((index, item)))
        assert time.monotonic() - started >= 0.5  # it waited for the sleeper
        assert progress == [(2, 0), (2, 1)]
        assert [worker.call("add", 1) for worker in workers] == [1, 11, 21]  # fresh replies, all workers alive
        workers[0].send("sleep", 0.5)
        workers[1].send("fail_after", 0.25, "late")
        workers[2].send("fail", "soon")
        with pytest.raises(ValueError, match="soon"):  # the first to arrive, not the first in the list
            gather(workers)
        assert [worker.call("add", 0) for worker in workers] == [1, 11, 21]
    finally:
        for worker in workers:
            worker.close(timeout=1)


class Squarer:
    """A worker object that works on shared arrays: squares ``inputs`` into ``squares`` and counts in ``counts``."""

    def __init__(self, shared: SharedArrays) -> None:
        self.shared = shared

    def square(self) -> int:
        self.shared["squares"][...] = self.shared["inputs"] ** 2
        self.shared["counts"][0] += 1
        return int(self.shared["counts"][0])

    def close(self) -> None:
        self.shared.close()


def test_shared_arrays_reach_a_worker_by_name_and_are_freed_by_their_maker() -> None:
    layout = {"inputs": ((3, 2), np.float64), "counts": ((1,), np.int64), "squares": ((3, 2), np.float32)}
    shared = SharedArrays(layout)
    assert {key: (array.shape, array.dtype) for key, array in shared.arrays.items()} == {
        "inputs": ((3, 2), np.float64),
        "counts": ((1,), np.int64),
        "squares": ((3, 2), np.float32),
    }
    worker = WorkerProcess(Squarer, (shared,), "squarer", spin=0.05)
    try:
        shared["inputs"][...] = [[1.0, -2.0], [0.5, 3.0], [10.0, 0.0]]
        assert worker.call("square") == 1
        assert shared["squares"].tolist() == [[1.0, 4.0], [0.25, 9.0], [100.0, 0.0]]
        shared["inputs"][1] = [4.0, 5.0]  # the worker reads what the parent writes now
        assert worker.call("square") == 2
        assert shared["squares"][1].tolist() == [16.0, 25.0] and shared["inputs"][1].tolist() == [4.0, 5.0]
    finally:
        worker.close()
    name = shared._memory.name
    attached = SharedArrays(layout, name)  # a second view, as a worker has: closing it leaves the block
    attached.close()
    reader = SharedArrays(layout, name)
    assert reader["counts"][0] == 2
    squares = shared["squares"]
    shared.close()
    with pytest.raises(FileNotFoundError):
        SharedArrays(layout, name)
    assert squares[1].tolist() == [16.0, 25.0] and reader["counts"][0] == 2  # views in use keep the memory mapped
    del squares
    reader.close()


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads CPU times from /proc")
def test_a_spinning_worker_polls_for_calls_then_sleeps() -> None:
    worker = WorkerProcess(Counter, (0,), "spinner", spin=0.3)
    try:
        assert [worker.call("add", 1) for _ in range(50)] == list(range(1, 51))
        worker.send("add", 1)
        assert gather([worker], spin=0.3) == [51]
        before = cpu_seconds(worker.process.pid)
        time.sleep(1.0)
        spun = cpu_seconds(worker.process.pid) - before
        # it polls, busy, for 0.3 s of the 1 s: at most that much CPU time (less on a loaded machine, where other
        # processes share the cores: no lower bound is held, as none holds under load)
        assert spun < 0.45
        before = cpu_seconds(worker.process.pid)
        time.sleep(1.0)
        assert cpu_seconds(worker.process.pid) - before < 0.05  # then it slept
        assert worker.call("add", 1) == 52  # and a call wakes it
    finally:
        worker.close()


# Workers and shared memory after kills, the __main__ guard, file names and YAML text ------------------------

SCRIPT_WITH_WORKERS = """
import sys
from sb3_formation.env.blocks import EngineBlocks
from sb3_formation.env.config import FormationConfig
{body}
"""


def run_script(tmp_path: Path, body: str, guarded: bool = True, **popen: object) -> subprocess.Popen:
    """Run ``body`` as a script (under the ``__main__`` guard unless told not to), its output piped."""
    if guarded:
        body = 'if __name__ == "__main__":\n' + "".join(f"    {line}\n" for line in body.strip().splitlines())
    path = tmp_path / "script.py"
    path.write_text(SCRIPT_WITH_WORKERS.format(body=body))
    return subprocess.Popen([sys.executable, str(path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def test_no_shared_memory_outlives_a_killed_process_group(tmp_path: Path) -> None:
    """The blocks' shared memory is unlinked as soon as every worker has mapped it: a ``kill -KILL`` of the whole
    process group leaves no ``/dev/shm`` segment, and stepping still works meanwhile."""
    body = """
blocks = EngineBlocks([FormationConfig.task("ch5-bearing")] * 2, n_workers=2, auto_reset=False)
print(*[shared._memory.name for shared in blocks.shared.values()], flush=True)
blocks.reset([0, 1], [0, 1], [None, None])
blocks.step(blocks.checked_actions([[0.1, 0.0]] * 12))
print("stepped", flush=True)
import time; time.sleep(60)
"""
    process = run_script(tmp_path, body, start_new_session=True)
    names = process.stdout.readline().split()
    assert process.stdout.readline().strip() == "stepped", process.stderr.read()
    assert names and not any(Path("/dev/shm", name.lstrip("/")).exists() for name in names)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=10)
    for name in names:
        with pytest.raises(FileNotFoundError):
            shared_memory.SharedMemory(name=name)


def test_workers_end_quietly_when_their_parent_is_killed(tmp_path: Path) -> None:
    body = """
blocks = EngineBlocks([FormationConfig.task("ch5-bearing")] * 4, n_workers=2, auto_reset=True)
blocks.reset([0, 1, 2, 3], [0, 1, 2, 3], [None] * 4)
for step in range(10**9):
    blocks.step(blocks.checked_actions([[0.1, 0.0]] * 24))
    if step == 10:
        print("stepping", flush=True)
"""
    process = run_script(tmp_path, body)
    assert process.stdout.readline().strip() == "stepping", process.stderr.read()  # the workers are mid-step
    started = time.monotonic()
    process.kill()  # the parent only: its workers must notice and end, without a word
    errors = process.stderr.read()  # returns once every process holding the pipe has ended
    assert time.monotonic() - started < 30 and "Traceback" not in errors and "Error" not in errors, errors


def test_a_script_without_the_main_guard_is_told_about_it(tmp_path: Path) -> None:
    body = 'blocks = EngineBlocks([FormationConfig.task("ch5-bearing")] * 2, n_workers=2)'
    process = run_script(tmp_path, body, guarded=False)
    _, errors = process.communicate(timeout=120)
    lines = errors.strip().splitlines()
    assert process.returncode != 0 and 'if __name__ == "__main__":' in lines[-1], errors
    assert len(lines) < 30, errors  # a worker's own report is one line


def test_yaml_files_that_are_not_utf8_and_unwritable_names_are_one_line_errors(tmp_path: Path) -> None:
    path = tmp_path / "latin1.yaml"
    path.write_bytes("name: caf\xe9\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"latin1\.yaml is not UTF-8 text \(byte 9\)"):
        read_yaml_file(path)
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_yaml_file(tmp_path / "absent.yaml")
    undecodable = os.fsdecode(b"runs/bad-\xff")  # a name the shell passed as bytes
    with pytest.raises(ValueError, match=r"--run-dir 'runs/bad-\\udcff' is not valid UTF-8"):
        check_path(undecodable, "--run-dir")
    with pytest.raises(ValueError, match="is longer than 255 bytes"):
        check_path(tmp_path / ("x" * 256), "logdir")
    check_path(tmp_path / "runs with spaces" / "ünïcode", "logdir")

"""Worker processes: an object built in its own process and driven by method calls over a pipe.

Used by the VecEnv (a block of teams per worker) and by evaluation (a share of the episodes per worker). Workers start
with ``forkserver`` where available (``spawn`` elsewhere), so scripts that start them need the usual
``if __name__ == "__main__":`` guard. Workers ignore Ctrl-C: the parent decides how to stop and closes them. A worker
that dies is named in the error with its process id and exit code.

Waking a process that sleeps on a pipe can take longer than a VecEnv step of a block of teams (woken for every step,
2 VecEnv workers ran at 0.44x one process on this project's machine). A worker made with ``spin`` > 0 therefore polls
its pipe for that long after each call before it sleeps, and :func:`gather` with ``spin`` polls for the replies: calls
that follow each other closely (the steps of a rollout) never wait for a wake-up, and a worker left alone (during
training) sleeps after ``spin`` seconds.
:class:`SharedArrays` carries the arrays of such calls, so the pipe carries only a few bytes.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Sequence
from multiprocessing import shared_memory
from multiprocessing.connection import Connection, wait
from typing import TYPE_CHECKING, Any, TypeAlias, cast

import cloudpickle
import numpy as np

#: Reply kinds sent by a worker (``_STARTED`` once, when its object is built).
_OK, _ERROR, _PROGRESS, _STARTED = "ok", "error", "progress", "started"
#: What a worker that dies while starting most likely met: a script without the ``__main__`` guard.
MAIN_GUARD_HINT = (
    'if a script starts the workers, put the code that does so under `if __name__ == "__main__":` (worker processes '
    "import the script again, and must not start workers of their own)"
)


if TYPE_CHECKING:
    #: The contexts :func:`worker_context` returns: those that can start a ``Process`` (typeshed's ``BaseContext`` has
    #: no ``Process``).
    WorkerContext: TypeAlias = (
        multiprocessing.context.ForkServerContext | multiprocessing.context.SpawnContext | multiprocessing.context.ForkContext
    )


def worker_context(start_method: str | None = None) -> WorkerContext:
    """The multiprocessing context for workers: ``start_method``, else ``forkserver`` where available, else ``spawn``."""
    if start_method is None:
        start_method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    return cast("WorkerContext", multiprocessing.get_context(start_method))


def _ready(remotes: list[Connection], spin: float) -> list[Connection]:
    """The connections of ``remotes`` that have something to read, once one has: poll them for up to ``spin``
    seconds, then sleep on them."""
    if spin > 0.0:
        deadline = time.perf_counter() + spin
        while time.perf_counter() < deadline:
            ready = wait(remotes, 0.0)
            if ready:
                return cast("list[Connection]", ready)
            os.sched_yield()  # let a process that has work run on this core
    return cast("list[Connection]", wait(remotes))


def _serve(remote: Connection, parent_remote: Connection, payload: bytes, spin: float) -> None:  # pragma: no cover
    """The worker's loop (in the subprocess): build the object, then answer ``(method, args, progress)`` calls until
    ``close``, polling ``spin`` seconds for each call before sleeping."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent_remote.close()
    try:
        factory, arguments = cloudpickle.loads(payload)
        try:
            target = factory(*arguments)
        except Exception as error:  # sent to the parent, which raises it
            _send_error(remote, error)
            return
        remote.send((_STARTED, None))
        while True:
            _ready([remote], spin)
            method, arguments, progress = remote.recv()
            if method is None:
                getattr(target, "close", lambda: None)()
                break
            try:
                if progress:
                    result = getattr(target, method)(*arguments, report=lambda item: remote.send((_PROGRESS, item)))
                else:
                    result = getattr(target, method)(*arguments)
            except Exception as error:  # sent to the parent, which raises it
                _send_error(remote, error)
            else:
                try:
                    remote.send((_OK, result))
                except Exception as error:  # an unpicklable result
                    _send_error(remote, error)
    except (EOFError, OSError):  # the parent is gone: end at once and quietly (the system frees what is left)
        os._exit(0)
    finally:
        remote.close()


def _send_error(remote: Connection, error: Exception) -> None:  # pragma: no cover - subprocess
    """Send ``error`` to the parent; one that pickling would lose is sent as a ``RuntimeError`` naming it."""
    try:
        cloudpickle.loads(cloudpickle.dumps(error))
        remote.send((_ERROR, error))
    except Exception:
        remote.send((_ERROR, RuntimeError(f"{type(error).__name__}: {error}")))


class WorkerProcess:
    """``factory(*arguments)`` built in its own process; its methods are called with :meth:`send` and :meth:`receive`.

    :param factory: a callable building the worker's object (pickled with cloudpickle, so lambdas and local classes work)
    :param arguments: its positional arguments
    :param name: what the worker is, for error messages
    :param context: multiprocessing context (default: :func:`worker_context`)
    :param spin: seconds the worker polls for its next call before it sleeps (0: sleep at once); worth it only for
        calls that follow each other within that time, as it keeps a core busy meanwhile
    """

    def __init__(
        self,
        factory: Callable[..., Any],
        arguments: Sequence[Any] = (),
        name: str = "worker",
        context: WorkerContext | None = None,
        spin: float = 0.0,
    ) -> None:
        if getattr(multiprocessing.current_process(), "_inheriting", False):  # importing the parent's script
            raise SystemExit(f"sb3-formation: a worker process tried to start workers of its own: {MAIN_GUARD_HINT}")
        context = context or worker_context()
        self.name = name
        #: whether the worker has built its object (see :func:`wait_started`)
        self.started = False
        self.remote, work_remote = context.Pipe()
        payload = cloudpickle.dumps((factory, tuple(arguments)))
        self.process = context.Process(target=_serve, args=(work_remote, self.remote, payload, spin), daemon=True)
        self.process.start()
        work_remote.close()

    def send(self, method: str, *arguments: Any, progress: bool = False) -> None:
        """Start ``method(*arguments)`` in the worker; with ``progress`` the method gets a ``report`` keyword argument,
        a function whose items reach :meth:`receive`'s ``on_progress``."""
        try:
            self.remote.send((method, arguments, progress))
        except (BrokenPipeError, ConnectionResetError, OSError) as error:
            raise self._died() from error

    def receive(self, on_progress: Callable[[Any], None] | None = None) -> Any:
        """The result of the call started by :meth:`send`; the worker's exception is raised here.

        :param on_progress: called with each item the method reports
        :raises RuntimeError: the worker died (its pid and exit code are named)
        """
        return gather([self], None if on_progress is None else lambda _, item: on_progress(item))[0]

    def call(self, method: str, *arguments: Any) -> Any:
        """:meth:`send` then :meth:`receive`."""
        self.send(method, *arguments)
        return self.receive()

    def _died(self) -> RuntimeError:
        self.process.join(timeout=1)
        message = f"{self.name} (pid {self.process.pid}) died, exit code {self.process.exitcode}"
        return RuntimeError(message if self.started else f"{message}, while starting: {MAIN_GUARD_HINT}")

    def close(self, timeout: float = 10.0) -> None:
        """Ask the worker to close its object and exit; terminate it if it does not within ``timeout`` seconds."""
        if self.remote.closed:
            return
        try:
            self.remote.send((None, (), False))
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass
        self.process.join(timeout=timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(timeout=timeout)
        self.remote.close()

    def terminate(self) -> None:
        """Stop the worker at once (e.g. after another worker failed)."""
        if self.process.is_alive():
            self.process.terminate()
        self.process.join(timeout=10)
        self.remote.close()


def gather(
    workers: Sequence[WorkerProcess],
    on_progress: Callable[[int, Any], None] | None = None,
    fail_fast: bool = False,
    spin: float = 0.0,
) -> list[Any]:
    """The results of every worker's current call (started with :meth:`WorkerProcess.send`), read as they arrive.

    :param workers: the workers
    :param on_progress: called with (worker index, item) for each item a method reports
    :param fail_fast: on the first error terminate the workers still busy and raise it at once; otherwise every reply
        is read before the first error is raised, so no stale reply is left in a pipe of a worker that is kept
    :param spin: seconds to poll for each reply before sleeping on the pipes
    :raises RuntimeError: a worker died (its pid and exit code are named)
    """
    pending = {worker.remote: index for index, worker in enumerate(workers)}
    results: list[Any] = [None] * len(workers)
    errors: list[BaseException] = []
    while pending:
        for remote in _ready(list(pending), spin):
            index = pending[remote]
            try:
                kind, value = remote.recv()
            except (EOFError, ConnectionResetError, OSError):
                kind, value = _ERROR, workers[index]._died()
            if kind == _STARTED:
                workers[index].started = True
                continue
            if kind == _PROGRESS:
                if on_progress is not None:
                    on_progress(index, value)
                continue
            del pending[remote]
            if kind == _OK:
                results[index] = value
                continue
            errors.append(value)
            if fail_fast:
                for busy in pending.values():
                    workers[busy].terminate()
                raise value
    if errors:
        raise errors[0]
    return results


def wait_started(workers: Sequence[WorkerProcess], spin: float = 0.0) -> None:
    """Return once every worker has built its object (they start side by side).

    :param spin: seconds to poll for each reply before sleeping on the pipes
    :raises Exception: the first worker's error in building its object
    :raises RuntimeError: a worker died starting (the message has a word on the ``__main__`` guard)
    """
    pending = {worker.remote: index for index, worker in enumerate(workers) if not worker.started}
    while pending:
        for remote in _ready(list(pending), spin):
            index = pending.pop(remote)
            try:
                kind, value = remote.recv()
            except (EOFError, ConnectionResetError, OSError):
                raise workers[index]._died() from None
            if kind == _ERROR:
                raise value
            workers[index].started = True


class SharedArrays:
    """Named numpy arrays in one block of shared memory (``multiprocessing.shared_memory``), made by one process and
    attached in others: pickling one (e.g. as an argument of a :class:`WorkerProcess`) sends only the block's name and
    layout, and unpickling attaches to the same memory.

    The maker of the block frees it in :meth:`close`; every process should call it once done. Worker processes share
    their parent's resource tracker, so attaching in a worker adds no second owner.

    :param layout: each array's name -> (shape, dtype)
    :param name: name of an existing block to attach to (default: make a new block)
    """

    _ALIGNMENT = 64  #: bytes: each array starts on its own cache line

    def __init__(self, layout: dict[str, tuple[tuple[int, ...], Any]], name: str | None = None) -> None:
        self.layout = {key: (tuple(map(int, shape)), np.dtype(dtype).str) for key, (shape, dtype) in layout.items()}
        offsets, end = {}, 0
        for key, (shape, dtype) in self.layout.items():
            offsets[key] = end
            end += -(-int(np.prod(shape)) * np.dtype(dtype).itemsize // self._ALIGNMENT) * self._ALIGNMENT
        self._owner = self._linked = name is None
        self._memory = shared_memory.SharedMemory(name=name, create=self._owner, size=max(end, 1) if self._owner else 0)
        # frombuffer views hold the block's buffer, so the block stays mapped while any view lives
        self.arrays = {
            key: np.frombuffer(cast(memoryview, self._memory.buf), dtype, int(np.prod(shape)), offsets[key]).reshape(shape)
            for key, (shape, dtype) in self.layout.items()
        }

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def __reduce__(self) -> tuple[type[SharedArrays], tuple[Any, ...]]:
        return SharedArrays, (self.layout, self._memory.name)

    def unlink(self) -> None:
        """Remove the block's name (its maker, once every process has attached): the memory stays mapped where it is
        and goes with the last mapping, so no segment outlives the processes, even ones killed without a word."""
        if self._owner and self._linked:
            self._linked = False
            self._memory.unlink()

    def close(self) -> None:
        """Drop this process's view of the block; its maker also frees it (the memory goes once no array of it is
        left in any process)."""
        if not self.arrays:
            return
        self.arrays = {}
        try:
            self._memory.close()
        except BufferError:  # an array of the block is still in use here: the mapping goes with it
            pass
        self.unlink()

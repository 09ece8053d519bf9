"""Atomic files and folders: every artefact of the package (configs, models, normaliser statistics, evaluations,
figures, videos, checkpoints) is written to a hidden temporary sibling and renamed into place only once complete, so a
crash or a kill leaves either the old file or the new one, never half of one; sets of files that belong together
(an evaluation, a figure set) are written by :func:`atomic_files` in a locked folder. Files get mode
:data:`FILE_MODE`."""

from __future__ import annotations

import contextlib
import contextvars
import errno
import hashlib
import json
import math
import os
import secrets
import shutil
import stat
import tempfile
import time
import zipfile
from collections.abc import Collection, Iterator, Sequence
from pathlib import Path
from typing import IO

import numpy as np

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows: folders are not locked
    fcntl = None  # type: ignore[assignment]

#: Name of the lock file :func:`folder_lock` keeps in a folder.
LOCK_FILE = ".lock"

#: Mode of every file the package writes (rw-r--r--), whatever the process's umask.
FILE_MODE = 0o644
#: Mode of every folder written whole by :func:`atomic_directory` (rwxr-xr-x), like its files readable by all.
DIRECTORY_MODE = 0o755
#: Seconds :func:`atomic_files` waits for another process writing a set into the same folder.
SET_LOCK_WAIT = 60.0


#: The installed package's own folder (its code, recipes and shipped policies): no command writes there, except
#: ``pretrained --export`` into the shipped policies (:func:`package_writes`).
PACKAGE_FOLDER = Path(__file__).resolve().parent.parent
_package_writes: contextvars.ContextVar[bool] = contextvars.ContextVar("package_writes", default=False)


@contextlib.contextmanager
def package_writes() -> Iterator[None]:
    """Let the writers of this module write into :data:`PACKAGE_FOLDER` while the block runs (the export of a shipped
    policy)."""
    token = _package_writes.set(True)
    try:
        yield
    finally:
        _package_writes.reset(token)


def check_writable(path: str | os.PathLike[str]) -> None:
    """Refuse to write at ``path`` inside the installed package's folder (a shipped policy's stored evaluation, say),
    unless inside :func:`package_writes`. Every writer of this module calls it; commands call it before they work.

    :raises ValueError: naming the path
    """
    if not _package_writes.get() and Path(path).resolve().is_relative_to(PACKAGE_FOLDER):
        raise ValueError(
            f"{path} is inside the installed package sb3_formation ({PACKAGE_FOLDER}), whose shipped policies and "
            "recipes no command overwrites: write elsewhere"
        )


def temporary_beside(path: Path) -> Path:
    """Create a new, empty hidden file in ``path``'s folder (created if needed) with :data:`FILE_MODE`.

    The temporary name keeps ``path``'s suffix (some writers, e.g. SB3's ``save``, choose the format from it).

    :raises ValueError: ``path`` is inside the package's folder (:func:`check_writable`)
    """
    check_writable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        candidate = path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")
        with contextlib.suppress(FileExistsError):
            os.close(os.open(candidate, flags, FILE_MODE))
            os.chmod(candidate, FILE_MODE)  # os.open applies the umask
            return candidate
    raise FileExistsError(f"could not create a temporary file beside {path}")


def flush_file(path: Path) -> None:
    """Flush a written file to disk and give it :data:`FILE_MODE`."""
    with open(path, "rb") as stream:
        os.fsync(stream.fileno())
    os.chmod(path, FILE_MODE)


def replace_with(temporary: Path, path: Path) -> None:
    """Flush ``temporary`` to disk and rename it to ``path`` (replacing any file there), then flush the folder."""
    flush_file(temporary)
    os.replace(temporary, path)
    fsync_directory(path.parent, files=False)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` to write to; on success it replaces ``path``, on error it is deleted.

    :param path: the file to (re)write; its folder is created if needed
    """
    path = Path(path)
    temporary = temporary_beside(path)
    try:
        yield temporary
        replace_with(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def atomic_write(path: str | os.PathLike[str], data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8, or bytes) to ``path`` atomically, with :data:`FILE_MODE`."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data.encode() if isinstance(data, str) else data)


@contextlib.contextmanager
def atomic_files(
    folder: Path, names: Sequence[str], remove: Collection[str] = (), what: str = "folder"
) -> Iterator[dict[str, Path]]:
    """Write a set of files into ``folder`` as one unit, leaving its other files alone.

    Yields a new hidden temporary file beside each of ``names`` to write to. Only once the block ends without error
    are they all flushed, the files of ``remove`` deleted, and the temporaries renamed into place in the order of
    ``names``: a failure while writing (a full disk included) deletes the temporaries and leaves the folder untouched.
    Put last the file that lists the others (e.g. with their digests, see :func:`file_digest`): a reader checking them
    against it never takes a half-renamed set for a whole one. The folder is locked (:func:`folder_lock`, waiting up
    to :data:`SET_LOCK_WAIT` seconds) while the block runs, so two sets written into it at once follow each other.

    :param folder: the folder (created if needed)
    :param names: the files of the set, in the order they are renamed into place
    :param remove: files of an earlier set that this one lacks, deleted before the last rename
    :param what: what the folder is, for the lock's message (e.g. ``"evaluation folder"``)
    """
    with folder_lock(folder, what, wait=SET_LOCK_WAIT, remove=True):
        temporaries: dict[str, Path] = {}
        try:
            for name in names:
                temporaries[name] = temporary_beside(folder / name)
            yield temporaries
            for temporary in temporaries.values():
                flush_file(temporary)
            for name in remove:
                (folder / name).unlink(missing_ok=True)
            for name, temporary in temporaries.items():
                os.replace(temporary, folder / name)
            fsync_directory(folder, files=False)
        finally:
            for temporary in temporaries.values():
                temporary.unlink(missing_ok=True)


def file_digest(path: Path) -> str:
    """The SHA-256 of a file, as hex digits."""
    digest = hashlib.sha256()
    with open(path, "rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


@contextlib.contextmanager
def atomic_directory(target: Path) -> Iterator[Path]:
    """Write into a hidden temporary sibling folder, then rename it to ``target`` only if all went well.

    An existing ``target`` is first renamed aside (hidden) and deleted after the swap, so a crash at any point leaves
    either the old or the new folder under a hidden name or under ``target``, never a half-written ``target``; a kill
    between the two renames is undone by :func:`restore_directory` (called here first, and by readers).
    """
    check_writable(target)
    restore_directory(target)
    temporary = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        yield temporary
        for path in temporary.rglob("*"):
            os.chmod(path, FILE_MODE if path.is_file() else DIRECTORY_MODE)
        os.chmod(temporary, DIRECTORY_MODE)  # mkdtemp makes it 0700
        fsync_directory(temporary)
        aside = None
        if target.exists():
            aside = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
            os.replace(target, aside / target.name)
        os.replace(temporary, target)
        fsync_directory(target.parent, files=False)
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)
    finally:
        if temporary.exists():
            shutil.rmtree(temporary, ignore_errors=True)


def restore_directory(target: Path) -> bool:
    """Put back a folder that :func:`atomic_directory` had renamed aside when a kill stopped it before the new folder
    took its place (the one window of its swap). Returns whether it put one back.

    :param target: the folder ``atomic_directory`` was replacing
    """
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists():
        return False
    for aside in sorted(target.parent.glob(f".{target.name}.old.*")):
        if (aside / target.name).is_dir():
            os.replace(aside / target.name, target)
            fsync_directory(target.parent, files=False)
            shutil.rmtree(aside, ignore_errors=True)
            return True
    return False


#: The most bytes a file the package reads (a model file, a normaliser's arrays, an ONNX graph) may hold or inflate to,
#: and the most any one array or tensor it declares may take: far above any policy the package trains (a shipped model
#: file inflates to about 2 MB), far below what would exhaust a machine's memory.
MAX_FILE_BYTES = 1 << 30


def oversized_entry(archive: zipfile.ZipFile) -> str | None:
    """What is wrong with a zip file whose entries declare more than :data:`MAX_FILE_BYTES` inflated (a zip bomb), or
    ``None``. ``zipfile`` reads no more than an entry declares, so checking the declared sizes before reading any entry
    bounds what reading takes.

    :param archive: the open file
    """
    total = 0
    for entry in archive.infolist():
        total += entry.file_size
        if total > MAX_FILE_BYTES:
            return (
                f"its entry {entry.filename!r} inflates to {entry.file_size} bytes, beyond the limit of "
                f"{MAX_FILE_BYTES} bytes for a whole file"
            )
    return None


def _overdeclared_array(archive: zipfile.ZipFile) -> str | None:
    """What is wrong with a ``.npz`` file one of whose arrays declares more bytes than its entry holds (an ``.npy``
    header can declare 10^10 floats in a few bytes, and numpy allocates what it declares before reading), or ``None``.
    """
    for entry in archive.infolist():
        with archive.open(entry) as stream:
            version = np.lib.format.read_magic(stream)
            header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = header(stream)
        if (declared := math.prod(shape) * dtype.itemsize) > entry.file_size:
            return f"its array {entry.filename!r} declares {declared} bytes in an entry of {entry.file_size}"
    return None


def read_arrays(path: Path, what: str, keys: Collection[str] = ()) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file at ``path``.

    :param path: the file
    :param what: what the file should be, for the message (e.g. ``"a normaliser file"``)
    :param keys: arrays the file must hold
    :raises FileNotFoundError: no file at ``path``
    :raises ValueError: the file is empty, cut short, not a ``.npz`` file, or lacks one of ``keys``
    """
    if not path.is_file():
        raise FileNotFoundError(f"no file {path} ({what})")
    try:
        with zipfile.ZipFile(path) as archive:
            problem = oversized_entry(archive) or _overdeclared_array(archive)
        if problem is None:  # what it declares fits: numpy may allocate it
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
    except (zipfile.BadZipFile, EOFError, ValueError, OSError) as error:
        reason = str(error) or type(error).__name__
        raise ValueError(f"{path} is not {what} (empty or damaged: {reason})") from None
    if problem is not None:
        raise ValueError(f"{path} is not {what}: {problem}")
    missing = [key for key in keys if key not in arrays]
    if missing:
        raise ValueError(f"{path} is not {what}: it lacks {missing}")
    return arrays


def fsync_directory(folder: Path, files: bool = True) -> None:
    """Flush a folder (and, with ``files``, the files directly in it) to disk."""
    if files:
        for path in folder.iterdir():
            if path.is_file():
                with open(path, "rb") as stream:
                    os.fsync(stream.fileno())
    handle = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


def read_json(path: str | os.PathLike[str]) -> object:
    """The JSON value in the file ``path``.

    :raises ValueError: the file is not UTF-8 JSON (a write cut short, an edit), naming the file
    :raises FileNotFoundError: there is no such file
    """
    try:
        return json.loads(Path(path).read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path} is damaged (not JSON: {error})") from None


def holds_files(folder: Path) -> bool:
    """Whether ``folder`` is a file, or a folder holding anything but a lock file (one a killed process left counts
    as nothing)."""
    return folder.exists() and (not folder.is_dir() or any(path.name != LOCK_FILE for path in folder.iterdir()))


@contextlib.contextmanager
def folder_lock(folder: Path, what: str = "folder", wait: float = 0.0, remove: bool = False) -> Iterator[None]:
    """Hold an exclusive lock on ``folder`` (created if needed) while the block runs, through ``folder/.lock``.

    The operating system drops the lock when the process ends, however it ends, so a killed process never leaves its
    folder locked. The file keeps the holder's process id for the message others get.

    :param folder: the folder to lock
    :param what: what the folder is, for the error message (e.g. ``"run folder"``)
    :param wait: seconds to wait for another holder to let go before giving up
    :param remove: delete the lock file when letting go (for folders that should hold only what is written in them)
    :raises RuntimeError: another process holds the lock (still, after ``wait`` seconds)
    """
    check_writable(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover
        yield
        return
    path = folder / LOCK_FILE
    deadline = time.monotonic() + wait
    while (stream := _try_lock(path, f"{what} {folder}")) is None:
        if time.monotonic() >= deadline:
            holder = _lock_holder(path)
            raise RuntimeError(f"{what} {folder} is in use by another process (pid {holder}); wait for it to end")
        time.sleep(0.01)
    with stream:
        stream.seek(0)
        stream.truncate()
        stream.write(str(os.getpid()))
        stream.flush()
        try:
            yield
        finally:
            if remove:
                path.unlink(missing_ok=True)
            fcntl.flock(stream.fileno(), fcntl.LOCK_UN)


def _try_lock(path: Path, where: str) -> IO[str] | None:
    """The open lock file ``path``, locked, or ``None`` if another holds it. A lock taken on a file that a holder
    deleted (see ``remove`` of :func:`folder_lock`) before letting go is let go and taken again on the new file.

    The lock file is opened without following a symbolic link, and only a regular file is taken: a planted
    ``.lock`` link (in a folder someone sent) must never truncate the file it points to.

    :raises RuntimeError: ``path`` is a symbolic link or not a regular file (``where`` names the folder)
    """
    while True:
        try:
            handle = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, FILE_MODE)
        except OSError as error:
            if error.errno == errno.ELOOP:
                raise RuntimeError(f"{where}: its {LOCK_FILE} is a symbolic link; remove it") from None
            if error.errno == errno.EISDIR:
                raise RuntimeError(f"{where}: its {LOCK_FILE} is not a regular file; remove it") from None
            raise
        if not stat.S_ISREG(os.fstat(handle).st_mode):
            os.close(handle)
            raise RuntimeError(f"{where}: its {LOCK_FILE} is not a regular file; remove it")
        stream = os.fdopen(handle, "r+")
        try:
            fcntl.flock(stream.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            stream.close()
            if error.errno not in (errno.EAGAIN, errno.EACCES, errno.EWOULDBLOCK):
                raise
            return None
        with contextlib.suppress(FileNotFoundError):
            if os.stat(path).st_ino == os.fstat(stream.fileno()).st_ino:
                return stream
        stream.close()  # the file was deleted under this lock: try the one now at path


def _lock_holder(path: Path) -> str:
    """The process id a lock file names, or ``"unknown"``."""
    try:
        return path.read_text().strip() or "unknown"
    except OSError:
        return "unknown"

"""Atomic file writes (a reader never sees a half-written file), a run folder held for one run
at a time (a killed run's temporaries removed by the next), and what a rerun into a run folder
reads of the earlier run there to remove what it would leave stale."""

from __future__ import annotations

import contextlib
import errno
import io
import json
import math
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "MARK",
    "atomic_dir",
    "atomic_path",
    "check_space",
    "earlier_summary",
    "held",
    "remove_stale",
    "remove_temporaries",
    "staged",
    "write_json",
    "write_npz",
    "write_text",
    "write_torch",
]


#: what ends the name of every temporary file or folder irc writes (before a format's extension
#: some writers insist on), so that a later run tells a killed run's from the user's files
MARK = ".irc-tmp"
#: a temporary's whole name: ``.summary.json.k2j4_a9x.irc-tmp``, ``.staged.q0a1b2c3.irc-tmp``,
#: ``.a.csv.k2j4_a9x.irc-tmp.csv`` (``mkstemp``'s and ``mkdtemp``'s 8 random characters)
_TEMPORARY = re.compile(r"\..+\.[a-z0-9_]{8}" + re.escape(MARK) + r"(\.npz|\.csv|\.csv\.gz|\.nwb)?")


@contextmanager
def atomic_path(path: str | Path, extension: str = "") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; renamed onto ``path`` only if the block succeeds.

    ``extension`` ends the temporary name (some writers insist on their format's extension).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=MARK + extension)
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp makes the file private (0600); give it the mode a plain open() would
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextmanager
def atomic_dir(path: str | Path) -> Iterator[Path]:
    """Yield an empty temporary folder beside ``path``; it replaces ``path`` only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=MARK))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp's is private (0700), mkdir's is not
        _move(tmp, path)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)


@contextmanager
def staged(folder: str | Path) -> Iterator[Path]:
    """Yield an empty temporary folder inside ``folder``; each file or folder written there
    moves into ``folder`` (replacing its namesake) only if the whole block succeeds, so an
    interrupted run leaves the set of files the run before it wrote, not a mixture of both.
    A ``summary.json`` moves last: where it is the new run's, everything else is too."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=folder, prefix=".staged.", suffix=MARK))
    try:
        yield tmp
        for entry in sorted(tmp.iterdir(), key=lambda e: (e.name == "summary.json", e.name)):
            _move(entry, folder / entry.name)
    finally:
        shutil.rmtree(tmp)


@contextmanager
def held(folder: str | Path, field: str = "--out") -> Iterator[Path]:
    """Hold ``folder`` for one run, made where it is not: a second run into it meanwhile is
    refused (both would write their files there, the last summary winning over a mixture),
    and the temporaries of a run killed before its cleanup (``kill -9``, a node lost) are
    removed from it and its ``stages/``, no run being left to own them; only names irc gives
    its temporaries (:data:`MARK`) are. Folders made here and left empty are removed.

    The hold is an advisory ``flock`` of the folder, released with the process however it
    ends. Where the file system has none (Windows) nothing is held or removed; where its
    locks are local to each machine (some network mounts), runs on two machines are not
    kept apart."""
    folder = Path(folder)
    made = [p for p in (folder, *folder.parents) if not p.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder, os.O_RDONLY)
    try:
        if _lock(fd, folder, field):
            for parent in (folder, folder / "stages"):
                remove_temporaries(parent)
        yield folder
    finally:
        os.close(fd)  # releases the lock
        for path in made:  # the deepest first
            if not path.is_dir() or any(path.iterdir()):
                break
            path.rmdir()


def _lock(fd: int, folder: Path, field: str) -> bool:
    """Take ``folder``'s exclusive lock; refuse it held by another process, ``False`` where
    locks are not supported."""
    if sys.platform == "win32":
        return False
    import fcntl

    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as error:
        if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return False  # e.g. ENOLCK: a file system without locks
        raise ValueError(
            f"{field}: {folder} is in use by another irc run (its files would mix with this "
            "run's); wait for it to end, or choose another folder"
        ) from None
    return True


def remove_temporaries(folder: Path) -> None:
    """Remove irc's temporaries in ``folder`` (none where it is not a folder): those of a
    killed run, where no run of this folder is writing."""
    if not folder.is_dir():
        return
    for path in folder.iterdir():
        if not _TEMPORARY.fullmatch(path.name):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):  # another user's, say: theirs to remove
                path.unlink()


def _move(source: Path, path: Path) -> None:
    """Rename ``source`` onto ``path``. A folder cannot be renamed over a non-empty one (nor a
    file over a folder), so such a ``path`` is first moved aside and removed once ``source``
    is in place."""
    old = None
    if path.exists() and (source.is_dir() or path.is_dir()):
        old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=MARK))
        os.replace(path, old / path.name)
    os.replace(source, path)
    if old is not None:
        shutil.rmtree(old)


def check_space(folder: str | Path, nbytes: int, what: str) -> None:
    """Refuse to write ``nbytes`` into ``folder`` where its file system has less free: a
    memmap written past a full disk ends the process with SIGBUS, not an error."""
    free = shutil.disk_usage(folder).free
    if nbytes > free:
        raise OSError(
            errno.ENOSPC,
            f"No space left on device: {what} needs {_megabytes(nbytes)}, its file system has "
            f"{_megabytes(free)} free",
        )


def _megabytes(nbytes: int) -> str:
    """A size for a message, in MB to 3 significant digits."""
    return f"{nbytes / 1e6:.3g} MB"


def _umask() -> int:
    """The process's file-creation mask (read by setting it, then restoring it)."""
    umask = os.umask(0)
    os.umask(umask)
    return umask


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` into ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_json(path: str | Path, data: object) -> Path:
    """Write ``data`` as strict JSON: a number that is not finite (the infinite sd of a
    parameter the data do not identify) becomes ``null``, which every JSON reader accepts."""
    return write_text(path, json.dumps(_finite(data), indent=2, allow_nan=False) + "\n")


def write_npz(path: str | Path, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write ``arrays`` into an ``.npz`` archive (plain arrays: it reads back without pickle)."""
    with atomic_path(path, extension=".npz") as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    return Path(path)


def write_torch(path: str | Path, data: object) -> Path:
    """Write ``data`` by ``torch.save`` atomically. It is serialised in memory first: torch's
    own writer reports a full disk as a RuntimeError of its C++ stream, a file write as the
    ``OSError`` (no space left on device) that it is."""
    buffer = io.BytesIO()
    torch.save(data, buffer)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getbuffer())
    return Path(path)


def _finite(value: object) -> object:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(item) for item in value]
    return value


def earlier_summary(out: Path, command: str) -> dict | None:
    """The ``summary.json`` an earlier ``irc <command>`` left in ``out`` (``None`` where no such
    run did: then nothing there is that run's to remove)."""
    try:
        summary = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(summary, dict) or summary.get("command") != command:
        return None
    return summary


def remove_stale(out: Path, names: Iterable[str], kept: set[str]) -> None:
    """Remove the files (or memmap folders) ``names`` an earlier run wrote in ``out`` that this
    run did not write again (``kept``)."""
    for name in set(names) - kept:
        if Path(name).name != name:  # only the run's own files, never a path out of it
            continue
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()

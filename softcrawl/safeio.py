"""Reading files a user hands us, and writing results without losing what was there.

Every file softcrawl reads from a user's folder (run configs, calibrations, rig files, recorded
logs, ground-truth tables) goes through :func:`read_text` or one of the loaders built on it:

- only a regular file is read (after symlinks are followed): a device (``/dev/zero``), a FIFO or
  a folder is refused with :class:`UnsafeFileError`, so a crafted link cannot hang the process or
  fill its memory;
- at most ``max_bytes`` are read; a larger file is refused, not truncated;
- JSON and TOML nested deeper than ``max_depth`` are refused with one line, not a
  ``RecursionError`` and a traceback of thousands of lines.

Results are written with :func:`atomic_write_text` (a temporary file in the same folder, flushed
and ``fsync``-ed, then renamed over the target): a reader never sees half a file, and an
interrupted write leaves the old file whole. A symlink at the target is replaced by the new
file, never written through.

A folder that a command writes (a training run, a ground truth, an output folder) is held with
:func:`folder_lock`: one writer at a time, the others refused at once with one line naming the
holder (process, host, command).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
import sys
import tempfile
import tomllib
from collections.abc import Iterator
from pathlib import Path

#: Default size limit of a file read by softcrawl (bytes). Run configs, calibrations and rig
#: files are a few kB; the largest tables (ground truth of 6,972 designs, a deploy log of
#: an hour at 100 Hz) are tens of MB.
MAX_BYTES = 256 * 1024 * 1024
#: Default nesting limit of JSON and TOML documents. softcrawl's own files nest at most 6 deep.
MAX_DEPTH = 64


class UnsafeFileError(ValueError):
    """A file that must not be read: not a regular file, too large, too deeply nested, or not
    valid text. A ``ValueError``, so the CLI reports it as bad input in one line."""


def _check_regular(path: Path, st: os.stat_result, max_bytes: int) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise UnsafeFileError(f"{path}: not a regular file")
    if st.st_size > max_bytes:
        raise UnsafeFileError(f"{path}: {st.st_size} bytes, more than the {max_bytes} allowed")


def check_regular_file(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> Path:
    """``path`` as a :class:`~pathlib.Path` once it is known to be a regular file (symlinks
    followed) of at most ``max_bytes`` bytes: for files a library opens by name (videos read
    by OpenCV), where :func:`read_bytes` cannot be used.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        UnsafeFileError: ``path`` is not a regular file, or holds more than ``max_bytes`` bytes.
    """
    path = Path(path)
    _check_regular(path, os.stat(path), max_bytes)
    return path


def read_bytes(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (symlinks followed), at most ``max_bytes``.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        UnsafeFileError: ``path`` is not a regular file, or holds more than ``max_bytes`` bytes.
    """
    path = Path(path)
    # O_NONBLOCK: opening a FIFO must not block before fstat can refuse it
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        _check_regular(path, os.fstat(fd), max_bytes)
        chunks, total = [], 0
        while True:
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
            if total > max_bytes:  # grew while being read
                raise UnsafeFileError(f"{path}: more than the {max_bytes} bytes allowed")
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_text(path: str | os.PathLike, max_bytes: int = MAX_BYTES) -> str:
    """The UTF-8 text of the regular file ``path`` (a leading byte-order mark, as spreadsheet
    programs write, is dropped).

    Raises:
        FileNotFoundError, UnsafeFileError: as :func:`read_bytes`; UnsafeFileError also for
            bytes that are not UTF-8.
    """
    try:
        return read_bytes(path, max_bytes).decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise UnsafeFileError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def check_depth(obj, max_depth: int = MAX_DEPTH, where: str = "document") -> None:
    """Raise :class:`UnsafeFileError` if the parsed JSON/TOML value ``obj`` nests lists and
    dicts deeper than ``max_depth`` (iterative: a deep value cannot exhaust the stack here)."""
    stack = [(obj, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict):
            children = value.values()
        elif isinstance(value, list):
            children = value
        else:
            continue
        if depth > max_depth:
            raise UnsafeFileError(f"{where}: nested more than {max_depth} levels deep")
        stack.extend((c, depth + 1) for c in children)


def _parse(parse, text: str, where: str, max_depth: int, kind: str):
    try:
        value = parse(text)
    except RecursionError:
        raise UnsafeFileError(f"{where}: nested too deeply to parse") from None
    except (ValueError, tomllib.TOMLDecodeError) as e:
        raise UnsafeFileError(f"{where}: not valid {kind} ({str(e).splitlines()[0]})") from None
    check_depth(value, max_depth, where)
    return value


def loads_json(text: str, where: str = "JSON", max_depth: int = MAX_DEPTH, allow_nan: bool = False):
    """Parse JSON text, refusing deep nesting and (unless ``allow_nan``, for a file softcrawl
    wrote with NaN in it) non-standard constants (``NaN``, ``Infinity``) with
    :class:`UnsafeFileError` naming ``where`` (a file, or file:line)."""

    def parse(s):
        def constant(name):
            raise ValueError(f"{name} is not a JSON number")

        return json.loads(s) if allow_nan else json.loads(s, parse_constant=constant)

    return _parse(parse, text, where, max_depth, "JSON")


def load_json(path: str | os.PathLike, max_bytes: int = MAX_BYTES, max_depth: int = MAX_DEPTH,
              allow_nan: bool = False):
    """The JSON value in the regular file ``path`` (``allow_nan``: as :func:`loads_json`).

    Raises:
        FileNotFoundError: no such file.
        UnsafeFileError: not a regular file, too large, not UTF-8, not JSON, or nested too deeply.
    """
    return loads_json(read_text(path, max_bytes), str(path), max_depth, allow_nan)


def load_toml(path: str | os.PathLike, max_bytes: int = 16 * 1024 * 1024, max_depth: int = MAX_DEPTH) -> dict:
    """The TOML document in the regular file ``path`` (a dict).

    Raises:
        FileNotFoundError: no such file.
        UnsafeFileError: not a regular file, too large, not UTF-8, not TOML, or nested too deeply.
    """
    return _parse(tomllib.loads, read_text(path, max_bytes), str(path), max_depth, "TOML")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Replace ``path`` by a file holding ``text`` (UTF-8) atomically: written to a temporary
    file in the same folder, flushed to disk, then renamed over ``path``. A symlink at ``path``
    is replaced, not followed.

    Raises:
        OSError: the folder cannot be written (the old file, if any, is left as it was).
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


class FolderLockedError(ValueError):
    """Another process holds the lock of a folder (:func:`folder_lock`); the message names it."""


def _holder(fd: int) -> str:
    """The holder recorded in an open lock file (what :func:`folder_lock` writes): ``process
    PID on HOST (COMMAND)``, or what of it is there (a bare pid, as earlier versions wrote)."""
    text = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip()
    try:
        info = json.loads(text)
    except ValueError:
        info = None
    if not isinstance(info, dict):
        info = {"pid": text.split()[0] if text.split() else ""}
    pid, host, command = (" ".join(str(info.get(k, "")).split())[:200] for k in ("pid", "host", "command"))
    return f"process {pid or '?'}" + (f" on {host}" if host else "") + (f" ({command})" if command else "")


@contextlib.contextmanager
def folder_lock(lock: str | os.PathLike, what: str | os.PathLike) -> Iterator[None]:
    """Hold the exclusive advisory lock (``fcntl.flock``) of the lock file ``lock`` (created if
    missing, in a folder that must exist) while the body runs, for the folder ``what`` names.

    The file records the holder (``{"pid", "host", "command"}``) and is removed when the body
    ends. The kernel releases the lock of a process that dies, so a killed holder leaves at
    most a file that the next run locks as if it were new (a file removed by its holder while
    being opened is opened again). Not re-entrant: a second lock of the same file in the same
    process is refused like any other.

    Raises:
        FolderLockedError: another process (or another lock in this one) holds it; nothing
            was written.
        OSError: the lock file cannot be created (a read-only or missing folder), or is a
            symbolic link.
    """
    import fcntl

    lock = Path(lock)
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _holder(fd)
            os.close(fd)
            raise FolderLockedError(f"{what} is being written by another softcrawl command: {holder}; wait for it "
                                    f"to finish (or stop it), or use another folder (lock file {lock})") from None
        try:
            same = os.stat(lock, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # its holder removed it as we opened it: open the new one
    try:
        command = " ".join(Path(a).name if i < 2 and os.sep in a else a for i, a in enumerate(sys.orig_argv))
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "command": command}) +
                       "\n").encode(), 0)
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)  # while still held: a process waiting on this file opens the new one
        os.close(fd)  # releases the lock

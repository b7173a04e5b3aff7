"""Atomic file writes: every file cr_nlp writes for a user (results, CSVs, reports, figures,
robot and scene files) and every cache entry goes through ``atomic_open`` or
``write_atomic``.

The data goes into a hidden temporary file beside the target (``.<name>.<random>.tmp``),
is flushed and fsynced, and is renamed over the target with ``os.replace``. A reader sees
the old complete file or the new complete one, never part of one; a writer killed at any
moment leaves the old file (or none) in place, at worst beside a hidden temporary file.
A writer that raises removes its temporary file. Standard library only: ``import cr_nlp``
stays light.

``read_json_file`` is the one reader of the JSON input files (robots, scenes, paths,
targets, problems, statics cases, results): UTF-8 text, parsed, with one ``ValueError``
saying what is wrong, which each loader words with the file's name and its error type.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "w", newline: str | None = None,
                encoding: str | None = None, sync: bool = True) -> Iterator[IO[Any]]:
    """Open a handle whose content replaces ``path`` when the ``with`` block ends.

    ``mode`` is ``"w"`` (text; ``newline`` and ``encoding`` as for ``open``) or ``"wb"``.
    On a normal exit the handle is flushed, fsynced (``sync``; ``False`` skips it, for a
    file whose loss in a power cut costs nothing) and renamed over ``path``; on an
    exception the temporary file is removed, ``path`` is left as it was, and the exception
    propagates. The new file gets the old file's permission bits, or the usual ones for a
    new file (0o666 less the umask). A symbolic link at ``path`` is followed: its target is
    replaced. The folder must exist: a missing one raises ``FileNotFoundError`` naming it.
    """
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: mode must be 'w' or 'wb', got {mode!r}")
    target = Path(os.path.realpath(path))
    fd, temporary = _create_beside(target)
    try:
        if hasattr(os, "fchmod"):
            with contextlib.suppress(OSError):  # keep the permission bits of the file replaced
                os.fchmod(fd, os.stat(target).st_mode & 0o7777)
        handle = os.fdopen(fd, mode, newline=newline, encoding=encoding)
    except BaseException:
        os.close(fd)
        os.unlink(temporary)
        raise
    try:
        with handle:
            yield handle
            handle.flush()
            if sync:
                os.fsync(handle.fileno())
        os.replace(temporary, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    if sync:
        _sync_folder(target.parent)


def write_atomic(path: str | os.PathLike, data: bytes, sync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (``atomic_open`` in binary mode)."""
    with atomic_open(path, "wb", sync=sync) as handle:
        handle.write(data)


def _create_beside(target: Path) -> tuple[int, str]:
    """A new hidden file in ``target``'s folder, opened for writing: (descriptor, path).
    Created with mode 0o666 so that the umask applies as for ``open(path, "w")``."""
    for _ in range(100):
        temporary = str(target.parent / f".{target.name}.{os.urandom(6).hex()}.tmp")
        try:
            return os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), temporary
        except FileExistsError:
            continue
        except FileNotFoundError:
            if not target.parent.is_dir():
                raise FileNotFoundError(errno.ENOENT, f"cannot write {target.name}: no such "
                                        f"folder", str(target.parent)) from None
            raise
    raise FileExistsError(errno.EEXIST, "no free temporary name beside", str(target))


def _sync_folder(folder: Path) -> None:
    """fsync a folder, so that a rename in it survives a power cut (where supported)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class UnreadableJSON(ValueError):
    """A file that is not UTF-8 JSON text; the message says what is wrong, not which file
    (the loader that reads it names the file)."""


class InputFileError(ValueError):
    """An input file cr_nlp reads (robot, scene, targets, problems, path, recording,
    result) that is missing, unreadable or not of its format; the message names the file
    and what is wrong. The readers' own error types (``ModelFileError``,
    ``ResultFileError``, ``DataFileError``) are kinds of it, so one ``except`` catches every
    bad input file."""


def read_json_or(path: str | os.PathLike, fail: Callable[[str], Exception]) -> Any:
    """``read_json_file(path)`` with each failure raised as ``fail(reason)``, the reason
    being "file not found", "cannot read: …" or "not UTF-8 text: …" / "not valid JSON:
    …": the one mapping every reader of a JSON input uses, each with its own error type
    and message shape."""
    try:
        return read_json_file(path)
    except FileNotFoundError:
        raise fail("file not found") from None
    except OSError as exc:
        raise fail(f"cannot read: {exc}") from None
    except UnreadableJSON as exc:
        raise fail(str(exc)) from None


def read_json_file(path: str | os.PathLike) -> Any:
    """The parsed content of a JSON file (UTF-8 text).

    Raises:
        OSError: the file cannot be read (``FileNotFoundError`` for a missing one).
        UnreadableJSON: "not UTF-8 text: …" or "not valid JSON: …" (with the line and
            column), never a raw ``UnicodeDecodeError`` or ``JSONDecodeError``.
    """
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UnreadableJSON(f"not UTF-8 text: byte 0x{data[exc.start]:02x} at position "
                             f"{exc.start}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise UnreadableJSON(f"not valid JSON: {exc}") from None
    except RecursionError:
        raise UnreadableJSON("not valid JSON: nested too deeply") from None

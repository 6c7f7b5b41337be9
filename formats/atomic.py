"""Atomic outputs: write to a temporary name beside the target, rename when complete.

A reader of the target path sees either the previous complete file (or nothing) or the new complete
file, never a half-written one; a failure or an interrupt removes the temporary.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import glob
import json
import os
import shutil
import signal
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from formats.outputs import MARKER, OutputError, directory_owner, mark_written, resolve_output


class _OutputSet:
    """Finished temporaries waiting to be renamed together (see :func:`output_set`)."""

    def __init__(self) -> None:
        self.pending: list[tuple[Path, Path]] = []  # (temporary, target)
        self.created: list[Path] = []  # directories made for the outputs, parents first


_OUTPUT_SET: contextvars.ContextVar[_OutputSet | None] = contextvars.ContextVar("relpoint_output_set", default=None)


@contextlib.contextmanager
def output_set() -> Iterator[None]:
    """Make the files written by :func:`atomic_path` in the body appear together, or not at all.

    Each finished file waits under its temporary name; when the body completes, all are renamed to their
    targets with SIGINT and SIGTERM held back, so an interrupt lands before the first rename (nothing
    is left: the temporaries and the directories made for them are removed) or after the last one (an
    :class:`~relpoint.errors.Interrupted` naming what was written). A command that writes several
    outputs (``evaluate --json --csv --plot``) thus never leaves a part of them.
    """
    from relpoint.errors import Interrupted

    outputs = _OutputSet()
    token = _OUTPUT_SET.set(outputs)
    try:
        yield
    except BaseException:
        _discard(outputs)
        raise
    finally:
        _OUTPUT_SET.reset(token)
    caught: list[int] = []
    previous = _defer_interrupts(caught)
    try:
        for tmp, target in outputs.pending:
            os.replace(tmp, target)
    except BaseException:
        _discard(outputs)  # a rename refused: the temporaries not yet renamed
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if caught:
        written = ", ".join(str(target) for _, target in outputs.pending)
        raise Interrupted(f"interrupted after every output was written ({written})")


def _discard(outputs: _OutputSet) -> None:
    for tmp, _ in outputs.pending:
        tmp.unlink(missing_ok=True)
    for directory in reversed(outputs.created):
        with contextlib.suppress(OSError):
            directory.rmdir()  # only if still empty


def _defer_interrupts(caught: list[int]) -> dict[int, Any]:
    """Note SIGINT/SIGTERM in ``caught`` instead of acting on them; returns the handlers to put back.

    A Python-level handler rather than a signal mask: the signal may land on any thread (BLAS threads
    among them), while Python handlers always run in the main thread. Ignored signals stay ignored.
    """
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous = {}
    for signum in (signal.SIGINT, signal.SIGTERM):
        handler = signal.getsignal(signum)
        if handler in (signal.SIG_IGN, None):
            continue
        previous[signum] = handler
        signal.signal(signum, lambda number, frame: caught.append(number))
    return previous


def _make_parent(directory: Path, outputs: _OutputSet | None) -> None:
    """``mkdir -p directory``, noting for an output set the directories it made (removed on an interrupt)."""
    missing = []
    parent = directory
    while not parent.exists() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    directory.mkdir(parents=True, exist_ok=True)
    if outputs is not None:
        outputs.created.extend(reversed(missing))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; on success rename it to ``path``.

    The temporary is removed if the body raises (including ``KeyboardInterrupt``). A symlink ``path``
    is written through. A file-system refusal (full disk, read-only) is an
    :class:`~formats.outputs.OutputError` naming ``path``. Inside :func:`output_set` the rename waits
    for the end of the set.
    """
    target = resolve_output(path)
    outputs = _OUTPUT_SET.get()
    try:
        _make_parent(target.parent, outputs)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        os.close(fd)
    except OSError as error:
        raise OutputError(f"cannot write {path}: {error.strerror or error}", "choose a writable place") from None
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        if outputs is not None:
            outputs.pending.append((tmp, target))
        else:
            os.replace(tmp, target)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        if not _is_write_error(error, tmp):
            raise
        raise OutputError(
            f"cannot write {path}: {error.strerror or error}", "free some space or write elsewhere"
        ) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike[str], command: str = "run") -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it replaces ``path`` as a whole.

    The finished directory gets the marker file (:data:`formats.outputs.MARKER`) naming ``command``
    and every file written, which is what lets a later run replace it. An existing ``path`` is
    replaced only if it is itself a relpoint output (callers check the finer rules first with
    :func:`formats.outputs.check_output_directory`); it is moved aside, and deleted only once the
    new directory is in place (put back if that fails). An existing empty directory (the working
    directory, a mount point) is filled in place instead, so whoever holds it keeps seeing it. A
    symlink ``path`` is written through. A file-system refusal (full disk, read-only) is an
    :class:`~formats.outputs.OutputError` naming ``path``; nothing is left behind.
    """
    target = resolve_output(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    except OSError as error:
        raise OutputError(f"cannot write {path}: {error.strerror or error}", "choose a writable place") from None
    old: Path | None = None
    token = _OUTPUT_SET.set(None)  # the files inside are written at once; the directory is renamed as a whole
    try:
        try:
            yield tmp
        finally:
            _OUTPUT_SET.reset(token)
        files = sorted(entry.name for entry in tmp.iterdir())
        (tmp / MARKER).write_text(json.dumps({"command": command, "files": files}, indent=1) + "\n", encoding="utf-8")
        os.chmod(tmp, 0o755)
        if target.is_dir() and (not any(target.iterdir()) or _in_use(target)):
            _clear(target)
            _fill(target, tmp)
            return
        if target.exists():
            if not target.is_dir() or directory_owner(target) is None:
                raise OutputError(f"{path} exists and is not a relpoint output", "choose another output directory")
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
            os.replace(target, old / target.name)
        try:
            os.replace(tmp, target)
        except BaseException:
            if old is not None and (old / target.name).exists():
                os.replace(old / target.name, target)
            raise
    except OutputError as error:  # from a file written inside: name the directory the user gave
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(error.message.replace(str(tmp), str(path)), error.hint) from None
    except OSError as error:
        shutil.rmtree(tmp, ignore_errors=True)
        if not _is_write_error(error, tmp):
            raise
        raise OutputError(
            f"cannot write {path}: {error.strerror or error}", "free some space or write elsewhere"
        ) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def remove_temporaries(path: str | os.PathLike[str]) -> int:
    """Remove what :func:`atomic_path` and :func:`atomic_directory` leave beside ``path`` when their
    process is killed before it can unwind: ``.NAME.*.tmp`` files and ``.NAME.*.partial`` directories.

    For a caller whose workers were killed (a cancelled batch). The ``.NAME.*.old`` directory, which
    holds a previous output while it is being replaced, is kept. Returns how many were removed.
    """
    target = resolve_output(path)
    removed = 0
    name = glob.escape(target.name)  # job names may hold "[" from a grid value
    for pattern in (f".{name}.*.tmp", f".{name}.*.partial"):
        for leftover in target.parent.glob(pattern):
            if leftover.is_dir() and not leftover.is_symlink():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)
            removed += 1
    return removed


def _is_write_error(error: OSError, tmp: Path) -> bool:
    """Whether an error met while a body wrote into ``tmp`` is the output's (not an input's)."""
    if error.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EFBIG):
        return True
    return error.filename is None or str(error.filename).startswith(str(tmp))


def _in_use(target: Path) -> bool:
    """Whether ``target`` must stay the same directory: the working directory, or a mount point."""
    return target == Path.cwd().resolve() or os.path.ismount(target)


def _clear(target: Path) -> None:
    """Remove a previous relpoint output's entries from ``target`` (checked to be relpoint's by the caller)."""
    owner = directory_owner(target)
    if owner is None:
        if any(target.iterdir()):
            raise OutputError(f"{target} is not a relpoint output", "choose another output directory")
        return
    for name in [*sorted(owner[1]), MARKER]:
        entry = target / name
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        elif entry.exists() or entry.is_symlink():
            entry.unlink()


def _fill(target: Path, tmp: Path) -> None:
    """Move every entry of ``tmp`` into the empty directory ``target``; on failure take them out again."""
    moved: list[Path] = []
    try:
        for entry in sorted(tmp.iterdir(), key=lambda e: e.name == MARKER):  # the marker last
            os.replace(entry, target / entry.name)
            moved.append(target / entry.name)
        tmp.rmdir()
    except BaseException:
        for entry in moved:
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike[str], text: str, *, mark: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically; ``mark``: record it as relpoint's
    (:func:`formats.outputs.mark_written`, for formats with no header to say so)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
        if mark:
            mark_written(tmp)

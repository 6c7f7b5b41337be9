"""Atomic outputs: write to a temporary name beside the target, rename when complete.

A reader of the target path sees either the previous complete file (or nothing) or the new complete
file, never a half-written one; a failure or an interrupt removes the temporary.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from formats.outputs import MARKER, OutputError, directory_owner, resolve_output


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the target's directory; on success rename it to ``path``.

    The temporary is removed if the body raises (including ``KeyboardInterrupt``). A symlink ``path``
    is written through. A file-system refusal (full disk, read-only) is an
    :class:`~formats.outputs.OutputError` naming ``path``.
    """
    target = resolve_output(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        os.close(fd)
    except OSError as error:
        raise OutputError(f"cannot write {path}: {error.strerror or error}", "choose a writable place") from None
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
    except OSError as error:
        tmp.unlink(missing_ok=True)
        if not _is_write_error(error, tmp):
            raise
        raise OutputError(f"cannot write {path}: {error.strerror or error}", "free some space or write elsewhere") from None
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
    try:
        yield tmp
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
        raise OutputError(f"cannot write {path}: {error.strerror or error}", "free some space or write elsewhere") from None
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


def write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")

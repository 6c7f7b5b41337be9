"""Atomic outputs: write to a temporary name beside the target, rename when complete.

A reader of the target path sees either the previous complete file (or nothing) or the new complete
file, never a half-written one; a failure or an interrupt removes the temporary.
"""

from __future__ import annotations

import contextlib
import errno
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

    The temporary is removed if the body raises (including ``KeyboardInterrupt``).
    """
    target = resolve_output(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
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
    new directory is in place (put back if that fails). A symlink ``path`` is written through.
    """
    target = resolve_output(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".partial", dir=target.parent))
    old: Path | None = None
    try:
        yield tmp
        files = sorted(entry.name for entry in tmp.iterdir())
        (tmp / MARKER).write_text(
            json.dumps({"command": command, "files": files}, indent=1) + "\n", encoding="utf-8"
        )
        os.chmod(tmp, 0o755)
        if target.exists():
            if not target.is_dir() or (any(target.iterdir()) and directory_owner(target) is None):
                raise OutputError(f"{path} exists and is not a relpoint output", "choose another output directory")
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".old", dir=target.parent))
            try:
                os.replace(target, old / target.name)
            except OSError as error:
                if error.errno not in (errno.EBUSY, errno.EXDEV, errno.EINVAL) or any(target.iterdir()):
                    raise
                # An empty directory that cannot move (a mount point, the working directory of
                # another process): fill it instead.
                old.rmdir()
                old = None
                for entry in tmp.iterdir():
                    os.replace(entry, target / entry.name)
                tmp.rmdir()
                return
        try:
            os.replace(tmp, target)
        except BaseException:
            if old is not None and (old / target.name).exists():
                os.replace(old / target.name, target)
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")

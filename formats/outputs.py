"""Where a command may write: the checks that keep relpoint from destroying a user's files.

Every output path goes through :func:`check_output_directory` or :func:`check_output_file` before any
work starts. The rules (README, "Outputs"):

- An output is never one of the command's inputs, and a directory output never contains one.
- An existing directory is replaced only when relpoint wrote it: it holds the marker file
  :data:`MARKER` (or, for outputs written before the marker existed, a relpoint ``run.json``) and
  nothing that relpoint did not write. An output of another relpoint command is replaced only with
  ``overwrite``. A directory of anything else is refused, ``overwrite`` or not.
- An existing file is replaced when relpoint recognisably wrote it (judged by its content, whatever its
  name: the header relpoint writes, or for KITTI and times files :func:`mark_written`'s record), or
  with ``overwrite``; never when it is one of the command's inputs.
- A symbolic link is written through (its target is replaced); a dangling one is refused.
- The place is writable: a probe file is made and removed before the work starts, so a read-only
  or missing destination fails at once, not after the run.

Each failure is a :class:`~relpoint.errors.UsageError` (exit 2) naming the path and the way out.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import math
import os
import re
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from formats.signatures import is_log, is_relpoint_result_zip
from relpoint.errors import InputError, UsageError

#: Name of the file that marks a directory as a relpoint output; JSON ``{"command", "files"}``.
MARKER = ".relpoint-output"

#: The files of a ``relpoint run`` output directory (:mod:`formats.run_output` writes them).
RUN_FILES = ("trajectory.tum", "trajectory.csv", "map.ply", "map.csv", "timing.csv", "run.json", "result.mcap")

#: Header lines of the CSV tables relpoint writes; a CSV file starting with one is relpoint's.
_CSV_HEADERS: set[str] = set()

#: Starts of CSV header lines whose columns vary (``relpoint compare`` tables); see :func:`register_csv_header`.
_CSV_HEADER_PREFIXES: set[str] = set()

_SNIFF_BYTES = 8192


class OutputError(UsageError):
    """An output path that cannot or must not be written (exit 2)."""


def register_csv_header(header: Iterable[str] | str) -> None:
    """Declare a CSV header line that relpoint writes, so its files are recognised as relpoint's."""
    _CSV_HEADERS.add(header if isinstance(header, str) else ",".join(header))


def register_csv_header_prefix(prefix: str) -> None:
    """Declare the start of CSV header lines that relpoint writes with varying further columns."""
    _CSV_HEADER_PREFIXES.add(prefix)


def shown_path(path: str | os.PathLike[str]) -> str:
    """``path`` as text that any UTF-8 writer accepts, for headers, titles and JSON: the bytes of a file name
    that are not UTF-8 appear as ``\\xNN`` (Python keeps them as lone surrogates, which no encoder takes)."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def resolve_output(path: str | os.PathLike[str]) -> Path:
    """The absolute path an output is written to: a symlink is followed; a dangling one is refused."""
    path = Path(path)
    if path.is_symlink():
        target = Path(os.path.realpath(path))
        if not target.exists() and not target.parent.is_dir():
            raise OutputError(f"{path} is a symbolic link to {target}, whose directory does not exist",
                              "remove the link or point it somewhere that exists")  # fmt: skip
        if not target.exists():
            raise OutputError(f"{path} is a dangling symbolic link (to {target})", "remove it or choose another output")
        return target
    return Path(os.path.abspath(path))


def _resolved_inputs(inputs: Iterable[str | os.PathLike[str] | None]) -> list[tuple[str, Path]]:
    return [(str(p), Path(os.path.realpath(p))) for p in inputs if p is not None and os.path.lexists(p)]


def _is_bag(path: Path) -> bool:
    """Whether ``path`` is a log directory (a rosbag2 bag): nothing may be written inside it."""
    return path.is_dir() and is_log(path)


def _refuse_inputs(shown: str | os.PathLike[str], target: Path, inputs: list[tuple[str, Path]], *, directory: bool):
    for name, resolved in inputs:
        if resolved == target:
            raise OutputError(
                f"output {shown} is the input {name}", "write to another path; relpoint never overwrites its input"
            )
        if directory and target in resolved.parents:
            raise OutputError(
                f"output directory {shown} contains the input {name}", "choose an output directory outside the input's"
            )
        if resolved in target.parents and _is_bag(resolved):  # a bag directory is an input as a whole
            raise OutputError(f"output {shown} is inside the input {name}", "write outside the input directory")


def _first_existing(path: Path) -> Path:
    while not path.exists():
        if path.parent == path:
            break
        path = path.parent
    return path


def probe_writable(directory: Path, shown: str | os.PathLike[str]) -> None:
    """Make and remove a file in ``directory`` (or its first existing ancestor); OutputError if refused."""
    where = _first_existing(directory)
    if not where.is_dir():
        raise OutputError(f"cannot write {shown}: {where} is not a directory", "choose another output path")
    try:
        fd, name = tempfile.mkstemp(prefix=".relpoint-probe.", dir=where)
        os.close(fd)
        os.unlink(name)
    except OSError as error:
        raise OutputError(f"cannot write {shown}: {error.strerror or error}", "choose a writable place") from None


def directory_owner(path: Path) -> tuple[str, set[str]] | None:
    """``(command, files)`` of a relpoint output directory, or None if relpoint did not write it."""
    marker = path / MARKER
    if marker.is_file():
        try:
            document = json.loads(marker.read_text(encoding="utf-8")[:1_000_000])
            return str(document["command"]), {str(f) for f in document["files"]}
        except (OSError, ValueError, KeyError, TypeError):
            return None
    run_json = path / "run.json"  # outputs written before the marker existed
    if run_json.is_file():
        try:
            document = json.loads(run_json.read_text(encoding="utf-8")[:10_000_000])
        except (OSError, ValueError):
            return None
        if isinstance(document, dict) and "relpoint_version" in document:
            return "run", {*RUN_FILES, "map_history.csv"}
    return None


def check_output_directory(
    path: str | os.PathLike[str],
    *,
    command: str,
    inputs: Iterable[str | os.PathLike[str] | None] = (),
    overwrite: bool = False,
) -> Path:
    """Check that ``path`` may be written as the output directory of ``relpoint COMMAND``; its resolved path.

    Raises :class:`OutputError` (exit 2) when it is or contains an input, is a file, holds anything
    relpoint did not write, holds another command's output without ``overwrite``, or is not writable.
    """
    target = resolve_output(path)
    _refuse_inputs(path, target, _resolved_inputs(inputs), directory=True)
    if target.exists():
        if not target.is_dir():
            raise OutputError(f"{path} exists and is not a directory", "choose another output directory")
        try:
            entries = sorted(entry.name for entry in target.iterdir())
        except OSError as error:
            raise OutputError(
                f"cannot read {path}: {error.strerror or error}", "choose another output directory"
            ) from None
        if entries:
            owner = directory_owner(target)
            if owner is None:
                raise OutputError(
                    f"{path} exists, is not empty and is not a relpoint output",
                    "choose a new or empty directory (relpoint never replaces what it did not write)",
                )
            owner_command, files = owner
            foreign = [name for name in entries if name not in files and name != MARKER]
            if foreign:
                raise OutputError(
                    f"{path} holds {foreign[0]!s}" + (f" and {len(foreign) - 1} more" if len(foreign) > 1 else "")
                    + ", which relpoint did not write",
                    "move it away or choose another output directory",
                )  # fmt: skip
            if owner_command != command and not overwrite:
                raise OutputError(
                    f"{path} holds the output of `relpoint {owner_command}`",
                    "pass --overwrite to replace it, or choose another output directory",
                )
    probe_writable(target.parent, path)
    return target


#: Extended attribute holding the SHA-256 of what relpoint wrote to a file whose format has no place for a
#: mark (KITTI poses, times files): see :func:`mark_written`.
WRITTEN_XATTR = "user.relpoint.sha256"

#: The first line of a TUM file relpoint writes (``# relpoint VERSION`` or ``# relpoint export of SOURCE``)
#: and of a ``relpoint compare`` text table; a comment that merely mentions relpoint does not match.
_TUM_FIRST_LINE = re.compile(rb"# relpoint (\d+\.\d+\S*|export of .*)")
_TUM_LEGEND = b"# timestamp tx ty tz qx qy qz qw"
_COMPARE_TEXT_FIRST_LINE = re.compile(rb"# relpoint compare: \d+ runs?")


def _sha256(path: Path) -> str | None:
    digest = hashlib.sha256()
    try:
        with path.open("rb") as stream:
            for block in iter(lambda: stream.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def mark_written(path: Path) -> None:
    """Record on ``path`` (a finished file, before its rename) that relpoint wrote exactly this content.

    For formats with no room for a header: KITTI poses (12 numbers a line, nothing else, or other tools
    cannot read them) and times files. The SHA-256 of the content goes into an extended attribute, which
    leaves no file beside the output, does not survive a plain copy, and no longer matches once the file
    is edited, so neither a copy nor an edited file counts as relpoint's. A file system without extended
    attributes keeps no mark: the next run then asks for ``--overwrite`` (the safe side).
    """
    digest = _sha256(path)
    if digest is None or not hasattr(os, "setxattr"):
        return
    with contextlib.suppress(OSError):
        os.setxattr(path, WRITTEN_XATTR, digest.encode("ascii"))


def _marked(path: Path) -> bool:
    try:
        recorded = os.getxattr(path, WRITTEN_XATTR)
    except (OSError, AttributeError):
        return False
    return recorded.decode("ascii", "replace") == _sha256(path)


def written_by_relpoint(path: Path) -> bool:
    """Whether a file's content says relpoint wrote it, whatever its name: the MCAP library, a PLY, TUM or
    text-table header, a JSON key, a CSV header, image metadata, a zip comment, or :func:`mark_written`'s."""
    try:
        with path.open("rb") as stream:
            head = stream.read(_SNIFF_BYTES)
    except OSError:
        return False
    first = head.split(b"\n", 1)[0].rstrip(b"\r")
    if head.startswith(b"\x89MCAP"):  # the header record's library string
        return b"relpoint/" in head[:256]
    if head.startswith(b"ply"):
        header = head.split(b"end_header", 1)[0]
        return any(line.startswith(b"comment") and b"relpoint" in line for line in header.splitlines())
    if head.startswith(b"\x89PNG"):
        return b"Software\x00relpoint" in head
    if head.startswith(b"%PDF"):  # the document information dictionary, near the end
        return b"/Creator (relpoint " in _tail(path)
    if head.startswith(b"PK"):  # an evo result zip: the archive comment
        return is_relpoint_result_zip(path)
    if b"<svg" in head:  # matplotlib's metadata: <dc:title>relpoint VERSION</dc:title> under dc:creator
        return b"<dc:title>relpoint " in head
    if head.startswith(b"<!-- relpoint "):
        return True
    if head.lstrip().startswith(b"{"):
        return _relpoint_json(path)
    if _COMPARE_TEXT_FIRST_LINE.fullmatch(first):
        return True
    if _TUM_FIRST_LINE.fullmatch(first):
        for line in head.splitlines()[1:]:
            if line.rstrip(b"\r") == _TUM_LEGEND:
                return True
            if not line.startswith(b"#"):
                break
    text = first.decode("utf-8", "replace").strip()
    if text in _CSV_HEADERS or any(text.startswith(prefix) for prefix in _CSV_HEADER_PREFIXES):
        return True
    return _marked(path)


def finite_json(value: Any) -> Any:
    """``value`` (dicts, lists, tuples and scalars) with every NaN or infinite float as None, which JSON
    writes ``null``: strict JSON has no NaN, and other readers (``jq``, browsers) refuse Python's."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: finite_json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite_json(item) for item in value]
    return value


def json_text(value: Any, **options: Any) -> str:
    """``value`` as strict JSON (:func:`finite_json`, ``allow_nan=False``); ``options`` go to ``json.dumps``
    (``indent``, ``sort_keys``, ``default``). Every JSON relpoint writes is made here."""
    return json.dumps(finite_json(value), allow_nan=False, **options)


def json_object(path: Path, max_bytes: int) -> dict | None:
    """The JSON object in ``path``, or None: unreadable, over ``max_bytes``, not JSON or not an object
    (for telling whether relpoint wrote a file, without trusting it)."""
    try:
        if path.stat().st_size > max_bytes:
            return None
        document = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) else None


def _relpoint_json(path: Path) -> bool:
    document = json_object(path, 50_000_000)
    return document is not None and "relpoint_version" in document


def _tail(path: Path) -> bytes:
    try:
        with path.open("rb") as stream:
            stream.seek(max(0, path.stat().st_size - _SNIFF_BYTES))
            return stream.read(_SNIFF_BYTES)
    except OSError:
        return b""


def check_output_file(
    path: str | os.PathLike[str],
    *,
    inputs: Iterable[str | os.PathLike[str] | None] = (),
    overwrite: bool = False,
) -> Path:
    """Check that file ``path`` may be written; its resolved path (a symlink's target).

    Raises :class:`OutputError` (exit 2) when it is one of ``inputs`` (whatever ``overwrite`` says), a
    directory, an existing file relpoint did not write (unless ``overwrite``), or not writable.
    """
    target = resolve_output(path)
    _refuse_inputs(path, target, _resolved_inputs(inputs), directory=False)
    if target.is_dir():
        raise OutputError(f"{path} is a directory", "give a file name")
    if target.exists() and not overwrite and not written_by_relpoint(target):
        raise OutputError(f"{path} exists and relpoint did not write it", "pass --overwrite to replace it")
    probe_writable(target.parent, path)
    return target


#: Operating-system errors that mean an output could not be written (exit 2); any other is an input's (exit 3).
OUTPUT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EBUSY, errno.EEXIST, errno.ENOTEMPTY,
                           errno.EXDEV, errno.EISDIR, errno.EFBIG})  # fmt: skip


def unreadable_input(path: str | os.PathLike[str], error: OSError) -> InputError:
    """The error (exit 3) of an input the system refused to read, with the way out."""
    if error.errno in (errno.EACCES, errno.EPERM):
        return InputError(f"{path}: cannot read (permission denied)", "check its permissions")
    return InputError(f"{path}: cannot read ({error.strerror or error})", "check the path")


def os_error_message(error: OSError) -> str:
    """One line for an operating-system error: the path, what the system said, and the way out."""
    where = f" {error.filename}" if error.filename else ""
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"cannot write{where}: no space left on the device; free some space or write elsewhere"
    if error.errno == errno.EROFS:
        return f"cannot write{where}: read-only file system; write elsewhere"
    if error.errno in (errno.EACCES, errno.EPERM):
        return f"cannot use{where}: permission denied; check its permissions or choose another path"
    return f"cannot use{where}: {error.strerror or error}; check the path"

"""Bag layouts a log may come in: a single MCAP file, a rosbag2 directory, a ROS 1 bag.

A *log* is what a relpoint command reads messages from. Besides the single ``.mcap`` file that relpoint
writes itself (``docs/log-format.md``), recordings made by other tools come as

- a **rosbag2 directory** written by ``ros2 bag record``: ``metadata.yaml`` beside one or more storage
  files (``mcap`` or ``sqlite3`` storage, split over several files when the recording hit a size or
  duration limit), optionally zstd-compressed per file (``*.mcap.zstd``) or per message;
- a **ROS 1 bag** (``.bag``, format 2.0), with chunks stored plain, bz2- or lz4-compressed.

All of them read through rosbags' ``AnyReader`` (:func:`open_reader`). ROS 1 messages decode into the
ROS 1 definitions the bag carries (``CameraInfo.K``, ``Header.seq``); a :class:`MessageMigrator` gives
them the standard ROS 2 types' fields (rebuilding, with rosbags' own migration as ``rosbags-convert``
does, only the types whose fields differ), so the rest of relpoint sees the same messages whatever the
layout.

:func:`describe_storage` tells what ``ros2 bag info`` tells about the storage (id, files, sizes,
compression); :func:`write_layout` copies a log's messages into any layout, which the tests and the
benchmark use to compare layouts on the same messages.
"""

from __future__ import annotations

import enum
import functools
import hashlib
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.interfaces import Nodetype
from rosbags.rosbag1 import Reader as Ros1Reader
from rosbags.rosbag1.reader import decompressors as ros1_decompressors

from formats import ros2
from formats.outputs import unreadable_input
from formats.signatures import MCAP_MAGIC, ROS1_MAGIC, ROSBAG2_METADATA
from relpoint.errors import InputError

try:  # the zstd codec rosbags writes and reads rosbag2 compression with
    from compression import zstd
except ImportError:  # Python < 3.14
    from backports import zstd  # type: ignore[no-redef]

SQLITE_MAGIC = b"SQLite format 3\x00"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"

_LOG_KINDS = "an MCAP file, a rosbag2 directory (metadata.yaml) or a ROS 1 .bag"


class Layout(enum.Enum):
    """How a log is laid out on disk."""

    MCAP = "mcap"  #: one MCAP file (what relpoint writes)
    ROSBAG2 = "rosbag2"  #: a directory with metadata.yaml and mcap or sqlite3 storage files
    ROS1 = "rosbag1"  #: a ROS 1 bag, format 2.0

    @property
    def noun(self) -> str:
        """How messages name the input, e.g. ``the rosbag2 directory``."""
        return {Layout.MCAP: "MCAP file", Layout.ROSBAG2: "rosbag2 bag", Layout.ROS1: "ROS 1 bag"}[self]

    @property
    def repair_hint(self) -> str:
        """What a user can do about a damaged log of this layout."""
        return {
            Layout.MCAP: "re-record it, or repair a cut-off recording with `mcap recover` (the MCAP CLI)",
            Layout.ROSBAG2: "re-record it, or rebuild a cut-off bag's metadata with `ros2 bag reindex`",
            Layout.ROS1: "re-record it, or repair a cut-off recording with `rosbag reindex`",
        }[self]


def detect_layout(path: str | os.PathLike[str]) -> Layout:
    """The layout of the log at ``path``, told by its content (magic bytes, ``metadata.yaml``).

    Raises
    ------
    InputError
        If nothing is at ``path``, it cannot be read, or it is none of the layouts.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory", "check the path")
    if path.is_dir():
        if (path / ROSBAG2_METADATA).is_file():
            return Layout.ROSBAG2
        raise InputError(
            f"{path} is a directory without {ROSBAG2_METADATA}, not a rosbag2 bag",
            "give a directory written by `ros2 bag record` (`ros2 bag reindex` rebuilds a lost metadata.yaml), "
            "or the .mcap or .bag file itself",
        )
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError as error:
        raise unreadable_input(path, error) from None
    if head.startswith(MCAP_MAGIC):
        _check_suffix(path, ".mcap")
        return Layout.MCAP
    if head.startswith(ROS1_MAGIC):
        _check_suffix(path, ".bag")
        return Layout.ROS1
    if head.startswith(b"#ROSBAG V"):
        raise InputError(f"{path} is a ROS 1 bag of an old format version", "migrate it with `rosbag fix`")
    if head.startswith(SQLITE_MAGIC) or head.startswith(ZSTD_MAGIC) or path.name == ROSBAG2_METADATA:
        what = {SQLITE_MAGIC[:4]: "sqlite3 storage file", ZSTD_MAGIC: "zstd-compressed storage file"}.get(head[:4])
        raise InputError(
            f"{path} is a rosbag2 {what or 'metadata file'}, not a log on its own",
            f"give the bag directory {path.parent} that holds it with its metadata.yaml",
        )
    raise InputError(f"{path} is not an MCAP file, nor a rosbag2 directory or ROS 1 bag", f"give {_LOG_KINDS}")


def is_rosbag2_part(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a file of a rosbag2 bag rather than the bag: its ``metadata.yaml``, or a sqlite3
    or zstd-compressed storage file (:func:`detect_layout` names the bag directory to give instead)."""
    path = Path(path)
    if not path.is_file():
        return False
    if path.name == ROSBAG2_METADATA:
        return True
    try:
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError:
        return False
    return head.startswith(SQLITE_MAGIC) or head.startswith(ZSTD_MAGIC)


def _check_suffix(path: Path, suffix: str) -> None:
    # AnyReader chooses its reader by the name, so a mis-named file would fail in a confusing way.
    if path.suffix != suffix:
        raise InputError(f"{path} holds a {suffix[1:]} log but is not named *{suffix}", f"rename it to end in {suffix}")


def open_reader(path: Path) -> AnyReader:
    """An unopened rosbags ``AnyReader`` over the log at ``path`` (any layout)."""
    _tolerate_foreign_schemas()
    return AnyReader([path], default_typestore=ros2.typestore())


def complete_typestore(reader: AnyReader) -> None:
    """Give an open reader the standard definitions of the types its schemaless channels carry.

    rosbags takes a log's definitions from its schemas, and the standard ones only when no channel has
    one; a channel written without a schema (an empty one) beside others with theirs could not be
    decoded. The log's own definitions take precedence.
    """
    standard = ros2.typestore().fielddefs
    known = reader.typestore.fielddefs
    missing = {c.msgtype for c in reader.connections if c.msgtype in standard and c.msgtype not in known}
    if not missing:
        return
    needed: dict[str, Any] = {}
    while missing:
        name = missing.pop()
        if name in needed or name in known or name not in standard:
            continue
        needed[name] = standard[name]
        missing |= set(_referenced_types(standard[name]))
    reader.typestore.register(needed)


def _referenced_types(fielddef: Any) -> list[str]:
    """The message types a typestore field definition refers to (its fields, arrays and sequences of them)."""
    names = []
    for _, (kind, detail) in fielddef[1]:
        if kind == Nodetype.NAME:
            names.append(detail)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE) and detail[0][0] == Nodetype.NAME:
            names.append(detail[0][1])
    return names


_MSG_SEPARATOR = "=" * 80


def normalised_msg_text(text: str) -> str:
    """A ``ros2msg`` schema's text as rosbags parses it: line ends ``\\n`` and each separator between
    the definitions exactly 80 ``=`` (the MCAP ros2 profile's). Writers differ on both (CRLF, 40 or 120
    ``=``, a trailing blank), and other readers (mcap-ros2-support) accept them."""
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    return "\n".join(_MSG_SEPARATOR if len(set(line.strip())) == 1 and line.strip()[:3] == "===" else line
                     for line in lines)  # fmt: skip


#: Schema encodings a ROS 2 reader decodes (the MCAP ros2 profile's, and schemaless).
ROS_SCHEMA_ENCODINGS = frozenset({"ros2msg", "ros2idl", "omgidl", ""})


@functools.cache
def _tolerate_foreign_schemas() -> None:
    """Let rosbags open an MCAP file that also holds channels of another schema encoding.

    An MCAP file may mix profiles: a Foxglove recording adds JSON or protobuf channels (``jsonschema``,
    ``protobuf``, ``flatbuffer`` schemas) beside the ROS 2 ones. rosbags' MCAP storage looks every
    schema's encoding up in a fixed table and fails the whole file on any other (a ``KeyError`` read as a
    corrupt file), where the log format says that anything else in the file is ignored. Such a schema
    is taken as schemaless instead: its channel is listed under its own type name, and no role reads it.
    """
    try:
        from rosbags.interfaces import MessageDefinition, MessageDefinitionFormat
        from rosbags.rosbag2 import storage_mcap
    except ImportError:  # another rosbags layout: nothing to adapt
        return
    original = getattr(storage_mcap, "get_msgdef", None)
    if original is None or getattr(original, "tolerates_foreign_schemas", False):
        return

    def get_msgdef(schema: Any) -> Any:
        if schema is not None and schema.encoding not in ROS_SCHEMA_ENCODINGS:
            return MessageDefinition(MessageDefinitionFormat.NONE, "")
        if schema is not None and schema.encoding == "ros2msg" and isinstance(schema.data, str):
            if not schema.data.strip():  # no definition at all: as a schemaless channel
                return MessageDefinition(MessageDefinitionFormat.NONE, "")
            schema = schema._replace(data=normalised_msg_text(schema.data))
        return original(schema)

    get_msgdef.tolerates_foreign_schemas = True  # type: ignore[attr-defined]
    storage_mcap.get_msgdef = get_msgdef


# --- what the storage holds -------------------------------------------------------------------------


@dataclass(frozen=True)
class StorageFile:
    """One file of a log's storage; counts and times where the layout records them."""

    name: str
    size_bytes: int
    message_count: int | None = None
    start_ns: int | None = None
    duration_ns: int | None = None


@dataclass(frozen=True)
class Storage:
    """How a log is stored: what ``ros2 bag info`` shows above the topic list.

    ``compression_mode`` is ``file`` or ``message`` (rosbag2), ``chunk`` (MCAP chunks, ROS 1 chunks),
    or empty when nothing is compressed; ``compression_format`` names the codecs (``zstd``, ``lz4``,
    ``bz2``; several joined by ``+`` when chunks differ).
    """

    layout: Layout
    storage_id: str
    files: tuple[StorageFile, ...]
    compression_format: str = ""
    compression_mode: str = ""
    ros_distro: str = ""

    @property
    def size_bytes(self) -> int:
        return sum(f.size_bytes for f in self.files)


def storage_paths(path: Path, layout: Layout) -> list[Path]:
    """Every file that makes up the log (for a rosbag2 directory: metadata.yaml first, then the storage)."""
    if layout is not Layout.ROSBAG2:
        return [path]
    metadata = _rosbag2_metadata(path)
    return [path / ROSBAG2_METADATA, *(path / Path(name).name for name in metadata.get("relative_file_paths", []))]


def _rosbag2_metadata(path: Path) -> dict[str, Any]:
    import yaml  # here, not at import: only a rosbag2 directory has a metadata.yaml

    try:
        document = yaml.safe_load((path / ROSBAG2_METADATA).read_text(encoding="utf-8"))
        info = document["rosbag2_bagfile_information"]
        if not isinstance(info, dict):
            raise TypeError("rosbag2_bagfile_information is not a mapping")
    except (OSError, yaml.YAMLError, KeyError, TypeError, UnicodeDecodeError) as error:
        detail = f"{type(error).__name__}: {error}"
        mark = getattr(error, "problem_mark", None)
        if isinstance(error, yaml.YAMLError) and mark is not None:  # the parser's report spans lines
            detail = (
                f"YAML {getattr(error, 'problem', None) or 'error'} at line {mark.line + 1}, column {mark.column + 1}"
            )
        raise InputError(
            f"{path / ROSBAG2_METADATA}: not a rosbag2 metadata file ({detail})", Layout.ROSBAG2.repair_hint
        ) from None
    return info


def describe_storage(path: str | os.PathLike[str], layout: Layout | None = None) -> Storage:
    """Storage id, files with sizes, and compression of the log at ``path``.

    Raises
    ------
    InputError
        If the log's own description (metadata.yaml, MCAP summary, ROS 1 index) cannot be read.
    """
    path = Path(path)
    layout = layout or detect_layout(path)
    try:
        if layout is Layout.MCAP:
            return _describe_mcap(path)
        if layout is Layout.ROS1:
            return _describe_ros1(path)
        return _describe_rosbag2(path)
    except InputError:
        raise
    except Exception as error:  # the readers raise assorted errors on damaged descriptions
        raise InputError(
            f"{path}: the {layout.noun} is truncated or corrupt ({type(error).__name__}: {error})", layout.repair_hint
        ) from None


def _describe_mcap(path: Path) -> Storage:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    if summary is not None and summary.chunk_indexes:
        codecs = sorted({c.compression for c in summary.chunk_indexes if c.compression})
    else:  # written without chunk indexes: the first chunk tells
        codecs = [codec] if (codec := _first_chunk_compression(path)) else []
    stats = summary.statistics if summary else None
    file = StorageFile(
        path.name, path.stat().st_size,
        stats.message_count if stats else None,
        stats.message_start_time if stats else None,
        stats.message_end_time - stats.message_start_time if stats else None,
    )  # fmt: skip
    return Storage(Layout.MCAP, "mcap", (file,), "+".join(codecs), "chunk" if codecs else "")


#: MCAP record opcodes read by :func:`_first_chunk_compression`.
_MCAP_MESSAGE, _MCAP_CHUNK, _MCAP_DATA_END, _MCAP_FOOTER = 0x05, 0x06, 0x0F, 0x02


def _first_chunk_compression(path: Path) -> str:
    """The compression of the MCAP file's first chunk (``""`` if none, or no chunk before the first
    message): read record by record from the start, skipping each record's content, so the cost is
    that of the records before the first chunk (schemas, channels, metadata)."""
    with path.open("rb") as stream:
        stream.seek(len(MCAP_MAGIC))
        while len(head := stream.read(9)) == 9:
            opcode, length = head[0], int.from_bytes(head[1:], "little")
            if opcode in (_MCAP_MESSAGE, _MCAP_DATA_END, _MCAP_FOOTER):
                return ""
            if opcode == _MCAP_CHUNK:  # start, end time, uncompressed size, crc, then the compression string
                fields = stream.read(32)
                size = int.from_bytes(fields[28:32], "little")
                return stream.read(min(size, 64)).decode("utf-8", "replace") if len(fields) == 32 else ""
            stream.seek(length, os.SEEK_CUR)
    return ""


def _describe_ros1(path: Path) -> Storage:
    names = {function: name for name, function in ros1_decompressors.items()}
    with Ros1Reader(path) as reader:
        codecs = sorted({names.get(chunk.decompressor, "?") for chunk in getattr(reader, "chunks", {}).values()})
        file = StorageFile(path.name, path.stat().st_size, reader.message_count, reader.start_time,
                           reader.end_time - 1 - reader.start_time if reader.message_count else 0)  # fmt: skip
    codecs = [codec for codec in codecs if codec != "none"]
    return Storage(Layout.ROS1, "rosbag1", (file,), "+".join(codecs), "chunk" if codecs else "")


def _describe_rosbag2(path: Path) -> Storage:
    metadata = _rosbag2_metadata(path)
    try:
        return _rosbag2_storage(path, metadata)
    except (AttributeError, TypeError, ValueError, KeyError) as error:  # fields of the wrong shape
        raise InputError(
            f"{path}: {ROSBAG2_METADATA} is malformed ({type(error).__name__}: {error})", Layout.ROSBAG2.repair_hint
        ) from None


def _rosbag2_storage(path: Path, metadata: dict[str, Any]) -> Storage:
    """:func:`_describe_rosbag2` from the bag's parsed metadata (raises on fields of the wrong type)."""
    per_file = {Path(f["path"]).name: f for f in metadata.get("files") or [] if isinstance(f, dict) and "path" in f}
    files = []
    for name in metadata.get("relative_file_paths") or []:
        storage_file = path / Path(name).name
        if not storage_file.is_file():
            raise InputError(f"{path}: the storage file {storage_file.name} named in {ROSBAG2_METADATA} is missing",
                             Layout.ROSBAG2.repair_hint)  # fmt: skip
        entry = per_file.get(storage_file.name, {})
        files.append(StorageFile(
            storage_file.name, storage_file.stat().st_size, entry.get("message_count"),
            (entry.get("starting_time") or {}).get("nanoseconds_since_epoch"),
            (entry.get("duration") or {}).get("nanoseconds"),
        ))  # fmt: skip
    mode = str(metadata.get("compression_mode") or "").lower()
    mode = "" if mode == "none" else mode
    return Storage(
        Layout.ROSBAG2, str(metadata.get("storage_identifier", "")), tuple(files),
        str(metadata.get("compression_format") or "") if mode else "", mode, str(metadata.get("ros_distro") or ""),
    )  # fmt: skip


def check_sqlite_file(path: Path) -> None:
    """Raise :class:`InputError` unless a SQLite file is as long as its header says.

    SQLite has no checksum, and reads a cut-off page as zeros; the header's page size and page count
    (valid when its change counter matches the version-valid-for number) tell a truncated file.
    """
    with path.open("rb") as stream:
        header = stream.read(100)
    if not header.startswith(SQLITE_MAGIC):
        return  # compressed (``.db3.zstd``) or not SQLite at all: the reader's own checks apply
    size = path.stat().st_size
    page_size = int.from_bytes(header[16:18], "big") if len(header) >= 18 else 0
    page_size = 65536 if page_size == 1 else page_size
    page_count = int.from_bytes(header[28:32], "big") if len(header) == 100 else 0
    counter_valid = len(header) == 100 and header[24:28] == header[92:96]
    expected = page_size * page_count if counter_valid and page_count else None
    if len(header) < 100 or (expected is not None and size != expected) or (page_size and size % page_size):
        raise InputError(
            f"{path.parent}: the rosbag2 bag is truncated or corrupt ({path.name} holds {size} bytes"
            + (f", its header says {expected})" if expected is not None else ", not whole SQLite pages)"),
            Layout.ROSBAG2.repair_hint,
        )


def check_storage(path: str | os.PathLike[str], layout: Layout) -> None:
    """What can be checked of a log before reading it: a rosbag2 bag's storage files are all there, and
    SQLite files are whole (:func:`check_sqlite_file`)."""
    path = Path(path)
    if layout is not Layout.ROSBAG2:
        return
    storage = _describe_rosbag2(path)
    if storage.storage_id == "sqlite3":
        for file in storage.files:
            check_sqlite_file(path / file.name)


def decompress_bag(path: Path, into: Path) -> Path:
    """A rosbag2 bag compressed per file, decompressed into the empty directory ``into``; returns ``into``.

    The copy holds the storage files without their ``.zstd`` and a metadata.yaml that says they are not
    compressed. rosbags would otherwise decompress every file again each time the bag is opened, and a
    command opens a log two or three times (the summary pass, then the messages it needs).
    """
    import yaml  # here, not at import: only a rosbag2 directory has a metadata.yaml

    metadata = _rosbag2_metadata(path)
    names = []
    for name in metadata.get("relative_file_paths") or []:
        source = path / Path(name).name
        target = into / source.name.removesuffix(".zstd")
        with source.open("rb") as compressed, zstd.open(compressed, "rb") as stream, target.open("wb") as out:
            shutil.copyfileobj(stream, out, 1 << 20)
        names.append(target.name)
    files = [{**f, "path": Path(str(f.get("path", ""))).name.removesuffix(".zstd")}
             for f in metadata.get("files") or [] if isinstance(f, dict)]  # fmt: skip
    plain = {**metadata, "relative_file_paths": names, "files": files, "compression_mode": "", "compression_format": ""}
    (into / ROSBAG2_METADATA).write_text(yaml.safe_dump({"rosbag2_bagfile_information": plain}, sort_keys=False))
    return into


def log_sha256(path: str | os.PathLike[str], layout: Layout | None = None) -> str:
    """SHA-256 of a log: its file's bytes, or for a rosbag2 directory every file's name and bytes in order.

    Remembered for the files' identity, size and modification time: a batch worker that runs several
    jobs on one log reads it once for the hash, and a file changed since is hashed again.
    """
    path = Path(path)
    layout = layout or detect_layout(path)
    files = tuple(storage_paths(path, layout))
    identity = tuple((str(file.resolve()), *_file_stamp(file)) for file in files)
    return _sha256_of(identity, files, layout is Layout.ROSBAG2)


def log_stamp(path: str | os.PathLike[str], layout: Layout | None = None) -> tuple[int, int]:
    """Total size (bytes) and latest modification time (ns) of a log's files: a cheap check of whether
    it is still the log a :func:`log_sha256` was taken of, before hashing it again."""
    path = Path(path)
    stats = [file.stat() for file in storage_paths(path, layout or detect_layout(path))]
    return sum(s.st_size for s in stats), max((s.st_mtime_ns for s in stats), default=0)


def _file_stamp(file: Path) -> tuple[int, int, int, int]:
    status = file.stat()
    return status.st_dev, status.st_ino, status.st_size, status.st_mtime_ns


@functools.lru_cache(maxsize=64)
def _sha256_of(identity: tuple[tuple[object, ...], ...], files: tuple[Path, ...], named: bool) -> str:
    """The hash of ``files`` in order (each name first when ``named``); cached on ``identity``."""
    digest = hashlib.sha256()
    for file in files:
        if named:
            digest.update(file.name.encode("utf-8") + b"\x00")
        with file.open("rb") as stream:
            for block in iter(lambda stream=stream: stream.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


# --- ROS 1 messages as ROS 2 messages ---------------------------------------------------------------


class MessageMigrator:
    """Turns messages of one typestore's definitions into the same-named types of another.

    A message whose source type holds every field of the target type under the same name and shape
    (recursively; extra source fields such as ROS 1's ``Header.seq`` allowed) reads exactly as the target
    type would and passes unchanged: that is most types, at no cost. Others are rebuilt as
    ``rosbags-convert`` rebuilds them: fields matched by name, renamed ones (ROS 1 ``CameraInfo.K`` ->
    ROS 2 ``k``) by type, dropped ones left out, added ones given defaults. Types either store lacks pass
    unchanged.

    Parameters
    ----------
    source_typestore:
        The definitions the messages were decoded with (for a bag: ``AnyReader.typestore``).
    target_typestore:
        The definitions wanted (default: the standard ROS 2 Humble types relpoint reads).
    """

    def __init__(self, source_typestore: Any, target_typestore: Any = None) -> None:
        self._source = source_typestore
        self._target = target_typestore if target_typestore is not None else ros2.typestore()
        self._cache: dict[str, object] = {}
        self._alike: dict[tuple[str, str], bool] = {}

    def __call__(self, message: Any, typename: str) -> Any:
        if typename not in self._target.fielddefs or typename not in self._source.fielddefs:
            return message
        if self.reads_alike(typename, typename):
            return message
        from rosbags.convert.converter import migrate_message  # here: only ROS 1 logs need it

        return migrate_message(self._source, self._target, typename, typename, self._cache, message)

    def reads_alike(self, source_type: str, target_type: str) -> bool:
        """Whether every field of ``target_type`` is in ``source_type`` under the same name and shape."""
        key = (source_type, target_type)
        if key not in self._alike:
            self._alike[key] = False  # a recursive type is not taken as alike
            source = dict(self._source.fielddefs[source_type][1])
            self._alike[key] = all(
                name in source and self._same_shape(source[name], desc)
                for name, desc in self._target.fielddefs[target_type][1]
            )
        return self._alike[key]

    def _same_shape(self, source: Any, target: Any) -> bool:
        if source[0] != target[0]:
            return False
        if target[0] == Nodetype.NAME:
            return self.reads_alike(source[1], target[1])
        if target[0] in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return source[1][1] == target[1][1] and self._same_shape(source[1][0], target[1][0])
        return bool(source == target)

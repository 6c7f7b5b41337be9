"""How a file announces what it is: the magic numbers of the log layouts and relpoint's mark on an
evo result zip. No other formats module is imported here, so every one may use it."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

MCAP_MAGIC = b"\x89MCAP0\r\n"
ROS1_MAGIC = b"#ROSBAG V2.0\n"
ROSBAG2_METADATA = "metadata.yaml"

#: The zip comment of a result file relpoint wrote.
ZIP_COMMENT_PREFIX = b"relpoint "


def is_log(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` holds a log of any layout by its content, even under a name relpoint then refuses
    (no error for anything else)."""
    path = Path(path)
    try:
        if path.is_dir():
            return (path / ROSBAG2_METADATA).is_file()
        with path.open("rb") as stream:
            head = stream.read(16)
    except OSError:
        return False
    return head.startswith(MCAP_MAGIC) or head.startswith(ROS1_MAGIC)


def is_relpoint_result_zip(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a zip whose comment says relpoint wrote it."""
    try:
        with zipfile.ZipFile(path) as archive:
            return archive.comment.startswith(ZIP_COMMENT_PREFIX)
    except (OSError, zipfile.BadZipFile, ValueError):
        return False

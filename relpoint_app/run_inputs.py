"""The log a run directory was made from, as its run.json records it, and whether a log given now is it.

``relpoint run`` and ``relpoint fuse`` record the log's absolute path, SHA-256, total size and latest
modification time; ``compare RUN_DIR`` finds the log by that path and ``fuse RUN_DIR --log LOG`` checks
LOG against it, so neither silently works on another log. The hash is only taken again when the size
or the time differ (hashing a log of gigabytes takes a while).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from formats.layouts import Layout, log_sha256, log_stamp
from formats.outputs import shown_path
from relpoint.errors import InputError


def log_record(path: Path, layout: Layout | None = None) -> dict[str, Any]:
    """The ``input`` entries of run.json that identify the log at ``path``."""
    size, mtime_ns = log_stamp(path, layout)
    return {
        "path": shown_path(os.path.abspath(path)),
        "sha256": log_sha256(path, layout),
        "size": size,
        "mtime_ns": mtime_ns,
    }


def recorded_input(run_dir: Path) -> dict[str, Any]:
    """The ``input`` object of ``run_dir``'s run.json (empty when there is none or it is unreadable)."""
    try:
        document = json.loads((run_dir / "run.json").read_text(encoding="utf-8")[:10_000_000])
    except (OSError, ValueError):
        return {}
    recorded = document.get("input") if isinstance(document, dict) else None
    return recorded if isinstance(recorded, dict) else {}


def recorded_log(run_dir: Path, recorded: dict[str, Any]) -> Path | None:
    """Where the log named by ``recorded`` (a run.json's ``input``) is, when it is there and is that log.

    An absolute path is taken as it is. A relative one (run.json of an older relpoint, which kept the
    path as given) is looked for from the working directory, and taken only when run.json holds its
    SHA-256 to confirm it. Raises :class:`InputError` when the file there is another log.
    """
    text = recorded.get("path")
    if not isinstance(text, str) or not text:
        return None
    path = Path(text)
    if not path.is_absolute() and not isinstance(recorded.get("sha256"), str):
        raise InputError(
            f"{run_dir}: its run.json names its log by a relative path ({text}) and holds no hash to check it by",
            "pass --reference LOG",
        )
    if not path.exists():
        return None
    check_same_log(path, recorded, run_dir, "pass --reference LOG with the log it was run on")
    return path


def check_same_log(log: Path, recorded: dict[str, Any], run_dir: Path, hint: str) -> None:
    """Raise :class:`InputError` (naming both logs) when ``log`` is not the one ``recorded`` describes.

    Nothing is checked without a recorded SHA-256 (a run.json not written by relpoint). A log whose size
    and modification time are those recorded is taken to be it without hashing.
    """
    sha256 = recorded.get("sha256")
    if not isinstance(sha256, str):
        return
    size, mtime_ns = log_stamp(log)
    if recorded.get("size") == size and recorded.get("mtime_ns") == mtime_ns:
        return
    was = recorded.get("path") or "its log"
    if isinstance(recorded.get("size"), int) and recorded["size"] != size:
        differs = f"{size} bytes, run.json records {recorded['size']} for {was}"
    else:
        here = log_sha256(log)
        if here == sha256:
            return
        differs = f"sha256 {here[:12]}..., run.json records {sha256[:12]}... for {was}"
    raise InputError(f"{log} is not the log {run_dir} was run on ({differs})", hint)

"""evo's result zip files (``evo_ape --save_results``, read by ``evo_res``), written and read without evo.

The layout is evo 1.38's ``evo.tools.file_interface.save_res_file``: ``info.json`` (``title``,
``ref_name``, ``est_name``, ``label``), ``stats.json`` (rmse, mean, median, std, min, max, sse), one
``NAME.npy`` per array (``error_array``, ``seconds_from_start``, ``timestamps``, ``distances_from_start``,
``distances``, ``alignment_transformation_sim3``) and one ``NAME.tum`` per trajectory (the matched
reference and the aligned estimate). relpoint adds a ``relpoint`` object to ``info.json`` (its summary,
settings, estimator and version; evo ignores it) and a zip comment naming relpoint, by which it
recognises its own files (:func:`formats.outputs.written_by_relpoint`).
"""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

import relpoint
from formats.atomic import atomic_path
from formats.outputs import json_text
from formats.signatures import ZIP_COMMENT_PREFIX
from relpoint.errors import InputError

#: Most bytes relpoint inflates from one result zip, all the members it reads together (a guard against
#: zip bombs: a few MB of zeros inflate to GB). An evo result of a million poses holds about 50 MB.
MAX_RESULT_BYTES = 256 << 20


@dataclass(frozen=True)
class EvoResult:
    """The content of an evo result zip (``evo.core.result.Result``).

    Attributes
    ----------
    info: ``title``, ``ref_name``, ``est_name``, ``label`` and whatever else the writer added.
    stats: statistic name -> value.
    arrays: array name -> numpy array (``error_array`` (N,), ``seconds_from_start`` (N,) s, ...).
    trajectories: name -> TUM text (``timestamp x y z qx qy qz qw`` per line, seconds and metres).
    """

    info: Mapping[str, Any]
    stats: Mapping[str, float]
    arrays: Mapping[str, np.ndarray] = field(default_factory=dict)
    trajectories: Mapping[str, str] = field(default_factory=dict)


def tum_text(stamps_s: np.ndarray, positions: np.ndarray, quats_xyzw: np.ndarray) -> str:
    """TUM lines as evo's ``write_tum_trajectory_file`` writes them (``np.savetxt``, space separated):
    stamps in seconds (N,), positions (N, 3) in metres, unit quaternions (N, 4) x, y, z, w."""
    table = np.column_stack((stamps_s, positions, quats_xyzw))
    buffer = io.StringIO()
    np.savetxt(buffer, table, delimiter=" ")
    return buffer.getvalue()


def _member_name(name: str) -> str:
    """A trajectory name as a flat zip member name (evo uses the name as given; paths would nest)."""
    return name.replace("/", "_").replace("\\", "_") or "trajectory"


def write_evo_result(path: str | os.PathLike[str], evo_result: EvoResult) -> None:
    """Write ``evo_result`` as an evo result zip, atomically (``load_res_file`` reads it back)."""
    with atomic_path(path) as tmp, zipfile.ZipFile(tmp, "w") as archive:
        archive.comment = ZIP_COMMENT_PREFIX + relpoint.__version__.encode()
        archive.writestr("info.json", json_text(evo_result.info))
        archive.writestr("stats.json", json_text(dict(evo_result.stats)))
        for name, array in evo_result.arrays.items():
            buffer = io.BytesIO()
            np.save(buffer, np.asarray(array))
            archive.writestr(f"{name}.npy", buffer.getvalue())
        for name, text in evo_result.trajectories.items():
            archive.writestr(f"{_member_name(name)}.tum", text.encode("utf-8"))


def _read_member(archive: zipfile.ZipFile, name: str, path: Path) -> bytes:
    """A member's bytes; the size it declares bounds what zipfile inflates (a longer stream is an error)."""
    return archive.read(name)


def _check_sizes(archive: zipfile.ZipFile, names: list[str], path: Path) -> None:
    """Refuse a zip whose members to read would inflate beyond :data:`MAX_RESULT_BYTES`, before any is read."""
    total = sum(archive.getinfo(name).file_size for name in names)
    if total > MAX_RESULT_BYTES:
        raise InputError(
            f"{path}: its arrays and JSON inflate to {total / 2**20:.0f} MiB, more than the "
            f"{MAX_RESULT_BYTES >> 20} MiB an evo result file may hold",
            "give a result zip written by evo_ape/evo_rpe --save_results or relpoint --save-results",
        )


def read_evo_result(path: str | os.PathLike[str]) -> EvoResult:
    """Read an evo result zip (written by evo or by :func:`write_evo_result`); trajectories are not read.

    Raises :class:`InputError` for a missing or unreadable file, a zip without ``info.json`` and
    ``stats.json``, or malformed members.
    """
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            if not {"info.json", "stats.json"} <= set(names):
                raise InputError(f"{path}: not an evo result file (no info.json and stats.json)",
                                 "give a zip written by evo_ape/evo_rpe --save_results or relpoint --save-results")  # fmt: skip
            arrays_to_read = [name for name in names if name.endswith(".npy")]  # evo writes no .npz
            _check_sizes(archive, ["info.json", "stats.json", *arrays_to_read], path)
            info = json.loads(_read_member(archive, "info.json", path).decode("utf-8"))
            stats = json.loads(_read_member(archive, "stats.json", path).decode("utf-8"))
            arrays = {}
            for name in arrays_to_read:
                with io.BytesIO(_read_member(archive, name, path)) as buffer:
                    arrays[Path(name).stem] = np.load(buffer, allow_pickle=False)
    except InputError:
        raise
    except (OSError, zipfile.BadZipFile) as error:
        raise InputError(f"{path}: cannot read as a zip file ({getattr(error, 'strerror', None) or error})") from None
    except (ValueError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: malformed evo result ({error})") from None
    if not isinstance(info, dict) or not isinstance(stats, dict):
        raise InputError(f"{path}: malformed evo result (info.json and stats.json must be JSON objects)")
    try:
        stats = {str(k): float(v) for k, v in stats.items()}
    except (TypeError, ValueError):
        raise InputError(f"{path}: malformed evo result (stats.json values must be numbers)") from None
    return EvoResult(info=info, stats=stats, arrays=arrays)

"""An older revision of relpoint's core, imported beside the current one for paired timings."""

from __future__ import annotations

import atexit
import importlib
import io
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def load_module(revision: str, module: str) -> ModuleType:
    """``module`` (e.g. ``relpoint.estimators.ekf``) as it was at git ``revision``, with the whole core
    package of that revision beside it.

    ``git archive`` writes the revision's ``relpoint/`` into a temporary folder as ``relpoint_reference``
    (its own imports renamed), so the old code runs on its own helpers however the current code has
    moved them since. The folder is removed when the process ends.
    """
    folder = Path(tempfile.mkdtemp(prefix="relpoint-reference-"))
    atexit.register(shutil.rmtree, folder, True)
    archive = subprocess.run(["git", "archive", revision, "relpoint"], cwd=REPO, check=True, capture_output=True)
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(folder, filter="data")
    package = folder / "relpoint_reference"
    (folder / "relpoint").rename(package)
    for path in package.rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        text = re.sub(r"\b(from|import) relpoint(?=[.\s])", r"\1 relpoint_reference", text)
        path.write_text(text, encoding="utf-8")
    sys.path.insert(0, str(folder))
    return importlib.import_module("relpoint_reference" + module.removeprefix("relpoint"))

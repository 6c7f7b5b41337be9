"""An older revision of relpoint's core, imported beside the current one for paired timings."""

from __future__ import annotations

import atexit
import copy
import dataclasses
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
from typing import Any

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


def reference_config(config: Any, reference_class: type) -> Any:
    """``reference_class`` (a settings dataclass of the reference revision) holding ``config``'s values of
    the settings both revisions have; the reference's own defaults for the rest, and for the settings
    ``config`` leaves unset (None: taken from the log now, where the reference may need a value)."""
    shared = {field.name: getattr(config, field.name) for field in dataclasses.fields(reference_class)
              if field.init and getattr(config, field.name, None) is not None}  # fmt: skip
    return reference_class(**shared)


def carry_state(reference: Any, current: Any) -> list[str]:
    """Overlay onto ``reference`` (a filter the reference revision's constructor built) a deep copy of
    ``current``'s state, for the attributes both revisions have; return the names of those the
    reference keeps as its constructor made them.

    Plain data (arrays, numbers, containers, random generators) is copied. A helper object of the core
    package is carried into the reference's own helper of the same class name attribute by attribute,
    as the filter is: its code may have changed since the reference too. A helper the current code
    no longer has (or has of another class) stays as the reference's constructor made it, so every
    attribute the old code reads exists. Settings objects are not carried (:func:`reference_config`).
    """
    kept = [name for name in vars(reference) if name not in vars(current)]
    for name, value in vars(current).items():
        if name not in vars(reference) or name == "config":
            continue
        own = getattr(reference, name)
        if not _is_core_object(value):
            setattr(reference, name, copy.deepcopy(value))
        elif _is_core_object(own) and type(own).__name__ == type(value).__name__ and hasattr(own, "__dict__"):
            if _is_frozen(own):
                kept.append(name)
            else:
                kept += [f"{name}.{inner}" for inner in carry_state(own, value)]
        else:
            kept.append(name)
    return kept


def _is_core_object(value: Any) -> bool:
    """Whether ``value`` is an instance of a class of the core package (current or reference)."""
    return type(value).__module__.split(".")[0] in ("relpoint", "relpoint_reference")


def _is_frozen(value: Any) -> bool:
    params = getattr(type(value), "__dataclass_params__", None)
    return bool(params is not None and params.frozen)

"""relpoint: offline 3D SLAM over recorded logs (core package: pure computation, no file I/O)."""

from __future__ import annotations

from functools import cache
from typing import Any

from relpoint.errors import EstimatorError, InputError, RelpointError, UsageError


@cache
def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version  # 30-40 ms: only when asked

    try:
        return version("relpoint")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
        return "0.0.0+unknown"


def __getattr__(name: str) -> Any:
    """``relpoint.__version__``, read from the installed metadata the first time it is asked for;
    ``relpoint.run`` and ``relpoint.evaluate``, the Python API, from the application layer
    (:mod:`relpoint_app`, which reads and writes files; this package itself never does)."""
    if name == "__version__":
        return _installed_version()
    if name in ("run", "evaluate"):
        import relpoint_app

        return getattr(relpoint_app, name)
    raise AttributeError(f"module 'relpoint' has no attribute {name!r}")

__all__ = ["EstimatorError", "InputError", "RelpointError", "UsageError", "__version__", "evaluate", "run"]

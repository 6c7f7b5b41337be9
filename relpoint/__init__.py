"""relpoint: offline 3D SLAM over recorded logs (core package: pure computation, no file I/O)."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("relpoint")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

from relpoint.errors import EstimatorError, InputError, RelpointError, UsageError

__all__ = ["EstimatorError", "InputError", "RelpointError", "UsageError", "__version__"]

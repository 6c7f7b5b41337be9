"""Lazy access to open3d.

open3d's wheel links against ``libusb-1.0`` without shipping it. When the system library is absent we
preload the copy from the ``libusb-package`` wheel so ``import open3d`` works on a bare machine. The
import costs about two seconds, so modules call :func:`open3d` only where they need it.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from types import ModuleType


@functools.cache
def open3d() -> ModuleType:
    """Import and return the ``open3d`` module, preloading libusb if the system lacks it."""
    if ctypes.util.find_library("usb-1.0") is None:
        try:
            import libusb_package

            path = libusb_package.get_library_path()
            if path is not None:
                ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        except (ImportError, OSError):  # pragma: no cover - falls through to open3d's own error
            pass
    import open3d as o3d

    return o3d

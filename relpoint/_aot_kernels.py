"""Numba kernels compiled ahead of time at install, with a JIT fallback: one mechanism for every kernel file.

A kernel source file (Relative Point's ``estimators/relative_point/_kernels.py``, FastSLAM's
``estimators/_fastslam_kernels.py``) makes one :class:`KernelSet` and declares each of its kernels
with :meth:`KernelSet.kernel`, naming the argument types in numba's notation::

    kernels = KernelSet(__file__, "relpoint.estimators._fastslam_kernels_aot")

    @kernels.kernel("f8[:, ::1], i8")
    def row_sum(values, row): ...

At install, ``setup.py`` compiles every declared kernel of each source into that source's extension
module (numba's ``pycc``, named after the source with ``_aot`` appended) and freezes the source's
digest into it. At import, each kernel is bound to the prebuilt function when that module is
present, wanted and built from this very source, and numba itself is not imported. Otherwise (no C
compiler at install, a source checkout, ``RELPOINT_KERNELS=jit``, or a source edited since the
build) each kernel is a ``numba.njit(cache=True)`` dispatcher of the same loops, compiled on its first
call or by :meth:`KernelSet.prepare`. Both are the same LLVM code of the same loops and give
bit-identical results. The only I/O here is reading the source file for its digest and importing
the extension.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import os
import re
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

MODE_VARIABLE = "RELPOINT_KERNELS"
"""Environment variable: ``jit`` refuses the prebuilt modules (``auto``, the default, takes them)."""

_DTYPES = {
    "f8": np.dtype(np.float64),
    "f4": np.dtype(np.float32),
    "i8": np.dtype(np.int64),
    "u1": np.dtype(np.uint8),
    "b1": np.dtype(np.bool_),
}
_ARGUMENT = re.compile(r"(\w+)(?:\[([^\]]*)\])?")


class KernelSet:
    """The compiled kernels of one source file, prebuilt in the extension module ``prebuilt`` (dotted name).

    ``signatures`` holds the argument types of every declared kernel, by name: what the
    ahead-of-time build compiles. ``compiled_ahead`` says whether the kernels are the prebuilt
    machine code (True) or numba dispatchers compiled on first call (False).
    """

    def __init__(self, source: str | Path, prebuilt: str) -> None:
        self.source = Path(source)
        self.prebuilt_name = prebuilt
        self.signatures: dict[str, str] = {}
        self._dispatchers: dict[str, Any] = {}
        self.prebuilt = self.load_prebuilt()

    @property
    def compiled_ahead(self) -> bool:
        return self.prebuilt is not None

    def source_digest(self) -> int:
        """First 60 bits of the SHA-256 of the source file: the prebuilt module must have been built from it."""
        return int(hashlib.sha256(self.source.read_bytes()).hexdigest()[:15], 16)

    def load_prebuilt(self) -> ModuleType | None:
        """The prebuilt module if present, wanted and built from this very source; else None."""
        if os.environ.get(MODE_VARIABLE, "auto") == "jit":
            return None
        try:
            module = importlib.import_module(self.prebuilt_name)
        except ImportError:
            return None
        return module if module.source_digest() == self.source_digest() else None

    def kernel(self, argument_types: str) -> Callable[[Callable[..., Any]], Any]:
        """Declare a compiled kernel taking ``argument_types`` (numba notation, e.g. ``"f8[:, ::1], i8"``).

        The name is bound to the prebuilt function (behind :func:`checked`) when the set is compiled
        ahead, else to a lazily compiling ``numba.njit(cache=True)`` dispatcher of the same loops.
        """

        def declare(function: Callable[..., Any]) -> Any:
            self.signatures[function.__name__] = argument_types
            if self.prebuilt is not None:
                return checked(getattr(self.prebuilt, function.__name__), function, argument_types)
            from numba import njit

            dispatcher = njit(cache=True)(function)
            self._dispatchers[function.__name__] = dispatcher
            return dispatcher

        return declare

    def prepare(self) -> None:
        """Compile every public kernel for its declared argument types, or load it from numba's cache.

        Nothing to do when compiled ahead. Otherwise a run calls this before its first iteration, so
        compilation is timed on its own and not inside an iteration; a kernel called with other
        types (a strided view, say) still compiles for those on first call.
        """
        for name, dispatcher in self._dispatchers.items():
            if not name.startswith("_"):
                dispatcher.compile(f"({self.signatures[name]},)")


def checked(prebuilt: Callable[..., Any], function: Callable[..., Any], argument_types: str) -> Callable[..., Any]:
    """``prebuilt`` behind a check of its array arguments' dtype, dimensions and C order.

    A prebuilt kernel reads its arrays as declared without looking (a strided view would be read
    wrongly, a float32 array past its end), where a numba dispatcher would compile a variant; so a
    call with any other array is refused with a TypeError naming the kernel and argument.

    The check is generated for the signature: one condition over every array argument, written out
    (class, dtype, dimensions, C order), rather than a loop over the declared arrays; a call it does
    not pass goes to the loop, which names the argument. About 1 us for four arrays against 1.8 us
    for the loop alone: an iteration of Relative Point makes some twenty such calls. (Dtypes are
    compared with ``==``: arrays the kernels return carry a dtype object of their own, equal to
    numpy's but not it.)
    """
    declared = _ARGUMENT.findall(argument_types)
    arrays = [
        (position, _DTYPES[code], dimensions.count(",") + 1)
        for position, (code, dimensions) in enumerate(declared)
        if dimensions
    ]

    def refuse_or_call(*arguments: Any) -> Any:
        for position, dtype, ndim in arrays:
            array = arguments[position]
            if (
                array.__class__ is not np.ndarray
                or array.dtype != dtype
                or array.ndim != ndim
                or not array.flags.c_contiguous
            ):
                raise TypeError(f"{function.__name__}: argument {position} must be a C-ordered {ndim}-d {dtype} array")
        return prebuilt(*arguments)

    names = ", ".join(f"a{position}" for position in range(len(declared)))
    tests = " and ".join(
        f"a{position}.__class__ is ndarray and a{position}.dtype == dtype{position}"
        f" and a{position}.ndim == {ndim} and a{position}.flags.c_contiguous"
        for position, _, ndim in arrays
    )
    source = f"def call({names}{', /' if declared else ''}):\n"
    if tests:
        source += f"    if {tests}:\n        return prebuilt({names})\n    return refuse_or_call({names})\n"
    else:
        source += f"    return prebuilt({names})\n"
    namespace: dict[str, Any] = {"ndarray": np.ndarray, "prebuilt": prebuilt, "refuse_or_call": refuse_or_call}
    namespace.update({f"dtype{position}": dtype for position, dtype, _ in arrays})
    exec(compile(source, f"<checked {function.__name__}>", "exec"), namespace)
    return functools.update_wrapper(namespace["call"], function)
